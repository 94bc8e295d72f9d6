"""OCN through LeRobot's own CLIs: `lerobot-train --policy.type=ocn` and `lerobot-eval --env.type=craft`.

One tiny dataset and one tiny training run are shared by the module; the CLIs run as real
subprocesses, the env config and the rollout plumbing in process.
"""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.envs.configs import EnvConfig
from lerobot.envs.factory import make_env, make_env_config
from lerobot.envs.utils import env_to_policy_features
from lerobot.scripts.lerobot_eval import rollout
from lerobot.utils.constants import ACTION, OBS_STATE
from torch import nn

from lerobot_policy_ocn.envs.craft import CraftEnv, CraftExpert, parse_task, task_description
from lerobot_policy_ocn.envs.craft.lerobot_config import CraftEnvConfig
from lerobot_policy_ocn.envs.craft.lerobot_env import action_index
from lerobot_policy_ocn.ocn_data.episodes_table import load_episodes, split_episodes
from lerobot_policy_ocn.ocn_data.record_demos import main as record_demos
from lerobot_policy_ocn.ocn import OCNPolicy
from lerobot_policy_ocn.tools.eval.parsing import load_policy
from conftest import run_cli

BIN = Path(sys.executable).parent
REPO_ID = "local/ocn_it"
STEPS = 4
AC = task_description(parse_task("AC"))  # "get wood, get iron"


def identity(x):
    return x


@pytest.fixture(scope="module")
def demos(tmp_path_factory) -> Path:
    """Root of a dataset of 12 demos of task AC."""
    root = tmp_path_factory.mktemp("lerobot") / "ds"
    args = ["--tasks", "AC", "--episodes-per-task", "12", "--root", str(root), "--repo-id", REPO_ID, "--seed", "1"]
    assert record_demos(args) == 0
    return root


def train(root: Path, base: Path, *extra: str) -> Path:
    """A few steps of `lerobot-train --policy.type=ocn` on `root`, logging every step into `base/train.log`;
    returns the final pretrained_model folder."""
    proc = run_cli(
        "lerobot-train",
        "--policy.type=ocn",
        f"--dataset.repo_id={REPO_ID}",
        f"--dataset.root={root}",
        "--policy.device=cpu",
        "--policy.push_to_hub=false",
        "--wandb.enable=false",
        "--env_eval_freq=0",
        f"--steps={STEPS}",
        "--batch_size=4",
        "--num_workers=0",
        "--policy.hidden_size=16",
        "--policy.mlp_hidden_size=16",
        "--log_freq=1",
        f"--output_dir={base / 'train'}",
        *extra,
        cwd=base,
    )
    (base / "train.log").write_text(proc.stdout + proc.stderr)
    return base / "train" / "checkpoints" / f"{STEPS:06d}" / "pretrained_model"


@pytest.fixture(scope="module")
def trained(demos) -> tuple[Path, Path]:
    """(dataset root, checkpoint) of a few steps of OCN training on `demos`."""
    return demos, train(demos, demos.parent)


def episode_batch(root: Path, episode: int) -> dict:
    """One whole episode as a batch of one: state [1, T, 81], action [1, T, 1] and its task string."""
    ds = LeRobotDataset(REPO_ID, root=root)
    table = ds.hf_dataset.with_format("numpy")
    rows = np.flatnonzero(np.asarray(table["episode_index"]) == episode)
    state = np.asarray(table["observation.state"])[rows]
    action = np.asarray(table["action"])[rows]
    return {
        OBS_STATE: torch.from_numpy(state).float()[None],
        ACTION: torch.from_numpy(action).float()[None],
        "task": [ds.meta.episodes[episode]["tasks"][0]],
    }


