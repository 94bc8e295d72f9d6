"""PPO in option space: hard execution semantics, decision recording, semi-MDP GAE, and learning."""

import numpy as np
import pytest
import torch

from lerobot_policy_ocn.envs.craft.batch import CraftBatch
from lerobot_policy_ocn.envs.craft.world import DOWN, EMPTY, LEFT, UP, USE, WOOD
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_STATE
from lerobot_policy_ocn.ocn import OCNConfig, OCNPolicy
from lerobot_policy_ocn.tools.rl.finetuning import primitive_action_pool
from lerobot_policy_ocn.tools.rl.craft_rollouts import craft_world
from lerobot_policy_ocn.tools.rl.ppo import (
    Acting, Decisions, PPOConfig, PPOTrainer, collect, finetune, replay_controller, semi_mdp_gae,
)
from conftest import CRAFT_STATE

torch.set_num_threads(1)

TASK = "get wood"
CRAFT = Acting(craft_world())  # policies built in memory: identity processors


def craft_policy(n_options: int = 3, **overrides) -> OCNPolicy:
    settings = dict(
        device="cpu", recipe="paper", hidden_size=16, mlp_hidden_size=16, n_options=n_options, temperature=1.0,
        tasks=[TASK], **CRAFT_STATE,
        execution="hard", input_features={OBS_STATE: PolicyFeature(FeatureType.STATE, (81,))},
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (1,))},
    )
    settings.update(overrides)
    torch.manual_seed(0)
    return OCNPolicy(OCNConfig(**settings))


def set_option(policy: OCNPolicy, option: int, action: int, end_logit: float) -> None:
    """Option `option` always picks `action` and terminates with probability sigmoid(end_logit)."""
    with torch.no_grad():
        cell = policy.core.options
        cell.w_out[option] = 0.0
        cell.b_out[option, :, : cell.n_out] = -50.0
        cell.b_out[option, :, action] = 50.0
        cell.b_out[option, :, -1] = end_logit


class WoodAhead(CraftBatch):
    """Craft maps where the agent starts at interior cell (4, 4) facing down, at wood: `use` at once
    completes "get wood", and once the agent has turned away no `use` can complete it."""

    def reset(self, seeds=None, tasks=None, env_ids=None) -> np.ndarray:
        super().reset(seeds, tasks, env_ids)
        self.grid[:, 4, 4] = EMPTY
        self.grid[:, 5, 4] = WOOD
        self.pos[:] = (4, 4)
        self.facing[:] = DOWN
        return self.observe()


def solving_pool() -> OCNPolicy:
    """Option 0 solves the task in one step; options 1 and 2 turn away (up, left); all stop after a step."""
    policy = craft_policy()
    for option, action in enumerate((USE, UP, LEFT)):
        set_option(policy, option, action, end_logit=50.0)
    return policy


# ---- hard execution ------------------------------------------------------------------------------


def test_hard_execution_queries_the_controller_exactly_at_start_and_where_termination_fired():
    """Options' termination reads one state feature (+1: fire, -1: keep going), so where the sampled
    termination fires is known in advance; the controller must choose exactly there and at t = 1."""
    policy = craft_policy(obs_encoder="identity", mlp_depth=1, input_features={
        OBS_STATE: PolicyFeature(FeatureType.STATE, (4,))})
    with torch.no_grad():
        cell = policy.core.options
        cell.w_h.zero_()
        cell.w_x.zero_()
        cell.b_in.zero_()
        cell.w_x[:, 0, 0] = 10.0
        cell.w_out[:, :, -1] = 0.0
        cell.w_out[:, 0, -1] = 60.0
        cell.b_out[:, :, -1] = 0.0
    gen = torch.Generator().manual_seed(5)
    steps, batch = 12, 32
    fire = torch.rand(steps, batch, generator=gen) < 0.3
    states = torch.randn(steps, batch, 4, generator=gen)
    states[..., 0] = torch.where(fire, 1.0, -1.0)
    policy.reset()
    previous = None
    for t in range(steps):
        policy.select_action({OBS_STATE: states[t], "task": [TASK] * batch})
        step = policy.last_step
        expected = torch.ones(batch, dtype=torch.bool) if t == 0 else fire[t]
        assert torch.equal(step.decided, expected)
        state = policy._state
        if previous is not None:
            kept = ~expected
            assert torch.equal(state.controller_h[kept], previous.controller_h[kept])
            assert torch.equal(state.option[kept], previous.option[kept])
            if expected.any():
                assert not torch.equal(state.controller_h[expected], previous.controller_h[expected])
        previous = state


