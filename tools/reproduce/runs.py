"""What every reproduction shares: recording a dataset once, and `lerobot-train` runs that resume
from their last checkpoint and are never silently reused when their settings changed."""

from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from tools import console_script
from tools.bench import machine
from tools.reproduce.report import machine_words

SAVE_EVERY = 1000  # lerobot-train checkpoints this often by default, so a stopped run resumes from its last one
# OCNConfig.lr_schedule values whose rate at a step does not depend on the run's length: a run under
# one of them may be extended to more steps (`check_reusable`).
LENGTH_FREE_SCHEDULES = ("constant", "step")
# Linux caps one command-line argument at 128 KiB; a train split listed in more goes through a file.
MAX_SPLIT_ARGUMENT = 100_000


def record_dataset(root: Path, tasks: str, repo_id: str, episodes_per_task: int, seed: int, env: str = "craft",
                   dart_noise: float = 0.0) -> None:
    """Record demonstrations of `tasks` (comma-separated: Craft tasks, or Dial PINs with env "dial"),
    with Craft's DART noise if given, unless `root` already holds exactly that dataset; a dataset
    recorded with other settings is refused (`check_recorded_as`)."""
    arguments = ["--env", env, "--tasks", tasks, "--episodes-per-task", str(episodes_per_task),
                 "--root", str(root), "--repo-id", repo_id, "--seed", str(seed)]
    if dart_noise:
        arguments += ["--dart-noise", str(dart_noise)]
    if (root / "meta" / "info.json").exists():
        check_recorded_as(root, arguments)
        print(f"reusing the dataset in {root}", flush=True)
        return
    subprocess.run([console_script("record_demos"), *arguments], check=True)


def check_recorded_as(root: Path, arguments: list[str]) -> None:
    """Refuse to reuse a dataset unless one finished `record_demos` session with these arguments
    wrote it (its --root aside, so that a moved workdir still counts): a changed --data-seed or
    --episodes-per-task must not silently train on the old data."""
    from ocn_data.provenance import load_provenance

    sessions = load_provenance(root)["sessions"]
    recorded = [_recording_settings(shlex.split(session["command"])[1:]) for session in sessions]
    if recorded == [_recording_settings(arguments)] and not sessions[0]["interrupted"]:
        return
    found = "; ".join(session["command"] for session in sessions) or "no record_demos session"
    raise SystemExit(
        f"{root} holds a dataset recorded by: {found}\nwhile this reproduction records:\n  "
        f"{shlex.join(['record_demos', *arguments])}\nMove that folder away or pass another --workdir."
    )


def _recording_settings(arguments: list[str]) -> list[str]:
    """A record_demos argument list without its --root value."""
    settings = list(arguments)
    if "--root" in settings:
        at = settings.index("--root")
        del settings[at : at + 2]
    return settings


@dataclass
class TrainSettings:
    """How every `lerobot-train` run of a study trains; `policy` holds extra `--policy.*` values for
    the policy type `policy_type`; `save_every` is the checkpoint interval (a study that scores the
    model over training keeps checkpoints more often)."""

    steps: int
    batch_size: int
    window_size: int
    num_workers: int = 2
    threads: int = 1
    policy: dict[str, Any] = field(default_factory=dict)
    policy_type: str = "ocn"
    save_every: int = SAVE_EVERY
    # An option label file (`ocn_data.option_labels`) that the packed view of every run holds, for
    # clones taught their options (`--policy.taught_options=true`).
    option_labels: Path | None = None


@dataclass
class TrainedRun:
    """A finished training run: its checkpoint, the command shown in records, its wall time (None when
    an earlier reproduction trained all of it and kept no timing), the step its timing starts from (not
    0 when it resumed a run whose first steps were trained before invocations were timed), the
    machines that trained it and whether this invocation trained any of its steps (False: found
    finished)."""

    checkpoint: Path
    command: str
    train_wall_s: float | None
    trained_on: list[str] = field(default_factory=list)
    timed_from_step: int = 0
    trained_now: bool = False


