#!/usr/bin/env bash
# Make the project's environment from nothing: uv (if missing), Python 3.12, the locked
# dependencies in .venv, and Debian's ffmpeg (torchcodec, LeRobot's video decoder, needs its
# shared libraries). Safe to rerun; it only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."

if ! command -v uv >/dev/null 2>&1; then
    py=""
    for candidate in python3.12 "$HOME/.pyenv/versions/3.12.1/bin/python" python3; do
        if command -v "$candidate" >/dev/null 2>&1; then py="$candidate"; break; fi
    done
    [ -n "$py" ] || { echo "bootstrap: no python found to install uv with" >&2; exit 1; }
    "$py" -m pip install --quiet --user uv 2>/dev/null || "$py" -m pip install --quiet uv
    export PATH="$HOME/.local/bin:$(dirname "$(command -v "$py")"):$PATH"
    command -v uv >/dev/null 2>&1 || export PATH="$("$py" -c 'import sysconfig; print(sysconfig.get_path("scripts"))'):$PATH"
fi

if ! command -v ffmpeg >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
    (apt-get install -y -q ffmpeg >/dev/null 2>&1 || (apt-get update -q >/dev/null && apt-get install -y -q ffmpeg >/dev/null)) \
        || echo "bootstrap: could not install ffmpeg; LeRobot falls back to PyAV for video" >&2
fi

uv sync --frozen --python 3.12
