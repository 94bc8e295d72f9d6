"""MCAP logs of JSON messages, and demonstrations written as one.

`JsonMcapLog` is the shared part: JSON-schema channels, one message per topic per frame, episodes
laid end to end on the log clock at the dataset's fps so Foxglove plays them back as one timeline.
Policy runs (`tools/rollout_mcap.py`) use it too.

Demonstration channels: `/observation` (the named state vector), `/action`, `/reward` (reward and
done) and `/subtask` (the ground-truth subtask being worked on and whether this step completes
it). Every message carries its episode and frame index. The state's element names are stored
once, as the MCAP metadata record `observation.state`.

A log is a stream: `flush()` (record_demos calls it after every chunk) writes every message so far
as complete MCAP records and fsyncs them; `close()` adds the summary and the index. A log whose
writer was killed holds every flushed message but no summary, which seeking readers (and
`mcap.reader.make_reader`) refuse: `read_mcap_messages` reads such a log up to its last complete
record, and `finish_log` (`ocn-doctor --repair LOG`) rewrites it as a finished log.
"""

from __future__ import annotations

import json
import os
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.records import Channel, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from lerobot_policy_ocn.ocn_data.durable import atomic_output
from lerobot_policy_ocn.ocn_data.episodes import EpisodeChunk

STEP_KEYS = {"episode_index": {"type": "integer"}, "frame_index": {"type": "integer"}}


def step_schema(title: str, properties: dict) -> bytes:
    """JSON schema of a per-step message: the episode and frame index plus `properties`."""
    return json.dumps(
        {"title": title, "type": "object", "properties": {**STEP_KEYS, **properties}}
    ).encode()


def number_array() -> dict:
    return {"type": "array", "items": {"type": "number"}}


def check_new_log(path: str | Path) -> None:
    """MCAP logs are never overwritten: called by the log itself, and by tools before their long work."""
    if Path(path).exists():
        raise FileExistsError(f"--mcap {path} already exists; MCAP logs are never overwritten")


class JsonMcapLog:
    """An MCAP file of JSON messages on JSON-schema channels, with episodes laid end to end on the
    log clock (one frame = 1/fps s). The file must not exist: logs are never overwritten."""

    def __init__(self, path: str | Path, fps: int, channels: dict[str, bytes], library: str) -> None:
        self.path = Path(path)
        check_new_log(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = self.path.open("wb")
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library=library)
        self._ns_per_frame = int(1e9 / fps)
        self._frame = 0
        self._channels = {}
        for topic, schema in channels.items():
            schema_id = self._writer.register_schema(name=topic.strip("/"), encoding="jsonschema", data=schema)
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding="json", schema_id=schema_id
            )

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._writer.add_metadata(name, data)

    def put_frame(self, messages: dict[str, dict]) -> None:
        """One frame: a message per topic, all stamped with the frame's time; the clock then advances."""
        stamp = self._frame * self._ns_per_frame
        for topic, message in messages.items():
            self._writer.add_message(
                channel_id=self._channels[topic], log_time=stamp, publish_time=stamp, data=json.dumps(message).encode()
            )
        self._frame += 1

    def flush(self) -> None:
        """Write every message so far as complete records and put them on the disk."""
        self._writer.flush()
        os.fsync(self._file.fileno())

    def close(self) -> None:
        self._writer.finish()
        self._file.close()


