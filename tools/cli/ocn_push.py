"""`ocn-push`: share a recorded dataset or a trained OCN on the Hugging Face Hub, with its card.

`ocn-push dataset` uploads a LeRobot v3.0 dataset recorded with record_demos, its card rebuilt from
`datacards/craft.md` for the target repo id, and tags the upload with LeRobot's codebase version
("v3.0"), as LeRobot's own `push_to_hub` does: LeRobot resolves a Hub dataset's revision by that tag.
`ocn-push policy` uploads a checkpoint's `pretrained_model` folder (config, weights, processors) with
a model card rendered from `datacards/ocn_policy.md`: architecture, tasks, how to load it, how it
was trained and, from an `ocn-eval` JSON, its metrics (also as model-index results).

Both first stage exactly the files to upload in one folder and check the card there with
huggingface_hub's card classes; `--dry-run DIR` stages into DIR and stops, with no network.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

from lerobot_policy_ocn.ocn_data.preflight import check_repo_id

DATASET_TAGS = ("LeRobot", "robotics")
POLICY_TAGS = ("lerobot", "robotics", "ocn", "option-controller-network", "hierarchical-imitation", "skill-induction")
POLICY_SUFFIXES = (".json", ".safetensors", ".yaml")
EVAL_KEYS = ("f1_tol0", "f1_tol1", "align_acc", "nmi", "success_rate", "option_subtask_success", "split", "dataset")
PARSING_METRICS = (
    ("f1_tol0", "f1", "boundary F1, tolerance 0"),
    ("f1_tol1", "f1", "boundary F1, tolerance 1"),
    ("align_acc", "accuracy", "task alignment accuracy"),
    ("nmi", "nmi", "NMI of options and subtasks"),
)


class HubError(Exception):
    """An upload cannot start (no token); reported as one line, like the Hub's own refusals."""


