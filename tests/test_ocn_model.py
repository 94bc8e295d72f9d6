"""Tests of the OCN policy: cell, recurrence (eq. 8-17), loss, inference state, LeRobot plumbing."""

import math

import pytest
import torch
from torch.nn import functional as F

from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_STATE
from lerobot_policy_ocn.ocn import OCNConfig, OCNPolicy, make_ocn_pre_post_processors
from lerobot_policy_ocn.ocn.cell import StackedCell, side_by_side, stacked_linear
from lerobot_policy_ocn.ocn.configuration_ocn import RECIPE_TABLE
from lerobot_policy_ocn.ocn.heads import DiscreteHead, GaussianHead, expected_log_prob, mixture_log_prob, sample_index
from lerobot_policy_ocn.ocn.modeling_ocn import settle_penalty, usage_imbalance
from lerobot_policy_ocn.ocn.recurrence import OCNState, StepOutput
from lerobot_policy_ocn.tools.bench.models import use_looped_cells

torch.set_num_threads(1)

TASKS = ["make plank", "get gold"]
STATE_DIM = 6
N_OPTIONS = 3


def make_policy(action_type: str = "discrete", action_dim: int = 1, **overrides) -> OCNPolicy:
    settings = dict(
        device="cpu",
        recipe="paper",
        obs_encoder="identity",
        action_type=action_type,
        n_actions=4,
        n_options=N_OPTIONS,
        hidden_size=8,
        mlp_hidden_size=12,
        tasks=list(TASKS),
        input_features={OBS_STATE: PolicyFeature(FeatureType.STATE, (STATE_DIM,))},
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (action_dim,))},
    )
    settings.update(overrides)
    torch.manual_seed(0)
    return OCNPolicy(OCNConfig(**settings))


def make_batch(batch: int = 4, steps: int = 5, action_dim: int = 0, seed: int = 1) -> dict:
    """Windows that all start an episode; action_dim 0 means discrete indices [B, T, 1]."""
    gen = torch.Generator().manual_seed(seed)
    if action_dim:
        action = torch.randn(batch, steps, action_dim, generator=gen)
    else:
        action = torch.randint(0, 4, (batch, steps, 1), generator=gen).float()
    return {
        OBS_STATE: torch.randn(batch, steps, STATE_DIM, generator=gen),
        ACTION: action,
        f"{ACTION}_is_pad": torch.zeros(batch, steps, dtype=torch.bool),
        "task": [TASKS[i % 2] for i in range(batch)],
    }


def force_termination(policy: OCNPolicy, logit: float) -> None:
    """Set every option's termination bias so that e_{i,t} = sigmoid(logit) (0 or 1 for |logit| huge)."""
    with torch.no_grad():
        policy.core.options.w_out[..., -1] = 0.0
        policy.core.options.b_out[..., -1] = logit


# ---- cell ----------------------------------------------------------------------------------------


def test_stacked_cell_equals_per_module_evaluation():
    torch.manual_seed(0)
    cell = StackedCell(3, in_dim=7, hidden_size=5, mlp_hidden_size=6, mlp_depth=3, n_out=4)
    x, h = torch.randn(2, 7), torch.randn(3, 2, 5)
    out = cell(x, h)
    for i in range(3):
        weight = torch.cat([cell.w_x[i], cell.w_h[i]]).T
        act = torch.tanh(F.linear(torch.cat([x, h[i]], -1), weight, cell.b_in[i, 0]))
        for w, b in zip(cell.w_mlp, cell.b_mlp, strict=True):
            act = torch.tanh(F.linear(act, w[i].T, b[i, 0]))
        head = F.linear(act, cell.w_out[i].T, cell.b_out[i, 0])
        torch.testing.assert_close(out.logits[i], head[:, :4])
        torch.testing.assert_close(out.hidden[i], torch.tanh(head[:, 4:9]))
        torch.testing.assert_close(out.end[i], torch.sigmoid(head[:, 9]))
    assert out.logits.shape == (3, 2, 4) and out.hidden.shape == (3, 2, 5) and out.end.shape == (3, 2)


def test_controller_cell_has_no_termination_head():
    cell = StackedCell(1, in_dim=7, hidden_size=5, mlp_hidden_size=6, mlp_depth=2, n_out=3, with_end=False)
    out = cell(torch.randn(2, 7), torch.zeros(1, 2, 5))
    assert out.end is None and cell.w_out.shape == (1, 6, 3 + 5)


def test_looped_cells_give_the_same_loss_and_gradients():
    batch = make_batch()
    stacked, looped = make_policy(), use_looped_cells(make_policy())
    loss_s, _ = stacked(batch)
    loss_l, _ = looped(batch)
    loss_s.backward()
    loss_l.backward()
    torch.testing.assert_close(loss_s, loss_l)
    looped_grads = torch.stack([w.grad for w in looped.core.options.w_h])
    torch.testing.assert_close(stacked.core.options.w_h.grad, looped_grads)


# ---- recurrence, eq. 8-17 --------------------------------------------------------------------------


def test_first_step_is_the_controller_choice_from_the_task_state():
    policy = make_policy()
    core = policy.core
    with torch.no_grad():
        core.controller_init[1] = torch.linspace(-1, 1, 8)
    x = torch.randn(2, STATE_DIM)
    task = torch.tensor([1, 0])
    state, out = core.step(core.initial_state(task), core.project(x), torch.ones(2, dtype=torch.bool))
    ctrl = core.controller(x, core.controller_init[task].unsqueeze(0))
    torch.testing.assert_close(out.p_c, torch.softmax(ctrl.logits[0] / policy.config.temperature, -1))
    torch.testing.assert_close(state.controller_h, ctrl.hidden[0])
    restarted = core.options(x, core.option_init.unsqueeze(1).expand(-1, 2, -1))
    torch.testing.assert_close(state.option_h, restarted.hidden)
    assert torch.equal(out.end, torch.ones(2))
    assert torch.equal(out.weights[:, :N_OPTIONS], torch.zeros(2, N_OPTIONS))


def _previous_state(batch: int = 2) -> OCNState:
    gen = torch.Generator().manual_seed(3)
    p_c = torch.softmax(torch.randn(batch, N_OPTIONS, generator=gen), -1)
    controller_h = torch.randn(batch, 8, generator=gen).tanh()
    option_h = torch.randn(N_OPTIONS, batch, 8, generator=gen)
    return OCNState(controller_h, p_c, option_h, torch.ones(batch, dtype=torch.long))


def test_not_done_keeps_controller_and_continues_options():
    policy = make_policy()
    force_termination(policy, -1e4)
    core, prev, x = policy.core, _previous_state(), torch.randn(2, STATE_DIM)
    state, out = core.step(prev, core.project(x), torch.zeros(2, dtype=torch.bool))
    assert torch.equal(out.end, torch.zeros(2))
    assert torch.equal(state.controller_h, prev.controller_h)
    assert torch.equal(state.p_c, prev.p_c)
    continued = core.options(x, prev.option_h)
    torch.testing.assert_close(state.option_h, continued.hidden)
    torch.testing.assert_close(out.weights, torch.cat([prev.p_c, torch.zeros(2, N_OPTIONS)], -1))


