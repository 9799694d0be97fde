"""RunLogger: files written, resume truncation, TensorBoard scalars, visitation summary, progress lines."""

from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest
from tensorboardX.proto import event_pb2

from morefree_jax.logger import DROPPED_SHARE, RunLogger, read_metrics

CONFIG = {"env": "point_umaze", "agent": {"alpha": 0.2}, "seed": 3}


def tensorboard_events(run_dir) -> list:
    """Every Event proto of the event files under run_dir/tb (TFRecord framing: length, crc, data, crc)."""
    events = []
    for path in sorted((run_dir / "tb").glob("events.out.tfevents.*")):
        data = path.read_bytes()
        offset = 0
        while offset < len(data):
            (length,) = struct.unpack("<Q", data[offset:offset + 8])
            events.append(event_pb2.Event.FromString(data[offset + 12:offset + 12 + length]))
            offset += 12 + length + 4
    return events


def tensorboard_scalars(run_dir) -> dict[str, list[tuple[int, float]]]:
    """(step, value) per tag."""
    scalars: dict[str, list] = {}
    for event in tensorboard_events(run_dir):
        for value in event.summary.value:
            scalars.setdefault(value.tag, []).append((event.step, value.simple_value))
    return scalars


def without_time(records):
    return [{k: v for k, v in r.items() if not k.startswith("time/")} for r in records]


def log_steps(logger, steps):
    for step in steps:
        logger.log(step, {"wm/loss": 1.0 / step, "eval/success": step / 10, "goal/type": step % 3})


def test_writes_config_metrics_tensorboard(tmp_path):
    with RunLogger(tmp_path, CONFIG, total_steps=50, progress="off") as logger:
        log_steps(logger, [10, 20, 30])
        assert logger.last_success == pytest.approx(3.0)
    assert json.loads((tmp_path / "config.json").read_text()) == CONFIG
    records = read_metrics(tmp_path / "metrics.jsonl")
    assert [r["step"] for r in records] == [10, 20, 30]
    assert records[1]["wm/loss"] == pytest.approx(0.05) and records[2]["goal/type"] == 0
    assert {"time/elapsed_s", "time/wall", "time/steps_per_s"} <= set(records[1])
    assert records[2]["time/elapsed_s"] >= records[1]["time/elapsed_s"] >= 0
    scalars = tensorboard_scalars(tmp_path)
    assert [step for step, _ in scalars["wm/loss"]] == [10, 20, 30]
    assert scalars["eval/success"][2][1] == pytest.approx(3.0)


def test_resume_drops_lines_after_the_checkpoint_and_appends(tmp_path):
    uninterrupted, interrupted = tmp_path / "a", tmp_path / "b"
    with RunLogger(uninterrupted, CONFIG, 60, progress="off") as logger:
        log_steps(logger, range(10, 70, 10))
    with RunLogger(interrupted, CONFIG, 60, progress="off") as logger:
        log_steps(logger, range(10, 50, 10))  # killed after logging step 40; last checkpoint at step 20
    with open(interrupted / "metrics.jsonl", "a") as handle:
        handle.write('{"step": 50, "wm/lo')  # torn line of the killed process
    first_run_elapsed = read_metrics(interrupted / "metrics.jsonl")[1]["time/elapsed_s"]
    with RunLogger(interrupted, CONFIG, 60, resume_step=20, progress="off") as logger:
        log_steps(logger, range(30, 70, 10))
    resumed = read_metrics(interrupted / "metrics.jsonl")
    assert without_time(resumed) == without_time(read_metrics(uninterrupted / "metrics.jsonl"))
    assert resumed[2]["time/elapsed_s"] >= first_run_elapsed  # elapsed time continues across the resume
    # TensorBoard's events after step 20 are cut from the killed run's file: each step once, as uninterrupted.
    steps = {tag: [step for step, _ in values] for tag, values in tensorboard_scalars(interrupted).items()}
    assert steps["wm/loss"] == [10, 20, 30, 40, 50, 60] and steps["eval/success"] == steps["wm/loss"]
    assert tensorboard_scalars(interrupted)["wm/loss"] == tensorboard_scalars(uninterrupted)["wm/loss"]
    # A fresh (non-resumed) start in the same dir starts the files over.
    with RunLogger(interrupted, CONFIG, 60, progress="off") as logger:
        log_steps(logger, [10])
    assert [r["step"] for r in read_metrics(interrupted / "metrics.jsonl")] == [10]
    assert [step for step, _ in tensorboard_scalars(interrupted)["wm/loss"]] == [10]


