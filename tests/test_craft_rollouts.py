"""Rollouts of OCN in Craft used by `ocn-eval`: each option alone, the whole policy, and the options
under an oracle controller."""

import numpy as np
import pytest
import torch

from lerobot_policy_ocn.envs.craft.batch import CraftBatch
from lerobot_policy_ocn.envs.craft.world import USE, default_max_steps
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_STATE
from lerobot_policy_ocn.ocn import OCNConfig, OCNPolicy
from lerobot_policy_ocn.tools.rl.craft_rollouts import craft_world
from lerobot_policy_ocn.tools.worlds import craft
from lerobot_policy_ocn.tools.rl.rollouts import free_run_success, option_subtask_success, oracle_controller_success
from conftest import CRAFT_STATE

TASK = "get wood, get iron"
CRAFT = craft_world("paper")
CRAFT_SUBTASK_IDS = {code: craft().subtask_codes.index(code) for code in "AC"}


def identity(x):
    return x


def make_policy(**overrides) -> OCNPolicy:
    torch.manual_seed(0)
    config = OCNConfig(
        device="cpu", recipe="paper", hidden_size=8, mlp_hidden_size=8, n_options=2, tasks=[TASK],
        inference_mode="greedy", **CRAFT_STATE,
        input_features={OBS_STATE: PolicyFeature(FeatureType.STATE, (81,))},
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (1,))}, **overrides,
    )
    return OCNPolicy(config)


def set_option_behaviour(policy: OCNPolicy, action: int, end_logit: float) -> None:
    """Every option always picks `action` and terminates with probability sigmoid(end_logit)."""
    with torch.no_grad():
        out = policy.core.options
        out.w_out[..., : out.n_out] = 0.0
        out.b_out[..., : out.n_out] = -50.0
        out.b_out[..., action] = 50.0
        out.w_out[..., -1] = 0.0
        out.b_out[..., -1] = end_logit


def first_use_completes(subtask: str, episodes: int) -> float:
    """Fraction of the maps (seeds 0..episodes-1) where `use` at step 1 already completes the subtask."""
    craft = CraftBatch(episodes, mode="paper")
    craft.reset(seeds=range(episodes), tasks=[subtask] * episodes)
    craft.step(np.full(episodes, USE))
    return float((craft.progress == 1).mean())


def test_an_option_that_terminates_at_once_only_gets_its_first_step():
    policy = make_policy()
    set_option_behaviour(policy, action=USE, end_logit=50.0)
    table = option_subtask_success(policy, identity, identity, CRAFT, ["A", "C"], episodes=64)
    expected = [first_use_completes("A", 64), first_use_completes("C", 64)]
    assert table.success.shape == (2, 2) and 0 < sum(expected)
    assert np.allclose(table.success, [expected, expected])
    assert np.allclose(table.stopped, 1 - table.success)  # every failure is the termination at step 2


def test_an_option_that_never_ends_runs_to_the_step_limit():
    policy = make_policy()
    set_option_behaviour(policy, action=0, end_logit=-50.0)  # always "down": never uses anything
    table = option_subtask_success(policy, identity, identity, CRAFT, ["A"], episodes=8)
    assert np.array_equal(table.success, np.zeros((2, 1))) and np.array_equal(table.stopped, np.zeros((2, 1)))
    assert free_run_success(policy, identity, identity, CRAFT, [TASK], episodes=8) == {TASK: 0.0}


def test_fixed_length_options_run_on_and_restart_every_skill_length():
    policy = make_policy(hierarchy="hil", skill_length=3)
    set_option_behaviour(policy, action=0, end_logit=50.0)  # a head that would stop an OCN option at once
    restarts = []
    act = policy.act_with_options

    def recording_act(state, option, option_h, restart, greedy):
        restarts.append(restart.tolist())
        return act(state, option, option_h, restart, greedy)

    policy.act_with_options = recording_act
    table = option_subtask_success(policy, identity, identity, CRAFT, ["A"], episodes=2)
    assert np.array_equal(table.success, np.zeros((2, 1)))  # "down" forever completes nothing
    assert np.array_equal(table.stopped, np.zeros((2, 1)))
    assert len(restarts) == default_max_steps(1)  # the termination head never cut a run short
    assert restarts == [[t % 3 == 0] * 4 for t in range(len(restarts))]