def train_command(
    settings: TrainSettings, data: Path, repo_id: str, out: Path, seed: int, overrides: dict[str, Any],
    init: Path | None = None,
) -> list[str]:
    """The `lerobot-train` call of one run on the dataset's train split: a fresh policy of the
    settings' type, or the pretrained_model `init` trained on (its config, then `overrides`)."""
    from ocn_data.episodes_table import split_episodes

    train = [int(episode) for episode in split_episodes(data, "train")]
    policy = f"--policy.path={init}" if init is not None else f"--policy.type={settings.policy_type}"
    command = [
        console_script("lerobot-train"), policy, f"--dataset.repo_id={repo_id}",
        f"--dataset.root={data}", split_argument(train, out), "--policy.device=cpu", "--policy.push_to_hub=false",
        "--wandb.enable=false", "--env_eval_freq=0", f"--steps={settings.steps}", f"--batch_size={settings.batch_size}",
        f"--num_workers={settings.num_workers}", f"--save_freq={min(settings.steps, settings.save_every)}",
        "--log_freq=50",
        f"--seed={seed}", f"--policy.window_size={settings.window_size}", f"--output_dir={out}",
    ]
    return command + [f"--policy.{key}={cli_value(value)}" for key, value in {**settings.policy, **overrides}.items()]


def cli_value(value: Any) -> str:
    """A setting as lerobot-train's parser reads it: booleans in lower case (draccus refuses `True`)."""
    return str(value).lower() if isinstance(value, bool) else str(value)


def training_data(settings: TrainSettings, data: Path, repo_id: str, overrides: dict[str, Any],
                  init: Path | None) -> Path:
    """The view of the dataset `data` that a run trains on: its packed view (`ocn_data.packed_view`) for
    a policy with window_start "packed" (set here or in `init`'s config; its longer episodes cut where
    the policy skips them on windows, `skip_long_episodes`), else its training view
    (`ocn_data.training_view`: the same windows as the recording, loaded faster). A packed view holds
    the settings' option labels, if any."""
    from ocn_data.packed_view import packed_view
    from ocn_data.training_view import training_view

    policy = {**settings.policy, **overrides}
    if init is not None:
        policy = {**json.loads((init / "config.json").read_text()), **policy}
    if policy.get("window_start") == "packed":
        cut_long = str(policy.get("skip_long_episodes", False)).lower() == "true"
        return packed_view(data, repo_id, settings.window_size, cut_long, settings.option_labels)
    if settings.option_labels is not None:
        raise ValueError(f"Option labels ({settings.option_labels}) are held by a packed view only: train with "
                         "window_start='packed'.")
    return training_view(data, repo_id)


def split_argument(train: list[int], out: Path) -> str:
    """`--dataset.episodes=[...]` naming the train split; for a split too long for one argument (the
    60,000-demonstrations-per-task study lists 144,000 episodes), `--config_path` to a JSON beside `out`
    that holds it: `lerobot-train` reads that file first and the other arguments on top of it."""
    listed = f"--dataset.episodes=[{','.join(map(str, train))}]"
    if len(listed) <= MAX_SPLIT_ARGUMENT:
        return listed
    path = out.parent / f"{out.name}_split.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"dataset": {"episodes": train}}) + "\n")
    return f"--config_path={path}"


def run_command(
    settings: TrainSettings, data: Path, repo_id: str, run_dir: Path, seed: int, overrides: dict[str, Any],
    init: Path | None = None,
) -> tuple[list[str], str]:
    """The `lerobot-train` call of the run in `run_dir` (`train_command` on the view it trains on,
    `training_data`), and its words as records show them, the train split's episodes elided."""
    source = training_data(settings, data, repo_id, overrides, init)
    command = train_command(settings, source, repo_id, run_dir / "train", seed, overrides, init)
    return command, " ".join(["lerobot-train", *command[1:4], "--dataset.episodes=[<train split>]", *command[5:]])