def test_train_checkpoint_reloads_identically(trained):
    root, checkpoint = trained
    assert (checkpoint / "model.safetensors").is_file() and (checkpoint / "config.json").is_file()
    first, second = OCNPolicy.from_pretrained(checkpoint), OCNPolicy.from_pretrained(checkpoint)
    assert first.config.tasks == second.config.tasks == [AC]
    longest = max(int(length) for length in LeRobotDataset(REPO_ID, root=root).meta.episodes["length"])
    assert first.config.hidden_size == 16 and first.config.window_size == longest
    assert (first.config.recipe, first.config.obs_encoder, first.config.n_actions) == ("craft", "craft", 5)

    batch = episode_batch(root, 0)
    assert batch["task"] == [AC]
    parsed_first, parsed_second = first.parse(batch), second.parse(batch)
    assert set(parsed_first) >= {"p_c", "option", "end", "mask", "action_log_prob"}
    assert parsed_first["p_c"].shape == (1, batch[OBS_STATE].shape[1], first.config.n_options)
    for key, value in parsed_first.items():
        torch.testing.assert_close(value, parsed_second[key], rtol=0, atol=0, msg=key)
    loss_first, _ = first.forward(batch)
    loss_second, _ = second.forward(batch)
    assert torch.isfinite(loss_first) and loss_first.item() > 0
    assert loss_first.item() == loss_second.item()


def test_moe_trains_through_lerobot_train_and_reloads_as_moe(demos, tmp_path):
    checkpoint = train(demos, tmp_path, "--policy.hierarchy=moe")
    policy = OCNPolicy.from_pretrained(checkpoint)
    assert policy.config.hierarchy == "moe" and policy.core.skill_length == 1 and policy.config.tasks == [AC]
    batch = episode_batch(demos, 0)
    assert torch.equal(policy.parse(batch)["end"], torch.ones(1, batch[OBS_STATE].shape[1]))
    loss, stats = policy.forward(batch)
    assert torch.isfinite(loss) and stats["mean_end"] == 1.0


def test_plain_lerobot_train_trains_the_craft_recipe_and_settles_in_its_final_steps(trained):
    log = (trained[0].parent / "train.log").read_text()
    phases = [float(value) for value in re.findall(r"final_phase:([0-9.]+)", log)]
    # 4 steps: the final sixth, rounded, is the last step, which adds the settling cost.
    assert phases == [0.0, 0.0, 0.0, 1.0]
    assert "settle_penalty" in log.splitlines()[[i for i, line in enumerate(log.splitlines())
                                                   if "final_phase:1.000" in line][0]]
    assert "Effective batch size: 4 x 1 = 4" in log


def test_the_policy_trains_on_the_whole_episodes_of_the_frames_lerobot_samples(demos):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy
    from lerobot_policy_ocn.ocn import OCNConfig

    meta = LeRobotDatasetMetadata(REPO_ID, root=demos)
    policy = make_policy(OCNConfig(device="cpu", hidden_size=8, mlp_hidden_size=8), ds_meta=meta)
    train_split, val_split = split_episodes(demos, "train"), split_episodes(demos, "val")
    frames = LeRobotDataset(REPO_ID, root=demos)  # single frames: the policy asks for no windows
    picked = [frames[int(meta.episodes["dataset_from_index"][episode]) + 2] for episode in (train_split[1], 0)]
    batch = torch.utils.data.default_collate(picked)
    assert batch[OBS_STATE].shape == (2, 81)
    policy.eval()  # every episode counts outside training
    mask, state, action, tasks, _ = policy.training_windows(batch)
    for row, episode in enumerate((train_split[1], 0)):
        whole = episode_batch(demos, episode)
        length = whole[OBS_STATE].shape[1]
        assert mask[row].sum() == length and tasks[row] == whole["task"][0]
        torch.testing.assert_close(state[row, :length].float(), whole[OBS_STATE][0])
        torch.testing.assert_close(action[row, :length].float(), whole[ACTION][0].reshape(-1))
    policy.train()
    held_out = torch.utils.data.default_collate(
        [frames[int(meta.episodes["dataset_from_index"][val_split[0]])]] * 2 + picked[:1])
    mask, *_ = policy.training_windows(held_out)
    assert mask.shape[0] == 1  # the dataset's val split leaves the training batch