def test_a_decision_restarts_the_chosen_option_from_its_initial_state():
    policy = craft_policy(obs_encoder="identity", input_features={OBS_STATE: PolicyFeature(FeatureType.STATE, (4,))})
    with torch.no_grad():
        policy.core.option_init.normal_()
    force_end = 50.0
    with torch.no_grad():
        policy.core.options.w_out[..., -1] = 0.0
        policy.core.options.b_out[..., -1] = force_end
    x = torch.randn(2, 6, 4)
    policy.reset()
    policy.select_action({OBS_STATE: x[0], "task": [TASK] * 6})
    policy.select_action({OBS_STATE: x[1], "task": [TASK] * 6})
    assert policy.last_step.decided.all()
    expected = policy.core.options(policy.encoder(x[1]), policy.core.option_init.unsqueeze(1)).hidden
    torch.testing.assert_close(policy._state.option_h, expected.expand_as(policy._state.option_h))


def test_soft_execution_is_unchanged_and_reports_no_decisions():
    policy = craft_policy(execution="soft")
    obs = CraftBatch(3).reset(seeds=[0, 1, 2], tasks=[TASK] * 3)
    policy.select_action({OBS_STATE: torch.from_numpy(obs).float(), "task": [TASK] * 3})
    assert policy.last_step.decided is None


# ---- rollouts and advantages ---------------------------------------------------------------------


def test_collect_records_one_decision_per_option_run_with_discounted_rewards():
    """Option 0 walks down forever and never terminates, option 1 uses and terminates after a step:
    decisions, durations and rewards are checked against the episode's own step count."""
    policy = craft_policy(n_options=2)
    set_option(policy, 0, DOWN, end_logit=-50.0)
    set_option(policy, 1, USE, end_logit=50.0)
    envs = WoodAhead(16, reward="dense", max_steps=6)
    batch = collect(policy, envs, CRAFT, [TASK] * 16, range(16), gamma=0.5)
    first = batch.option[:, 0]
    assert set(first.tolist()) == {0, 1}
    solved = first == 1
    assert batch.success[solved].all() and not batch.success[~solved].any()
    # option 1 at t = 1: one decision, one step, reward 1 (no discount at k = 0)
    assert (batch.count[solved] == 1).all() and (batch.duration[solved, 0] == 1).all()
    np.testing.assert_allclose(batch.reward[solved, 0], 1.0)
    # option 0 at t = 1 never ends: one decision lasting the whole 6-step episode, no reward
    assert (batch.count[~solved] == 1).all() and (batch.duration[~solved, 0] == 6).all()
    assert (batch.reward[~solved] == 0).all()
    assert np.array_equal(batch.frames, batch.duration.sum(1))


def test_rewards_inside_an_option_are_discounted_by_their_step_within_it():
    policy = craft_policy(n_options=1)
    set_option(policy, 0, USE, end_logit=-50.0)  # one decision for the whole episode

    class LateWood(WoodAhead):
        """Wood ahead only from the third step on: the reward arrives at k = 2 within the option."""

        def reset(self, seeds=None, tasks=None, env_ids=None):
            obs = super().reset(seeds, tasks, env_ids)
            self.grid[:, 5, 4] = EMPTY
            self.steps_taken = 0
            return obs

        def step(self, actions):
            self.steps_taken += 1
            if self.steps_taken == 3:
                self.grid[:, 5, 4] = WOOD
            return super().step(actions)

    batch = collect(policy, LateWood(2, max_steps=10), CRAFT, [TASK] * 2, [0, 1], gamma=0.9)
    assert (batch.count == 1).all() and (batch.duration[:, 0] == 3).all()
    np.testing.assert_allclose(batch.reward[:, 0], 0.9**2)


def test_semi_mdp_gae_by_hand():
    gamma, lam = 0.9, 0.5
    reward = torch.tensor([[1.0, 0.0, 2.0], [0.5, 0.0, 0.0]])
    duration = torch.tensor([[2, 1, 3], [4, 0, 0]])
    value = torch.tensor([[0.3, 0.2, 0.1], [0.7, 9.0, 9.0]])
    count = torch.tensor([3, 1])
    advantage, returns = semi_mdp_gae(reward, duration, value, count, gamma, lam)
    d2 = 2.0 - 0.1
    a2 = d2
    d1 = 0.0 + gamma * 0.1 - 0.2
    a1 = d1 + gamma * lam * a2
    d0 = 1.0 + gamma**2 * 0.2 - 0.3
    a0 = d0 + gamma**2 * lam * a1
    torch.testing.assert_close(advantage[0], torch.tensor([a0, a1, a2]))
    torch.testing.assert_close(advantage[1], torch.tensor([0.5 - 0.7, 0.0, 0.0]))
    torch.testing.assert_close(returns[0], advantage[0] + value[0])
    torch.testing.assert_close(returns[1], torch.tensor([0.5, 0.0, 0.0]))