def train_policy(
    settings: TrainSettings, data: Path, repo_id: str, run_dir: Path, seed: int, overrides: dict[str, Any],
    init: Path | None = None,
) -> TrainedRun:
    """Train one run into `run_dir/train` (or finish or reuse it) and return its last checkpoint;
    `init`: a pretrained_model to train on instead of a fresh policy. `lerobot-train` reads the
    dataset's view that the policy trains on (`training_data`)."""
    command, shown = run_command(settings, data, repo_id, run_dir, seed, overrides, init)
    check_reusable(run_dir, shown)
    wall, trained_now = train(settings, command, shown, run_dir)
    return TrainedRun(run_dir / "train" / "checkpoints" / "last" / "pretrained_model", shown, wall, trained_on(run_dir),
                      timed_from_step(run_dir), trained_now)


@dataclass
class Restarts:
    """Several seeds for one run: `count` restarts train `select_step` steps each, and the one that
    clones the validation split's demonstrations best (lowest `validation_nll`, over its first
    `val_episodes` episodes; no subtask label read) trains on to the run's full steps. On Dial a lower
    NLL at step 2,000 went with a better digit split, loosely (results/dial_memoryless/, "Choosing
    among restarts"). Restart j of seed s trains with seed s * count + j, so the restarts of different
    seeds never share one, and a single restart is the seed itself."""

    count: int = 1
    select_step: int = 0
    val_episodes: int = 600

    def seeds(self, seed: int) -> list[int]:
        return [seed * self.count + j for j in range(self.count)]

    def check(self, steps: int) -> None:
        """Refuse restarts that cannot be chosen in a run of `steps` steps, before anything trains."""
        if self.count < 1:
            raise SystemExit(f"--restarts {self.count}: a run needs at least one.")
        if self.count > 1 and not 0 < self.select_step <= steps:
            raise SystemExit(f"restarts are chosen at step {self.select_step} (--select-step), which must lie in "
                             f"1..{steps} (--steps).")


def train_best_restart(
    settings: TrainSettings, data: Path, repo_id: str, run_dir: Path, seed: int, overrides: dict[str, Any],
    restarts: Restarts,
) -> tuple[TrainedRun, dict[str, Any] | None]:
    """`train_policy` of the run in `run_dir`, or with several `restarts` the best of them trained to
    the full steps in `run_dir/restart<j>`, with the choice (every restart's seed, command and
    validation NLL) kept in `run_dir/restarts.json` and returned, with the training wall seconds of all
    the restarts added up (`train_wall_s`, None if one was not timed): the clone's whole cost. A choice
    made by the same commands is reused, so that an interrupted reproduction goes on training the
    chosen restart."""
    restarts.check(settings.steps)
    if restarts.count == 1:
        return train_policy(settings, data, repo_id, run_dir, seed, overrides), None
    early = replace(settings, steps=restarts.select_step)
    folders = [run_dir / f"restart{j}" for j in range(restarts.count)]
    commands = [run_command(early, data, repo_id, folder, restart_seed, overrides)[1]
                for folder, restart_seed in zip(folders, restarts.seeds(seed), strict=True)]
    record_path = run_dir / "restarts.json"
    choice = json.loads(record_path.read_text()) if record_path.exists() else None
    if choice is None or choice["val_episodes"] != restarts.val_episodes or len(choice["restarts"]) != len(commands) \
            or not all(same_training(r["command"], c) for r, c in zip(choice["restarts"], commands, strict=True)):
        from tools.episode_parsing import validation_nll

        scored = []
        for folder, restart_seed in zip(folders, restarts.seeds(seed), strict=True):
            trained = train_policy(early, data, repo_id, folder, restart_seed, overrides)
            scored.append({"seed": restart_seed, "command": trained.command,
                           "val_nll": validation_nll(trained.checkpoint, data, restarts.val_episodes)})
        best = min(range(len(scored)), key=lambda j: scored[j]["val_nll"])
        choice = {"select_step": restarts.select_step, "val_episodes": restarts.val_episodes, "chosen": best,
                  "chosen_seed": scored[best]["seed"], "restarts": scored}
        run_dir.mkdir(parents=True, exist_ok=True)
        record_path.write_text(json.dumps(choice, indent=2) + "\n")
    chosen = train_policy(settings, data, repo_id, folders[choice["chosen"]], choice["chosen_seed"], overrides)
    return chosen, {**choice, "train_wall_s": added_wall_s([recorded_wall_s(folder) for folder in folders])}