def test_ocn_eval_scores_a_hil_checkpoint(trained, tmp_path):
    """A HIL checkpoint is an OCN checkpoint with `hierarchy="hil"` (same layout): the trained OCN's
    weights under HIL's schedule, saved with its processors, parse and roll out through ocn-eval."""
    from lerobot_policy_ocn.tools.eval.parsing import load_ocn
    from lerobot_policy_ocn.tools.cli.ocn_eval import main as ocn_eval
    from lerobot_policy_ocn.tools.rl.finetuning import save_checkpoint

    root, checkpoint = trained
    source, preprocessor, postprocessor = load_ocn(checkpoint)
    hil = OCNPolicy(dataclasses.replace(source.config, hierarchy="hil", skill_length=3, pretrained_path=None))
    hil.load_state_dict(source.state_dict())
    save_checkpoint(hil, preprocessor, postprocessor, tmp_path / "hil")
    policy = OCNPolicy.from_pretrained(tmp_path / "hil")
    assert policy.config.hierarchy == "hil" and policy.core.skill_length == 3
    batch = episode_batch(root, 0)
    parsed = policy.parse(batch)
    scheduled = torch.arange(batch[OBS_STATE].shape[1]) % 3 == 0
    assert torch.equal(parsed["end"][0], scheduled.float())
    switched = torch.cat([torch.tensor([True]), parsed["option"][0, 1:] != parsed["option"][0, :-1]])
    assert not (switched & ~scheduled).any()  # p^c, so the option, only changes where a skill starts
    out = tmp_path / "eval.json"
    assert ocn_eval(["--policy", str(tmp_path / "hil"), "--root", str(root), "--repo-id", REPO_ID, "--out", str(out),
                     "--rollouts", "2"]) == 0
    result = json.loads(out.read_text())
    assert 0.0 <= result["f1_tol0"] <= result["f1_tol1"] <= 1.0 and list(result["success_rate"]) == [AC]
    # HIL's options have no termination of their own for the oracle to decide at, but it can switch
    # where the env's subtask completes.
    oracle_args = ["--policy", str(tmp_path / "hil"), "--root", str(root), "--repo-id", REPO_ID,
                   "--out", str(tmp_path / "oracle.json"), "--oracle-tasks", "CA", "--rollouts", "2"]
    assert ocn_eval(oracle_args) == 2
    assert ocn_eval([*oracle_args, "--oracle-switch", "progress"]) == 0
    oracle = json.loads((tmp_path / "oracle.json").read_text())["oracle_controller"]
    assert oracle["switch"] == "progress" and list(oracle["success_rate"]) == ["CA"]


def test_lerobot_eval_counts_the_episode(trained):
    _, checkpoint = trained
    out = checkpoint.parents[3] / "eval"
    run_cli(
        "lerobot-eval",
        f"--policy.path={checkpoint}",
        "--env.type=craft",
        "--env.task=AC",
        "--eval.n_episodes=1",
        "--eval.batch_size=1",
        "--policy.device=cpu",
        f"--output_dir={out}",
        cwd=checkpoint.parents[3],
    )
    info = json.loads((out / "eval_info.json").read_text())
    overall = info["overall"]
    assert overall["n_episodes"] == 1
    assert overall["pc_success"] in (0.0, 100.0)
    assert 0.0 <= overall["avg_sum_reward"] <= 2.0
    metrics = info["per_task"][0]["metrics"]
    assert info["per_task"][0]["task_group"] == "craft"
    assert len(metrics["successes"]) == len(metrics["sum_rewards"]) == 1
    assert Path(metrics["video_paths"][0]).is_file()


def test_unknown_task_names_the_known_ones(trained):
    _, checkpoint = trained
    policy = OCNPolicy.from_pretrained(checkpoint)
    vec = make_env(make_env_config("craft", task="CD"), n_envs=1)["craft"][0]
    with pytest.raises(ValueError, match=r"Unknown task 'get iron, get grass'.*'get wood, get iron'"):
        rollout(vec, policy, identity, identity, identity, identity, seeds=[0])
    vec.close()