def test_replay_gives_the_log_probs_the_rollout_sampled_with():
    """The update's replay of an episode's decisions reproduces the controller's p^c at each decision."""
    policy = craft_policy()
    for option in range(3):
        set_option(policy, option, LEFT, end_logit=0.0)
    envs = CraftBatch(4, max_steps=8)
    obs = envs.reset(seeds=range(4), tasks=[TASK] * 4)
    policy.reset()
    seen = [[] for _ in range(4)]
    states = [[] for _ in range(4)]
    while not envs.done.all():
        active = ~envs.done
        action = policy.select_action({OBS_STATE: torch.from_numpy(obs).float(), "task": [TASK] * 4})
        for e in np.flatnonzero(policy.last_step.decided.numpy() & active):
            seen[e].append(policy.last_step.p_c[e].clone())
            states[e].append(obs[e].copy())
        obs, *_ = envs.step(action.numpy().astype(int).ravel())
    trainer = PPOTrainer(policy, PPOConfig())
    for e in range(4):
        logits, _ = replay_controller(policy, trainer.critic, torch.tensor(np.array(states[e]))[None],
                                      torch.tensor([0]))
        torch.testing.assert_close(torch.softmax(logits[0], -1), torch.stack(seen[e]), rtol=1e-5, atol=1e-6)


# ---- learning ------------------------------------------------------------------------------------


def test_ppo_learns_to_pick_the_option_that_solves_the_task_and_leaves_options_untouched():
    policy = solving_pool()
    frozen = {name: p.clone() for name, p in policy.named_parameters() if not name.startswith("core.controller")}
    envs = WoodAhead(64, reward="sparse", max_steps=6)
    config = PPOConfig(batch_size=64)  # the paper's lr, epochs, entropy and gamma
    rows = finetune(policy, envs, CRAFT, [TASK], total_frames=8_000, config=config, seed=0)
    assert rows[0]["success"] < 0.5  # chance: option 0 first with probability 1/3
    assert np.mean([row["success"] for row in rows[-5:]]) > 0.9
    for name, param in policy.named_parameters():
        if name in frozen:
            assert torch.equal(param, frozen[name]), name
            assert not param.requires_grad, name
    assert rows[-1]["frames"] >= 8_000 and rows[-1]["lr"] < rows[0]["lr"]


def test_only_the_controller_its_task_states_and_the_critic_are_optimised():
    policy = solving_pool()
    trainer = PPOTrainer(policy, PPOConfig())
    optimised = {id(p) for group in trainer.optimizer.param_groups for p in group["params"]}
    expected = [policy.core.controller_init, *policy.core.controller.parameters(), *trainer.critic.parameters()]
    assert optimised == {id(p) for p in expected}
    assert all(not p.requires_grad for p in [*policy.core.options.parameters(), policy.core.option_init])


def test_finetuning_is_reproducible_with_its_seed():
    def run() -> list[dict]:
        return finetune(solving_pool(), WoodAhead(16, reward="sparse", max_steps=6), CRAFT, [TASK], total_frames=600,
                        config=PPOConfig(lr=3e-3, batch_size=16), seed=3)

    assert run() == run()


def test_finetuning_refuses_soft_or_greedy_policies():
    with pytest.raises(ValueError, match="execution='hard' and inference_mode='sample'"):
        PPOTrainer(craft_policy(execution="soft"), PPOConfig())
    with pytest.raises(ValueError, match="execution='hard' and inference_mode='sample'"):
        collect(craft_policy(inference_mode="greedy"), CraftBatch(2), CRAFT, [TASK] * 2, [0, 1], 0.97)


def test_decisions_mask_marks_real_decisions():
    batch = Decisions(
        state=np.zeros((2, 3, 81)), option=np.zeros((2, 3), dtype=int), reward=np.zeros((2, 3)),
        duration=np.zeros((2, 3), dtype=int), count=np.array([1, 3]), task_index=np.zeros(2, dtype=int),
        return_=np.zeros(2), success=np.zeros(2, dtype=bool), frames=np.zeros(2, dtype=int),
    )
    assert batch.mask.tolist() == [[True, False, False], [True, True, True]]


# ---- baselines: MoE (one-step options) and flat PPO ------------------------------------------------


def test_moe_rollouts_are_one_step_options_with_undiscounted_step_rewards():
    """Under MoE the semi-MDP is the plain MDP: one decision per env step, each lasting one step, with
    that step's reward; options that would never terminate under OCN change nothing."""
    policy = craft_policy(n_options=2, hierarchy="moe")
    set_option(policy, 0, USE, end_logit=-50.0)
    set_option(policy, 1, DOWN, end_logit=-50.0)  # blocked by the wood: the agent keeps facing it
    batch = collect(policy, WoodAhead(16, reward="dense", max_steps=5), CRAFT, [TASK] * 16, range(16), gamma=0.5)
    assert np.array_equal(batch.count, batch.frames) and (batch.duration[batch.mask] == 1).all()
    assert (batch.duration[~batch.mask] == 0).all()
    np.testing.assert_allclose(batch.reward.sum(1), batch.return_)
    chose_use = (batch.option == 0) & batch.mask
    assert np.array_equal(batch.success, chose_use.any(1)) and batch.success.any() and (batch.count > 1).any()
    assert np.array_equal(batch.count[batch.success], chose_use.argmax(1)[batch.success] + 1)