def test_done_steps_controller_and_restarts_options():
    policy = make_policy()
    force_termination(policy, 1e4)
    core, prev, x = policy.core, _previous_state(), torch.randn(2, STATE_DIM)
    state, out = core.step(prev, core.project(x), torch.zeros(2, dtype=torch.bool))
    assert torch.equal(out.end, torch.ones(2))
    ctrl = core.controller(x, prev.controller_h.unsqueeze(0))
    new_p_c = torch.softmax(ctrl.logits[0] / policy.config.temperature, -1)
    torch.testing.assert_close(state.controller_h, ctrl.hidden[0])
    torch.testing.assert_close(state.p_c, new_p_c)
    restarted = core.options(x, core.option_init.unsqueeze(1).expand(-1, 2, -1))
    torch.testing.assert_close(state.option_h, restarted.hidden)
    torch.testing.assert_close(out.weights, torch.cat([torch.zeros(2, N_OPTIONS), new_p_c], -1))


def test_usage_imbalance_is_the_kl_of_the_real_frames_option_share_to_uniform():
    p_c = torch.tensor([[[1.0, 0.0]], [[0.5, 0.5]], [[0.0, 1.0]]])  # [T=3, B=1, N=2]
    mask = torch.tensor([[True, True, False]])  # the last frame is padding
    expected = 0.75 * math.log(0.75 * 2) + 0.25 * math.log(0.25 * 2)
    assert usage_imbalance(p_c, mask).item() == pytest.approx(expected)
    assert usage_imbalance(torch.full((4, 2, 3), 1 / 3),
                           torch.ones(2, 4, dtype=torch.bool)).item() == pytest.approx(0.0)
    one_option = torch.nn.functional.one_hot(torch.zeros(4, 2, dtype=torch.long), 3).float()
    assert usage_imbalance(one_option, torch.ones(2, 4, dtype=torch.bool)).item() == pytest.approx(math.log(3))


def test_expected_nll_charges_each_weighted_option_for_its_own_prediction():
    policy = make_policy()
    # One frame, two components of the 2N mixing the (hand-set) prediction of two options that each
    # favour another action; action 0 is taken.
    probs = torch.tensor([[0.9, 0.1 / 3, 0.1 / 3, 0.1 / 3], [0.1 / 3, 0.9, 0.1 / 3, 0.1 / 3]])
    params = torch.full((1, 2 * N_OPTIONS, 1, 4), -30.0)
    params[0, :2, 0] = probs.log()
    weights = torch.zeros(1, 1, 2 * N_OPTIONS)
    weights[0, 0, :2] = 0.5
    out = StepOutput(weights, params, torch.full((1, 1, N_OPTIONS), 1 / N_OPTIONS), torch.ones(1, 1),
                     torch.ones(1, 1, N_OPTIONS))
    action = torch.zeros(1, 1, 1)
    mixed = math.log(0.5 * 0.9 + 0.5 * 0.1 / 3)
    expected = 0.5 * math.log(0.9) + 0.5 * math.log(0.1 / 3)
    component = policy._component_log_prob(out, action)
    assert policy._action_log_prob(out, component).item() == pytest.approx(mixed, rel=1e-5)
    assert expected_log_prob(out.weights, component).item() == pytest.approx(expected, rel=1e-5)


# ---- the recipes -----------------------------------------------------------------------------------


def train_clock(policy: OCNPolicy, total_steps: int, steps_done: int):
    """The training clock LeRobot builds from the policy's scheduler preset for `total_steps`, advanced by
    `steps_done` updates (with no gradient, so that no weight moves)."""
    optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())
    clock = policy.config.get_scheduler_preset().build(optimizer, num_training_steps=total_steps)
    for _ in range(steps_done):
        optimizer.step()
        clock.step()
    return optimizer, clock


