"""The benchmark harness: section discovery, argument errors and the printed table."""

from __future__ import annotations

import pytest

from experiments.benchmarks import bench


def test_sections_are_discovered():
    assert "envs" in bench.SECTIONS


def test_unknown_section_exits_2_listing_valid_ones(capsys):
    assert bench.main(["only=envs,nope"]) == 2
    assert "valid sections: " in capsys.readouterr().err


def test_table_shows_every_row():
    rows = [{"section": "envs", "name": "x/fused_scan", "value": 1234.5, "unit": "steps/s", "note": "ok"}]
    table = bench.format_table(rows)
    assert "x/fused_scan" in table and "1234" in table and "steps/s" in table


def _whole_run_result(precision: str, train_s: float, cadence: str = "chunk") -> dict:
    # two chunks of 100 steps: collect 1 s (one searched: 0.5 s of search), train, host 0.1 s
    times = [(1.0, train_s, 0.1, True), (0.5, train_s, 0.1, False)]
    return {"task": "point_umaze", "agent": "morefree", "precision": precision, "cadence": cadence,
            "chunk_len": 100, "updates": 50, "times": times, "compile_s": 1.0, "search": 0.5,
            "evaluate": 10.0, "checkpoint": 5.0, "log": 0.01, "eval_every": 1000, "checkpoint_every": 1000,
            "log_every": 1000}


def test_whole_run_charges_each_part_per_env_step_and_compares_precisions_and_cadences():
    from experiments.benchmarks import whole_run

    parts = whole_run.seconds_per_step(_whole_run_result("f32", 2.0))
    assert parts["search"] == 0.5 * 0.5 / 100  # half the chunks searched
    assert parts["collect"] == (0.75 - 0.25) / 100
    assert (parts["train"], parts["host"]) == (0.02, 0.1 / 100)
    assert (parts["evaluate"], parts["checkpoint"]) == (0.01, 0.005)
    interleaved = _whole_run_result("f32", 0.0, "interleaved")
    interleaved["times"] = [(3.0, 0.0, 0.1, True), (2.5, 0.0, 0.1, False)]  # collect ran the updates
    assert whole_run.seconds_per_step(interleaved)["collect+train"] == (2.75 - 0.25) / 100
    rows = whole_run.rows_of([_whole_run_result("f32", 2.0), _whole_run_result("bf16", 1.0), interleaved])
    speeds = {row["name"]: row["value"] for row in rows}
    f32, bf16 = (speeds[f"whole_run/point_umaze_morefree_{p}_chunk_steps_per_s"] for p in ("f32", "bf16"))
    assert f32 == 1 / sum(parts.values())
    assert speeds["whole_run/point_umaze_morefree_chunk_bf16_over_f32"] == bf16 / f32 > 1
    assert speeds["whole_run/point_umaze_morefree_f32_interleaved_over_chunk"] == pytest.approx(
        speeds["whole_run/point_umaze_morefree_f32_interleaved_steps_per_s"] / f32)
    assert "collect+train 57.5%" in rows[2]["note"] and " train " not in rows[2]["note"]  # 0.025 of 0.0435
    assert "train 46.0%, host 2.3%, evaluate 23.0%" in rows[0]["note"]  # train: 0.02 of 0.0435 s a step
