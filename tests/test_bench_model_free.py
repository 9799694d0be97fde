"""The model-free bench's update rows: the update's time next to its FLOPs at the 256-layer rate."""

from __future__ import annotations

import math

from experiments.benchmarks import model_free as bench_model_free


def test_update_rows_give_the_update_and_its_time_at_the_layer_rate():
    rows, update_ms = bench_model_free.update_rows(updates=2)
    by_name = {row["name"]: row for row in rows}
    assert set(by_name) == {"sac_update_ms", "sac_update_at_layer_rate_ms"}
    assert by_name["sac_update_ms"]["value"] == update_ms
    at_rate = by_name["sac_update_at_layer_rate_ms"]
    assert math.isfinite(at_rate["value"]) and at_rate["value"] > 0
    assert at_rate["note"].startswith("701 MFLOP at ")  # MEDAL's sizes at point_umaze shapes


def test_bar_rows_put_pytorch_update_over_the_fused_step(monkeypatch):
    update = [{"name": "sac_update_ms", "value": 7.0}, {"name": "sac_update_at_layer_rate_ms", "value": 5.0}]
    monkeypatch.setattr(bench_model_free, "update_rows", lambda: (update, 7.0))
    monkeypatch.setattr(bench_model_free, "torch_update_ms",
                        lambda: {"update_ms": 15.0, "torch": "x", "threads": 2})
    ratio = bench_model_free.bar_rows(point_umaze_rate=250.0)[-1]  # 4 ms per env step
    assert ratio["name"] == "fused_step_vs_torch_update"
    assert ratio["value"] == 15.0 / 4.0 and ratio["note"].startswith("meets the bar >= 3")
    assert bench_model_free.bar_rows(point_umaze_rate=100.0)[-1]["note"].startswith("misses")


def test_bar_rows_without_pytorch_are_the_update_rows(monkeypatch):
    monkeypatch.setattr(bench_model_free, "update_rows", lambda: (["update"], 7.0))
    monkeypatch.setattr(bench_model_free, "torch_update_ms", lambda: None)
    assert bench_model_free.bar_rows(point_umaze_rate=100.0) == ["update"]


def test_the_section_measures_the_bar_rows_first(monkeypatch):
    monkeypatch.setattr(bench_model_free, "chunk_rate", lambda task, agent, chunk: (100.0, 1.0, "sizes"))
    monkeypatch.setattr(bench_model_free, "bar_rows", lambda rate: [{"name": "bar"}])
    monkeypatch.setattr(bench_model_free, "matching_row", lambda: {"name": "matching"})
    names = [row["name"] for row in bench_model_free.run()]
    assert names[:2] == ["point_umaze_oracle_sac_steps_per_s", "bar"] and names[-1] == "matching"
    assert len(names) == len(set(names)) == 2 + 7 + 3 * 2 + 1  # the other 7 tasks' oracle_sac, 3 agents x 2


def test_the_bar_alone_prints_its_rows_as_a_table(monkeypatch, capsys):
    rows = [{"section": "model_free", "name": "fused_step_vs_torch_update", "value": 2.5, "unit": "x",
             "note": "misses the bar >= 3"}]
    monkeypatch.setattr(bench_model_free, "bar_section", lambda: rows)
    monkeypatch.delenv("TORCH_PYTHON", raising=False)
    assert bench_model_free.main([]) == 0
    out, err = capsys.readouterr()
    assert "fused_step_vs_torch_update" in out and "misses the bar >= 3" in out
    assert "TORCH_PYTHON is not set" in err