@dataclass
class Settling:
    """A second `lerobot-train` run that continues an OCN run for `steps` steps under the log
    termination cost (`--policy.termination_cost`, `--policy.termination_penalty=log`): once the options
    have split the subtasks, it removes their terminations inside a subtask
    (results/imitation_s1_termination_penalty). A cost from step 0 kept them from splitting in the
    one trial made (README, the settling phase)."""

    steps: int
    termination_cost: float
    # Further `--policy.*` settings of the settling run alone (`ocn-reproduce imitation-s1 --settle-*`),
    # such as a usage balance that lets spare options idle once the split is found.
    policy: dict[str, Any] = field(default_factory=dict)

    def overrides(self) -> dict[str, Any]:
        return {"termination_cost": self.termination_cost, "termination_penalty": "log", **self.policy}


def settings_suffix(overrides: dict[str, Any] | None) -> str:
    """Folder-name suffix naming non-default settings (`_cosine`, `_usage_balance1.0`, a switch set on as
    `_usage_balance_exact`)."""
    def part(key: str, value: Any) -> str:
        if isinstance(value, bool):
            return f"_{key}" if value else f"_no_{key}"
        return f"_{value}" if isinstance(value, str) else f"_{key}{value}"

    return "".join(part(key, value) for key, value in (overrides or {}).items())


def settle_dir(run_dir: Path, settling: Settling | None = None) -> Path:
    """Where a run's settling run lives (`settle_policy`): `settle`, or a folder named after the
    settling's further policy settings (`settle_usage_balance_options3`), so that each keeps its own."""
    return run_dir / f"settle{settings_suffix(settling.policy if settling else None)}"


def settle_policy(settings: TrainSettings, trained: TrainedRun, data: Path, repo_id: str, run_dir: Path, seed: int,
                  settling: Settling) -> TrainedRun:
    """Settle the finished run `trained` into `run_dir/settle` (or reuse it): `continue_policy`."""
    return continue_policy(settings, trained, data, repo_id, settle_dir(run_dir, settling), seed, settling.steps,
                           settling.overrides(), origin_file="settled_from.txt")


def continue_policy(settings: TrainSettings, trained: TrainedRun, data: Path, repo_id: str, folder: Path, seed: int,
                    steps: int, overrides: dict[str, Any], origin_file: str = "continued_from.txt") -> TrainedRun:
    """Train the finished run `trained` on for `steps` steps under its config and `overrides`, into
    `folder` (or reuse it); the result's command chains both trainings and its wall time adds them up.
    A continuation made from the first run before it was trained on (more `--steps`) starts over:
    `origin_file` keeps the command it started from."""
    origin = folder / origin_file
    if origin.exists() and not same_training(origin.read_text().strip(), trained.command):
        print(f"training {folder} again: the run it continues was trained on since", flush=True)
        shutil.rmtree(folder)
    folder.mkdir(parents=True, exist_ok=True)
    origin.write_text(trained.command + "\n")
    continued = train_policy(replace(settings, steps=steps), data, repo_id, folder, seed, overrides,
                             init=trained.checkpoint)
    return TrainedRun(continued.checkpoint, f"{trained.command} && {continued.command}",
                      added_wall_s([trained.train_wall_s, continued.train_wall_s]),
                      list(dict.fromkeys(trained.trained_on + continued.trained_on)), trained.timed_from_step,
                      trained.trained_now or continued.trained_now)


def machine_name() -> str:
    """This machine in a few words, for records that gather runs made on several machines."""
    return machine_words(machine())