def per_episode_mean_after_first(value: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The mean over episodes of each episode's mean of `value` [T, B] over its real frames t > 1."""
    later = mask[:, 1:].float()
    return ((value[1:].transpose(0, 1) * later).sum(1) / later.sum(1)).mean()


def test_the_paper_recipe_is_the_nll_of_the_mixture_alone():
    policy = make_policy(recipe="paper")
    batch = make_batch()
    batch[f"{ACTION}_is_pad"][0, 3:] = True
    loss, stats = policy(batch)
    parsed = policy.parse(batch)
    nll = -(parsed["action_log_prob"] * parsed["mask"]).sum(1) / parsed["mask"].sum(1)
    torch.testing.assert_close(loss, nll.mean())
    assert stats["final_phase"] == 0.0 and "expected_nll" not in stats


def test_the_craft_recipe_adds_the_usage_balance_and_the_expected_nll_before_its_final_phase():
    batch = make_batch(steps=5)
    batch[f"{ACTION}_is_pad"][0, 3:] = True
    paper, craft = make_policy(recipe="paper"), make_policy(recipe="craft")
    with torch.no_grad():  # tilt the controller toward option 0 alike, so that the usage is unbalanced
        for tilted in (paper, craft):
            tilted.core.controller.b_out[0, 0, 0] += 5.0
    _, clock = train_clock(craft, total_steps=60, steps_done=0)
    plain_loss, _ = paper(batch)
    loss, stats = craft(batch)
    terms = RECIPE_TABLE["craft"]
    out = craft._unroll(batch[OBS_STATE], batch["task"])
    mask = ~batch[f"{ACTION}_is_pad"]
    component = craft.head.log_prob(out.params, batch[ACTION].transpose(0, 1))
    expected_nll = -(out.weights * component.transpose(-1, -2)).sum(-1).transpose(0, 1).detach()
    per_episode = (expected_nll * mask).sum(1) / mask.sum(1)
    imbalance = usage_imbalance(out.p_c, mask)
    assert imbalance.item() > 0.01 and stats["usage_imbalance"] == pytest.approx(imbalance.item())
    torch.testing.assert_close(loss, plain_loss + terms.usage_balance * imbalance
                               + terms.expected_nll_weight * per_episode.mean())
    assert stats["final_phase"] == 0.0 and not clock.in_final_phase
    # The balance's gradient on the controller's output bias: descent lowers the favoured option's logit
    # and raises the others'.
    (grad,) = torch.autograd.grad(imbalance, craft.core.controller.b_out)
    assert grad[0, 0, 0] > 0 and (grad[0, 0, 1:N_OPTIONS] < 0).all()


def test_the_craft_recipe_settles_over_the_final_sixth_of_the_run_under_the_log_termination_cost():
    batch = make_batch(steps=5)
    batch[f"{ACTION}_is_pad"][0, 3:] = True
    policy = make_policy(recipe="craft")
    optimizer, clock = train_clock(policy, total_steps=60, steps_done=49)
    before, stats_before = policy(batch)
    assert stats_before["final_phase"] == 0.0 and "settle_penalty" not in stats_before
    optimizer.step()
    clock.step()  # 50 updates done: the last 10 of 60 are the final phase
    loss, stats = policy(batch)
    assert stats["final_phase"] == 1.0 and clock.in_final_phase
    end = policy._unroll(batch[OBS_STATE], batch["task"]).end.detach()
    penalty = per_episode_mean_after_first(-torch.log(1 - end), ~batch[f"{ACTION}_is_pad"])
    torch.testing.assert_close(loss, before + RECIPE_TABLE["craft"].settle_termination_cost * penalty)
    assert [group["lr"] for group in optimizer.param_groups] == [1e-3]  # Craft's final phase keeps the lr
    # The log cost's gradient in the termination logit is e, where a linear one's is e (1 - e): at e = 0.99
    # it still pulls 100 times harder.
    logit = torch.tensor(4.59512, requires_grad=True)  # sigmoid = 0.99
    (grad,) = torch.autograd.grad(settle_penalty(torch.sigmoid(logit)), logit)
    assert grad.item() == pytest.approx(0.99, rel=1e-3)
    policy.eval()  # outside training the loss is the main phase's
    assert policy(batch)[1]["final_phase"] == 0.0


def test_a_recipe_with_a_final_phase_needs_the_training_clock_and_the_baselines_skip_the_settling_cost():
    batch = make_batch()
    with pytest.raises(ValueError, match="scheduler preset"):
        make_policy(recipe="craft")(batch)
    moe = make_policy(recipe="craft", hierarchy="moe")
    train_clock(moe, total_steps=6, steps_done=5)
    _, stats = moe(batch)
    assert stats["final_phase"] == 1.0 and "settle_penalty" not in stats  # MoE's options end every step anyway


def test_the_phase_clock_gives_the_final_phase_its_lr_scale_and_resumes_from_its_state():
    policy = make_policy(recipe="dial", action_type="continuous", action_dim=2, obs_encoder="identity")
    optimizer, clock = train_clock(policy, total_steps=10, steps_done=0)
    terms = RECIPE_TABLE["dial"]
    clock.set_final_phase(terms.final_fraction, terms.final_lr_scale)  # what the policy's first forward does
    seen = []
    for _ in range(10):
        seen.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        clock.step()
    assert seen == pytest.approx([1e-3] * 8 + [1e-3 * terms.final_lr_scale] * 2)
    resumed_optimizer, resumed = train_clock(policy, total_steps=10, steps_done=0)
    resumed.load_state_dict(clock.state_dict())
    assert resumed.step_count == 10 and resumed.in_final_phase


def test_soft_step_mixes_both_branches_by_eq_17():
    policy = make_policy()
    core, prev, x = policy.core, _previous_state(), torch.randn(2, STATE_DIM)
    state, out = core.step(prev, core.project(x), torch.zeros(2, dtype=torch.bool))
    continued = core.options(x, prev.option_h)
    restarted = core.options(x, core.option_init.unsqueeze(1).expand(-1, 2, -1))
    ctrl = core.controller(x, prev.controller_h.unsqueeze(0))
    new_p_c = torch.softmax(ctrl.logits[0] / policy.config.temperature, -1)
    e = (prev.p_c * continued.end.T).sum(-1)
    torch.testing.assert_close(out.end, e)
    g = e[:, None]
    torch.testing.assert_close(state.controller_h, g * ctrl.hidden[0] + (1 - g) * prev.controller_h)
    torch.testing.assert_close(state.p_c, g * new_p_c + (1 - g) * prev.p_c)
    torch.testing.assert_close(state.option_h, g[None] * restarted.hidden + (1 - g[None]) * continued.hidden)
    action = torch.tensor([[2.0], [0.0]])
    not_done = torch.einsum("bn,nba->ba", prev.p_c, torch.softmax(continued.logits, -1))
    done = torch.einsum("bn,nba->ba", new_p_c, torch.softmax(restarted.logits, -1))
    p_a = (e[:, None] * done + (1 - e[:, None]) * not_done).gather(1, action.long()).squeeze(1)
    got = mixture_log_prob(out.weights, policy.head.log_prob(out.params, action))
    torch.testing.assert_close(got, p_a.log())


def test_teacher_forcing_steps_the_controller_and_restarts_options_only_where_a_choice_is_given():
    policy = make_policy()
    core = policy.core
    option = torch.tensor([[0, 2], [0, 1], [1, 1]])  # [T, B]
    decided = torch.tensor([[True, True], [False, True], [True, False]])
    x = torch.randn(3, 2, STATE_DIM)
    state = core.initial_state(torch.tensor([0, 1]))

    def run(inputs):
        return core.teacher_forced(core.project(inputs), state, option, decided)

    out = run(x)
    assert out.controller_logits.shape == (3, 2, N_OPTIONS) and out.end.shape == (3, 2)
    # t = 0: the task's controller state chooses and the given option starts from h^o_0.
    first_logits, after_first = core.decide(core.project(x[0]).controller, state.controller_h)
    torch.testing.assert_close(out.controller_logits[0], first_logits)
    restarted = core.options(x[0], core.option_init.unsqueeze(1).expand(-1, 2, -1))
    torch.testing.assert_close(out.params[0], restarted.logits[option[0], torch.arange(2)])
    # t = 1, row 0 continues option 0 from its state and reports option 0's termination; row 1 restarts option 1.
    continued = core.options(x[1], restarted.hidden)
    torch.testing.assert_close(out.params[1, 0], continued.logits[0, 0])
    torch.testing.assert_close(out.end[1, 0], continued.end[0, 0])
    torch.testing.assert_close(out.end[1, 1], continued.end[2, 1])  # row 1 ran option 2 before
    fresh = core.options(x[1], core.option_init.unsqueeze(1).expand(-1, 2, -1))
    torch.testing.assert_close(out.params[1, 1], fresh.logits[1, 1])
    # t = 2, row 0 decides from the controller state of its last decision (t = 0): t = 1 did not step it.
    logits, _ = core.decide(core.project(x[2]).controller, after_first)
    torch.testing.assert_close(out.controller_logits[2, 0], logits[0])
    # So what row 0 saw at t = 1 reaches neither its choice nor its restarted option at t = 2.
    changed = x.clone()
    changed[1, 0] += 1.0
    again = run(changed)
    torch.testing.assert_close(again.controller_logits[2, 0], out.controller_logits[2, 0])
    torch.testing.assert_close(again.params[2, 0], out.params[2, 0])
    assert not torch.allclose(again.params[1, 0], out.params[1, 0])
    # Options of a fixed length have no terminations to teach; MoE's one-step options take a choice at every step only.
    moe = make_policy(hierarchy="moe").core
    with pytest.raises(ValueError, match="fixed length"):
        moe.teacher_forced(moe.project(x), state, option, decided)
    with pytest.raises(ValueError, match="fixed length"):
        make_policy(hierarchy="hil").core.teacher_forced(core.project(x), state, option, torch.ones_like(decided))
    every_step = moe.teacher_forced(moe.project(x), state, option, torch.ones_like(decided))
    fresh = moe.options(x[1], moe.option_init.unsqueeze(1).expand(-1, 2, -1))
    torch.testing.assert_close(every_step.params[1], fresh.logits[option[1], torch.arange(2)])


def restarting_reference(policy: OCNPolicy, batch: dict, labels: torch.Tensor) -> tuple[float, float]:
    """The labelled NLL and choice cross-entropy of a model that chooses and restarts its option at
    every frame: the soft recurrence's p^c of each frame's label, and each label's option run from h^o_0."""
    real = labels >= 0
    with torch.no_grad():
        soft = policy._unroll(batch[OBS_STATE], batch["task"])
        initial = policy.core.option_init.unsqueeze(1).expand(-1, labels.shape[0], -1)
        restarted = torch.stack([policy.core.options(x, initial).logits for x in batch[OBS_STATE].unbind(1)])
    index = labels.clamp_min(0).T
    p_c = soft.p_c.gather(-1, index[..., None]).squeeze(-1)
    params = restarted.gather(1, index[:, None, :, None].expand(-1, 1, -1, restarted.shape[-1]))
    log_prob = policy.head.log_prob(params, batch[ACTION].transpose(0, 1)).squeeze(1)
    return -log_prob.T[real].mean().item(), -p_c.T[real].log().mean().item()


def test_labelled_loss_is_the_given_options_nll_plus_the_choice_and_termination_cross_entropies():
    # Labels that change at every frame: each frame restarts its option and the controller chooses at
    # each, which is what the soft recurrence does where every termination fires (e_t = 1).
    policy = make_policy(temperature=1.0)
    force_termination(policy, 1e4)
    batch = make_batch(batch=3, steps=4)
    labels = torch.tensor([[0, 1, 0, 2], [2, 0, 1, 0], [1, 2, -1, -1]])
    batch[f"{ACTION}_is_pad"][2, 2:] = True
    loss, stats = policy.labelled_forward(batch, labels)
    nll, choice_ce = restarting_reference(policy, batch, labels)
    assert stats["frames_used"] == 10
    assert stats["nll"] == pytest.approx(nll, rel=1e-5)
    assert stats["choice_ce"] == pytest.approx(choice_ce, rel=1e-5)
    assert stats["termination_bce"] == pytest.approx(0.0, abs=1e-6) and stats["mean_end"] == 1.0
    assert stats["mean_end_at_switch"] == 1.0
    assert loss.item() == pytest.approx(stats["nll"] + stats["choice_ce"] + stats["termination_bce"], rel=1e-5)


def test_labelled_moe_loss_scores_the_choice_at_every_frame_and_has_no_termination_term():
    # The MoE baseline given the split: its controller chooses at every frame, also where the label
    # runs on, and every option restarts from h^o_0, so the loss is the restarting model's at all frames.
    policy = make_policy(temperature=1.0, hierarchy="moe")
    batch = make_batch(batch=3, steps=4)
    labels = torch.tensor([[0, 0, 1, 1], [2, 2, 2, 0], [1, 1, -1, -1]])
    loss, stats = policy.labelled_forward(batch, labels)
    nll, choice_ce = restarting_reference(policy, batch, labels)
    assert stats["nll"] == pytest.approx(nll, rel=1e-5) and stats["choice_ce"] == pytest.approx(choice_ce, rel=1e-5)
    assert "termination_bce" not in stats and stats["frames_used"] == 10
    assert loss.item() == pytest.approx(nll + choice_ce, rel=1e-5)
    loss.backward()
    assert policy.core.controller_init.grad.abs().sum() > 0 and policy.core.options.w_out.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="termination_weight 3.0"):
        policy.labelled_forward(batch, labels, termination_weight=3.0)