def test_semi_mdp_gae_of_one_step_options_is_plain_gae():
    gamma, lam = 0.9, 0.8
    gen = torch.Generator().manual_seed(2)
    reward, value = torch.rand(3, 6, generator=gen), torch.rand(3, 6, generator=gen)
    count = torch.tensor([6, 4, 1])
    real = torch.arange(6) < count[:, None]
    reward, value = reward * real, value * real
    advantage, returns = semi_mdp_gae(reward, real.long(), value, count, gamma, lam)
    for e, n in enumerate(count.tolist()):
        following = 0.0
        for t in reversed(range(n)):
            next_value = value[e, t + 1] if t + 1 < n else 0.0
            following = reward[e, t] + gamma * next_value - value[e, t] + gamma * lam * following
            torch.testing.assert_close(advantage[e, t], following)
    torch.testing.assert_close(returns, advantage + value)


def test_hil_rollouts_run_every_option_for_exactly_skill_length_steps():
    """Under HIL (L = 3) the controller chooses at t = 1, 4, 7, ...: an option that would never end
    under OCN (down, blocked by the wood, so the agent keeps facing it) runs 3 steps, and one that
    would end after every step (use) runs on too, unless the episode ends first."""
    policy = craft_policy(n_options=2, hierarchy="hil", skill_length=3)
    set_option(policy, 0, DOWN, end_logit=-50.0)
    set_option(policy, 1, USE, end_logit=50.0)
    batch = collect(policy, WoodAhead(32, reward="dense", max_steps=10), CRAFT, [TASK] * 32, range(32), gamma=0.5)
    last = batch.count - 1
    assert np.array_equal(batch.count, -(-batch.frames // 3))
    for e in range(32):
        assert (batch.duration[e, : last[e]] == 3).all() and batch.duration[e, last[e]] == batch.frames[e] - 3 * last[e]
    assert (batch.duration[~batch.mask] == 0).all()
    chose_use = (batch.option == 1) & batch.mask
    assert np.array_equal(batch.success, chose_use.any(1)) and batch.success.any() and (batch.count > 1).any()
    won = batch.success
    # use ends the episode at its first step, k = 0 within its option: reward 1, undiscounted
    assert np.array_equal(batch.frames[won], 3 * chose_use.argmax(1)[won] + 1)
    np.testing.assert_allclose(batch.reward[won, last[won]], 1.0)
    np.testing.assert_allclose(batch.reward.sum(1), batch.return_)


def test_primitive_action_pool_option_a_always_emits_action_a():
    policy = primitive_action_pool([TASK], hidden_size=16)
    obs = torch.from_numpy(CraftBatch(8).reset(seeds=range(8), tasks=[TASK] * 8)).float()
    for action in range(5):
        chosen = torch.full((8,), action)
        emitted, _, _ = policy.act_with_options(obs, chosen, None, torch.ones(8, dtype=torch.bool), greedy=False)
        assert torch.equal(emitted, torch.full((8, 1), float(action)))
    assert policy.config.hierarchy == "moe" and policy.config.temperature == 1.0


def wood_success_before_and_after(policy, frames: int, config: PPOConfig) -> tuple[float, float]:
    """Success of a policy on 256 fresh `WoodAhead` maps, before and after `frames` env frames of PPO
    (64 envs, seed 0)."""

    def success_rate() -> float:
        batch = collect(policy, WoodAhead(256, reward="sparse", max_steps=6), CRAFT, [TASK] * 256, range(256), 0.97)
        return float(batch.success.mean())

    random_rate = success_rate()
    finetune(policy, WoodAhead(64, reward="sparse", max_steps=6), CRAFT, [TASK], total_frames=frames, config=config,
             seed=0)
    return random_rate, success_rate()


def test_flat_ppo_learns_to_use_the_wood_it_faces_well_above_the_random_rate():
    """The untrained flat policy's success on fresh maps is measured first (about 1/4: it must `use`
    before it turns away); 8k frames of PPO with the paper's settings must lift it above 0.9."""
    torch.manual_seed(0)
    policy = primitive_action_pool([TASK], hidden_size=32)
    random_rate, learned = wood_success_before_and_after(policy, 8_000, PPOConfig(batch_size=256))
    assert random_rate < 0.4 and learned > 0.9 and learned > random_rate + 0.5, (random_rate, learned)