def recorded_options(policy: OCNPolicy) -> list[tuple[list[int], list[bool]]]:
    """Wrap `act_with_options` to record each call's (option, restart) per row."""
    calls = []
    act = policy.act_with_options

    def recording_act(state, option, option_h, restart, greedy):
        calls.append((option.tolist(), restart.tolist()))
        return act(state, option, option_h, restart, greedy)

    policy.act_with_options = recording_act
    return calls


def test_the_oracle_decides_only_where_the_running_option_terminates():
    """Option 1 (A's) never terminates, so the oracle never gets to start C's option: no success,
    and every acting call runs option 1."""
    policy = make_policy()
    set_option_behaviour(policy, action=0, end_logit=-50.0)
    calls = recorded_options(policy)
    wood, iron = CRAFT_SUBTASK_IDS["A"], CRAFT_SUBTASK_IDS["C"]
    success = oracle_controller_success(policy, identity, identity, CRAFT, ["AC"], {wood: 1, iron: 0}, episodes=3)
    assert success == {"AC": 0.0}
    assert all(option == [1, 1, 1] for option, _ in calls)
    assert calls[0][1] == [True] * 3 and not any(any(restart) for _, restart in calls[1:])


def test_the_progress_oracle_switches_where_the_subtask_completes_whatever_the_terminations_say():
    """Options that `use` at every step and never terminate: under switch="progress" the oracle still
    starts C's option (1) right after the step that got the wood, and only there; a bad switch name
    is refused."""
    episodes = 64
    policy = make_policy()
    set_option_behaviour(policy, action=USE, end_logit=-50.0)
    calls = recorded_options(policy)
    wood, iron = CRAFT_SUBTASK_IDS["A"], CRAFT_SUBTASK_IDS["C"]
    oracle_controller_success(policy, identity, identity, CRAFT, ["AC"], {wood: 0, iron: 1}, episodes=episodes,
                              switch="progress")
    craft = CraftBatch(episodes, mode="paper")
    craft.reset(seeds=range(episodes), tasks=["AC"] * episodes)
    craft.step(np.full(episodes, USE))
    got_wood = craft.progress == 1
    assert 0 < got_wood.sum() < episodes
    assert len(calls) > 3  # one acting call per step: the terminations are not consulted
    assert calls[1] == (np.where(got_wood, 1, 0).tolist(), got_wood.tolist())
    assert not any(any(restart) for _, restart in calls[2:])  # nobody can use iron (C) from the wood's cell
    with pytest.raises(ValueError, match="switch must be one of"):
        oracle_controller_success(policy, identity, identity, CRAFT, ["AC"], {wood: 0, iron: 1}, episodes=1,
                                  switch="always")


def test_the_progress_oracle_restarts_fixed_length_options_every_skill_length():
    policy = make_policy(hierarchy="hil", skill_length=3)
    set_option_behaviour(policy, action=0, end_logit=50.0)  # "down" forever completes nothing
    calls = recorded_options(policy)
    wood, iron = CRAFT_SUBTASK_IDS["A"], CRAFT_SUBTASK_IDS["C"]
    assert oracle_controller_success(policy, identity, identity, CRAFT, ["AC"], {wood: 0, iron: 1}, episodes=2,
                                     switch="progress") == {"AC": 0.0}
    assert [restart for _, restart in calls] == [[t % 3 == 0] * 2 for t in range(len(calls))]


def test_the_oracle_starts_the_option_of_the_current_subtask_at_each_termination():
    """Every option uses and terminates at every step. Where the first `use` completes A, the next
    decision starts C's option (1); elsewhere A's option (0) restarts at every step."""
    episodes = 64
    policy = make_policy()
    set_option_behaviour(policy, action=USE, end_logit=50.0)
    calls = recorded_options(policy)
    wood, iron = CRAFT_SUBTASK_IDS["A"], CRAFT_SUBTASK_IDS["C"]
    oracle_controller_success(policy, identity, identity, CRAFT, ["AC"], {wood: 0, iron: 1}, episodes=episodes)
    craft = CraftBatch(episodes, mode="paper")
    craft.reset(seeds=range(episodes), tasks=["AC"] * episodes)
    craft.step(np.full(episodes, USE))
    got_wood = craft.progress == 1
    assert 0 < got_wood.sum() < episodes
    second_step = calls[2]  # calls: step 1 acting, step 2 termination check, step 2 acting
    assert second_step[1] == [True] * episodes
    assert second_step[0] == np.where(got_wood, 1, 0).tolist()