def test_labelled_loss_trains_the_controller_its_task_states_every_labelled_option_and_the_terminations():
    policy = make_policy()
    labels = torch.tensor([[0, 0, 1, 1, 1], [2, 2, 2, 0, 0], [1, 1, 0, 0, 0], [2, 1, 1, 1, 1]])
    loss, stats = policy.labelled_forward(make_batch(batch=4, steps=5), labels)
    weighted, _ = policy.labelled_forward(make_batch(batch=4, steps=5), labels, termination_weight=3.0)
    assert weighted.item() == pytest.approx(loss.item() + 2.0 * stats["termination_bce"], rel=1e-5)
    loss.backward()
    core = policy.core
    assert 0 < stats["mean_end"] < 1 and stats["termination_bce"] > 0
    # Four switches among the 16 frames after the first: the mean over all is their weighted mean.
    mixed = (4 * stats["mean_end_at_switch"] + 12 * stats["mean_end_elsewhere"]) / 16
    assert stats["mean_end"] == pytest.approx(mixed, rel=1e-5)
    for name, param in core.controller.named_parameters():
        assert param.grad.abs().sum() > 0, name
    assert (core.controller_init.grad.abs().sum(1) > 0).all()
    assert (core.options.w_out.grad.flatten(1).abs().sum(1) > 0).all()
    assert (core.options.w_out.grad[..., -1].abs().sum(1) > 0).all()
    assert (core.option_init.grad.abs().sum(1) > 0).all()


# ---- loss, masks, windows ------------------------------------------------------------------------


def test_forward_shapes_and_padding_mask():
    policy = make_policy()
    batch = make_batch()
    batch[f"{ACTION}_is_pad"][0, 3:] = True
    loss, stats = policy(batch)
    assert loss.shape == () and stats["frames_used"] == 4 * 5 - 2
    per_window, _ = policy(batch, reduction="none")
    assert per_window.shape == (4,)
    changed = dict(batch, **{ACTION: batch[ACTION].clone()})
    changed[ACTION][0, 4] = (changed[ACTION][0, 4] + 1) % 4
    torch.testing.assert_close(policy(changed)[0], loss)
    changed[ACTION][0, 1] = (changed[ACTION][0, 1] + 1) % 4
    assert not torch.allclose(policy(changed)[0], loss)
    parsed = policy.parse(batch)
    assert parsed["p_c"].shape == (4, 5, N_OPTIONS) and parsed["option"].shape == (4, 5)
    assert parsed["end"].shape == (4, 5) and torch.equal(parsed["end"][:, 0], torch.ones(4))
    assert parsed["mask"][0].tolist() == [True, True, True, False, False]
    nll = -(parsed["action_log_prob"] * parsed["mask"]).sum(1) / parsed["mask"].sum(1)
    torch.testing.assert_close(nll.mean(), loss)


