"""Where a LeRobot v3.0 dataset keeps its files, and the splits `record_demos` writes into its info.

Apart from the writer (which needs LeRobot) so that `ocn-doctor` can name and check a dataset's files
without loading LeRobot and torch.
"""

DATA_PATH = "data/chunk-{chunk:03d}/file-{file:03d}.parquet"
EPISODES_PATH = "meta/episodes/chunk-{chunk:03d}/file-{file:03d}.parquet"
VIDEO_PATH = "videos/{key}/chunk-{chunk:03d}/file-{file:03d}.mp4"
INFO_PATH, STATS_PATH, TASKS_PATH = "meta/info.json", "meta/stats.json", "meta/tasks.parquet"


def split_ranges(total: int, val_fraction: float) -> dict[str, str]:
    """`meta/info.json` splits: the last `val_fraction` of the episodes is the validation split."""
    n_train = total - int(round(total * val_fraction))
    splits = {"train": f"0:{n_train}"}
    if n_train < total:
        splits["val"] = f"{n_train}:{total}"
    return splits
