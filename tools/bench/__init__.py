"""`ocn-bench`: speed and time-to-result benchmarks, each writing one JSON and Markdown pair under ./results/.

One module per benchmark (see tools/bench/README.md): `train` (OCN training in 1, 2, ... processes),
`ppo` (PPO finetuning against the number of envs), `env` (Craft stepping and recording), `dial` (Dial's
physics rate and expert), `stacked` (stacked option cells against a per-option loop), `first-layer`
(the training step with each way of reading Craft's sparse features), `skills` (the plain commands from
an empty folder to an S1 model that parses) and `quickstart`. The modules import torch
and LeRobot only when they run, so that `--help` answers at once.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from types import ModuleType

from lerobot_policy_ocn.tools.bench import dial, env, first_layer, ppo, quickstart, skills, stacked, train
from lerobot_policy_ocn.tools.bench.common import new_result, write

BENCHMARKS: dict[str, tuple[ModuleType, str]] = {
    "train": (train, "OCN training with lerobot-train in 1, 2, ... processes: frames/s and parse quality"),
    "ppo": (ppo, "PPO finetuning env frames/s against the number of envs, and where the time goes"),
    "env": (env, "Craft env steps/s and record_demos frames/s"),
    "dial": (dial, "Dial env steps/s, its physics rate against bare mj_step, expert success"),
    "stacked": (stacked, "stacked option cells against a per-option loop, swept"),
    "first-layer": (first_layer, "the training step with each way of reading Craft's sparse features"),
    "skills": (skills, "wall time from an empty folder to an S1 model with NMI >= 0.95, plain commands"),
    "quickstart": (quickstart, "ocn-quickstart's wall time and NMI against its goals"),
}


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Defaults shown, and each benchmark's description as its module docstring lays it out."""


def build_parser() -> argparse.ArgumentParser:
    """`ocn-bench` and one subcommand per benchmark, with that benchmark's own arguments."""
    parser = argparse.ArgumentParser(prog="ocn-bench", description=__doc__.splitlines()[0],
                                     formatter_class=HelpFormatter)
    sub = parser.add_subparsers(dest="benchmark", required=True)
    for name, (module, summary) in BENCHMARKS.items():
        command = sub.add_parser(name, help=summary, description=module.__doc__, formatter_class=HelpFormatter)
        module.add_arguments(command)
        command.set_defaults(module=module)
    return parser


def main(argv: list[str] | None = None) -> None:
    """Run the benchmark the command line names and write its result with the date, the machine and this
    command line (`lerobot_policy_ocn.tools.bench.common.new_result`), as JSON and as its Markdown report."""
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    args.command = shlex.join(["ocn-bench", *argv])
    result = new_result(args) | args.module.run(args)
    write(result, args.module.markdown(result), args.out)
