"""Where a checkpoint's training gradient spikes: each batch's gradient norm, and the worst batch taken apart.

A `lerobot-train` log whose gradient norm (`grdn`) jumps by orders of magnitude says that some batches
pull hard, not which or through what. This tool computes the training loss and its gradient at a
checkpoint, without stepping, on `--batches` batches of whole training episodes drawn as `lerobot-train`
draws them on a packed view (`tools.fast_imitation`'s "epoch" sampler). For the batch of the largest
norm it then reports each episode's gradient norm alone and, for the worst episode, each parameter's:
a spike from one episode through the options' recurrence shows up as one episode far above the others,
its norm on the options' weights.

`python -m tools.gradient_spikes --policy CKPT --root DATASET [--set FIELD=VALUE ...] [--out FILE]`;
`--set taught_options=false` scores a taught checkpoint on the paper's loss.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm


def gradient_norms(policy: torch.nn.Module) -> dict[str, float]:
    """Each parameter's gradient norm (those with a gradient)."""
    return {name: float(p.grad.norm()) for name, p in policy.named_parameters() if p.grad is not None}


def total_norm(norms: dict[str, float]) -> float:
    """The global gradient norm, as gradient clipping measures it, from the parameters' norms."""
    return float(np.sqrt(sum(value * value for value in norms.values())))


def episode_losses(policy: Any, preprocessor: Any, split: Any, rows: np.ndarray) -> torch.Tensor:
    """Each episode's share of the training loss of the episodes `rows` of `split` as one batch, the
    whole episodes as a packed view's rows hold them (cut after `window_size` frames): its mean NLL
    weighted by its frames, as the packed view's loss weighs it; they add up to the batch's loss."""
    from policies.sequence import batch_mean
    from tools.fast_imitation import episode_batch

    batch = preprocessor(episode_batch(split, rows, policy.config.window_size))
    per_window, _ = policy.forward(batch, reduction="none")
    frames = torch.from_numpy(np.minimum(split.lengths[rows], policy.config.window_size)).float()
    return torch.stack([batch_mean(per_window * (torch.arange(len(rows)) == row), frames, packed=True)
                        for row in range(len(rows))])


def batch_gradients(policy: Any, preprocessor: Any, split: Any, rows: np.ndarray) -> dict[str, Any]:
    """The loss of the episodes `rows` of `split` as one batch, its gradient norm, and each episode's
    gradient norm alone (its share of the loss), with each parameter's norm for the worst episode."""
    policy.zero_grad()
    shares = episode_losses(policy, preprocessor, split, rows)
    loss = shares.sum()
    loss.backward(retain_graph=True)
    norms = gradient_norms(policy)
    episodes = []
    for share in shares:
        policy.zero_grad()
        share.backward(retain_graph=True)
        episodes.append(gradient_norms(policy))
    episode_norms = [total_norm(each) for each in episodes]
    worst = int(np.argmax(episode_norms))
    return {"loss": loss.item(), "grad_norm": total_norm(norms),
            "episode_index": [int(split.episode_index[row]) for row in rows],
            "episode_grad_norm": episode_norms,
            "worst_episode": int(split.episode_index[rows[worst]]),
            "worst_episode_length": int(split.lengths[rows[worst]]),
            "worst_episode_parameters": dict(sorted(episodes[worst].items(), key=lambda item: -item[1]))}


def scan(policy: Any, preprocessor: Any, split: Any, batches: int, batch_size: int, seed: int) -> dict[str, Any]:
    """Every batch's loss and gradient norm, then `batch_gradients` of the batch of the largest norm."""
    from tools.fast_imitation import episode_draws

    draws = episode_draws(split.lengths, batch_size, "epoch", np.random.default_rng(seed))
    policy.train()
    drawn, losses, norms = [], [], []
    for _ in tqdm(range(batches), desc="batches", unit="batch"):
        rows = next(draws)
        policy.zero_grad()
        loss = episode_losses(policy, preprocessor, split, rows).sum()
        loss.backward()
        drawn.append(rows)
        losses.append(loss.item())
        norms.append(total_norm(gradient_norms(policy)))
    worst, median = int(np.argmax(norms)), float(np.median(norms))
    return {"batch_loss": losses, "batch_grad_norm": norms, "median_grad_norm": median,
            "batches_over_10x_median": int(sum(norm > 10 * median for norm in norms)), "worst_batch": worst,
            **batch_gradients(policy, preprocessor, split, drawn[worst])}


def summary(result: dict[str, Any], top: int = 5) -> str:
    """A few lines for the terminal: the norms' spread, the worst batch's episodes and parameters."""
    episode_norms = sorted(zip(result["episode_grad_norm"], result["episode_index"], strict=True), reverse=True)
    parameters = list(result["worst_episode_parameters"].items())[:top]
    return "\n".join([
        f"{len(result['batch_grad_norm'])} batches: median gradient norm {result['median_grad_norm']:.3g}, "
        f"{result['batches_over_10x_median']} over ten times that, largest {max(result['batch_grad_norm']):.3g} "
        f"(batch {result['worst_batch']}, loss {result['loss']:.4f})",
        "its episodes by gradient norm: " + ", ".join(f"{episode} {norm:.3g}" for norm, episode in episode_norms[:top]),
        f"episode {result['worst_episode']} ({result['worst_episode_length']} frames), by parameter: "
        + ", ".join(f"{name} {norm:.3g}" for name, norm in parameters)])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.gradient_spikes", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--policy", type=Path, required=True, help="a checkpoint's pretrained_model folder")
    parser.add_argument("--root", type=Path, required=True, help="the LeRobot dataset it was trained on")
    parser.add_argument("--split", default="train", help="the dataset split whose episodes make the batches")
    parser.add_argument("--batches", type=int, default=60, help="batches to score")
    parser.add_argument("--batch-size", type=int, default=32, help="episodes per batch")
    parser.add_argument("--seed", type=int, default=0, help="seed of the batches' draw")
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="OCNConfig fields to change before scoring, e.g. taught_options=false")
    parser.add_argument("--out", type=Path, help="write the result as JSON here")
    args = parser.parse_args(argv)
    if args.batches < 1 or args.batch_size < 1:
        parser.error("--batches and --batch-size must be at least 1")

    from ocn_data.episodes_table import load_episodes, split_episodes
    from tools.bench import machine
    from tools.episode_parsing import load_policy
    from tools.fast_imitation import parse_overrides

    torch.manual_seed(args.seed)
    policy, preprocessor, _ = load_policy(args.policy)
    # Whole episodes from their first frame, which is how window_start="any" reads a batch's rows.
    for key, value in {**parse_overrides(args.set), "window_start": "any"}.items():
        setattr(policy.config, key, value)
    split = load_episodes(args.root, split_episodes(args.root, args.split))
    result = {"command": "python -m tools.gradient_spikes " + " ".join(sys.argv[1:] if argv is None else argv),
              "date": time.strftime("%Y-%m-%d"), "machine": machine(),
              "policy": str(args.policy), "root": str(args.root), "split": args.split, "settings": args.set,
              "batch_size": args.batch_size, "seed": args.seed,
              **scan(policy, preprocessor, split, args.batches, args.batch_size, args.seed)}
    print(summary(result))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
