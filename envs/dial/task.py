"""Dial tasks: PINs (digit sequences) to dial on the key pad, their names and their step limits.

A task is a PIN such as "124": press 1, then 2, then 4. Each digit is one subtask, named
"press <digit>"; the LeRobot task string of a PIN is its subtask names joined by ", "
("press 1, press 2, press 4"), as Craft joins its subtask names. Random PINs are drawn from a digit
set (the paper's S = 1, 2, 4, 8) with no digit following itself.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

DIGITS = tuple(range(10))
DEFAULT_DIGITS = (1, 2, 4, 8)
SUBTASK_NAMES = tuple(f"press {d}" for d in DIGITS)
# Env steps (of 20 physics steps, 0.04 s) allowed per digit of the PIN. The noise-free expert needs
# about 20 per digit and rarely more than 60 from a random start; its DART-noised demonstrations
# occasionally take over 100.
STEPS_PER_DIGIT = 150
REWARDS = ("dense", "sparse")


def default_max_steps(pin_length: int) -> int:
    """Step limit of a PIN: `STEPS_PER_DIGIT` per digit."""
    return STEPS_PER_DIGIT * pin_length


def pin_code(pin: Sequence[int]) -> str:
    """Compact form of a PIN, e.g. (1, 2, 4) -> "124"."""
    return "".join(str(d) for d in pin)


def task_description(pin: Sequence[int]) -> str:
    """LeRobot task string of a PIN, e.g. (1, 2) -> "press 1, press 2"."""
    return ", ".join(SUBTASK_NAMES[d] for d in pin)


def parse_pin(spec: str) -> tuple[int, ...]:
    """A PIN from its digits ("124") or its description ("press 1, press 2, press 4")."""
    text = " ".join(str(spec).lower().split())
    if text.startswith("press"):
        parts = [p.strip() for p in text.split(",")]
        if not all(p in SUBTASK_NAMES for p in parts):
            raise ValueError(f"unknown Dial task {spec!r}; write a PIN as digits (\"124\") or as "
                             "\"press 1, press 2, press 4\"")
        return tuple(SUBTASK_NAMES.index(p) for p in parts)
    if not text.isdigit() or not text.isascii():
        raise ValueError(f"a Dial task is a PIN of digits 0-9 such as \"124\"; got {spec!r}")
    return tuple(int(c) for c in text)


def parse_pin_list(spec: str) -> list[tuple[int, ...]]:
    """A comma-separated list of PINs (`--tasks 12,48`); a PIN named twice is an error."""
    pins = [parse_pin(part) for part in spec.split(",")]
    if len(set(pins)) != len(pins):
        raise ValueError(f"--tasks lists a PIN twice: {spec!r}")
    return pins


def parse_digits(spec: str | Sequence[int]) -> tuple[int, ...]:
    """A digit set ("1,2,4,8" or a sequence): at least two distinct digits, so that random PINs
    can avoid immediate repeats."""
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    try:
        digits = tuple(int(str(d).strip()) for d in items)
    except ValueError:
        raise ValueError(f"digits are comma-separated integers 0-9 such as 1,2,4,8; got {spec!r}") from None
    if any(d not in DIGITS for d in digits) or len(set(digits)) != len(digits) or len(digits) < 2:
        raise ValueError(f"digits must be at least two distinct integers 0-9, such as 1,2,4,8; got {spec!r}")
    return digits


def sample_pin(rng: np.random.Generator, length: int, digits: Sequence[int] = DEFAULT_DIGITS) -> tuple[int, ...]:
    """A random PIN of `length` digits from `digits`, no digit directly following itself."""
    if length < 1:
        raise ValueError(f"a PIN has at least one digit, got length {length}")
    pin = [int(rng.choice(digits))]
    while len(pin) < length:
        pin.append(int(rng.choice([d for d in digits if d != pin[-1]])))
    return tuple(pin)