def test_log_visitation_saves_histogram_and_summary(tmp_path):
    histogram = np.array([[1.0, 0.0], [0.0, 3.0]])
    with RunLogger(tmp_path, CONFIG, 100, progress="off") as logger:
        record = logger.log_visitation(40, {"task_relevant": 0.25, "xy": histogram})
    np.testing.assert_array_equal(np.load(tmp_path / "plots" / "visitation_000000040.npy"), histogram)
    assert not list((tmp_path / "plots").glob("side_visitation_*")) and "visitation/in_air" not in record
    assert record["visitation/task_relevant"] == 0.25
    assert record["visitation/occupied_cells"] == 0.5
    expected_entropy = -(0.25 * math.log(0.25) + 0.75 * math.log(0.75)) / math.log(4)  # 0.4056
    assert record["visitation/entropy"] == pytest.approx(expected_entropy)
    logged = read_metrics(tmp_path / "metrics.jsonl")[0]
    assert logged["visitation/entropy"] == pytest.approx(expected_entropy)


def test_log_visitation_saves_the_side_view_where_the_task_has_one(tmp_path):
    side = np.array([[0.0, 2.0], [5.0, 1.0]])
    views = {"task_relevant": 0.5, "xy": np.ones((2, 2)), "in_air": 0.125, "xz": side}
    with RunLogger(tmp_path, CONFIG, 100, progress="off") as logger:
        record = logger.log_visitation(60, views)
    np.testing.assert_array_equal(np.load(tmp_path / "plots" / "side_visitation_000000060.npy"), side)
    assert record["visitation/in_air"] == 0.125
    assert read_metrics(tmp_path / "metrics.jsonl")[0]["visitation/in_air"] == 0.125


def test_plain_progress_lines_when_not_a_tty(tmp_path, capsys):
    # pytest's captured stderr is not a TTY, so "auto" prints plain lines: the first, then at most one per
    # line_every_s (an hour here), and the last step.
    with RunLogger(tmp_path, CONFIG, total_steps=40, line_every_s=3600) as logger:
        log_steps(logger, [10, 20, 30, 40])
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2
    assert lines[0].startswith("step 10/40 (25.0%)") and lines[0].endswith("success 1.00")
    assert lines[1].startswith("step 40/40 (100.0%)") and "steps/s" in lines[1]


def test_the_dropped_share_is_in_the_progress_line_and_over_one_percent_said_once(tmp_path, capsys):
    with RunLogger(tmp_path, CONFIG, total_steps=40, line_every_s=0, tensorboard=False) as logger:
        for step, share in ((10, 0.0), (20, 0.02), (30, 0.03)):
            logger.log(step, {DROPPED_SHARE: share})
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].endswith("success - dropped 0.0%")
    assert lines[1].startswith("warning: 2.0% of this run's updates so far were non-finite and dropped")
    assert lines[2].startswith("step 20/40") and lines[2].endswith("dropped 2.0%")
    assert lines[3].endswith("dropped 3.0%") and len(lines) == 4  # the warning once


def test_timers_and_bad_metrics(tmp_path):
    with RunLogger(tmp_path, CONFIG, 10, progress="off", tensorboard=False) as logger:
        for _ in range(3):
            with logger.timer("collect"):
                sum(range(1000))
        timing = logger.timing_metrics()
        assert set(timing) == {"time/collect_first_s", "time/collect_s"}
        assert timing["time/collect_s"] >= 0
        with pytest.raises(TypeError, match="'wm/kl' must be a scalar"):
            logger.log(1, {"wm/kl": np.ones(3)})
        record = logger.log(2, {"wm/kl": np.float32(0.5), "nan_ok": float("nan")})
        assert record["wm/kl"] == 0.5 and math.isnan(record["nan_ok"])
    with pytest.raises(ValueError, match="progress must be one of"):
        RunLogger(tmp_path, CONFIG, 10, progress="fancy")


def test_progress_bar_mode(tmp_path, capsys):
    with RunLogger(tmp_path, CONFIG, 40, resume_step=10, progress="bar", tensorboard=False) as logger:
        log_steps(logger, [20, 30])
    err = capsys.readouterr().err
    assert "30/40" in err and "success 3.00" in err
