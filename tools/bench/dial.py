"""`ocn-bench dial`: Dial env steps per second, the env's physics rate against bare `mujoco.mj_step`
on the same model and trajectory, and the expert's success over random two-digit PINs, noise-free and
with the DART noise it records with (and the reference demonstrations' noise)."""

from __future__ import annotations

import argparse
import time
from typing import Any

from lerobot_policy_ocn.tools.bench.common import add_common_arguments, best_rate, header


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_common_arguments(parser, "dial")
    parser.add_argument("--steps", type=int, default=2000, help="env steps per timing")
    parser.add_argument("--pins", type=int, default=200, help="random two-digit PINs for the expert success rate")


def physics_rates(n_steps: int) -> dict[str, float]:
    """Dial env steps per second, and the env's physics rate against bare `mj_step` replaying the very
    same controls from the same start (so both integrate the identical trajectory, contacts included)."""
    import mujoco
    import numpy as np

    from lerobot_policy_ocn.envs.dial import FRAME_SKIP, DialEnv, DialVectorEnv

    controls = np.random.default_rng(0).uniform(-0.3, 0.3, size=(n_steps, 9))
    env = DialEnv(task="12", max_steps=10**9)
    env.reset(seed=0)
    start_qpos = env.batch.data[0].qpos.copy()
    counter = iter(range(10**12))

    def env_run() -> None:
        env.reset(seed=0)
        for u in controls:
            env.step(u)

    model = env.batch.model
    data = mujoco.MjData(model)

    def bare_run() -> None:
        mujoco.mj_resetData(model, data)
        data.qpos[:] = start_qpos
        for u in controls:
            data.ctrl[:] = u
            mujoco.mj_step(model, data, nstep=FRAME_SKIP)

    env_rate = bare_rate = 0.0
    for _ in range(5):  # interleaved, best of 5 each: both see the same load on a shared machine
        env_rate = max(env_rate, best_rate(env_run, 1, n_steps, repeats=1))
        bare_rate = max(bare_rate, best_rate(bare_run, 1, n_steps, repeats=1))
    vector = DialVectorEnv(16, task="12", max_steps=10**9)
    vector.reset(seed=0)
    vector_controls = np.random.default_rng(1).uniform(-0.3, 0.3, size=(64, 16, 9))
    return {
        "frame_skip": FRAME_SKIP,
        "single_env_steps_per_s": best_rate(lambda: env.step(controls[next(counter) % n_steps]), n_steps, 1),
        "vector_env_16_steps_per_s": best_rate(lambda: vector.step(vector_controls[next(counter) % 64]),
                                               n_steps // 16, 16),
        "replay_env_steps_per_s": env_rate,
        "replay_bare_mj_step_env_steps_per_s": bare_rate,
        "bare_mj_step_physics_steps_per_s": bare_rate * FRAME_SKIP,
        "physics_ratio": env_rate / bare_rate,
        "wrapper_overhead": 1.0 - env_rate / bare_rate,
    }


def expert_success(pins: int, noise_levels: tuple[float, ...]) -> dict[str, Any]:
    """Success of the Dial expert on `pins` random two-digit PINs from 1, 2, 4, 8, all run as one batch."""
    import numpy as np

    from lerobot_policy_ocn.envs.dial import DialBatch, DialExpert, sample_pin

    rng = np.random.default_rng(2024)
    tasks = [sample_pin(rng, 2, (1, 2, 4, 8)) for _ in range(pins)]
    batch = DialBatch(pins)
    batch.reset(seeds=list(range(pins)), tasks=tasks)
    expert = DialExpert(batch, noise_levels)
    expert.reset(seeds=list(range(pins)))
    success = np.zeros(pins, dtype=bool)
    start = time.perf_counter()
    while not batch.done.all():
        success |= batch.step(expert.perturb(expert.act()))[2]
    wall = time.perf_counter() - start
    steps = batch.t[success]
    return {
        "pins": pins,
        "noise_levels": list(noise_levels),
        "success": float(success.mean()),
        "failed": [list(tasks[i]) for i in np.flatnonzero(~success)],
        "steps_median": float(np.median(steps)),
        "steps_p99": float(np.percentile(steps, 99)),
        "steps_max": int(steps.max()),
        "step_limit": int(batch.max_steps[0]),
        "wall_s": wall,
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The measurements; `ocn-bench` adds the provenance and writes the report (`markdown`)."""
    from lerobot_policy_ocn.envs.dial.expert import NOISE_LEVELS, REFERENCE_NOISE_LEVELS

    return {
        "env": physics_rates(args.steps),
        "expert": expert_success(args.pins, (0.0,)),
        "expert_dart": expert_success(args.pins, NOISE_LEVELS),
        "expert_reference_dart": expert_success(args.pins, REFERENCE_NOISE_LEVELS),
    }


def _levels(expert: dict[str, Any]) -> str:
    return ", ".join(f"{level:g}" for level in expert["noise_levels"])


def markdown(r: dict[str, Any]) -> str:
    e = r["env"]
    rows = "".join(
        f"| expert success, {x['pins']} random two-digit PINs from 1, 2, 4, 8, {name} | **{x['success']:.3f}** "
        f"(median {x['steps_median']:.0f} steps, p99 {x['steps_p99']:.0f}, "
        f"max {x['steps_max']} of {x['step_limit']}) |\n"
        for name, x in (("noise-free", r["expert"]),
                        (f"with DART noise as recorded (levels {_levels(r['expert_dart'])})", r["expert_dart"]),
                        (f"with the reference demonstrations' DART noise (levels "
                         f"{_levels(r['expert_reference_dart'])}; not recorded)", r["expert_reference_dart"]))
    )
    return (
        header("Dial env speed and expert success", r)
        + "| what | result |\n|---|---|\n"
        f"| one `DialEnv` (gymnasium API), random controls | {e['single_env_steps_per_s']:,.0f} env steps/s "
        f"({e['single_env_steps_per_s'] * e['frame_skip']:,.0f} physics steps/s) |\n"
        f"| 16 envs, `DialVectorEnv.step` | {e['vector_env_16_steps_per_s']:,.0f} env steps/s |\n"
        f"| bare `mujoco.mj_step(nstep={e['frame_skip']})`, same model, same controls and start | "
        f"{e['replay_bare_mj_step_env_steps_per_s']:,.0f} env steps/s "
        f"({e['bare_mj_step_physics_steps_per_s']:,.0f} physics steps/s) |\n"
        f"| `DialEnv` replaying those controls | {e['replay_env_steps_per_s']:,.0f} env steps/s |\n"
        f"| physics rate of the env / bare `mj_step` | **{e['physics_ratio']:.3f}** (wrapper overhead "
        f"{e['wrapper_overhead']:.1%}; goal: under 20%) |\n"
        f"{rows}\n"
        "The replay rows integrate the identical trajectory (same start pose, same controls), so their ratio is "
        "the cost of the env around the physics: observation, press detection, rewards, gymnasium API. "
        "The replay timings are interleaved, best of 5 each; the other rates are the best of 3.\n"
    )