def test_actions_without_a_feature_axis_as_lerobot_loads_them():
    policy = make_policy()
    batch = make_batch(batch=1)
    flat = dict(batch, **{ACTION: batch[ACTION][..., 0].long()})
    torch.testing.assert_close(policy(flat)[0], policy(batch)[0])


@pytest.mark.parametrize("hierarchy", ["ocn", "moe", "hil"])
def test_computing_only_real_frames_changes_no_output_read_and_no_gradient(hierarchy):
    """Training computes the real frames alone: projected alone, and each step over the rows still in
    their episode, longest first (`OCNCore.unroll_frames`). Rows of four lengths, in no order."""
    policy = make_policy(hierarchy=hierarchy, skill_length=2)
    batch = make_batch()
    batch[f"{ACTION}_is_pad"][0, 3:] = batch[f"{ACTION}_is_pad"][2, 1:] = batch[f"{ACTION}_is_pad"][3, 4:] = True
    mask, state, action, _, _ = policy.training_windows(batch)
    results = []
    for real in (None, mask):
        policy.zero_grad(set_to_none=True)
        out = policy._unroll(state, batch["task"], real)
        log_prob = policy._action_log_prob(out, policy._component_log_prob(out, action))
        (-(log_prob * mask).sum()).backward()
        results.append((out, [p.grad.clone() for p in policy.parameters()]))
    (every, every_grads), (only_real, real_grads) = results
    time_major = mask.transpose(0, 1)
    for field in ("p_c", "end", "weights"):
        torch.testing.assert_close(getattr(only_real, field)[time_major], getattr(every, field)[time_major], msg=field)
    for got, expected in zip(real_grads, every_grads, strict=True):
        torch.testing.assert_close(got, expected)
    assert not only_real.p_c[~time_major].any()  # the frames after a row's end are not computed


def test_craft_features_read_as_their_set_entries_give_the_dense_first_layers_loss_and_gradients():
    from lerobot_policy_ocn.envs.craft import CraftEnv

    craft_state = {OBS_STATE: PolicyFeature(FeatureType.STATE, (81,))}
    policy = make_policy(obs_encoder="craft", n_actions=5, input_features=craft_state)
    states = torch.stack([torch.as_tensor(CraftEnv().reset(seed=seed)[0]) for seed in range(20)]).reshape(4, 5, 81)
    batch = {**make_batch(), OBS_STATE: states}
    batch[f"{ACTION}_is_pad"][1, 3:] = True
    results = []
    for sparse in (True, False):
        policy.zero_grad(set_to_none=True)
        if not sparse:
            policy.encoder.sparse = lambda state: None  # the dense path the encoder's features take
        loss, _ = policy(batch)
        loss.backward()
        results.append((loss.detach(), [p.grad.clone() for p in policy.parameters()]))
    (sparse_loss, sparse_grads), (dense_loss, dense_grads) = results
    torch.testing.assert_close(sparse_loss, dense_loss)
    for got, expected in zip(sparse_grads, dense_grads, strict=True):
        torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)


def test_unroll_frames_names_rows_out_of_order():
    policy = make_policy()
    core = policy.core
    x = torch.randn(3, 2, STATE_DIM)
    start = torch.zeros(3, 2, dtype=torch.bool)
    start[0] = True
    initial = core.initial_state(torch.tensor([0, 1]))
    shorter_first = torch.tensor([[True, True], [False, True], [False, True]])
    with pytest.raises(ValueError, match="longest first"):
        core.unroll_frames(x, initial, start, shorter_first)
    gap = torch.tensor([[True, True], [False, True], [True, False]])
    with pytest.raises(ValueError, match="real frames first"):
        core.unroll_frames(x, initial, start, gap)


def test_loss_is_the_mean_over_episodes_of_each_episodes_frame_mean():
    policy = make_policy()
    batch = make_batch()
    batch[f"{ACTION}_is_pad"][1, 2:] = True
    per_window, _ = policy(batch, reduction="none")
    torch.testing.assert_close(policy(batch)[0], per_window.mean())
    short = {k: (v[1:2, :2] if torch.is_tensor(v) else [v[1]]) for k, v in batch.items()}
    torch.testing.assert_close(per_window[1], policy(short)[0])


def test_gradients_reach_every_part():
    policy = make_policy(temperature=1.0)
    loss, _ = policy(make_batch(batch=6, steps=5))
    loss.backward()
    core = policy.core
    for name, param in core.controller.named_parameters():
        assert param.grad is not None and param.grad.abs().sum() > 0, name
    for name, param in core.options.named_parameters():
        per_option = param.grad.flatten(1).abs().sum(1)
        assert (per_option > 0).all(), name
    termination = core.options.w_out.grad[..., -1].abs().sum(1)
    assert (termination > 0).all()
    assert (core.controller_init.grad.abs().sum(1) > 0).all()
    assert (core.option_init.grad.abs().sum(1) > 0).all()


def test_unknown_task_is_a_value_error_listing_the_tasks():
    policy = make_policy()
    batch = make_batch()
    batch["task"] = ["make plank", "fly to the moon", "get gold", "get gold"]
    with pytest.raises(ValueError, match="fly to the moon") as error:
        policy(batch)
    assert all(task in str(error.value) for task in TASKS)


# ---- action choice ---------------------------------------------------------------------------------


def test_sample_index_draws_what_torch_multinomial_draws():
    torch.manual_seed(0)
    probs = torch.softmax(torch.randn(64, 6) * 3, dim=-1)
    probs[::3, :3] = 0.0
    probs[5] = torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    torch.manual_seed(3)
    expected = torch.multinomial(probs, 1).squeeze(-1), torch.rand(4)
    torch.manual_seed(3)
    drawn = sample_index(probs), torch.rand(4)
    assert torch.equal(drawn[0], expected[0]) and torch.equal(drawn[1], expected[1])
    assert drawn[0][5] == 2 and (drawn[0][::3] >= 3).all()


@pytest.mark.parametrize("batch", [1, 64])
def test_discrete_choice_is_the_einsum_mixture_and_its_multinomial_draw(batch):
    head = DiscreteHead(n_actions=5)
    torch.manual_seed(0)
    for n_components in (1, 2, 6):
        weights = torch.softmax(torch.randn(batch, n_components), dim=-1)
        params = torch.randn(n_components, batch, 5) * 2
        mixture = torch.einsum("bk,kba->ba", weights, torch.softmax(params, dim=-1))
        assert torch.equal(head.mixture(weights, params), mixture)
        assert torch.equal(head.choose(weights, params, greedy=True), mixture.argmax(-1, keepdim=True).float())
        torch.manual_seed(4)
        expected = torch.multinomial(mixture, 1).float()
        torch.manual_seed(4)
        assert torch.equal(head.choose(weights, params, greedy=False), expected)


