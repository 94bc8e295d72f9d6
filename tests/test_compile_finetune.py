"""compILE's RL form through `ocn-finetune`: the frozen decoder's latents as one-step options under a
fresh controller, the finetuned `ocn` checkpoint, `lerobot-eval` on it, and what is refused."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from lerobot_policy_ocn.envs.craft.batch import CraftBatch
from lerobot_policy_ocn.envs.craft.world import parse_task, task_description
from lerobot_policy_ocn.compile import CompILEPolicy
from test_ocn_finetune import assert_refused, decisions_match_frames, hard_rollout, save_variant, variant
from lerobot_policy_ocn.tools.eval.parsing import load_ocn, load_policy
from lerobot_policy_ocn.tools.cli.ocn_finetune import main
from lerobot_policy_ocn.tools.rl.finetuning import compile_latent_options, merge_option_pools

torch.set_num_threads(1)

ADC = task_description(parse_task("ADC"))
LATENTS = 4  # conftest's compile_checkpoint


def decoder_weights(policy: CompILEPolicy) -> list[torch.Tensor]:
    """A compILE decoder's parameters in `LatentDecoderPool`'s stacked layout (one decoder)."""
    obs, latent, out = policy.decoder_obs, policy.decoder_latent, policy.decoder_out
    return [obs.weight.T, obs.bias[None], latent.weight.T, out.weight.T, out.bias[None]]


@pytest.fixture(scope="module")
def second_compile(compile_checkpoint, tmp_path_factory) -> Path:
    """Another compILE of the same shape (S2's second model)."""
    return save_variant(compile_checkpoint, tmp_path_factory.mktemp("compile2") / "pretrained_model", seed=7)


@pytest.fixture(scope="module")
def finetuned(compile_checkpoint, second_compile, tmp_path_factory) -> Path:
    """ocn-finetune over the merged latents of both compILE decoders (S2's form: 4 + 4 options)."""
    out = tmp_path_factory.mktemp("compile_finetune") / "run"
    args = ["--checkpoint", str(compile_checkpoint), "--checkpoint", str(second_compile), "--tasks", "ADC,CAD",
            "--reward", "dense", "--frames", "400", "--envs", "4", "--max-steps", "20", "--seed", "1",
            "--batch-size", "32", "--out", str(out)]
    assert main(args) == 0
    return out


def test_each_option_acts_exactly_as_its_decoder_with_that_latent(compile_checkpoint):
    first, _, _ = load_policy(compile_checkpoint)
    second = variant(compile_checkpoint, seed=11)
    pool = merge_option_pools([compile_latent_options(c, name) for c, name in ((first, "a"), (second, "b"))], [ADC])
    config = pool.config
    assert (config.n_options, config.decoder_latents, config.hierarchy, config.execution) == (8, 4, "moe", "hard")
    assert config.temperature == 1.0 and config.hidden_size == first.config.hidden_size
    obs = torch.from_numpy(CraftBatch(6).reset(seeds=range(6), tasks=["ADC"] * 6)).float()
    with torch.no_grad():
        pooled = pool.core.options(pool.encoder(obs), pool.core.option_init.unsqueeze(1))
        for d, decoder in enumerate((first, second)):
            latents = torch.eye(LATENTS).unsqueeze(1).expand(-1, 6, -1)
            own = decoder._decode(decoder.encoder(obs).unsqueeze(1), latents).squeeze(2)  # [K, B, actions]
            options = slice(d * LATENTS, (d + 1) * LATENTS)
            torch.testing.assert_close(pooled.logits[options], own, rtol=0, atol=1e-6)
            for k in range(LATENTS):
                option = torch.full((6,), d * LATENTS + k)
                action, _, end = pool.act_with_options(obs, option, None, torch.ones(6, dtype=torch.bool), greedy=True)
                assert torch.equal(action[:, 0].long(), own[k].argmax(-1)) and not end.any()


def test_finetuning_keeps_both_decoders_bit_identical_and_chooses_every_step(finetuned, compile_checkpoint,
                                                                             second_compile):
    with open(finetuned / "curve.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert rows and {"frames", "mean_return", "success", "success[ADC]", "success[CAD]"} <= set(rows[0])
    assert int(rows[-1]["frames"]) >= 400 and (finetuned / "curve.png").stat().st_size > 0
    assert decisions_match_frames(finetuned)
    summary = json.loads((finetuned / "finetune.json").read_text())
    assert (summary["n_options"], summary["decoder_latents"], summary["hierarchy"]) == (8, 4, "moe")

    policy, _, _ = load_ocn(finetuned / "pretrained_model")
    sources = [load_policy(path)[0] for path in (compile_checkpoint, second_compile)]
    stacked = [torch.stack(weights) for weights in zip(*map(decoder_weights, sources), strict=True)]
    pool = policy.core.options
    for name, param, expected in zip(("obs_weight", "obs_bias", "latent_weight", "out_weight", "out_bias"),
                                     (pool.obs_weight, pool.obs_bias, pool.latent_weight, pool.out_weight,
                                      pool.out_bias), stacked, strict=True):
        assert torch.equal(param, expected), name
    assert not torch.equal(policy.core.controller_init, torch.zeros_like(policy.core.controller_init))
    decided = hard_rollout(finetuned / "pretrained_model", ["ADC", "CAD"], max_steps=6)
    assert all(rows.all() for rows in decided)


def test_lerobot_eval_runs_an_episode_of_the_finetuned_checkpoint(finetuned):
    out = finetuned.parent / "eval"
    command = [str(Path(sys.executable).with_name("lerobot-eval")), f"--policy.path={finetuned / 'pretrained_model'}",
               "--env.type=craft", "--env.task=ADC", "--env.max_steps=20", "--eval.n_episodes=1",
               "--eval.batch_size=1", "--policy.device=cpu", f"--output_dir={out}"]
    proc = subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=finetuned.parent)
    assert proc.returncode == 0, proc.stderr[-4000:]
    overall = json.loads((out / "eval_info.json").read_text())["overall"]
    assert overall["n_episodes"] == 1 and overall["pc_success"] in (0.0, 100.0)


def test_gaussian_latents_and_mixed_pools_are_refused(compile_checkpoint, ocn_checkpoint, tmp_path, capsys):
    gaussian = save_variant(compile_checkpoint, tmp_path / "gaussian" / "pretrained_model", seed=3,
                                    latent_type="gaussian")
    base = ["--tasks", "ADC", "--frames", "10", "--envs", "2"]
    cases = {
        "needs a compILE trained with --policy.latent_type=concrete": [*base, "--checkpoint", str(gaussian),
                                                                       "--out", str(tmp_path / "a")],
        "Cannot pool OCN options with compILE decoders' latents": [
            *base, "--checkpoint", str(ocn_checkpoint), "--checkpoint", str(compile_checkpoint),
            "--out", str(tmp_path / "b")],
    }
    assert_refused(cases, capsys)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_a_decoder_pool_needs_one_step_options():
    from lerobot_policy_ocn.ocn import OCNConfig

    with pytest.raises(ValueError, match="need hierarchy='moe' and n_options a multiple of decoder_latents"):
        OCNConfig(device="cpu", recipe="paper", n_options=6, decoder_latents=4, hierarchy="moe")
    with pytest.raises(ValueError, match="got 'ocn' and 4"):
        OCNConfig(device="cpu", recipe="paper", n_options=4, decoder_latents=4)
    assert OCNConfig(device="cpu", n_options=8, decoder_latents=4, hierarchy="moe").decoder_latents == 4
