"""The work of `ocn-finetune` (its command line is `tools.cli.ocn_finetune`): the option pool a fresh
controller chooses over, built from one or more checkpoints (OCN options, compILE's decoder latents, MoE
or HIL options) or from Craft's primitive actions (flat PPO), or an OMPN made finetunable, then PPO
(`tools.rl.ppo`) with snapshots to resume from, the learning curve and the finetuned checkpoint.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from lerobot.configs import NormalizationMode
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot_policy_ocn.ocn_data.preflight import check_can_create
from lerobot_policy_ocn.compile import CompILEPolicy
from lerobot_policy_ocn.ocn import OCNConfig, OCNPolicy, make_ocn_pre_post_processors
from lerobot_policy_ocn.ompn import OMPNPolicy
from lerobot_policy_ocn.sequence import SequenceConfig
from lerobot_policy_ocn.tools.eval.parsing import Processor, load_policy
from lerobot_policy_ocn.tools.rl.ompn_rl import finetunable_ompn, ompn_for_tasks
from lerobot_policy_ocn.tools.rl.ppo import Acting, PPOConfig, RunSnapshot, env_tasks, finetune
from lerobot_policy_ocn.tools.worlds import World, craft, dial, policy_world

# The checkpoint types --checkpoint takes: options to pool (ocn), a decoder's latents (compile), OMPN's RL form.
from lerobot_policy_ocn.tools.rl.finetune_settings import FRESH_CONTROLLER_TEMPERATURE, STATE_FILE
FINETUNED_TYPES = ("ocn", "compile", "ompn")

# Arguments that do not change what a run computes, so a resumed run may differ in them (--threads may
# change the last bits of the floating-point sums, so a resume on other threads is not bit-identical).
NOT_SETTINGS = ("out", "resume", "threads")

# Config fields that must agree for options of different checkpoints to share one encoder, one
# action head and one stacked cell.
# `hierarchy` and the skill length it fixes too: MoE's and HIL's options were trained to run a fixed
# number of steps (1 or `skill_length`) and never learned to terminate; the pool keeps that schedule.
# compILE decoders' latents stack only with decoders of the same latent count and width.
POOL_FIELDS = ("obs_encoder", "action_type", "n_actions", "hidden_size", "mlp_hidden_size", "mlp_depth", "log_std_min",
               "log_std_max", "hierarchy", "fixed_skill_length", "decoder_latents", "decoder_hidden_size",
               "normalization_mapping")


def check_poolable(policies: Sequence[OCNPolicy], names: Sequence[str]) -> None:
    """Options can only be pooled if they read the same inputs and write the same action head."""
    first = policies[0].config
    if len({bool(policy.config.decoder_latents) for policy in policies}) > 1:
        raise ValueError("Cannot pool OCN options with compILE decoders' latents: finetune each kind on its own.")
    for policy, name in zip(policies[1:], names[1:], strict=True):
        config = policy.config
        for field in POOL_FIELDS:
            if getattr(config, field) != getattr(first, field):
                raise ValueError(
                    f"Cannot pool the options of {names[0]} and {name}: {field} is {getattr(first, field)!r} "
                    f"vs {getattr(config, field)!r} (pooled options must share encoder, action head and sizes)."
                )
        for kind in ("input_features", "output_features"):
            shapes = {key: tuple(feature.shape) for key, feature in getattr(config, kind).items()}
            if shapes != {key: tuple(feature.shape) for key, feature in getattr(first, kind).items()}:
                raise ValueError(f"Cannot pool the options of {names[0]} and {name}: their {kind} differ.")


def check_same_normalisation(
    policies: Sequence[OCNPolicy], preprocessors: Sequence[Processor], names: Sequence[str]
) -> None:
    """Pooled options all read states through the first checkpoint's preprocessor and act through its
    postprocessor: unless the normalisation is the identity (Craft), the checkpoints must have been
    trained with the same statistics."""
    if all(mode == NormalizationMode.IDENTITY for mode in policies[0].config.normalization_mapping.values()):
        return
    first = preprocessors[0].state_dict()
    for preprocessor, name in zip(preprocessors[1:], names[1:], strict=True):
        theirs = preprocessor.state_dict()
        same = first.keys() == theirs.keys() and all(
            first[step].keys() == theirs[step].keys()
            and all(torch.equal(first[step][key], theirs[step][key]) for key in first[step])
            for step in first
        )
        if not same:
            raise ValueError(
                f"Cannot pool the options of {names[0]} and {name}: their normalisation statistics differ "
                "(pooled options read states through one preprocessor: train them on the same dataset)."
            )


def merge_option_pools(
    policies: Sequence[OCNPolicy], tasks: Sequence[str], temperature: float | None = None,
    names: Sequence[str] | None = None,
) -> OCNPolicy:
    """A new hard-execution OCN whose options are those of `policies`, in order, and whose controller is
    fresh (drawn from torch's current RNG) with one zero initial state per new task and softmax
    temperature `temperature` (None: `FRESH_CONTROLLER_TEMPERATURE`, whatever the checkpoints' was).

    The stacked option weights and the options' initial states are concatenated along the module
    axis, so option k of the pool is exactly option k - offset of its source model.
    """
    if not policies:
        raise ValueError("Pool at least one checkpoint's options.")
    names = list(names) if names is not None else [f"checkpoint {i}" for i in range(len(policies))]
    check_poolable(policies, names)
    changes: dict[str, Any] = {
        "n_options": sum(policy.config.n_options for policy in policies),
        "tasks": list(tasks),
        "execution": "hard",
        "inference_mode": "sample",
        "pretrained_path": None,
        "temperature": FRESH_CONTROLLER_TEMPERATURE if temperature is None else temperature,
    }
    pooled = OCNPolicy(dataclasses.replace(policies[0].config, **changes))
    with torch.no_grad():
        for name, param in pooled.core.options.named_parameters():
            param.copy_(torch.cat([source.core.options.get_parameter(name) for source in policies]))
        pooled.core.option_init.copy_(torch.cat([source.core.option_init for source in policies]))
    return pooled.eval()


def primitive_action_pool(tasks: Sequence[str], hidden_size: int, temperature: float | None = None) -> OCNPolicy:
    """A hard-execution MoE over Craft whose option a always emits primitive action a: the flat baseline.

    Each option's action logits are its output bias alone (0 for its action, -1e4 for the others, so
    sampling is exact); under `hierarchy="moe"` every option lasts one step, so the fresh controller
    (drawn from torch's current RNG) is a recurrent policy over primitive actions.
    """
    from lerobot_policy_ocn.envs.craft.observation import OBS_DIM
    from lerobot_policy_ocn.envs.craft.world import N_ACTIONS
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.utils.constants import ACTION, OBS_STATE

    config = OCNConfig(
        device="cpu", recipe="paper", obs_encoder="craft", action_type="discrete", n_options=N_ACTIONS,
        n_actions=N_ACTIONS, hidden_size=hidden_size, mlp_hidden_size=hidden_size,
        temperature=FRESH_CONTROLLER_TEMPERATURE if temperature is None else temperature, tasks=list(tasks),
        hierarchy="moe",
        execution="hard", inference_mode="sample",
        input_features={OBS_STATE: PolicyFeature(FeatureType.STATE, (OBS_DIM,))},
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (1,))},
    )
    policy = OCNPolicy(config)
    with torch.no_grad():
        cell = policy.core.options
        cell.w_out[..., :N_ACTIONS] = 0.0
        cell.b_out[:, 0, :N_ACTIONS] = torch.where(torch.eye(N_ACTIONS, dtype=torch.bool), 0.0, -1e4)
    return policy.eval()


def compile_latent_options(policy: CompILEPolicy, name: str) -> OCNPolicy:
    """compILE's RL form: its frozen decoder as an MoE whose `latent_dim` one-step options are the
    decoder given each one-hot latent (the controller is a placeholder until `merge_option_pools`).

    The shared LeRobot plumbing (features, encoder, action head, normalisation) is the compILE
    config's; the controller's widths are compILE's `hidden_size`, and its temperature is 1, as flat
    PPO's is: it picks a one-step behaviour at every step.
    """
    config = policy.config
    if config.latent_type != "concrete":
        raise ValueError(
            f"{name} is a compILE with {config.latent_type} latents: its RL form chooses one of the decoder's "
            "categorical latents at every step, so it needs a compILE trained with --policy.latent_type=concrete."
        )
    shared = {field.name: getattr(config, field.name) for field in dataclasses.fields(SequenceConfig)}
    options = OCNPolicy(OCNConfig(
        **shared, recipe="paper", n_options=config.latent_dim, hidden_size=config.hidden_size,
        mlp_hidden_size=config.hidden_size, temperature=1.0, hierarchy="moe", decoder_latents=config.latent_dim,
        decoder_hidden_size=config.hidden_size,
    ))
    options.core.options.load_decoder(0, policy.decoder_obs, policy.decoder_latent, policy.decoder_out)
    return options.eval()


def option_source(policy: PreTrainedPolicy, name: str) -> OCNPolicy:
    """The OCN whose options a checkpoint adds to the pool: an `ocn` checkpoint as it is, a `compile`
    one as its decoder's latents (`load_policy` let no other type through)."""
    if isinstance(policy, CompILEPolicy):
        return compile_latent_options(policy, name)
    return policy


def save_checkpoint(policy: PreTrainedPolicy, preprocessor: Any, postprocessor: Any, path: Path) -> None:
    """A pretrained_model folder as `lerobot-train` writes one: config and weights, and the pre/post-processor
    pipelines (`ocn-finetune` writes `ocn` ones)."""
    policy.save_pretrained(path)
    preprocessor.save_pretrained(path)
    postprocessor.save_pretrained(path)


def plot_curve(rows: list[dict[str, Any]], labels: Sequence[str], path: Path, title: str) -> None:
    """Success (overall and per task) and mean return against env frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import EngFormatter

    frames = [row["frames"] for row in rows]
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.6))
    left.plot(frames, [row["success"] for row in rows], color="black", label="all tasks")
    for label in labels:
        left.plot(frames, [row[f"success[{label}]"] for row in rows], alpha=0.7, label=label)
    left.set_ylim(-0.02, 1.02)
    left.set_ylabel("success rate")
    left.legend(fontsize=8)
    right.plot(frames, [row["mean_return"] for row in rows], color="black")
    right.set_ylabel("mean episode return")
    for ax in (left, right):
        ax.set_xlabel("env frames")
        ax.xaxis.set_major_formatter(EngFormatter())
        ax.grid(alpha=0.3)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _check_args(args: argparse.Namespace) -> None:
    if bool(args.checkpoint) == args.flat:
        raise ValueError("Give either --checkpoint (one or more) or --flat.")
    if args.frames < 1 or args.envs < 1 or args.threads < 1 or args.hidden_size < 1:
        raise ValueError("--frames, --envs, --threads and --hidden-size must be >= 1.")
    if args.max_steps is not None and args.max_steps < 1:
        raise ValueError("--max-steps must be >= 1.")
    if args.resume:
        if (args.out / "finetune.json").exists():
            raise FileExistsError(f"--out {args.out} holds a finished run (finetune.json): nothing to resume.")
        if not (args.out / STATE_FILE).exists():
            raise FileNotFoundError(f"--resume: {args.out / STATE_FILE} does not exist: no run to go on with.")
    elif args.out.exists() and (not args.out.is_dir() or any(args.out.iterdir())):
        raise FileExistsError(f"--out {args.out} exists and is not an empty folder; outputs are never overwritten "
                              "(--resume goes on with an interrupted run).")
    check_can_create(args.out / "curve.csv", "--out")


def run_settings(args: argparse.Namespace) -> dict[str, Any]:
    """What identifies a run: every argument but `NOT_SETTINGS`, paths as strings."""
    def plain(value: Any) -> Any:
        if isinstance(value, list):
            return [plain(v) for v in value]
        return str(value) if isinstance(value, Path) else value

    return {key: plain(value) for key, value in vars(args).items() if key not in NOT_SETTINGS}


@dataclasses.dataclass
class Start:
    """What PPO starts from: the policy, the world it acts in, the new tasks as the policy's task
    strings (what the env hands the policy, e.g. "press 1, press 2, press 4", keying the new
    controller's initial states) and as the curve's labels ("124"), and the processors the policy
    acts through and its checkpoint is saved with."""

    policy: OCNPolicy | OMPNPolicy
    world: World
    tasks: list[str]
    labels: list[str]
    preprocessor: Processor
    postprocessor: Processor


def _new_tasks(world: World, spec: str) -> tuple[list[str], list[str]]:
    """--tasks in `world`: the policy's task strings and their labels."""
    parsed = world.parse_task_list(spec)
    return [world.task_description(task) for task in parsed], [world.task_code(task) for task in parsed]


def _flat_world(args: argparse.Namespace) -> World:
    """Craft, the one world with a flat baseline; --tasks of Dial PINs ask for flat PPO on Dial, refused."""
    try:
        dial().parse_task_list(args.tasks)
    except ValueError:
        return craft(args.mode)
    raise ValueError(
        "--flat is Craft's flat baseline over its 5 primitive actions; Dial's actions are 9 continuous torques and "
        "the paper's Dial comparison (figure 6) has no flat PPO, so --flat with Dial PINs is refused: finetune a "
        "Dial checkpoint with --checkpoint instead."
    )


def _start(args: argparse.Namespace) -> Start:
    """The pooled options of --checkpoint under a fresh controller, in the checkpoints' world, OMPN's
    RL form of an ompn --checkpoint (Craft), or with --flat Craft's primitive-action pool."""
    if args.flat:
        world = _flat_world(args)
        tasks, labels = _new_tasks(world, args.tasks)
        torch.manual_seed(args.seed)
        policy = primitive_action_pool(tasks, args.hidden_size, args.temperature)
        return Start(policy, world, tasks, labels, *make_ocn_pre_post_processors(policy.config))
    loaded = [load_policy(path, types=FINETUNED_TYPES) for path in args.checkpoint]
    names = [str(path) for path in args.checkpoint]
    if any(isinstance(policy, OMPNPolicy) for policy, _, _ in loaded):
        ompn = finetunable_ompn([policy for policy, _, _ in loaded], names, args.temperature)
        world = craft(args.mode)
        tasks, labels = _new_tasks(world, args.tasks)
        policy = ompn_for_tasks(ompn, tasks)
        return Start(policy, world, tasks, labels, loaded[0][1], loaded[0][2])
    sources = [option_source(policy, name) for (policy, _, _), name in zip(loaded, names, strict=True)]
    world = policy_world(sources[0].config.state_dim, sources[0].config.action_dim, args.mode)
    tasks, labels = _new_tasks(world, args.tasks)
    torch.manual_seed(args.seed)
    policy = merge_option_pools(sources, tasks, args.temperature, names)
    check_same_normalisation(sources, [preprocessor for _, preprocessor, _ in loaded], names)
    return Start(policy, world, tasks, labels, loaded[0][1], loaded[0][2])


def _source(args: argparse.Namespace, policy: OCNPolicy | OMPNPolicy) -> str:
    """What the curve's title says was finetuned."""
    if isinstance(policy, OMPNPolicy):
        return "the whole OMPN"
    if args.flat:
        source = "flat PPO"
    elif policy.config.decoder_latents:
        source = f"latents of {len(args.checkpoint)} compILE decoder(s)"
    else:
        source = f"options of {len(args.checkpoint)} checkpoint(s)"
    return f"{source}, T={policy.config.temperature:g}"


def _hierarchy(policy: OCNPolicy | OMPNPolicy) -> dict[str, Any]:
    """finetune.json's account of the finetuned hierarchy: an OCN's option pool, or OMPN's memory
    (no options, no controller)."""
    config = policy.config
    if isinstance(policy, OMPNPolicy):
        return {"hierarchy": None, "temperature": None, "n_options": None, "decoder_latents": None,
                "n_slots": config.n_slots}
    return {"hierarchy": config.hierarchy, "temperature": config.temperature, "n_options": config.n_options,
            "decoder_latents": config.decoder_latents}


def finetune_checkpoints(args: argparse.Namespace) -> dict[str, Any]:
    """Everything `ocn-finetune` does; returns the summary it writes to finetune.json."""
    from tqdm import tqdm

    _check_args(args)
    snapshot = RunSnapshot(args.out / STATE_FILE, run_settings(args))
    resume = snapshot.load() if args.resume else None
    torch.set_num_threads(args.threads)
    start = _start(args)
    policy, tasks, labels = start.policy, start.tasks, start.labels
    env_tasks(tasks, args.envs)
    config = PPOConfig(lr=args.lr, epochs=args.epochs, batch_size=args.batch_size, gamma=args.gamma,
                       gae_lambda=args.gae_lambda, clip=args.clip, entropy_coef=args.entropy)
    acting = Acting(start.world.rollouts(), start.preprocessor, start.postprocessor)
    envs = acting.world.new_batch(args.envs, args.reward, args.max_steps)

    args.out.mkdir(parents=True, exist_ok=True)
    done = resume["rows"] if resume else []
    # A resumed run's seconds go on from the interrupted run's last row.
    started = time.perf_counter() - (done[-1]["seconds"] if done else 0.0)
    with open(args.out / "curve.csv", "w", newline="") as handle, \
            tqdm(total=args.frames, desc="ocn-finetune", unit="frame") as bar:
        writer: csv.DictWriter | None = None

        def write(row: dict[str, Any]) -> None:
            nonlocal writer
            if writer is None:
                writer = csv.DictWriter(handle, fieldnames=list(row))
                writer.writeheader()
            writer.writerow(row)
            handle.flush()
            bar.update(min(row["frames"], args.frames) - bar.n)
            bar.set_postfix(success=f"{row['success']:.2f}", ret=f"{row['mean_return']:.2f}")

        def record(row: dict[str, Any]) -> None:
            row["seconds"] = round(time.perf_counter() - started, 2)
            write(row)

        for row in done:
            write(row)
        rows = finetune(policy, envs, acting, tasks, args.frames, config, args.seed, record, labels, snapshot, resume)
    wall = time.perf_counter() - started
    checkpoint = args.out / "pretrained_model"
    save_checkpoint(policy, start.preprocessor, start.postprocessor, checkpoint)
    title = f"ocn-finetune {','.join(labels)} ({args.reward}), {_source(args, policy)}, seed {args.seed}"
    plot_curve(rows, labels, args.out / "curve.png", title)
    summary = {
        "checkpoints": [str(path) for path in args.checkpoint],
        "world": start.world.name,
        "flat": args.flat,
        "policy_type": policy.name,
        **_hierarchy(policy),
        "tasks": tasks,
        "reward": args.reward,
        "mode": args.mode if start.world.name == "craft" else None,  # Craft's world mode; Dial has none
        "envs": args.envs,
        "seed": args.seed,
        "ppo": dataclasses.asdict(config),
        "frames": rows[-1]["frames"],
        "iterations": len(rows),
        "wall_s": round(wall, 2),
        "resumed_at_frames": done[-1]["frames"] if done else None,
        "frames_per_s": round(rows[-1]["frames"] / wall, 1),
        "final_success": rows[-1]["success"],
        "final_mean_return": rows[-1]["mean_return"],
        "pretrained_model": str(checkpoint),
    }
    (args.out / "finetune.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary
