"""`ocn-reproduce`: the paper's experiments from plain commands, each writing one results set with its checks.

`imitation-s1` (`imitation.py`): OCN's skill induction on Craft S1 and the paper's ablations.
`s1`, `s2` (`finetune.py`): PPO over the cloned skills of OCN and the baselines on new tasks.
`dial` (`dial.py`): skills cloned from 2-digit PINs, finetuned on 3-digit PINs against MoE.
`babyai` (`babyai.py`): OCN, OMPN and compILE cloned from BabyAI's bot, scored against its subgoals.
`craft-images` (`images.py`): OCN on Craft's rendered frames alone against OCN on its state.
`combine` (`combine.py`): one study from the results of several invocations run side by side.
Each study is made of plain `record_demos` (BabyAI: `python -m lerobot_policy_ocn.ocn_data.record_babyai`),
`lerobot-train`, `ocn-eval` and `ocn-finetune` commands (`runs.py`, `clones.py`), each run once in the workdir; the
recipe is the policy's default, so no command carries a recipe flag. Nothing here imports torch or
LeRobot until a study runs.
"""

from __future__ import annotations

import argparse
import sys

from lerobot_policy_ocn.tools.reproduce import babyai, combine, dial, finetune, images, imitation


def build_parser() -> argparse.ArgumentParser:
    """Every subcommand's command line."""
    parser = argparse.ArgumentParser(prog="ocn-reproduce", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    imitation.add_parser(sub)
    finetune.add_parsers(sub)
    dial.add_parser(sub)
    babyai.add_parser(sub)
    images.add_parser(sub)
    combine.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    args.argv = argv
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