# ---- continuous head -------------------------------------------------------------------------------


def test_gaussian_log_prob_by_hand():
    head = GaussianHead(action_dim=2, log_std_min=-5, log_std_max=2)
    params = torch.tensor([[[0.5, -1.0, math.log(2.0), 0.0]]])
    action = torch.tensor([[1.5, -1.0]])
    expected = (-0.5 * 0.25 - math.log(2.0) - 0.5 * math.log(2 * math.pi)) + (-0.5 * math.log(2 * math.pi))
    assert head.log_prob(params, action).item() == pytest.approx(expected, rel=1e-6)


def test_continuous_nll_of_first_step_is_the_restarted_options_gaussian_mixture():
    policy = make_policy("continuous", action_dim=2, n_options=1)
    batch = make_batch(batch=1, steps=1, action_dim=2)
    loss, _ = policy(batch)
    core, x = policy.core, batch[OBS_STATE][:, 0]
    out = core.options(x, core.option_init.unsqueeze(1))
    mean, log_std = out.logits[0, 0].chunk(2)
    normal = torch.distributions.Normal(mean, log_std.exp())
    torch.testing.assert_close(loss, -normal.log_prob(batch[ACTION][0, 0]).sum())


# ---- inference -------------------------------------------------------------------------------------


def test_select_action_keeps_state_and_reset_clears_it():
    policy = make_policy(inference_mode="greedy")
    episode = make_batch(batch=2, steps=4)
    actions = []
    for t in range(4):
        obs = {OBS_STATE: episode[OBS_STATE][:, t], "task": episode["task"]}
        actions.append(policy.select_action(obs))
        assert policy.last_step.p_c.shape == (2, N_OPTIONS) and policy.last_step.option.shape == (2,)
        assert torch.equal(policy.last_step.end == 1, torch.full((2,), t == 0))
    parsed = policy.parse(episode)
    torch.testing.assert_close(policy.last_step.p_c, parsed["p_c"][:, -1])
    policy.reset()
    first = policy.select_action({OBS_STATE: episode[OBS_STATE][:, 0], "task": episode["task"]})
    assert torch.equal(first, actions[0]) and torch.equal(policy.last_step.end, torch.ones(2))
    assert actions[0].shape == (2, 1) and policy.predict_action_chunk(
        {OBS_STATE: episode[OBS_STATE][:, 1], "task": episode["task"]}
    ).shape == (2, 1, 1)


def fresh_projection(cell: StackedCell, x: torch.Tensor) -> torch.Tensor:
    """The observation projection from a side-by-side copy of the cell's weights made now."""
    return stacked_linear(x, side_by_side(cell.w_x.detach()), cell.b_in.detach())


def test_inference_projection_keeps_its_weight_copy_until_the_weights_change():
    policy = make_policy()
    other = make_policy()
    with torch.no_grad():
        for param in other.parameters():
            param.add_(torch.rand_like(param))
    cells = (policy.core.controller, policy.core.options)
    x = torch.randn(3, STATE_DIM)
    with torch.inference_mode():
        kept = [cell.w_x_matrix(cell.w_x) for cell in cells]
    assert not any(matrix.is_inference() for matrix in kept)
    with torch.no_grad():
        assert all(cell.w_x_matrix(cell.w_x) is matrix for cell, matrix in zip(cells, kept, strict=True))
    optimizer = torch.optim.SGD(policy.parameters(), lr=0.1)
    policy(make_batch())[0].backward()
    optimizer.step()
    with torch.inference_mode():
        for cell in cells:
            assert torch.equal(cell.project(x), fresh_projection(cell, x))
    policy.load_state_dict(other.state_dict())
    with torch.no_grad():
        for cell, other_cell in zip(cells, (other.core.controller, other.core.options), strict=True):
            assert torch.equal(cell.project(x), fresh_projection(other_cell, x))
    loss, _ = policy(make_batch())
    loss.backward()
    assert policy.core.options.w_x.grad.abs().sum() > 0


@pytest.mark.parametrize("execution", ["soft", "hard"])
@pytest.mark.parametrize("inference_mode", ["greedy", "sample"])
@pytest.mark.parametrize("action_type", ["discrete", "continuous"])
def test_select_action_in_inference_mode_as_lerobot_eval_calls_it_is_unchanged(execution, inference_mode, action_type):
    """The same actions, hierarchy readout and recurrent states as without inference mode."""
    runs = []
    for mode in (torch.inference_mode, torch.enable_grad):
        action_dim = 2 if action_type == "continuous" else 1
        policy = make_policy(action_type, action_dim, execution=execution, inference_mode=inference_mode)
        episode = make_batch(batch=3, steps=6)
        torch.manual_seed(5)
        steps = []
        for t in range(6):
            with mode():
                action = policy.select_action({OBS_STATE: episode[OBS_STATE][:, t], "task": episode["task"]})
            steps.append((action, *vars(policy.last_step).values(), *vars(policy._state).values()))
        runs.append(steps)
    for inference, plain in zip(*runs, strict=True):
        assert all(a is b or torch.equal(a, b) for a, b in zip(inference, plain, strict=True))


def test_continuous_select_action_shape():
    policy = make_policy("continuous", action_dim=3)
    action = policy.select_action({OBS_STATE: torch.randn(5, STATE_DIM), "task": "get gold"})
    assert action.shape == (5, 3) and torch.isfinite(action).all()


# ---- LeRobot plumbing ------------------------------------------------------------------------------


def test_config_defaults_and_registration():
    import lerobot_policy_ocn  # noqa: F401

    assert PreTrainedConfig.get_choice_class("ocn") is OCNConfig
    default = OCNConfig(device="cpu")
    assert (default.recipe, default.obs_encoder, default.action_type, default.n_options) == ("auto", "auto", "auto", 0)
    assert not default.resolved and not default.normalization_mapping  # both follow from the dataset
    craft = OCNConfig(device="cpu", recipe="craft", obs_encoder="craft", action_type="discrete", n_actions=5)
    identity = NormalizationMode.IDENTITY
    assert craft.resolved and craft.n_options == 3
    assert craft.normalization_mapping == {"STATE": identity, "ENV": identity, "VISUAL": identity, "ACTION": identity}
    dial = OCNConfig(device="cpu", recipe="dial", obs_encoder="identity", action_type="continuous")
    assert dial.normalization_mapping["ACTION"] is NormalizationMode.MEAN_STD and dial.n_options == 4
    assert craft.observation_delta_indices is None and craft.action_delta_indices is None  # single frames
    assert craft.get_optimizer_preset().lr == 1e-3 and craft.get_scheduler_preset().type == "ocn_phases"
    with pytest.raises(ValueError, match="recipe"):
        OCNConfig(device="cpu", recipe="sometimes")
    with pytest.raises(ValueError, match="follow from its training data"):
        OCNPolicy(OCNConfig(device="cpu", tasks=["a"], input_features=craft.input_features))