class DemoMcapWriter(JsonMcapLog):
    """Stream chunks of episodes into an MCAP file; `close()` writes the summary and index."""

    def __init__(self, path: str | Path, fps: int, state_names: list[str]) -> None:
        channels = {
            "/observation": step_schema("Observation", {"state": number_array()}),
            "/action": step_schema("Action", {"action": number_array()}),
            "/reward": step_schema("Reward", {"reward": {"type": "number"}, "done": {"type": "boolean"}}),
            "/subtask": step_schema(
                "Subtask",
                {
                    "task": {"type": "string"},
                    "subtask_index": {"type": "integer"},
                    "subtask": {"type": "string"},
                    "subtask_end": {"type": "boolean"},
                },
            ),
        }
        super().__init__(path, fps, channels, library="ocn record_demos")
        self.add_metadata("observation.state", {"names": json.dumps(list(state_names))})

    def write(self, chunk: EpisodeChunk, first_episode_index: int) -> None:
        """Log every step of the chunk; `first_episode_index` is the chunk's first dataset episode."""
        state = chunk.columns["observation.state"].reshape(chunk.num_frames, -1).tolist()
        action = chunk.columns["action"].reshape(chunk.num_frames, -1).tolist()
        reward = chunk.columns["next.reward"].reshape(-1).tolist()
        done = chunk.columns["next.done"].reshape(-1).tolist()
        sub_index = chunk.columns["subtask.index"].reshape(-1).tolist()
        sub_end = chunk.columns["subtask.end"].reshape(-1).tolist()
        row = 0
        for e, (length, task, segments) in enumerate(zip(chunk.lengths, chunk.tasks, chunk.segments, strict=True)):
            episode = first_episode_index + e
            names = [name for _, name in segments]
            for frame in range(int(length)):
                step = {"episode_index": episode, "frame_index": frame}
                self.put_frame(
                    {
                        "/observation": {**step, "state": state[row]},
                        "/action": {**step, "action": action[row]},
                        "/reward": {**step, "reward": reward[row], "done": done[row]},
                        "/subtask": {
                            **step,
                            "task": task,
                            "subtask_index": sub_index[row],
                            "subtask": names[sub_index[row]],
                            "subtask_end": sub_end[row],
                        },
                    }
                )
                row += 1


def complete_records(path: str | Path) -> Iterator[Any]:
    """The records of an MCAP file in order (chunks opened), up to the last complete one: a log
    whose writer was killed ends with a cut-off record, or with no summary at all."""
    with Path(path).open("rb") as handle:
        records = StreamReader(handle).records
        while True:
            try:
                yield next(records)
            except (StopIteration, McapError, struct.error):
                return


def log_is_finished(path: str | Path) -> bool:
    """Whether the MCAP file ends with its summary and footer, as a closed writer leaves it."""
    from mcap.reader import make_reader

    try:
        with Path(path).open("rb") as handle:
            return make_reader(handle).get_summary() is not None
    except (McapError, struct.error):
        return False


def read_mcap_messages(path: str | Path) -> dict[str, list[dict]]:
    """Every message of one of our MCAP logs, finished or not, decoded and grouped by topic."""
    topics: dict[int, str] = {}
    out: dict[str, list[dict]] = {}
    for record in complete_records(path):
        if isinstance(record, Channel):
            topics[record.id] = record.topic
        elif isinstance(record, Message):
            out.setdefault(topics[record.channel_id], []).append(json.loads(record.data))
    return out


def finish_log(path: str | Path) -> int:
    """Rewrite a log whose writer was killed as a finished one (summary and index), keeping every
    complete record: schemas, channels, metadata and messages. Returns the messages kept."""
    messages, started = 0, False
    with atomic_output(path) as handle:
        writer = Writer(handle, compression=CompressionType.ZSTD)
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for record in complete_records(path):
            if isinstance(record, Header):
                writer.start(profile=record.profile, library=record.library)
                started = True
            elif isinstance(record, Schema) and record.id not in schemas:
                schemas[record.id] = writer.register_schema(record.name, record.encoding, record.data)
            elif isinstance(record, Channel) and record.id not in channels:
                channels[record.id] = writer.register_channel(
                    record.topic, record.message_encoding, schemas.get(record.schema_id, 0), record.metadata
                )
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, record.metadata)
            elif isinstance(record, Message):
                writer.add_message(channels[record.channel_id], record.log_time, record.data, record.publish_time,
                                   record.sequence)
                messages += 1
        if not started:  # killed before its header reached the disk: an empty log
            writer.start()
        writer.finish()
    return messages
