"""Training in several processes: the losses are the global batch's, and LeRobot's own launch trains OCN.

Under DDP each process computes the loss of its shard and the gradients are averaged. The policies'
statistics over the batch (episode means, frame means, the usage balance) are the global batch's
only when their sums run over every shard (`lerobot_policy_ocn.distributed`). The in-process test runs two
gloo processes that each take an uneven shard of one batch (as held-out episodes leave a shard) and
checks that the average of their gradients is the gradient of the whole batch in one process, for
every loss the policies train; a plain per-shard mean is the control that must differ. The
end-to-end test runs `torchrun ... lerobot-train` on 2 processes against one process with the same
global batch and seed, and evaluates the 2-process checkpoint with `lerobot-eval`.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch import Tensor, nn

from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_STATE

from lerobot_policy_ocn.tools.bench.common import run_timed

TASKS = ["task a", "task b"]
STATE_DIM = 5
LENGTHS = [6, 3, 5, 2, 4]  # episode lengths of the batch; the shards below hold 3 and 2 of them
SHARDS = ([0, 1, 2], [3, 4])
WORLD = len(SHARDS)


def _features(action_dim: int) -> dict:
    return {"input_features": {OBS_STATE: PolicyFeature(FeatureType.STATE, (STATE_DIM,))},
            "output_features": {ACTION: PolicyFeature(FeatureType.ACTION, (action_dim,))}}


def _episodes(continuous: bool) -> dict:
    """Whole episodes from their first frame, of `LENGTHS` real frames, padded to the longest."""
    gen = torch.Generator().manual_seed(3)
    batch, steps = len(LENGTHS), max(LENGTHS)
    action = (torch.randn(batch, steps, 2, generator=gen) if continuous
              else torch.randint(0, 4, (batch, steps, 1), generator=gen).float())
    return {OBS_STATE: torch.randn(batch, steps, STATE_DIM, generator=gen), ACTION: action,
            f"{ACTION}_is_pad": torch.arange(steps)[None] >= torch.tensor(LENGTHS)[:, None],
            "task": [TASKS[i % 2] for i in range(batch)]}


def _rows(batch: dict, rows: list[int]) -> dict:
    """The episodes `rows` of a batch, trimmed to the longest of them (a shard's windows are its own)."""
    steps = max(LENGTHS[i] for i in rows)
    return {key: [value[i] for i in rows] if key == "task" else value[rows, :steps] for key, value in batch.items()}


def _ocn(**settings) -> nn.Module:
    from lerobot_policy_ocn.ocn import OCNConfig, OCNPolicy

    torch.manual_seed(0)
    config = OCNConfig(device="cpu", obs_encoder="identity", n_actions=4, n_options=3, hidden_size=8,
                       mlp_hidden_size=8, tasks=list(TASKS), **settings)
    return OCNPolicy(config)


def _craft_recipe(final_phase: bool) -> tuple[nn.Module, Callable[[list[int]], Tensor]]:
    """OCN's Craft recipe (usage balance, expected NLL; in the final phase the settling cost), on its clock."""
    from lerobot_policy_ocn.schedules import PhaseScheduleConfig

    policy = _ocn(recipe="craft", action_type="discrete", **_features(1))
    clock = PhaseScheduleConfig().build(torch.optim.SGD(policy.parameters(), lr=0.1), 6)
    clock.last_epoch = 5 if final_phase else 0  # the recipe's final sixth of 6 steps is the last one
    batch = _episodes(continuous=False)
    return policy, lambda rows: policy.forward(_rows(batch, rows))[0]


def _taught(hierarchy: str) -> tuple[nn.Module, Callable[[list[int]], Tensor]]:
    """The taught loss (`labelled_forward`) on labels that switch mid-episode, -1 on padding."""
    policy = _ocn(recipe="dial", action_type="continuous", hierarchy=hierarchy, **_features(2))
    batch = _episodes(continuous=True)
    steps = torch.arange(max(LENGTHS))[None]
    option = torch.where(steps < torch.tensor(LENGTHS)[:, None], (steps + torch.arange(5)[:, None]) // 3 % 3, -1)
    weight = 5.0 if hierarchy == "ocn" else 1.0

    def loss(rows: list[int]) -> Tensor:
        shard = _rows(batch, rows)
        return policy.labelled_forward(shard, option[rows, :shard[OBS_STATE].shape[1]], weight)[0]

    return policy, loss


def _ompn() -> tuple[nn.Module, Callable[[list[int]], Tensor]]:
    from lerobot_policy_ocn.ompn import OMPNConfig, OMPNPolicy

    torch.manual_seed(0)
    policy = OMPNPolicy(OMPNConfig(device="cpu", obs_encoder="identity", action_type="discrete", n_actions=4,
                                   hidden_size=8, cell_hidden_size=8, tasks=list(TASKS), **_features(1)))
    batch = _episodes(continuous=False)
    return policy, lambda rows: policy.forward(_rows(batch, rows))[0]


def _compile() -> tuple[nn.Module, Callable[[list[int]], Tensor]]:
    """compILE's loss with argmax samples (eval mode), so that the shards draw no noise of their own."""
    from lerobot_policy_ocn.compile import CompILEConfig, CompILEPolicy

    torch.manual_seed(0)
    policy = CompILEPolicy(CompILEConfig(device="cpu", obs_encoder="identity", action_type="discrete", n_actions=4,
                                         hidden_size=8, latent_dim=3, tasks=list(TASKS), **_features(1))).eval()
    batch = _episodes(continuous=False)
    return policy, lambda rows: policy.forward(_rows(batch, rows))[0]


def _squared_global_sum() -> tuple[nn.Module, Callable[[list[int]], Tensor]]:
    """`global_sum` alone: (sum over the batch of w . x)^2, a function of the whole batch's sum."""
    from lerobot_policy_ocn.distributed import global_sum

    torch.manual_seed(0)
    layer, x = nn.Linear(STATE_DIM, 1, bias=False), torch.randn(len(LENGTHS), STATE_DIM)
    return layer, lambda rows: global_sum(layer(x[rows]).sum()).square()


def _per_shard_mean() -> tuple[nn.Module, Callable[[list[int]], Tensor]]:
    """The control: a plain mean over the shard's episode losses, which is not the global batch's."""
    policy = _ocn(recipe="paper", action_type="discrete", **_features(1))
    batch = _episodes(continuous=False)
    return policy, lambda rows: policy.forward(_rows(batch, rows), reduction="none")[0].mean()


CASES: dict[str, Callable[[], tuple[nn.Module, Callable[[list[int]], Tensor]]]] = {
    "ocn craft recipe": lambda: _craft_recipe(final_phase=False),
    "ocn craft recipe, final phase": lambda: _craft_recipe(final_phase=True),
    "ocn taught": lambda: _taught("ocn"),
    "moe taught": lambda: _taught("moe"),
    "ompn": _ompn,
    "compile": _compile,
    "global_sum": _squared_global_sum,
    "per-shard mean (control)": _per_shard_mean,
}


def _loss_and_gradients(case: str, rows: list[int]) -> tuple[Tensor, list[Tensor]]:
    module, loss_of = CASES[case]()
    loss = loss_of(rows)
    loss.backward()
    return loss.detach(), [p.grad if p.grad is not None else torch.zeros_like(p) for p in module.parameters()]


def _shard_worker(rank: int, rendezvous: str, out: str) -> None:
    """One of `WORLD` gloo processes: each case's loss and gradients on shard `rank`, averaged over the
    processes as DDP averages them (rank 0 saves them to `out`)."""
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{rendezvous}", rank=rank, world_size=WORLD)
    averaged = {}
    for case in CASES:
        loss, grads = _loss_and_gradients(case, SHARDS[rank])
        for tensor in (loss, *grads):
            dist.all_reduce(tensor)
            tensor /= WORLD
        averaged[case] = (loss, grads)
    if rank == 0:
        torch.save(averaged, out)
    dist.destroy_process_group()


@pytest.fixture(scope="module")
def shard_results(tmp_path_factory) -> dict:
    tmp = tmp_path_factory.mktemp("ddp")
    out = tmp / "averaged.pt"
    mp.spawn(_shard_worker, args=(str(tmp / "rendezvous"), str(out)), nprocs=WORLD, join=True)
    return torch.load(out)


@pytest.mark.parametrize("case", [case for case in CASES if "control" not in case])
def test_two_shards_average_to_the_whole_batchs_loss_and_gradient(shard_results, case):
    """DDP's average over 2 gloo processes of uneven shards (3 episodes of up to 6 frames, 2 of up to 4)
    equals one process on the whole batch: the loss to 1e-5, every gradient to 1e-5 relative."""
    torch.set_num_threads(1)
    loss, grads = _loss_and_gradients(case, [row for shard in SHARDS for row in shard])
    shard_loss, shard_grads = shard_results[case]
    torch.testing.assert_close(shard_loss, loss, rtol=1e-5, atol=1e-6)
    assert any(grad.abs().sum() > 0 for grad in grads)
    for shard_grad, grad in zip(shard_grads, grads, strict=True):
        torch.testing.assert_close(shard_grad, grad, rtol=1e-5, atol=1e-6)


def test_a_per_shard_mean_is_not_the_global_batchs(shard_results):
    """The control: the shards are uneven enough that a plain mean over each one gives another loss."""
    loss, _ = _loss_and_gradients("per-shard mean (control)", [row for shard in SHARDS for row in shard])
    assert abs(shard_results["per-shard mean (control)"][0] - loss) > 1e-3


@pytest.mark.parametrize("n_modules", [1, 3])
def test_side_by_side_is_the_same_matrix_and_hands_back_gradients_in_the_weights_layout(n_modules):
    """The stacked weights as one matrix: the same values as the transposed stack, the same gradient, and
    that gradient in the weight's own strides (what DDP's buckets expect; the controller has N = 1)."""
    from lerobot_policy_ocn.ocn.cell import side_by_side

    weight = nn.Parameter(torch.randn(n_modules, 7, 5))
    transposed = nn.Parameter(weight.detach().clone())
    x, upstream = torch.randn(4, 7), torch.randn(4, n_modules * 5)
    matrix = side_by_side(weight)
    assert torch.equal(matrix, transposed.transpose(0, 1).reshape(7, n_modules * 5))
    (x @ matrix).backward(upstream)
    (x @ transposed.transpose(0, 1).reshape(7, n_modules * 5)).backward(upstream)
    assert torch.equal(weight.grad, transposed.grad)
    assert weight.grad.stride() == weight.stride()


def test_every_ocn_gradient_has_its_parameters_strides():
    policy, loss_of = _craft_recipe(final_phase=False)
    loss_of(list(range(len(LENGTHS)))).backward()
    for name, parameter in policy.named_parameters():
        assert parameter.grad is not None and parameter.grad.stride() == parameter.stride(), name


def _train(root: Path, out: Path, processes: int, steps: int, global_batch: int) -> str:
    """`lerobot-train --policy.type=ocn` with `processes` gloo processes through torchrun (one: plainly),
    `global_batch` windows a step in all; returns its log."""
    bin_dir = Path(sys.executable).parent
    train = [str(bin_dir / "lerobot-train"), "--policy.type=ocn", "--policy.device=cpu", "--dataset.repo_id=local/ddp",
             f"--dataset.root={root}", f"--steps={steps}", f"--batch_size={global_batch // processes}",
             f"--output_dir={out}", "--seed=1", "--wandb.enable=false", "--policy.push_to_hub=false",
             "--env_eval_freq=0", "--num_workers=0", "--log_freq=1"]
    launch = [str(bin_dir / "torchrun"), "--standalone", f"--nproc_per_node={processes}"] if processes > 1 else []
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return run_timed([*launch, *train], cwd=out.parent, env=env, ends_at="End of training")[1]


def _logged(log: str, key: str) -> list[float]:
    return [float(value) for value in re.findall(rf" {key}:([-0-9.]+)", log)]


def test_torchrun_trains_ocn_in_two_processes_as_one_with_the_same_global_batch(tmp_path):
    """2 gloo processes of batch 4 against one of batch 8, same seed, 4 steps on a recorded dataset with a
    held-out split: the same loss at every logged step (3 decimals) and on the validation episodes
    afterwards (to 1e-4), weights within 1e-4 (measured: 1e-5; per-shard means: 6e-3), the final phase at
    the same step, no grad-stride warning; the checkpoint plays in `lerobot-eval`."""
    from lerobot_policy_ocn.ocn_data.record_demos import main as record_demos
    from safetensors.torch import load_file

    from lerobot_policy_ocn.tools.eval.parsing import validation_nll

    root = tmp_path / "ds"
    assert record_demos(["--tasks", "AC,CD,DA", "--episodes-per-task", "6", "--root", str(root), "--repo-id",
                         "local/ddp", "--seed", "5"]) == 0
    assert json.loads((root / "meta" / "info.json").read_text())["splits"]["val"]  # a shard loses its val frames
    one, two = _train(root, tmp_path / "one", 1, 4, 8), _train(root, tmp_path / "two", 2, 4, 8)
    assert "Effective batch size: 8 x 1 = 8" in one and "Effective batch size: 4 x 2 = 8" in two
    assert "Grad strides do not match" not in two
    assert len(_logged(two, "loss")) == 4
    for key in ("loss", "final_phase"):
        assert _logged(two, key) == pytest.approx(_logged(one, key), abs=1.5e-3), key
    checkpoints = [tmp_path / run / "checkpoints" / "last" / "pretrained_model" for run in ("one", "two")]
    weights = [load_file(path / "model.safetensors") for path in checkpoints]
    for name, value in weights[0].items():
        torch.testing.assert_close(weights[1][name], value, rtol=0, atol=1e-4, msg=name)
    assert validation_nll(checkpoints[1], root) == pytest.approx(validation_nll(checkpoints[0], root), abs=1e-4)

    eval_dir = tmp_path / "eval"
    proc = subprocess.run(
        [str(Path(sys.executable).parent / "lerobot-eval"), f"--policy.path={checkpoints[1]}", "--env.type=craft",
         "--env.task=AC", "--eval.n_episodes=2", "--eval.batch_size=2", "--eval.use_async_envs=false",
         "--policy.device=cpu", f"--output_dir={eval_dir}"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert json.loads((eval_dir / "eval_info.json").read_text())["overall"]["n_episodes"] == 2
