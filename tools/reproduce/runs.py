"""The commands a study is made of, each run once: `record_demos`, `lerobot-train`, `ocn-eval`, `ocn-finetune`.

A study is a list of plain commands, and this module runs each of them at most once. Every command
runs in the workdir with paths relative to it, so the command a results file records is the one
that ran (its program named, not its path) and a workdir moved elsewhere keeps its runs. A command
owns one folder, which keeps it in `command.txt`, its output in `log.txt` and its wall seconds per
invocation in `timing.json`. A finished command is reused; an interrupted one goes on (`lerobot-train
--resume=true` from its last checkpoint, `ocn-finetune --resume` from its last PPO iteration) or,
with nothing to go on from, starts over; a folder that holds another command is refused, never
overwritten nor reused. A lock on each folder lets invocations share a workdir side by side (seeds
in parallel processes; `imitation-s1` and `s1` share OCN's clones): the second waits, then reuses.

Training is `lerobot-train --policy.type=T` with the data, the size of the run (steps, batch, seed)
and the folders; the policy's defaults are the recipe, so the only `--policy.*` flags a study may
add are the model-size and baseline ones of `POLICY_FLAGS`. Beside them go three flags that change
how the run is carried out, not what it learns:

- `--num_workers=1` (`WORKERS`). Measured on the 2-core VM while other trainings ran (S1, 2,000
  demonstrations per task, batch 128; runs of 20 and 220 steps differenced): a step cost 0.22 s of
  CPU with no data worker, 0.21 s with one and 0.25 s with two, and each spawned worker about 8 s
  of CPU to start; a step took 0.67, 0.52 and 0.57 s of wall time. One worker loads the next
  batch's frames (0.04-0.07 s a step) while the update runs, at no more CPU than the main process
  loading them; more workers only add CPU on two cores that other runs share. LeRobot's default is 4.
- `--save_freq=1000` (`SAVE_EVERY`): a checkpoint every 1,000 steps (LeRobot's default, 20,000,
  keeps none before the end), so an interrupted run loses at most that many.
- `--log_freq=100`: the loss in `log.txt` every 100 steps.

Every command runs with one math thread (`OMP_NUM_THREADS=1`, `THREADS`). Alternating runs of 200
steps with one worker took 0.29 and 0.43 s a step with one thread, 0.25 and 0.43 s with torch's two,
at the same CPU (58-68 s a run): no difference through the noise of a shared machine, and with one
thread two invocations side by side (the way to use both cores, `ocn-reproduce combine`) do not
fight over them.
"""

from __future__ import annotations

import fcntl
import json
import os
import shlex
import shutil
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from lerobot_policy_ocn.tools import console_script

WORKERS = 1
SAVE_EVERY = 1000
THREADS = 1
# The `--policy.*` flags a study may pass: model size and baselines. "recipe" is there for one value,
# "paper", which `ocn-reproduce dial --split induced` passes and which writes no headline set.
POLICY_FLAGS = ("n_options", "temperature", "hierarchy", "recipe")
CHECKPOINT = "train/checkpoints/last/pretrained_model"  # a training folder's final policy


def train_command(policy_type: str, data: str, repo_id: str, folder: str, steps: int, batch_size: int, seed: int,
                  policy: dict[str, Any]) -> list[str]:
    """The plain `lerobot-train` command of one run, writing into `folder/train`; `policy` holds
    `--policy.*` values, of `POLICY_FLAGS` only (anything else would change the recipe)."""
    unknown = sorted(set(policy) - set(POLICY_FLAGS))
    if unknown or policy.get("recipe", "paper") != "paper":
        raise ValueError(f"A study passes no recipe flag: {policy} (allowed: {POLICY_FLAGS}, recipe only 'paper').")
    return ["lerobot-train", f"--policy.type={policy_type}", f"--dataset.repo_id={repo_id}", f"--dataset.root={data}",
            "--policy.device=cpu", f"--steps={steps}", f"--batch_size={batch_size}", f"--seed={seed}",
            f"--output_dir={folder}/train", "--wandb.enable=false", "--policy.push_to_hub=false",
            f"--num_workers={WORKERS}", f"--save_freq={SAVE_EVERY}", "--log_freq=100",
            *(f"--policy.{key}={value}" for key, value in policy.items())]