def test_full_view_encoder_feeds_the_exact_map_and_keeps_craft_states_unnormalised():
    from lerobot_policy_ocn.envs.craft import CraftEnv
    from lerobot_policy_ocn.envs.craft.observation import FULL_VIEW_DIM, full_view_features

    craft_state = {OBS_STATE: PolicyFeature(FeatureType.STATE, (81,))}
    policy = make_policy(obs_encoder="craft_full_view", n_actions=5, input_features=craft_state)
    assert policy.encoder.out_dim == FULL_VIEW_DIM
    assert policy.config.normalization_mapping["STATE"] is NormalizationMode.IDENTITY
    states = torch.stack([torch.as_tensor(CraftEnv().reset(seed=seed)[0]) for seed in range(4)])
    torch.testing.assert_close(policy.encoder(states.float()), full_view_features(states))
    batch = make_batch(steps=1)
    batch[OBS_STATE] = states[:, None].float()
    loss, _ = policy(batch)
    loss.backward()
    assert torch.isfinite(loss) and policy.core.options.w_x.grad.shape[1] == FULL_VIEW_DIM


def test_save_and_load_round_trip(tmp_path):
    policy = make_policy(recipe="craft")
    with torch.no_grad():
        policy.core.controller_init.normal_()
    batch = make_batch()
    policy.save_pretrained(tmp_path)
    loaded = OCNPolicy.from_pretrained(tmp_path)
    assert loaded.config.tasks == TASKS and loaded.config.recipe == "craft"
    policy.eval(), loaded.eval()  # outside training no recipe phase applies, so no training clock is needed
    torch.testing.assert_close(loaded(batch)[0], policy(batch)[0], rtol=0, atol=0)
    torch.testing.assert_close(loaded.parse(batch)["p_c"], policy.parse(batch)["p_c"], rtol=0, atol=0)


def test_task_strings_survive_the_preprocessor():
    policy = make_policy()
    stats = {OBS_STATE: {"mean": torch.zeros(STATE_DIM), "std": torch.ones(STATE_DIM)}}
    pre, post = make_ocn_pre_post_processors(policy.config, stats)
    processed = pre(make_batch())
    assert processed["task"] == [TASKS[i % 2] for i in range(4)]
    loss, _ = policy(processed)
    assert torch.isfinite(loss)
    action = post(policy.select_action(pre({OBS_STATE: torch.randn(STATE_DIM), "task": "get gold"})))
    assert action.shape == (1, 1)


def test_craft_policy_acts_in_the_craft_env():
    craft = pytest.importorskip("lerobot_policy_ocn.envs.craft.env")
    env = craft.CraftEnv(task="AC")
    obs, _ = env.reset(seed=0)
    config = OCNConfig(
        device="cpu",
        recipe="craft",
        obs_encoder="craft",
        action_type="discrete",
        n_actions=5,
        hidden_size=8,
        mlp_hidden_size=8,
        tasks=[env.task_description],
        input_features={OBS_STATE: PolicyFeature(FeatureType.STATE, (81,))},
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (1,))},
    )
    policy = OCNPolicy(config)
    assert policy.encoder.out_dim == 1075
    for _ in range(3):
        observation = {OBS_STATE: torch.from_numpy(obs)[None], "task": [env.task_description]}
        action = policy.select_action(observation)
        assert action.shape == (1, 1) and 0 <= int(action) < config.n_actions
        obs, *_ = env.step(int(action))



# ---- MoE baseline (hierarchy="moe") ----------------------------------------------------------------


def test_moe_termination_is_one_at_every_step_in_training_parsing_and_inference():
    """Options that would never terminate under OCN still hand control back at every step under MoE."""
    policy = make_policy(hierarchy="moe")
    force_termination(policy, -1e4)
    batch = make_batch()
    loss, stats = policy(batch)
    per_window, _ = policy(batch, reduction="none")
    assert loss.shape == () and per_window.shape == (4,) and stats["mean_end"] == 1.0
    parsed = policy.parse(batch)
    assert parsed["p_c"].shape == (4, 5, N_OPTIONS) and torch.equal(parsed["end"], torch.ones(4, 5))
    for execution in ("soft", "hard"):
        policy.config.execution = execution
        policy.reset()
        for t in range(5):
            policy.select_action({OBS_STATE: batch[OBS_STATE][:, t], "task": batch["task"]})
            assert torch.equal(policy.last_step.end, torch.ones(4))
            if execution == "hard":
                assert policy.last_step.decided.all()
    ocn = make_policy()
    force_termination(ocn, -1e4)
    assert torch.equal(ocn.parse(batch)["end"][:, 1:], torch.zeros(4, 4))


def test_moe_loss_is_the_nll_of_a_fresh_controller_mixture_of_restarted_options_at_every_step():
    """Eq. 17 with e_t = 1: the controller steps every step and every option restarts from h^o_0, so
    p(a_t) = sum_i p^c_{t,i} p^o_i(a_t | x_t, h^o_{i,0})."""
    policy = make_policy(hierarchy="moe")
    batch = make_batch(batch=2, steps=4)
    core, task = policy.core, policy.task_index(batch["task"], 2)
    controller_h = core.controller_init[task]
    initial = core.option_init.unsqueeze(1).expand(-1, 2, -1)
    log_p = []
    with torch.no_grad():
        for t in range(4):
            x = batch[OBS_STATE][:, t]
            ctrl = core.controller(x, controller_h.unsqueeze(0))
            controller_h = ctrl.hidden[0]
            p_c = torch.softmax(ctrl.logits[0] / policy.config.temperature, -1)
            p_o = torch.softmax(core.options(x, initial).logits, -1)
            p_a = torch.einsum("bn,nba->ba", p_c, p_o).gather(1, batch[ACTION][:, t].long()).squeeze(1)
            log_p.append(p_a.log())
        loss, _ = policy(batch)
    torch.testing.assert_close(loss, -torch.stack(log_p, 1).mean(1).mean())
    assert not torch.allclose(make_policy()(batch)[0], loss)  # same weights, OCN's recurrence differs


def test_moe_switch_is_saved_and_checked(tmp_path):
    make_policy(hierarchy="moe").save_pretrained(tmp_path)
    assert OCNPolicy.from_pretrained(tmp_path).core.skill_length == 1
    assert OCNConfig(device="cpu").hierarchy == "ocn"
    with pytest.raises(ValueError, match="hierarchy"):
        OCNConfig(device="cpu", hierarchy="flat")


# ---- HIL baseline (hierarchy="hil": skills of a fixed length) ---------------------------------------


def hil_schedule(steps: int, length: int) -> torch.Tensor:
    """e_t [steps] of HIL: 1 at t = 1, 1 + L, 1 + 2L, ... (0-based 0, L, 2L, ...), 0 elsewhere."""
    return (torch.arange(steps) % length == 0).float()


