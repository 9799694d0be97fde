"""TensorBoard event files read and cut back without TensorFlow (TFRecord framing + tensorboardX's protos).

    records = read_records(path)                  # [(Event, raw record bytes), ...]
    truncate_events(run_dir / "tb", last_step)    # drops events logged after `last_step`, file by file
    writer = ScalarWriter(run_dir / "tb")         # scalars written synchronously; flush() = on disk

A resumed run continues from its checkpoint at step S and logs the steps after S again, so the events an
interrupted process wrote after S are removed (as metrics.jsonl is cut back); each kept record is copied
byte for byte (its CRCs stay valid). A torn record at the end of a file (a killed writer) is dropped.
"""

from __future__ import annotations

import os
import pathlib
import struct
import time

from tensorboardX import summary
from tensorboardX.event_file_writer import EventsWriter
from tensorboardX.proto import event_pb2

_HEADER = 12  # uint64 length + uint32 masked CRC of the length
_FOOTER = 4  # uint32 masked CRC of the data


def read_records(path) -> list[tuple[event_pb2.Event, bytes]]:
    """Every complete record of one event file: (the parsed Event, its raw bytes)."""
    data = pathlib.Path(path).read_bytes()
    records, offset = [], 0
    while offset + _HEADER <= len(data):
        (length,) = struct.unpack("<Q", data[offset:offset + 8])
        end = offset + _HEADER + length + _FOOTER
        if end > len(data):
            break  # torn by a kill
        records.append((event_pb2.Event.FromString(data[offset + _HEADER:end - _FOOTER]), data[offset:end]))
        offset = end
    return records


def event_files(tb_dir) -> list[pathlib.Path]:
    return sorted(pathlib.Path(tb_dir).glob("events.out.tfevents.*"))


def truncate_events(tb_dir, last_step: int) -> int:
    """Rewrites every event file under tb_dir without the summaries of steps > last_step (atomically, per
    file); returns how many records were dropped."""
    dropped = 0
    for path in event_files(tb_dir):
        records = read_records(path)
        kept = [raw for event, raw in records if not (event.HasField("summary") and event.step > last_step)]
        if len(kept) == len(records) and sum(map(len, kept)) == path.stat().st_size:
            continue
        dropped += len(records) - len(kept)
        temporary = path.with_name(path.name + ".tmp")
        temporary.write_bytes(b"".join(kept))
        os.replace(temporary, path)
    return dropped


class ScalarWriter:
    """Scalars into a new event file under tb_dir, written synchronously: after `flush` every scalar added
    so far is on disk. (tensorboardX's SummaryWriter queues events for a thread, and its flush does not
    drain the queue, so a kill right after a checkpoint lost the scalars of the checkpointed step.)"""

    def __init__(self, tb_dir):
        pathlib.Path(tb_dir).mkdir(parents=True, exist_ok=True)
        # The file name has whole seconds only: the suffix keeps two starts within a second (a quick resume)
        # out of each other's file.
        suffix = f".{os.getpid()}.{time.time_ns()}"
        self._writer = EventsWriter(str(pathlib.Path(tb_dir) / "events"), filename_suffix=suffix)

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        scalar = summary.scalar(tag, float(value))
        event = event_pb2.Event(wall_time=time.time(), step=int(step), summary=scalar)
        self._writer.write_event(event)

    def flush(self) -> None:
        self._writer.flush()

    def close(self) -> None:
        self._writer.close()
