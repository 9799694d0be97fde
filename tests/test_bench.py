"""The benchmark harness: section discovery, argument errors and the printed table."""

from __future__ import annotations

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