class Job:
    """One command in its folder (relative to the workdir): run unless it has finished, refused if the
    folder holds another command. Subclasses say when the command has finished, what its output is,
    and how it goes on after an interruption."""

    output = "out"

    def __init__(self, workdir: Path, folder: str, command: list[str]) -> None:
        self.workdir, self.folder, self.command = workdir, folder, command
        self.path = workdir / folder

    @property
    def shown(self) -> str:
        return shlex.join(self.command)

    def finished(self) -> bool:
        raise NotImplementedError

    def resumed(self) -> list[str] | None:
        """The command that goes on from an interrupted run; None: it starts over."""
        return None

    def run(self) -> Job:
        """Run the command unless it has finished (waiting for an invocation running it beside this one)."""
        self.path.mkdir(parents=True, exist_ok=True)
        with _locked(self.path / ".lock"):
            record = self.path / "command.txt"
            if record.exists() and record.read_text().strip() != self.shown:
                raise SystemExit(f"{self.path} holds the run of\n  {record.read_text().strip()}\nnot of\n  "
                                 f"{self.shown}\nMove that folder away or pass another --workdir.")
            record.write_text(self.shown + "\n")
            if self.finished():
                return self
            command = self.resumed()
            if command is None:
                shutil.rmtree(self.path / self.output, ignore_errors=True)
                command = self.command
            print(f"{'resuming' if command is not self.command else 'running'}: {shlex.join(command)}", flush=True)
            started = time.perf_counter()
            with open(self.path / "log.txt", "a") as log:
                done = subprocess.run([console_script(command[0]), *command[1:]], cwd=self.workdir, stdout=log,
                                      stderr=subprocess.STDOUT, env={**os.environ, "OMP_NUM_THREADS": str(THREADS)})
            if done.returncode:
                tail = (self.path / "log.txt").read_text().splitlines()[-5:]
                raise SystemExit(f"{command[0]} failed (exit {done.returncode}) in {self.workdir}:\n  "
                                 f"{shlex.join(command)}\nthe end of {self.path / 'log.txt'}:\n" + "\n".join(tail))
            timing = self.timing()
            timing.append({"wall_s": round(time.perf_counter() - started, 1), "resumed": command is not self.command})
            (self.path / "timing.json").write_text(json.dumps(timing, indent=2) + "\n")
        return self

    def timing(self) -> list[dict[str, Any]]:
        """The invocations that ran the command, each with its wall seconds (none: found finished)."""
        path = self.path / "timing.json"
        return json.loads(path.read_text()) if path.exists() else []

    @property
    def wall_s(self) -> float | None:
        """The command's wall seconds over every invocation (None if none was timed, or if the first timed
        one resumed a run whose start went untimed, as when the machine stopped under it)."""
        timing = self.timing()
        if not timing or timing[0]["resumed"]:
            return None
        return round(sum(entry["wall_s"] for entry in timing), 1)


class Recording(Job):
    """`record_demos ARGUMENTS --root FOLDER/dataset`: a dataset recorded once."""

    output = "dataset"

    def __init__(self, workdir: Path, folder: str, arguments: list[str]) -> None:
        super().__init__(workdir, folder, ["record_demos", *arguments, "--root", f"{folder}/{self.output}"])

    @property
    def root(self) -> str:
        return f"{self.folder}/{self.output}"

    def finished(self) -> bool:
        path = self.path / self.output / "meta" / "ocn_recording.json"
        return path.exists() and not json.loads(path.read_text())["sessions"][-1]["interrupted"]


class Training(Job):
    """A `lerobot-train` command (`train_command`) writing into FOLDER/train."""

    output = "train"

    def steps_done(self) -> int:
        path = self.path / "train" / "checkpoints" / "last" / "training_state" / "training_step.json"
        return json.loads(path.read_text())["step"] if path.exists() else 0

    def finished(self) -> bool:
        steps = next(int(word.split("=")[1]) for word in self.command if word.startswith("--steps="))
        return self.steps_done() >= steps

    def resumed(self) -> list[str] | None:
        if not self.steps_done():
            return None
        return ["lerobot-train", f"--config_path={self.folder}/{CHECKPOINT}/train_config.json", "--resume=true"]

    @property
    def checkpoint(self) -> str:
        return f"{self.folder}/{CHECKPOINT}"


class Evaluation(Job):
    """`ocn-eval` of a checkpoint on a dataset's validation split, writing FOLDER/out/eval.json."""

    def __init__(self, workdir: Path, folder: str, checkpoint: str, data: str, repo_id: str, rollouts: int) -> None:
        super().__init__(workdir, folder, ["ocn-eval", "--policy", checkpoint, "--root", data, "--repo-id", repo_id,
                                           "--split", "val", "--rollouts", str(rollouts),
                                           "--out", f"{folder}/{self.output}/eval.json"])

    def finished(self) -> bool:
        return (self.path / self.output / "eval.json").exists()

    def scores(self) -> dict[str, Any]:
        return json.loads((self.path / self.output / "eval.json").read_text())


class Finetuning(Job):
    """An `ocn-finetune` command (its arguments without --out) writing FOLDER/out: curve.csv, finetune.json,
    and training_state.pt after every PPO iteration, from which `--resume` goes on."""

    def __init__(self, workdir: Path, folder: str, arguments: list[str]) -> None:
        super().__init__(workdir, folder, ["ocn-finetune", *arguments, "--out", f"{folder}/{self.output}"])

    def finished(self) -> bool:
        return (self.path / self.output / "finetune.json").exists()

    def resumed(self) -> list[str] | None:
        from lerobot_policy_ocn.tools.rl.finetune_settings import STATE_FILE

        return [*self.command, "--resume"] if (self.path / self.output / STATE_FILE).exists() else None

    def summary(self) -> dict[str, Any]:
        return json.loads((self.path / self.output / "finetune.json").read_text())

    @property
    def curve(self) -> Path:
        return self.path / self.output / "curve.csv"


@contextmanager
def _locked(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on `path` (created if need be) while the block runs."""
    with open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