def test_config_features_and_registration():
    cfg = make_env_config("craft")
    assert isinstance(cfg, CraftEnvConfig) and EnvConfig.get_choice_class("craft") is CraftEnvConfig
    fields = (cfg.type, cfg.task, cfg.mode, cfg.reward, cfg.max_steps, cfg.fps)
    assert fields == ("craft", "AC", "paper", "dense", None, 10)
    assert env_to_policy_features(cfg) == {
        ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(1,)),
        OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(81,)),
    }


def test_gym_kwargs_reach_every_sub_env():
    cfg = make_env_config("craft", task="ACD", mode="full", reward="sparse", max_steps=7)
    expected = {"task": "ACD", "mode": "full", "reward": "sparse", "max_steps": 7, "render_mode": "rgb_array"}
    assert cfg.gym_kwargs == expected
    vec = make_env(cfg, n_envs=2)["craft"][0]
    assert vec.call("_max_episode_steps") == (7, 7)
    assert vec.call("task_description") == (task_description(parse_task("ACD")),) * 2
    craft = vec.envs[1].unwrapped
    assert (craft.task, craft.mode, craft.batch.reward) == ("ACD", "full", "sparse")
    assert craft.render_mode == "rgb_array"
    obs, _ = vec.reset(seed=[3, 4])
    np.testing.assert_array_equal(obs["agent_pos"][1], CraftEnv("ACD", mode="full").reset(seed=4)[0])
    assert vec.envs[0].render().shape == (160, 160, 3)
    vec.close()
    default = make_env(make_env_config("craft", task="ACD"), n_envs=1)["craft"][0]
    assert default.call("_max_episode_steps") == (100,)  # the env's own limit for three subtasks
    default.close()


def test_action_casting():
    assert action_index(np.array([3.0], dtype=np.float32)) == 3
    assert action_index(np.int64(0)) == 0
    for bad in (2.5, -1.0, 5.0, float("nan")):
        with pytest.raises(ValueError, match=r"integer indices in \[0, 4\] \(down, up, left, right, use\); got"):
            action_index(np.array([bad]))
    with pytest.raises(ValueError, match=r"one action index per step, got an action of shape \(2,\)"):
        action_index(np.array([1.0, 2.0]))
    vec = make_env(make_env_config("craft"), n_envs=2)["craft"][0]
    vec.reset(seed=0)
    with pytest.raises(ValueError, match="got 0.5"):
        vec.step(np.array([[1.0], [0.5]], dtype=np.float32))
    vec.close()


class ExpertPolicy(nn.Module):
    """The scripted expert behind LeRobot's policy interface, acting in each sub-env's own batch."""

    def __init__(self, vec) -> None:
        super().__init__()
        self.vec = vec
        self.experts: list[CraftExpert] | None = None

    def reset(self) -> None:
        self.experts = None

    def select_action(self, observation: dict) -> torch.Tensor:
        assert observation["task"] == [AC] * self.vec.num_envs
        assert observation[OBS_STATE].shape == (self.vec.num_envs, 81)
        if self.experts is None:
            self.experts = [CraftExpert(env.unwrapped.batch) for env in self.vec.envs]
        return torch.tensor([[float(expert.act()[0])] for expert in self.experts])


def test_rollout_counts_successes_and_rewards_once():
    """Episodes of different lengths under same-step autoreset: each success counted, and a finished
    sub-env stays on its last state (no new episode leaks into the step lerobot-eval still keeps)."""
    vec = make_env(make_env_config("craft", task="AC"), n_envs=3)["craft"][0]
    for seeds in ([0, 1, 2], [5, 6, 7]):
        out = rollout(
            vec, ExpertPolicy(vec), identity, identity, identity, identity, seeds=seeds, return_observations=True
        )
        done_at = out["done"].int().argmax(1)
        assert len(set(done_at.tolist())) > 1  # the sub-envs really finish at different steps
        keep = torch.arange(out["done"].shape[1]) <= (done_at + 1)[:, None]  # lerobot-eval's mask
        assert (out["success"] & keep).any(1).all()
        torch.testing.assert_close((out["reward"] * keep).sum(1), torch.full((3,), 2.0, dtype=torch.float64))
        states = out["observation"][OBS_STATE]  # [3, steps + 1, 81]; index t + 1 follows action t
        for i, end in enumerate(done_at.tolist()):
            assert states[i, end].ne(states[i, end + 1]).any()  # the last action changed the state
            assert (states[i, end + 1 :] == states[i, end + 1]).all()  # then it stays frozen
    vec.close()


