"""The model-free bench's update rows: the update's time next to its FLOPs at the 256-layer rate."""

from __future__ import annotations

import math

from experiments import bench_model_free


def test_update_rows_give_the_update_and_its_time_at_the_layer_rate():
    rows, update_ms = bench_model_free.update_rows(updates=2)
    by_name = {row["name"]: row for row in rows}
    assert set(by_name) == {"sac_update_ms", "sac_update_at_layer_rate_ms"}
    assert by_name["sac_update_ms"]["value"] == update_ms
    at_rate = by_name["sac_update_at_layer_rate_ms"]
    assert math.isfinite(at_rate["value"]) and at_rate["value"] > 0
    assert at_rate["note"].startswith("701 MFLOP at ")  # MEDAL's sizes at point_umaze shapes