def _parse_args(argv: list[str] | None) -> argparse.Namespace:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--repo-id", required=True, help="Hub repository, ORG/NAME")
    common.add_argument("--private", action="store_true", help="create the repository as private")
    common.add_argument("--dry-run", type=Path, metavar="DIR",
                        help="write the files that would be uploaded into DIR (new or empty) and upload nothing")
    parser = argparse.ArgumentParser(prog="ocn-push", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="what", required=True, metavar="{dataset,policy}")
    dataset = commands.add_parser(
        "dataset", parents=[common], help="a dataset recorded with record_demos",
        description="Upload a LeRobot v3.0 dataset recorded with record_demos, with its card rebuilt for "
        "--repo-id, and tag it v3.0.", formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    dataset.add_argument("--root", type=Path, required=True, help="the LeRobot dataset's folder")
    policy = commands.add_parser(
        "policy", parents=[common], help="an ocn checkpoint",
        description="Upload an ocn checkpoint's pretrained_model folder with a model card (and the ocn-eval "
        "JSON and figure, if given).", formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    policy.add_argument("--path", type=Path, required=True, help="a pretrained_model folder of an ocn checkpoint")
    policy.add_argument("--eval-json", type=Path, help="an ocn-eval JSON of the checkpoint: metrics for the card")
    policy.add_argument("--train-command", help="the command that trained it, shown in the card")
    return parser.parse_args(argv)


def dataset_files(root: Path) -> dict[str, Path]:
    """Files of a LeRobot v3.0 dataset to upload, by path in the repo: all but its README.md (rebuilt),
    LeRobot's `images/` scratch folder, hidden files and half-written `*.tmp` files."""
    from lerobot.datasets.dataset_metadata import CODEBASE_VERSION

    from lerobot_policy_ocn.ocn_data.episodes_table import read_info

    version = read_info(root).get("codebase_version")
    if version != CODEBASE_VERSION:
        raise ValueError(f"{root} is a LeRobot {version} dataset; ocn-push publishes {CODEBASE_VERSION} datasets.")
    if not any((root / "data").glob("*/*.parquet")):
        raise FileNotFoundError(f"{root} holds no data files (data/*/*.parquet).")
    files = {}
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        parts = path.relative_to(root).parts
        if parts == ("README.md",) or parts[0] == "images" or path.suffix == ".tmp":
            continue
        if any(part.startswith(".") for part in parts):
            continue
        files["/".join(parts)] = path
    return files


def policy_files(path: Path) -> dict[str, Path]:
    """The checkpoint's config, weights and processor files, as LeRobot's own policy push selects them."""
    return {p.name: p for p in sorted(path.iterdir()) if p.is_file() and p.suffix in POLICY_SUFFIXES}


def read_eval(path: Path) -> dict[str, Any]:
    """An `ocn-eval` JSON, checked to hold what the card reports."""
    if not path.is_file():
        raise FileNotFoundError(f"--eval-json {path} does not exist.")
    result = json.loads(path.read_text())
    missing = [key for key in EVAL_KEYS if key not in result]
    if missing:
        raise ValueError(f"--eval-json {path} is not an ocn-eval JSON: it lacks {missing}.")
    return result


def eval_results(result: dict[str, Any]) -> list:
    """The metrics of an ocn-eval JSON as model-index entries: parsing on the dataset split, success in the env."""
    from huggingface_hub import EvalResult

    dataset = result["dataset"]["repo_id"]
    entries = [
        EvalResult(task_type="robotics", task_name="demonstration parsing", dataset_type=dataset, dataset_name=dataset,
                   dataset_split=result["split"], metric_type=kind, metric_name=name, metric_value=float(result[key]))
        for key, kind, name in PARSING_METRICS
    ]
    rollouts = result.get("rollouts_per_cell")
    env = f"Craft env ({rollouts} rollouts per task)" if rollouts else "Craft env"
    entries += [
        EvalResult(task_type="robotics", task_name="task success", dataset_type="craft", dataset_name=env,
                   metric_type="success_rate", metric_name=f"success rate: {task}", metric_value=float(rate))
        for task, rate in result["success_rate"].items()
    ]
    return entries


def _train_settings(path: Path) -> dict[str, Any] | None:
    """Key settings from the `train_config.json` that lerobot-train saves with a checkpoint, if any."""
    config = path / "train_config.json"
    if not config.is_file():
        return None
    train = json.loads(config.read_text())
    return {
        "dataset": train["dataset"]["repo_id"],
        "steps": train["steps"],
        "batch_size": train["batch_size"],
        "seed": train["seed"],
    }


def _craft_mode(tasks: list[str]) -> str:
    """The Craft mode that holds every task (the env's `--env.mode`): paper unless a task needs the full book."""
    from lerobot_policy_ocn.envs.craft.world import parse_task

    try:
        for task in tasks:
            parse_task(task, "paper")
    except ValueError:
        return "full"
    return "paper"


def model_card(path: Path, repo_id: str, result: dict[str, Any] | None, train_command: str | None, figure: bool) -> str:
    """The checkpoint's README.md from `datacards/ocn_policy.md`; loading the policy first proves that
    `--policy.path` will load what is published."""
    from huggingface_hub import ModelCardData

    from lerobot_policy_ocn.ocn_data.datacard import render_card
    from lerobot_policy_ocn.sequence import CRAFT_ENCODERS
    from lerobot_policy_ocn.tools.eval.parsing import load_ocn

    policy, _, _ = load_ocn(path)
    config = policy.config
    train = _train_settings(path)
    dataset = train["dataset"] if train else (result["dataset"]["repo_id"] if result else None)
    card_data = ModelCardData(
        license="apache-2.0",
        library_name="lerobot",
        pipeline_tag="robotics",
        tags=list(POLICY_TAGS) + (["craft"] if config.obs_encoder in CRAFT_ENCODERS else []),
        # A dataset recorded here and never pushed keeps a local/... id, which names no Hub dataset.
        datasets=[dataset] if dataset and not dataset.startswith("local/") else None,
        model_name=repo_id,
        eval_results=eval_results(result) if result else None,
    )
    action = (
        f"{config.n_actions} discrete actions (categorical head)"
        if config.action_type == "discrete"
        else f"continuous ({config.action_dim},) (Gaussian head)"
    )
    arch = {
        "n_options": config.n_options,
        "hidden_size": config.hidden_size,
        "mlp_hidden_size": config.mlp_hidden_size,
        "mlp_depth": config.mlp_depth,
        "temperature": config.temperature,
        "state_dim": config.state_dim,
        "obs_encoder": config.obs_encoder,
        "action": action,
        "recipe": config.recipe,
        "longest_episode": config.window_size,
        "inference_mode": config.inference_mode,
        "parameters": f"{sum(p.numel() for p in policy.parameters()):,}",
    }
    evaluation = None
    if result:
        table = result["option_subtask_success"]
        evaluation = {
            "split": result["split"],
            "dataset": result["dataset"]["repo_id"],
            "episodes": result.get("episodes_parsed", "?"),
            "rollouts": result.get("rollouts_per_cell", "?"),
            "metrics": [{"name": name, "value": result[key]} for key, _, name in PARSING_METRICS]
            + [{"name": f"success rate: {task}", "value": rate} for task, rate in result["success_rate"].items()],
            "table": {"subtasks": table["subtasks"], "rows": list(zip(table["rows"], table["table"], strict=True))},
            "figure": figure,
        }
    return render_card(
        "ocn_policy",
        {
            "card_data": card_data.to_yaml(),
            "repo_id": repo_id,
            "arch": arch,
            "tasks": config.tasks,
            "craft": _craft_mode(config.tasks) if config.obs_encoder in CRAFT_ENCODERS else None,
            "train_command": train_command,
            "train": train,
            "eval": evaluation,
        },
    )


def check_card(folder: Path, kind: str, expect_eval: bool) -> None:
    """Parse the staged README.md with huggingface_hub's card class and check its metadata.

    `RepoCard.validate()` asks the Hub, so the fields the Hub and LeRobot rely on are checked here.
    """
    from huggingface_hub import DatasetCard, ModelCard

    card = (DatasetCard if kind == "dataset" else ModelCard).load(folder / "README.md")
    data = card.data
    problems = []
    if data.license != "apache-2.0":
        problems.append(f"license is {data.license!r}")
    missing_tags = set(DATASET_TAGS if kind == "dataset" else POLICY_TAGS) - set(data.tags or [])
    if missing_tags:
        problems.append(f"tags lack {sorted(missing_tags)}")
    if kind == "dataset":
        if "robotics" not in (data.task_categories or []):
            problems.append("task_categories lacks 'robotics'")
        if not data.get("configs"):
            problems.append("no configs (the Hub's viewer reads data/*/*.parquet through them)")
    else:
        if data.library_name != "lerobot" or data.pipeline_tag != "robotics":
            problems.append(f"library_name {data.library_name!r} / pipeline_tag {data.pipeline_tag!r}")
        if expect_eval and not data.eval_results:
            problems.append("no model-index results")
    if problems:
        raise ValueError(f"the {kind} card {folder / 'README.md'} is invalid: {'; '.join(problems)}.")


def _place(source: Path, target: Path, link: bool) -> None:
    """Hard-link into a throwaway upload folder when the filesystem allows it (no copy of a large
    dataset), else copy."""
    if link:
        with contextlib.suppress(OSError):
            os.link(source, target)
            return
    shutil.copy2(source, target)


def stage(dest: Path, files: dict[str, Path], texts: dict[str, str], link: bool) -> None:
    """Lay out the repository under dest: `files` by their path in the repo, and the generated `texts`."""
    for name, source in files.items():
        (dest / name).parent.mkdir(parents=True, exist_ok=True)
        _place(source, dest / name, link)
    for name, text in texts.items():
        (dest / name).parent.mkdir(parents=True, exist_ok=True)
        (dest / name).write_text(text)


def plan(args: argparse.Namespace) -> tuple[dict[str, Path], dict[str, str], str]:
    """Files to upload, generated texts and the Hub repo type for one `ocn-push` command."""
    check_repo_id(args.repo_id)
    if args.what == "dataset":
        from lerobot_policy_ocn.ocn_data.datacard import dataset_card

        files = dataset_files(args.root)
        return files, {"README.md": dataset_card(args.root, args.repo_id)}, "dataset"
    if not (args.path / "config.json").is_file():
        raise FileNotFoundError(
            f"--path {args.path} holds no config.json: pass a checkpoint's pretrained_model folder."
        )
    files = policy_files(args.path)
    result = read_eval(args.eval_json) if args.eval_json else None
    if result:
        files["eval/ocn_eval.json"] = args.eval_json
        if args.eval_json.with_suffix(".png").is_file():  # ocn-eval's option x subtask figure
            files["eval/ocn_eval.png"] = args.eval_json.with_suffix(".png")
    card = model_card(args.path, args.repo_id, result, args.train_command, "eval/ocn_eval.png" in files)
    return files, {"README.md": card}, "model"


def require_login() -> str:
    """Fail before staging anything when the upload cannot work: no token, a token the Hub refuses,
    or no Hub to reach. Returns the user name the token belongs to."""
    from huggingface_hub import HfApi, get_token

    if not get_token():
        raise HubError("no Hugging Face token: run `hf auth login` or set HF_TOKEN to a write token.")
    return HfApi().whoami()["name"]


def upload(folder: Path, repo_id: str, repo_type: str, private: bool) -> str:
    """Create the repo if needed, upload the staged folder in one commit and, for a dataset, move the
    LeRobot version tag to that commit. Returns the commit's URL."""
    from huggingface_hub import HfApi
    from huggingface_hub.errors import RevisionNotFoundError
    from lerobot.datasets.dataset_metadata import CODEBASE_VERSION

    api = HfApi()
    api.create_repo(repo_id, repo_type=repo_type, private=private or None, exist_ok=True)
    commit = api.upload_folder(
        repo_id=repo_id,
        repo_type=repo_type,
        folder_path=folder,
        commit_message=f"ocn-push {repo_type}",
        # a re-pushed dataset with fewer files must not keep stale ones: LeRobot reads every data file
        delete_patterns=["data/**", "meta/**", "videos/**"] if repo_type == "dataset" else None,
    )
    if repo_type == "dataset":
        with contextlib.suppress(RevisionNotFoundError):
            api.delete_tag(repo_id, tag=CODEBASE_VERSION, repo_type=repo_type)
        api.create_tag(repo_id, tag=CODEBASE_VERSION, revision=commit.oid, repo_type=repo_type)
    return commit.commit_url


def push(args: argparse.Namespace) -> str:
    """Stage, check the card, then upload unless it is a dry run; returns what was done, in words."""
    dry_run = args.dry_run
    if dry_run is not None and dry_run.exists() and (not dry_run.is_dir() or any(dry_run.iterdir())):
        raise FileExistsError(f"--dry-run {dry_run} is not an empty folder; it must hold only the files to upload.")
    user = require_login() if dry_run is None else None
    files, texts, repo_type = plan(args)
    count, with_eval = len(files) + len(texts), "eval/ocn_eval.json" in files
    if dry_run is not None:
        dry_run.mkdir(parents=True, exist_ok=True)
        stage(dry_run, files, texts, link=False)
        check_card(dry_run, repo_type, with_eval)
        return f"dry run: wrote the {count} files of {repo_type} repo {args.repo_id} into {dry_run}"
    with tempfile.TemporaryDirectory(prefix="ocn-push-") as tmp:
        stage(Path(tmp), files, texts, link=True)
        check_card(Path(tmp), repo_type, with_eval)
        url = upload(Path(tmp), args.repo_id, repo_type, args.private)
    return f"pushed {count} files to {repo_type} repo {args.repo_id} as {user}: {url}"


def main(argv: list[str] | None = None) -> int:
    import httpx
    from huggingface_hub import constants
    from huggingface_hub.errors import HfHubHTTPError

    args = _parse_args(argv)
    try:
        print(push(args))
    except HubError as error:
        message = str(error)
    except HfHubHTTPError as error:
        message = f"the Hub refused: {str(error).splitlines()[0]}"
    except (httpx.TransportError, ConnectionError) as error:
        message = f"cannot reach the Hugging Face Hub at {constants.ENDPOINT}: {error}"
    except (FileNotFoundError, FileExistsError, ValueError) as error:
        message = str(error)
    else:
        return 0
    print(f"ocn-push: {message}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
