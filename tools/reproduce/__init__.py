"""`ocn-reproduce`: the paper's experiments end to end, from recording to the committed results.

Each experiment is a subcommand in its own module: `imitation-s1` (skill induction and its
ablations, `imitation.py`), `s1` and `s2` (finetuning over frozen skills against MoE, HIL and flat
PPO, `finetune.py`), `parsing-s1` (how OCN and the baselines parse S1 over training, `parsing.py`),
`dial` (skills cloned from 2-digit PINs, finetuned on 3-digit PINs against MoE, `dial.py`),
`combine` (one finetuning or parsing study from the results files of several invocations,
`combine.py`), and `gather` (one finetuning study from `ocn-finetune` folders run by hand,
`gather.py`).
What they share is in `runs.py` (recording, resumable `lerobot-train` runs) and `report.py` (the
results files' provenance and checks table).
"""

from __future__ import annotations

import argparse
import sys

from tools.reproduce import combine, dial, finetune, gather, imitation, parsing


def build_parser() -> argparse.ArgumentParser:
    """Every subcommand's command line."""
    parser = argparse.ArgumentParser(prog="ocn-reproduce", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="experiment", required=True)
    imitation.add_parser(sub)
    finetune.add_parsers(sub)
    parsing.add_parser(sub)
    dial.add_parser(sub)
    combine.add_parser(sub)
    gather.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.argv = argv
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