def _timings(run_dir: Path) -> dict[str, Any] | None:
    """A run's `train_wall_s.json`: its timed training invocations and their total (None for a run
    trained before timing)."""
    path = run_dir / "train_wall_s.json"
    return json.loads(path.read_text()) if path.exists() else None


def _invocations(run_dir: Path) -> list[dict[str, Any]]:
    """The timed training invocations of a run, in order (none for a run trained before timing)."""
    timings = _timings(run_dir)
    return timings["invocations"] if timings else []


def trained_on(run_dir: Path) -> list[str]:
    """The machines of a run's training invocations, in order, each once ("not recorded" for those
    made before invocations recorded their machine)."""
    return list(dict.fromkeys(invocation.get("machine", "not recorded") for invocation in _invocations(run_dir)))


def timed_from_step(run_dir: Path) -> int:
    """The training step the run's recorded wall time starts from: 0 when every step was timed."""
    invocations = _invocations(run_dir)
    return invocations[0]["from_step"] if invocations else 0


def training_record(trained: TrainedRun) -> dict[str, Any]:
    """How a run was trained, for its record: read afresh from its timing file whenever the record is
    used, so that a record scored before a field existed still reports it, and whether the invocation
    that uses it trained the run or found it finished."""
    return {"train_wall_s": trained.train_wall_s, "train_timed_from_step": trained.timed_from_step,
            "trained_on": trained.trained_on, "trained_by_this_invocation": trained.trained_now}


def evaluate_run(folder: Path, trained: TrainedRun, data: Path, repo_id: str, rollouts: int,
                 labels: dict[str, Any]) -> dict[str, Any]:
    """`ocn-eval` of a trained run on the validation split, with the option table read
    (`option_table_summary`), kept as the run's `record.json` (under `labels`, e.g. its variant and
    seed) and reused from there once written: its scores, under this call's labels, which may say more
    of the run than the labels it was scored under (a clone's restarts, with their summed time)."""
    from tools.parsing_metrics import option_table_summary

    record_path, eval_json = folder / "record.json", folder / "eval.json"
    if record_path.exists():
        record = json.loads(record_path.read_text())
        if same_training(record["train_command"], trained.command):
            return {**record, **labels, **training_record(trained)}
        print(f"rescoring {folder}: its run was trained on since it was scored", flush=True)
    started = time.perf_counter()
    subprocess.run(
        [console_script("ocn-eval"), "--policy", str(trained.checkpoint), "--root", str(data), "--repo-id", repo_id,
         "--split", "val", "--out", str(eval_json), "--rollouts", str(rollouts)],
        check=True,
    )
    scores = json.loads(eval_json.read_text())
    scores.update(option_table_summary(np.array(scores["option_subtask_success"]["table"])))
    record = {
        **labels,
        **training_record(trained),
        "evaluated_on": machine_name(),
        "eval_wall_s": round(time.perf_counter() - started, 1),
        "train_command": trained.command,
        "scores": scores,
    }
    record_path.write_text(json.dumps(record, indent=2) + "\n")
    return record


def _trained_steps(train_dir: Path) -> int:
    """The step of the run's latest lerobot-train checkpoint (0 if it has none)."""
    path = train_dir / "checkpoints" / "last" / "training_state" / "training_step.json"
    return json.loads(path.read_text())["step"] if path.exists() else 0


def recorded_wall_s(run_dir: Path) -> float | None:
    """The wall seconds of every timed training invocation of the run in `run_dir` added up (None
    if none was timed)."""
    timings = _timings(run_dir)
    return timings["total"] if timings else None


def added_wall_s(walls: list[float | None]) -> float | None:
    """Wall seconds of several trainings that make one run, added up (None if one was not timed)."""
    return None if None in walls else round(sum(walls), 1)


