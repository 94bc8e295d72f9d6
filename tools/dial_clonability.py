"""How much of the Dial expert's control a memoryless network can predict, and from what.

An option of OCN sees the 39-float observation; which digit it serves is the only thing the
controller adds. If the expert's control is a function of the observation and the digit, options
that each serve one digit can clone it exactly, and the digit is the one thing worth splitting by.
If part of the control depends on something the observation lacks (joint velocities, say), that
part is noise to every option, and it can pay a model better to split by something other than the
digit. `measure()` records the expert's frames (two-digit PINs under its recorded DART noise) and
fits one small MLP per feature set on 4 in 5 episodes; the score is the fraction of each control's
variance explained on the held-out fifth (R^2), per joint and averaged.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from tqdm import tqdm

from tools.bench import conditions_paragraph

DIGITS = (1, 2, 4, 8)
HIDDEN = 256
BATCH = 256
LR = 1e-3
HELD_OUT_EVERY = 5  # episode index % HELD_OUT_EVERY == 0 is held out


def expert_frames(episodes: int, seed: int = 0, num_envs: int = 100) -> dict[str, np.ndarray]:
    """Clean expert controls with what a model could condition on, one row per frame of `episodes`
    random two-digit PINs over `DIGITS`, executed with the DART noise the recorder uses."""
    from envs.dial import DialBatch, DialExpert

    rows: dict[str, list[np.ndarray]] = {k: [] for k in ("obs", "digit", "qvel", "action", "episode", "t")}
    for first in range(0, episodes, num_envs):
        n = min(num_envs, episodes - first)
        batch = DialBatch(n, pin_length=2, digits=DIGITS)
        expert = DialExpert(batch)
        seeds = [seed * 1_000_000 + first + i for i in range(n)]
        batch.reset(seeds=seeds)
        expert.reset(seeds=seeds)
        while not batch.done.all():
            live = np.flatnonzero(~batch.done)
            action = expert.act()
            rows["obs"].append(batch.observe()[live])
            rows["digit"].append(batch.current_digit()[live])
            rows["qvel"].append(batch.qvel[live].copy())
            rows["action"].append(action[live])
            rows["episode"].append(first + live)
            rows["t"].append(batch.t[live].copy())
            batch.step(expert.perturb(action))
    return {k: np.concatenate(v) for k, v in rows.items()}


def feature_sets(frames: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The inputs compared: the observation; with the digit one-hot; with the last step's change of
    the observation too (what one frame of memory could add); with the joint velocities (privileged)."""
    obs, t = frames["obs"], frames["t"]
    digit = (frames["digit"][:, None] == np.array(DIGITS)[None]).astype(np.float32)
    previous = np.roll(obs, 1, axis=0)
    previous[t == 0] = obs[t == 0]  # frames of one episode are consecutive rows; the first has no past
    return {
        "observation": obs,
        "observation + digit": np.concatenate([obs, digit], axis=1),
        "observation + digit + last change": np.concatenate([obs, digit, obs - previous], axis=1),
        "observation + digit + joint velocities": np.concatenate([obs, digit, frames["qvel"]], axis=1),
    }


def explained_variance(x: np.ndarray, y: np.ndarray, held_out: np.ndarray, steps: int, seed: int = 0) -> np.ndarray:
    """Held-out R^2 per output column of an MLP (2 hidden layers) fitted to standardised x and y."""
    train = np.flatnonzero(~held_out)

    def standardise(a: np.ndarray) -> torch.Tensor:
        mean, std = a[train].mean(axis=0), a[train].std(axis=0) + 1e-6
        return torch.as_tensor((a - mean) / std, dtype=torch.float32)

    xs, ys = standardise(x), standardise(y)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = torch.nn.Sequential(
        torch.nn.Linear(x.shape[1], HIDDEN), torch.nn.ReLU(),
        torch.nn.Linear(HIDDEN, HIDDEN), torch.nn.ReLU(),
        torch.nn.Linear(HIDDEN, y.shape[1]),
    )
    optimizer = torch.optim.Adam(net.parameters(), lr=LR)
    for _ in range(steps):
        rows = torch.as_tensor(rng.choice(train, BATCH))
        loss = (net(xs[rows]) - ys[rows]).square().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        test = torch.as_tensor(np.flatnonzero(held_out))
        residual = (net(xs[test]) - ys[test]).square().mean(dim=0)
        variance = ys[test].var(dim=0, unbiased=False)
    return (1.0 - residual / variance).numpy()


def measure(episodes: int, steps: int, progress: Callable = tqdm) -> dict:
    """Frames of the current expert and the held-out R^2 of every feature set."""
    frames = expert_frames(episodes)
    held_out = frames["episode"] % HELD_OUT_EVERY == 0
    scores = {}
    for name, x in progress(feature_sets(frames).items(), desc="fit", unit="feature set"):
        r2 = explained_variance(x.astype(np.float32), frames["action"], held_out, steps)
        scores[name] = {"mean": float(r2.mean()), "per_joint": [round(float(v), 4) for v in r2]}
    lengths = np.bincount(frames["episode"])
    return {
        "episodes": episodes,
        "frames": int(len(frames["t"])),
        "held_out_frames": int(held_out.sum()),
        "episode_length_median": float(np.median(lengths)),
        "fit_steps": steps,
        "r2": scores,
    }


def markdown(r: dict) -> str:
    """The results table of `ocn-bench clonability`."""
    m, c = r["machine"], r["clonability"]
    conditions = conditions_paragraph(r)
    rows = "".join(
        f"| {name} | **{s['mean']:.3f}** | {' / '.join(f'{v:.3f}' for v in s['per_joint'][:6])} | "
        f"{' / '.join(f'{v:.3f}' for v in s['per_joint'][6:])} |\n"
        for name, s in c["r2"].items()
    )
    return (
        "# How much of the Dial expert's control a memoryless network predicts\n\n"
        f"Command: `ocn-bench clonability`. Machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}.\n\n"
        f"{conditions}"
        f"{c['episodes']} two-digit PINs over 1, 2, 4, 8 under the recorded DART noise ({c['frames']:,} frames, "
        f"median episode {c['episode_length_median']:.0f} steps); one MLP (2 x {HIDDEN}) per input, "
        f"{c['fit_steps']:,} Adam steps of {BATCH} frames; R^2 on the {c['held_out_frames']:,} frames of every "
        f"{HELD_OUT_EVERY}th episode, held out.\n\n"
        "| input | R^2, mean | arm joints 1-6 | fingers |\n|---|---|---|---|\n"
        f"{rows}\n"
        "An option sees the observation; the controller adds which digit it serves. The gap between "
        "\"observation + digit\" and 1 is control that no option can predict.\n"
    )
