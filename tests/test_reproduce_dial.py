"""`ocn-reproduce dial`: the affine split is the plain recipe and writes the headline set, the induced
split is the paper's loss and writes elsewhere; the checks use results/archive/dial_affine_2026-12-06's bars."""

from __future__ import annotations

import shlex

import pytest

from lerobot_policy_ocn.tools.bench.common import RESULTS
from lerobot_policy_ocn.tools.reproduce import dial, main
from lerobot_policy_ocn.tools.reproduce.finetune import CLONED
from lerobot_policy_ocn.tools.reproduce.runs import train_command


def _policy_flags(split: str, method: str) -> set[str]:
    model = CLONED[method].with_flags(**dial.SETTINGS[split].clone_flags)
    command = train_command(model.policy_type, "data", "local/dial2", "out", 20, 4, 1, model.flags)
    return {word for word in command if word.startswith("--policy.")} - {
        "--policy.type=ocn", "--policy.device=cpu", "--policy.push_to_hub=false"}


def test_the_affine_split_is_the_plain_recipe_and_induced_the_papers_loss():
    assert _policy_flags("affine", "ocn") == set()
    assert _policy_flags("affine", "moe") == {"--policy.hierarchy=moe"}
    assert _policy_flags("induced", "ocn") == {"--policy.recipe=paper", "--policy.n_options=4"}
    assert dial.SETTINGS["affine"].name == "dial" and dial.SETTINGS["induced"].name == "dial_induced"
    assert shlex.join(dial.SETTINGS["affine"].ppo) == "--gamma 0.995"


@pytest.mark.parametrize("results", [None, str(RESULTS)])
def test_the_induced_split_writes_no_headline_set(results, tmp_path):
    argv = ["dial", "--split", "induced", "--workdir", str(tmp_path)] + ([] if results is None else
                                                                         ["--results", results])
    with pytest.raises(SystemExit, match="no headline set"):
        main(argv)
    assert not any(tmp_path.iterdir())  # refused before anything was recorded


def test_the_five_checks():
    imitation = [{"seed": seed, "scores": {"f1_tol1": 0.96, "nmi": 0.83, "mean_success_rate": 0.99}} for seed in (1, 2)]
    summary = {f"{method} | sparse": {"at_budget": {"success": {"mean": value}}}
               for method, value in (("ocn", 0.92), ("moe", 0.0))}
    checks = dial.checks(imitation, summary)
    assert [check["check"] for check in checks] == [
        "OCN imitation: F1@1 >= 0.9", "OCN imitation: NMI >= 0.8", "OCN imitation: 2-digit success >= 0.8",
        "OCN, sparse: 3-digit success >= 0.7", "sparse: MoE's 3-digit success below OCN's"]
    assert all(check["holds"] for check in checks)
    assert all(check["holds"] is None for check in dial.checks([], {}))