def train(settings: TrainSettings, command: list[str], shown: str, run_dir: Path) -> tuple[float | None, bool]:
    """Run lerobot-train until the run has all its steps: from scratch, or resumed from the last
    checkpoint of a stopped run (a run folder with no checkpoint yet starts over). Returns the wall
    seconds of every training invocation of this run added up (None if an earlier reproduction
    trained it all) and whether this call trained any steps (False: the run was found finished)."""
    train_dir, times_path = run_dir / "train", run_dir / "train_wall_s.json"
    done = _trained_steps(train_dir)
    if done >= settings.steps:
        return recorded_wall_s(run_dir), False
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "train_command.txt").write_text(shown + "\n")
    if done == 0:
        shutil.rmtree(train_dir, ignore_errors=True)
        print(f"training {run_dir}", flush=True)
    else:
        config = train_dir / "checkpoints" / "last" / "pretrained_model" / "train_config.json"
        # The run's own settings, with this command's steps and save interval (a run extended to more steps)
        # and paths: the checkpoint's config names the folders it was trained in, which may since have moved.
        kept = ("--steps=", "--save_freq=", "--output_dir=", "--dataset.root=")
        command = [command[0], f"--config_path={config}", "--resume=true", *(w for w in command if w.startswith(kept))]
        print(f"resuming {run_dir} from step {done}", flush=True)
    times = _timings(run_dir) or {"invocations": [], "total": 0.0}
    started = time.perf_counter()
    # One math thread per process: the data workers already fill the other cores.
    env = {**os.environ, "OMP_NUM_THREADS": str(settings.threads), "MKL_NUM_THREADS": str(settings.threads)}
    with open(run_dir / "train.log", "a") as log:
        subprocess.run(command, check=True, stdout=log, stderr=subprocess.STDOUT, env=env)
    wall = round(time.perf_counter() - started, 1)
    times["invocations"].append({"from_step": done, "wall_s": wall, "machine": machine_name()})
    times["total"] = round(times["total"] + wall, 1)
    times_path.write_text(json.dumps(times, indent=2) + "\n")
    return times["total"], True


def check_reusable(run_dir: Path, command: str) -> None:
    """Refuse to reuse a run that was trained by another command (other seed, overrides...). Other
    steps are refused too, except more steps under a learning rate that does not depend on the run's
    length (constant, or dropped at a fixed step): training on from the last checkpoint then is the
    longer run, so the run is extended rather than started over."""
    record_path, command_path = run_dir / "record.json", run_dir / "train_command.txt"
    if command_path.exists():
        before = command_path.read_text().strip()
    elif record_path.exists():
        before = json.loads(record_path.read_text())["train_command"]
    else:
        return
    same = same_training(before, command)
    extends = _settings(before, "--steps=") == _settings(command, "--steps=") and _steps(before) < _steps(command)
    if not (same or (extends and _argument(command, "--policy.lr_schedule=", "constant") in LENGTH_FREE_SCHEDULES)):
        raise SystemExit(
            f"{run_dir} holds a run trained with other settings:\n  {before}\nwhile this reproduction "
            f"would run:\n  {command}\nMove that folder away or pass another --workdir (a run is extended to "
            f"more steps only under a learning-rate schedule of {' or '.join(LENGTH_FREE_SCHEDULES)})."
        )


def same_training(before: str, command: str) -> bool:
    """Whether two training commands train the same model (paths and save intervals aside)."""
    return _settings(before) == _settings(command)


def _settings(command: str, *also_ignored: str) -> list[str]:
    """A training command's arguments in any order, without what does not change the trained model:
    its paths (program, data root, output dir, the checkpoint it starts from), which may move, and how
    often it logs and saves."""
    ignored = ("--dataset.root=", "--output_dir=", "--policy.path=", "--save_freq=", "--log_freq=", *also_ignored)
    return sorted(word for word in command.split()[1:] if not word.startswith(ignored))


def _argument(command: str, prefix: str, default: str) -> str:
    """The value of a `--name=value` word of a command (the default when absent)."""
    return next((word[len(prefix):] for word in command.split() if word.startswith(prefix)), default)


def _steps(command: str) -> int:
    return int(_argument(command, "--steps=", "0"))