@pytest.mark.parametrize("logit", [-1e4, 1e4])
def test_hil_termination_is_the_schedule_in_training_parsing_and_inference(logit):
    """Whatever the options' termination heads say (never or always), e_t is 1 exactly every L steps."""
    policy = make_policy(hierarchy="hil", skill_length=2, window_size=7)
    force_termination(policy, logit)
    batch = make_batch(steps=7)
    schedule = hil_schedule(7, 2)
    _, stats = policy(batch)
    assert stats["mean_end"] == pytest.approx(schedule[1:].mean().item())  # over t > 1
    assert torch.equal(policy.parse(batch)["end"], schedule.expand(4, -1))
    for execution in ("soft", "hard"):
        policy.config.execution = execution
        policy.reset()
        for t in range(7):
            policy.select_action({OBS_STATE: batch[OBS_STATE][:, t], "task": batch["task"]})
            assert torch.equal(policy.last_step.end, schedule[t].expand(4)), (execution, t)
            if execution == "hard":
                assert torch.equal(policy.last_step.decided, schedule[t].bool().expand(4))


def test_hil_controller_state_changes_only_at_the_scheduled_steps():
    """At t = 1 + kL the controller steps and the options restart (eq. 17's "done" branch); in between
    h^c and p^c are kept exactly and the options continue from their own states."""
    policy = make_policy(hierarchy="hil", skill_length=3, window_size=8)
    batch = make_batch(batch=2, steps=8)
    core = policy.core
    state = core.initial_state(policy.task_index(batch["task"], 2))
    start = torch.ones(2, dtype=torch.bool)
    for t in range(8):
        x = batch[OBS_STATE][:, t]
        previous, (state, _) = state, core.step(state, core.project(x), start)
        start = torch.zeros(2, dtype=torch.bool)
        if t % 3 == 0:
            ctrl = core.controller(x, previous.controller_h.unsqueeze(0))
            torch.testing.assert_close(state.controller_h, ctrl.hidden[0])
            restarted = core.options(x, core.option_init.unsqueeze(1).expand(-1, 2, -1))
            torch.testing.assert_close(state.option_h, restarted.hidden)
        else:
            assert torch.equal(state.controller_h, previous.controller_h)
            assert torch.equal(state.p_c, previous.p_c)
            torch.testing.assert_close(state.option_h, core.options(x, previous.option_h).hidden)
        assert torch.equal(state.steps, torch.full((2,), t + 1))


def test_hil_rows_keep_their_own_schedule_from_their_own_start():
    """Rows of one batch that start episodes at different steps (vector envs resetting one env) count
    their skills from their own start."""
    policy = make_policy(hierarchy="hil", skill_length=3)
    core = policy.core
    x = torch.randn(9, 2, STATE_DIM)
    start = torch.zeros(9, 2, dtype=torch.bool)
    start[0] = True
    start[4, 1] = True
    state, out = core.unroll(x, core.initial_state(torch.tensor([0, 1])), start)
    assert torch.equal(out.end[:, 0], hil_schedule(9, 3))
    assert torch.equal(out.end[:, 1], torch.cat([hil_schedule(4, 3), hil_schedule(5, 3)]))
    assert torch.equal(state.steps, torch.tensor([9, 5]))


def test_hil_gradients_reach_controller_and_options_but_not_termination():
    policy = make_policy(hierarchy="hil", skill_length=2, temperature=1.0)
    loss, _ = policy(make_batch(batch=6, steps=5))
    loss.backward()
    core = policy.core
    for name, param in core.controller.named_parameters():
        assert param.grad is not None and param.grad.abs().sum() > 0, name
    assert (core.options.w_h.grad.flatten(1).abs().sum(1) > 0).all()
    assert (core.options.w_out.grad[..., :-1].flatten(1).abs().sum(1) > 0).all()
    assert not core.options.w_out.grad[..., -1].any() and not core.options.b_out.grad[..., -1].any()
    assert (core.controller_init.grad.abs().sum(1) > 0).all()
    assert (core.option_init.grad.abs().sum(1) > 0).all()


def test_hil_of_skill_length_one_is_moe():
    batch = make_batch()
    hil, moe = make_policy(hierarchy="hil", skill_length=1), make_policy(hierarchy="moe")
    assert torch.equal(hil(batch)[0], moe(batch)[0])
    assert not torch.equal(make_policy(hierarchy="hil")(batch)[0], moe(batch)[0])


def test_hil_switch_and_skill_length_are_saved_and_checked(tmp_path):
    make_policy(hierarchy="hil", skill_length=5).save_pretrained(tmp_path)
    loaded = OCNPolicy.from_pretrained(tmp_path)
    assert loaded.config.hierarchy == "hil" and loaded.core.skill_length == 5
    assert OCNConfig(device="cpu").skill_length == 4 and make_policy().core.skill_length is None
    with pytest.raises(ValueError, match="skill_length must be >= 1, got 0"):
        OCNConfig(device="cpu", hierarchy="hil", skill_length=0)


# ---- GPU -----------------------------------------------------------------------------------------


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (CI has none)")
@pytest.mark.parametrize("action_type,action_dim", [("discrete", 1), ("continuous", 2)])
def test_cuda_loss_gradients_and_parse_match_cpu(action_type: str, action_dim: int):
    """The same weights and windows give the CPU's loss, gradients and parse on the GPU: nothing in
    the recurrence, heads or penalties is created on the wrong device or silently cast."""
    cpu = make_policy(action_type, action_dim, usage_balance=1.0, termination_cost=0.1)
    gpu = make_policy(action_type, action_dim, usage_balance=1.0, termination_cost=0.1, device="cuda").to("cuda")
    gpu.load_state_dict(cpu.state_dict())
    batch = make_batch(action_dim=0 if action_type == "discrete" else action_dim)
    on_gpu = {k: v.to("cuda") if torch.is_tensor(v) else v for k, v in batch.items()}
    loss_cpu, _ = cpu.forward(batch)
    loss_gpu, _ = gpu.forward(on_gpu)
    loss_cpu.backward()
    loss_gpu.backward()
    torch.testing.assert_close(loss_gpu.cpu(), loss_cpu, rtol=1e-4, atol=1e-5)
    for (name, p_cpu), p_gpu in zip(cpu.named_parameters(), gpu.parameters(), strict=True):
        assert p_cpu.grad is not None, name
        torch.testing.assert_close(p_gpu.grad.cpu(), p_cpu.grad, rtol=1e-3, atol=1e-5, msg=name)
    parse_cpu, parse_gpu = cpu.parse(batch), gpu.parse(on_gpu)
    for key in ("p_c", "end", "action_log_prob"):
        torch.testing.assert_close(parse_gpu[key].cpu(), parse_cpu[key], rtol=1e-4, atol=1e-5, msg=key)
