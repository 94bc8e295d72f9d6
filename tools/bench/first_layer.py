"""`ocn-bench first-layer`: one training step of the default Craft policy with each way its cells' first
layer can read Craft's OMPN features (1,075 wide, 140 entries set), on the same batches of a recorded S1
dataset: the policy's own (`embedding_bag` forward, the weight's gradient as one matmul:
`ocn.cell.sparse_rows_product`), `embedding_bag` both ways (the implementation it replaced; its backward
sorts the indices first) and the dense features both ways. A step is LeRobot's update: forward,
backward, gradient clipping and Adam. The variants take turns in blocks of steps, and each one's median
block counts."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from lerobot_policy_ocn.tools.bench.common import add_common_arguments, header, int_list

BEFORE, AFTER, DENSE = "embedding_bag", "matmul_backward", "dense"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_common_arguments(parser, "first_layer")
    parser.add_argument("--root", type=Path, default=Path("outputs/bench/craft_s1"),
                        help="the S1 dataset (recorded there by record_demos if missing)")
    parser.add_argument("--episodes-per-task", type=int, default=2000, help="record_demos size when --root is missing")
    parser.add_argument("--batch-sizes", type=int_list, default="64,128",
                        help="episodes per batch, e.g. 64,128 (the quickstart's and the study's)")
    parser.add_argument("--threads", type=int_list, default="1,2", help="math threads, e.g. 1,2")
    parser.add_argument("--rounds", type=int, default=8, help="turns of every variant")
    parser.add_argument("--block", type=int, default=10, help="timed steps per turn")


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The measurements; `ocn-bench` adds the provenance and writes the report (`markdown`)."""
    from lerobot_policy_ocn.tools.bench.models import compare_first_layers, dataset_policy, torch_threads
    from lerobot_policy_ocn.tools.bench.train import REPO_ID, ensure_dataset

    recorded = ensure_dataset(args.root, args.episodes_per_task)
    rows = []
    for threads in args.threads:
        with torch_threads(threads):
            for batch in args.batch_sizes:
                step_s = compare_first_layers(dataset_policy(args.root, REPO_ID, "cpu"), batch, args.rounds, args.block)
                rows.append({"threads": threads, "batch_size": batch, "step_s": step_s,
                             "speedup": step_s[BEFORE] / step_s[AFTER],
                             "against_dense": step_s[DENSE] / step_s[AFTER]})
    return {"dataset": {"root": str(args.root), "recorded_by": recorded}, "rounds": args.rounds,
            "block": args.block, "rows": rows}


def markdown(r: dict[str, Any]) -> str:
    rows = "".join(
        f"| {row['threads']} | {row['batch_size']} | {row['step_s'][BEFORE] * 1000:.1f} | "
        f"{row['step_s'][AFTER] * 1000:.1f} | **{row['speedup']:.2f}x** | {row['step_s'][DENSE] * 1000:.1f} | "
        f"{row['against_dense']:.2f}x |\n"
        for row in r["rows"]
    )
    return (
        header("The first layer on Craft's sparse features: one training step three ways", r)
        + f"One `lerobot-train` update (forward, backward, gradient clipping, Adam) of the default OCN built from "
        f"the S1 dataset at `{r['dataset']['root']}`, on the CPU, over batches drawn as LeRobot's sampler draws "
        f"them. The three ways of computing the cells' first layer from the 1,075-wide OMPN features (140 "
        f"entries set) take turns, {r['block']} steps each, for {r['rounds']} rounds; the median turn counts.\n\n"
        "- before: `embedding_bag` forward and its own backward, which sorts the indices first;\n"
        "- now (`ocn.cell.sparse_rows_product`): `embedding_bag` forward, the weight's gradient as one matmul "
        "of the dense rows;\n"
        "- dense: the dense features through a matmul both ways.\n\n"
        "| math threads | episodes per batch | before (ms) | now (ms) | now against before | dense (ms) | "
        "now against dense |\n|---|---|---|---|---|---|---|\n" + rows
    )
