"""Who explains the last step of each subtask: the diagnosis of boundaries that an OCN parse puts one
step early.

When a subtask's last action (Craft: the `use` that completes it) is explained as well by the next
subtask's option as by the running one, the NLL does not care which acts, and a parse may hand that
step to the successor. Scores only show the offset (`ocn-eval`'s `boundary_offsets`); this shows why.
For every inner true boundary step of the demonstrations it reads, from the soft recurrence: e_t,
the probability of the demonstrated action under the running option continued and restarted, and
under the best other restarted option, and whether the parse's label (argmax p^c_t) there is no
longer the running option's (`handed_over`: the step went to another option; `ocn-eval`'s offsets
instead measure to the nearest predicted boundary). Steps are grouped, as in `ocn-eval`, by the demonstrated action
one step before the boundary step.

    python -m tools.boundary_probe --policy CKPT --root DIR [--split val] [--max-episodes 1200] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from envs.craft.world import ACTION_NAMES
from ocn_data.episodes_table import EpisodeArrays, load_episodes, split_episodes
from policies.ocn.modeling_ocn import OCNPolicy
from tools.episode_parsing import Processor, load_ocn, parsed_episodes
from tools.parsing_metrics import boundaries_from_labels

PROBE_KEYS = ("end", "option", "component_log_prob")
COLUMNS = ("boundaries", "handed_over", "end", "running_continued", "running_restarted", "best_other_restarted")


def probe_boundaries(
    policy: OCNPolicy, preprocessor: Processor, episodes: EpisodeArrays, batch_size: int = 1024
) -> dict[str, dict[str, float]]:
    """Per previous action (a string key, "-1" at step 0; "all" for every boundary), the number of
    inner true boundary steps and the means of COLUMNS' other quantities over them."""
    n_options = policy.config.n_options
    rows: list[tuple[int, list[float]]] = []
    parsed = parsed_episodes(policy, preprocessor, episodes, batch_size, PROBE_KEYS)
    for i, episode in enumerate(parsed):
        length = int(episodes.lengths[i])
        action_prob = np.exp(episode["component_log_prob"])
        for t in boundaries_from_labels(episodes.subtask_index[i, :length])[:-1]:
            if t == 0:
                continue  # a one-step first subtask: no option ran before its step
            running = int(episode["option"][t - 1])
            others = np.delete(action_prob[t, n_options:], running)
            rows.append((int(episodes.action[i, t - 1, 0]), [
                float(episode["option"][t] != running), float(episode["end"][t]), float(action_prob[t, running]),
                float(action_prob[t, n_options + running]), float(others.max()),
            ]))
    groups = {str(action): [values for a, values in rows if a == action] for action in sorted({a for a, _ in rows})}
    groups["all"] = [values for _, values in rows]
    return {key: {"boundaries": len(values), **dict(zip(COLUMNS[1:], np.mean(values, axis=0).round(4).tolist(),
                                                         strict=True))}
            for key, values in groups.items() if values}


def table(probe: dict[str, dict[str, float]], action_names: tuple[str, ...] | None = None) -> str:
    """The probe as a markdown table, one row per previous action."""
    lines = ["| previous action | " + " | ".join(COLUMNS) + " |", "|---" * (len(COLUMNS) + 1) + "|"]
    for key, row in probe.items():
        name = action_names[int(key)] if action_names and key.isdigit() else key
        lines.append(f"| {name} | " + " | ".join(f"{row[column]:g}" for column in COLUMNS) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", type=Path, required=True, help="an ocn pretrained_model folder")
    parser.add_argument("--root", type=Path, required=True, help="a record_demos dataset with subtask labels")
    parser.add_argument("--split", default="val", help="episodes read: a split of meta/info.json, or 'all'")
    parser.add_argument("--max-episodes", type=int, default=1200, help="the split's first episodes read")
    parser.add_argument("--out", type=Path, default=None, help="also write the probe as JSON here")
    args = parser.parse_args(argv)
    episodes = load_episodes(args.root, split_episodes(args.root, args.split), args.max_episodes)
    if episodes.action.shape[-1] != 1:
        raise ValueError(f"{args.root} has continuous actions; the probe groups boundaries by discrete ones (Craft).")
    policy, preprocessor, _ = load_ocn(args.policy)
    policy.eval()
    probe = probe_boundaries(policy, preprocessor, episodes)
    print(table(probe, ACTION_NAMES))
    result = {"policy": str(args.policy), "root": str(args.root), "split": args.split,
              "episodes": len(episodes.tasks), "by_previous_action": probe}
    if args.out:
        args.out.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