def test_ocn_eval_scores_the_checkpoint_on_the_validation_split(trained, tmp_path):
    root, checkpoint = trained
    out = tmp_path / "eval.json"
    run_cli(
        "ocn-eval", "--policy", str(checkpoint), "--root", str(root), "--repo-id", REPO_ID,
        "--out", str(out), "--rollouts", "3", "--oracle-tasks", "CA", cwd=tmp_path,
    )
    result = json.loads(out.read_text())
    oracle = result["oracle_controller"]
    assert set(oracle["option_of_subtask"]) == {"A", "C"} and set(oracle["option_of_subtask"].values()) <= {0, 1, 2}
    assert list(oracle["success_rate"]) == ["CA"] and 0.0 <= oracle["mean_success_rate"] <= 1.0
    for key in ("f1_tol0", "f1_tol1", "align_acc", "nmi", "mean_success_rate"):
        assert 0.0 <= result[key] <= 1.0, key
    assert result["f1_tol1"] >= result["f1_tol0"]
    info = json.loads((root / "meta" / "info.json").read_text())
    start, stop = map(int, info["splits"]["val"].split(":"))
    assert result["episodes_parsed"] == stop - start
    table = result["option_subtask_success"]
    assert table["subtasks"] == ["A", "C"] and np.array(table["table"]).shape == (3, 2)
    assert list(result["success_rate"]) == [AC]
    assert out.with_suffix(".png").read_bytes()[:4] == b"\x89PNG"
    # action_nll, from the parse, is the frame-weighted mean of the paper's loss per episode (the NLL alone).
    policy, preprocessor, _ = load_policy(checkpoint)
    policy.config.recipe = "paper"
    episodes = load_episodes(root, split_episodes(root, "val"))
    batch = preprocessor({
        OBS_STATE: torch.from_numpy(episodes.state).float(), ACTION: torch.from_numpy(episodes.action).float(),
        f"{ACTION}_is_pad": torch.from_numpy(~episodes.mask), "task": list(episodes.tasks),
    })
    with torch.no_grad():
        per_window, _ = policy(batch, reduction="none")
    frames = torch.from_numpy(episodes.lengths).float()
    assert result["action_nll"] == pytest.approx(float((per_window * frames).sum() / frames.sum()), rel=1e-4)


def test_ocn_eval_names_bad_input(trained, tmp_path, capsys):
    root, checkpoint = trained
    proc = subprocess.run(
        [str(BIN / "ocn-eval"), "--policy", str(tmp_path), "--root", str(root), "--repo-id", REPO_ID,
         "--out", str(tmp_path / "x.json")],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 2 and "config.json" in proc.stderr
    proc = subprocess.run(
        [str(BIN / "ocn-eval"), "--policy", str(checkpoint), "--root", str(root), "--repo-id", REPO_ID,
         "--split", "test", "--out", str(tmp_path / "x.json")],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 2 and "no split 'test'" in proc.stderr
    from lerobot_policy_ocn.tools.cli.ocn_eval import main as ocn_eval

    args = ["--policy", str(checkpoint), "--root", str(root), "--repo-id", REPO_ID, "--out", str(tmp_path / "o.json")]
    assert ocn_eval([*args, "--oracle-tasks", "AD"]) == 2  # D is no subtask of the dataset's AC
    assert "subtask(s) ['D']" in capsys.readouterr().err and not (tmp_path / "o.json").exists()
