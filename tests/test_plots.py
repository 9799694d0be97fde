"""experiments.plots / run_groups on hand-made run dirs: grouping, mean and standard error, skipped dirs,
the files written, the one-line error when no run is found."""

from __future__ import annotations

import csv
import json
import math
import shutil

import numpy as np
import pytest

from experiments import plots
from experiments.analysis import figures, run_groups, run_record
from tests.plot_helpers import STEPS, SUCCESS, write_run, write_runs


@pytest.fixture
def runs(tmp_path):
    return write_runs(tmp_path / "runs")


def test_curve_is_the_mean_and_standard_error_over_seeds(runs):
    found, skipped = run_groups.find_runs(runs)
    groups = run_groups.group_runs(found)
    assert sorted(groups) == [("point_umaze", "morefree"), ("point_umaze", "rf_peg")] and not skipped
    steps, mean, stderr = run_groups.curve(groups[("point_umaze", "morefree")], "eval/success")
    assert steps.tolist() == list(STEPS)
    last = [1.0, 0.8, 0.6]
    assert mean[-1] == pytest.approx(0.8)
    assert stderr[-1] == pytest.approx(np.std(last, ddof=1) / math.sqrt(3))


def test_runs_set_apart_by_alpha_precision_or_cadence_are_separate_groups_filtered_by_agent(runs):
    for alpha in (0.5, 0.7):
        run_dir = runs / "point_umaze" / f"alpha{alpha}" / "seed0"
        write_run(run_dir, "point_umaze", "morefree", 0, [0.0, 0.1, alpha])
        config = json.loads((run_dir / "config.json").read_text())
        config |= {"schedule": {"alpha": alpha}, "agent": {"alpha": alpha if alpha == 0.5 else 0.2}}
        (run_dir / "config.json").write_text(json.dumps(config))
    found, _ = run_groups.find_runs(runs, agents=["morefree"])
    groups = run_groups.group_runs(found)
    assert sorted(groups) == [("point_umaze", "morefree"), ("point_umaze", "morefree alpha=0.5"),
                              ("point_umaze", "morefree schedule.alpha=0.7 agent.alpha=0.2")]
    assert [run.seed for run in groups[("point_umaze", "morefree")]] == [0, 1, 2]  # the defaults' group
    chunk_bf16 = {"run": {"agent": "morefree", "update_cadence": "chunk"}, "agent": {"precision": "bf16"}}
    assert run_record.agent_label(chunk_bf16) == "morefree cadence=chunk precision=bf16"
    assert run_record.agent_label({"run": {"agent": "morefree", "update_cadence": "interleaved"},
                                   "agent": {"precision": "f32", "alpha": 0.2}}) == "morefree"
    assert run_record.agent_label({"run": {"agent": "morefree"}}) == "morefree cadence=chunk"  # an older dir
    assert run_record.agent_label({"run": {"agent": "oracle_sac"}}) == "oracle_sac"


def test_plots_writes_every_figure_and_the_table(runs, tmp_path, capsys):
    write_run(runs / "tabletop" / "morefree" / "seed0", "tabletop", "morefree", 0, [0, 0, 0])
    shutil.copytree(runs / "point_umaze" / "rf_peg" / "seed1", runs / "zz_copy" / "seed1")  # a second copy
    (runs / "broken").mkdir()
    (runs / "broken" / "config.json").write_text("{}")
    out = tmp_path / "results"
    assert plots.main([f"runs={runs}", f"out={out}", "task=point_umaze", "marks=5000,7500"]) == 0
    printed = capsys.readouterr().out
    assert "skipped" in printed and "broken: no metrics.jsonl" in printed
    assert "holds task tabletop, not point_umaze" in printed
    assert f"skipped {runs}/zz_copy/seed1: seed 1 of rf_peg on point_umaze is taken from " in printed
    names = {path.name for path in out.iterdir()}
    for figure in ("success", "final_success", "task_relevant", "visitation", "back_starts"):
        assert {f"point_umaze_{figure}.png", f"point_umaze_{figure}.svg"} <= names
    with open(out / "point_umaze_results.csv") as file:
        rows = list(csv.DictReader(file))
    assert [(r["agent"], r["step"], r["seeds"]) for r in rows] == [
        ("morefree", "5000", "3"), ("morefree", "7500", "3"), ("rf_peg", "5000", "2"),
        ("rf_peg", "7500", "2")]
    assert float(rows[3]["success_mean"]) == pytest.approx(0.3)
    assert float(rows[3]["success_stderr"]) == pytest.approx(0.1)
    assert float(rows[3]["final_success_mean"]) == pytest.approx(0.15)
    assert rows[0]["commits"] == "aaaaaaa"
    table = (out / "point_umaze_results.md").read_text()
    # rf_peg sends no chunk back ("-"); morefree's back chunks reached the start 0, 10 and 20% of the time.
    row = "| point_umaze | rf_peg | 2 | 7,500 | 0.30 ± 0.10 | 0.15 ± 0.05 | 0.050 | - | 0.1% | aaaaaaa |"
    assert row in table
    row = "| point_umaze | morefree | 3 | 7,500 | 0.80 ± 0.12 | 0.40 ± 0.06 | 0.100 | 10.0% | 0.2% |"
    assert row in table
    assert "| success (any step) | success (last step) |" in table and "runs: aaaaaaa" in table
    assert float(rows[3]["dropped_share_mean"]) == pytest.approx(0.001)
    assert b"runs: aaaaaaa" in (out / "point_umaze_success.svg").read_bytes()
    assert {"ablation.png", "ablation.svg", "ablation.csv", "ablation.md"} <= names  # morefree and rf_peg ran


def test_ablation_normalises_each_variants_final_success_by_morefrees_on_the_same_task(runs, tmp_path):
    write_run(runs / "ant" / "morefree" / "seed0", "ant", "morefree", 0, [0.0, 0.4, 0.8])
    write_run(runs / "ant" / "mf_no_bfge" / "seed0", "ant", "mf_no_bfge", 0, [0.0, 0.2, 0.2])
    write_run(runs / "tabletop" / "morefree" / "seed0", "tabletop", "morefree", 0, [0.0, 0.0, 0.5])  # alone
    out = tmp_path / "results"
    assert plots.main([f"runs={runs}", f"out={out}"]) == 0
    with open(out / "ablation.csv") as file:
        rows = {(r["task"], r["agent"]): r for r in csv.DictReader(file)}
    assert sorted(rows) == [("ant", "mf_no_bfge"), ("ant", "morefree"), ("point_umaze", "morefree"),
                            ("point_umaze", "rf_peg")]
    # The last quarter before 7,500 holds only the 7,500 evaluation: morefree 0.8 (mean of 1.0, 0.8, 0.6).
    assert rows["point_umaze", "rf_peg"]["evaluations"] == "1"
    assert float(rows["point_umaze", "rf_peg"]["normalised"]) == pytest.approx(0.3 / 0.8, abs=1e-4)
    assert float(rows["ant", "mf_no_bfge"]["normalised"]) == pytest.approx(0.25, abs=1e-4)
    table = (out / "ablation.md").read_text()
    assert "| morefree | 2 | 1.00 ± 0.00 |" in table and "| rf_peg | 1 | 0.38 |" in table
    assert "| mf_no_bfge | 1 | 0.25 |" in table


def test_default_marks_are_evaluated_steps(runs):
    groups = run_groups.group_runs(run_groups.find_runs(runs)[0])
    assert run_groups.default_marks(groups, "point_umaze", count=3) == list(STEPS)


def test_agents_evaluated_at_other_steps_get_rows_at_their_latest_evaluation_before_each_mark(runs):
    """ibc evaluates from its own seed phase (steps ending in 800 here): the default marks are not empty and
    its rows sit at its last evaluation at or before each mark; a mark past its last one gets no row."""
    for seed in (0, 1):
        write_run(runs / "point_umaze" / "ibc" / f"seed{seed}", "point_umaze", "ibc", seed, [0.0, 0.5, 1.0])
        metrics = runs / "point_umaze" / "ibc" / f"seed{seed}" / "metrics.jsonl"
        lines = [json.loads(line) for line in metrics.read_text().splitlines()]
        shifted = [{**line, "step": line["step"] - 1700} for line in lines]
        metrics.write_text("".join(json.dumps(line) + "\n" for line in shifted))
    groups = run_groups.group_runs(run_groups.find_runs(runs)[0])
    marks = run_groups.default_marks(groups, "point_umaze", count=3)
    assert marks == [800, 3300, 5800]  # up to ibc's last evaluation, 5,800
    rows = {(r["agent"], r["step"]) for r in run_groups.results_rows(groups, {"point_umaze": [*marks, 7500]})}
    assert rows == {("ibc", 800), ("ibc", 3300), ("ibc", 5800), ("morefree", 2500), ("morefree", 5000),
                    ("morefree", 7500), ("rf_peg", 2500), ("rf_peg", 5000), ("rf_peg", 7500)}


def test_back_starts_title_says_up_to_which_steps_the_seeds_saved(runs):
    seed1 = runs / "point_umaze" / "morefree" / "seed1" / "plots" / "back_starts.npz"
    with np.load(seed1) as data:
        np.savez(seed1, xy=data["xy"], stream_step=data["stream_step"], step=np.int64(5000))
    groups = run_groups.group_runs(run_groups.find_runs(runs)[0])
    fig = figures.back_starts_figure("point_umaze", groups, figures.TaskGeometry("point_umaze"))
    title = fig.axes[0].get_title()
    assert "morefree: 9 successful back chunks" in title and "3 seeds, up to step 5,000-7,500" in title


@pytest.mark.parametrize("commits", [1, 12])
def test_the_stamp_fits_under_a_one_panel_figure(runs, commits):
    """A stamp listing many commits is wider than a one-panel figure: it wraps between words and the panel
    moves up to leave it room."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    stamp = "runs: " + " ".join(f"{i:07x}+dirty" for i in range(commits)) + " · drawn: 0123456"
    groups = run_groups.group_runs(run_groups.find_runs(runs)[0])
    fig = figures.back_starts_figure("point_umaze", groups, figures.TaskGeometry("point_umaze"))
    text = figures.add_stamp(fig, stamp)
    FigureCanvasAgg(fig).draw()
    box, panel = text.get_window_extent(), fig.axes[0].get_tightbbox()
    assert box.x0 >= 0 and box.x1 <= fig.bbox.width and box.y0 >= 0
    assert box.y1 <= panel.y0  # below the panel's tick labels
    assert text.get_text().replace("\n", " ") == stamp
    assert (text.get_text().count("\n") > 0) == (commits > 1)


def test_no_run_found_is_one_line(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert plots.main([f"runs={tmp_path / 'empty'}", f"out={tmp_path / 'out'}"]) == 2
    error = capsys.readouterr().err
    assert error.startswith("error: no run with evaluations found below") and error.count("\n") == 1


def test_rest_density_counts_nearby_points():
    trajectory = np.zeros((100, 2))
    trajectory[50:] = [5.0, 5.0]
    trajectory[99] = [np.nan, np.nan]
    density = figures.rest_density(trajectory, radius=1.0)
    assert density[0] == pytest.approx(0.5) and density[60] == pytest.approx(0.49) and density[99] == 0.0


def test_window_table_averages_each_seed_over_its_evaluations_first(runs, tmp_path):
    out = tmp_path / "results"
    assert plots.main([f"runs={runs}", f"out={out}", "window=5000:7500"]) == 0
    with open(out / "point_umaze_window.csv") as file:
        rows = {r["agent"]: r for r in csv.DictReader(file)}
    per_seed = [np.mean(SUCCESS["morefree", seed][1:]) for seed in range(3)]  # 0.75, 0.55, 0.5
    assert rows["morefree"]["evaluations"] == "2" and rows["morefree"]["seeds"] == "3"
    assert float(rows["morefree"]["success_mean"]) == pytest.approx(np.mean(per_seed), abs=1e-4)
    assert float(rows["morefree"]["success_stderr"]) == pytest.approx(np.std(per_seed, ddof=1) / math.sqrt(3),
                                                                      abs=1e-4)
    assert float(rows["rf_peg"]["final_success_mean"]) == pytest.approx(np.mean([0.075, 0.175]), abs=1e-4)
    table = (out / "point_umaze_window.md").read_text()
    assert "| point_umaze | morefree | 3 | 5,000-7,500 | 2 | 0.60 ± 0.08 |" in table
    # Task-relevant at 7,500: 0, 0.1, 0.2 over the seeds; in the window: unknown, as these configs do not
    # say how many rows the replay keeps.
    assert "| 10.0% ± 5.8 | - | aaaaaaa |" in table
    # A window past the runs' last evaluation has no rows.
    assert plots.main([f"runs={runs}", f"out={out}", "window=5000:10000"]) == 0
    assert (out / "point_umaze_window.csv").read_text().count("\n") == 1



def test_the_share_in_the_window_counts_only_the_steps_between_its_evaluations(tmp_path):
    run_dir = tmp_path / "point_umaze" / "morefree" / "seed0"
    write_run(run_dir, "point_umaze", "morefree", 0, [0.0, 0.5, 1.0])
    config = json.loads((run_dir / "config.json").read_text())
    (run_dir / "config.json").write_text(json.dumps(config | {"agent": {"replay": {"capacity": 7500}}}))
    lines = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    shares = {2500: 1.0, 5000: 0.6, 7500: 0.5}  # in-region rows: 2,500, 3,000, 3,750
    for line in lines:
        if "visitation/task_relevant" in line:
            line["visitation/task_relevant"] = shares[line["step"]]
    (run_dir / "metrics.jsonl").write_text("".join(json.dumps(line) + "\n" for line in lines))
    run = run_record.read_run(run_dir)
    assert run.replay_capacity == 7500
    assert run_groups.share_between(run, 2500, 5000) == pytest.approx(0.2)
    assert run_groups.share_between(run, 5000, 7500) == pytest.approx(0.3)
    assert run_groups.share_between(run, 2500, 7500) == pytest.approx(0.25)
    assert math.isnan(run_groups.share_between(run, 7500, 7500))
    row = run_groups.window_rows({("point_umaze", "morefree"): [run]}, 5000, 7500)[0]
    assert row["window_relevant_mean"] == pytest.approx(0.3) and math.isnan(row["window_relevant_stderr"])
    run.steps[7500]["visitation/task_relevant"] = 0.4 - 1e-9  # float32 shares: no row in the region
    assert run_groups.share_between(run, 5000, 7500) == 0.0
    run.replay_capacity = 5000  # the ring wrapped by 7,500: its rows are no longer one per step since 0
    assert math.isnan(run_groups.share_between(run, 5000, 7500))
    assert run_groups.share_between(run, 2500, 5000) == pytest.approx(0.2)


def test_without_a_window_each_task_gets_the_last_quarter_every_agent_reached(runs, tmp_path):
    write_run(runs / "tabletop" / "morefree" / "seed0", "tabletop", "morefree", 0, [0.0, 0.5, 1.0])
    groups = run_groups.group_runs(run_groups.find_runs(runs)[0])
    assert run_groups.last_quarter(groups, "point_umaze") == (5625, 7500)
    out = tmp_path / "results"
    assert plots.main([f"runs={runs}", f"out={out}"]) == 0
    with open(out / "tabletop_window.csv") as file:
        rows = list(csv.DictReader(file))
    assert [(r["agent"], r["start"], r["stop"], r["evaluations"]) for r in rows] == [
        ("morefree", "5625", "7500", "1")]


@pytest.mark.parametrize("window", ["5000", "a:b", "7500:5000"])
def test_bad_window_is_one_line(runs, tmp_path, window, capsys):
    assert plots.main([f"runs={runs}", f"out={tmp_path / 'out'}", f"window={window}"]) == 2
    assert "window" in capsys.readouterr().err.splitlines()[-1]


def test_visitation_shows_each_agent_at_its_latest_step_or_at_the_cap(runs):
    # ibc's seeds ran for different lengths and saved at steps no other agent has.
    for seed, saved in ((0, (2800, 5800)), (1, (2800,))):
        run_dir = runs / "point_umaze" / "ibc" / f"seed{seed}"
        write_run(run_dir, "point_umaze", "ibc", seed, [0.0, 0.0, 0.0])
        for step in STEPS:
            (run_dir / "plots" / f"visitation_{step:09d}.npy").unlink()
        for step in saved:
            np.save(run_dir / "plots" / f"visitation_{step:09d}.npy", np.zeros((50, 50)))
    groups = run_groups.group_runs(run_groups.find_runs(runs)[0])
    geometry = figures.TaskGeometry("point_umaze")
    fig, steps = figures.visitation_figure("point_umaze", groups, geometry)
    assert steps == {"ibc": 2800, "morefree": 7500, "rf_peg": 7500}  # ibc: the latest both seeds saved
    assert [ax.get_title().splitlines()[1:] for ax in figures.heatmap_panels(fig)] == [
        ["task-relevant -", "2 seeds, step 2,800"], ["task-relevant 10.0%", "3 seeds, step 7,500"],
        ["task-relevant 5.0%", "2 seeds, step 7,500"]]
    _, capped = figures.visitation_figure("point_umaze", groups, geometry, cap=5000)
    assert capped == {"ibc": 2800, "morefree": 5000, "rf_peg": 5000}
    assert figures.visitation_figure("point_umaze", groups, geometry, cap=1000) == (None, {})


@pytest.mark.parametrize("extra_agents", [(), ("r3l", "medal", "ibc")])
def test_heatmap_titles_and_labels_stay_inside_the_figure(runs, extra_agents):
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    for agent in extra_agents:
        write_run(runs / "point_umaze" / agent / "seed0", "point_umaze", agent, 0, [0.0, 0.0, 0.0])
    groups = run_groups.group_runs(run_groups.find_runs(runs)[0])
    fig, steps = figures.visitation_figure("point_umaze", groups, figures.TaskGeometry("point_umaze"))
    assert len(steps) == 2 + len(extra_agents)
    FigureCanvasAgg(fig).draw()
    width, height = fig.get_size_inches() * fig.dpi
    for ax in fig.axes:  # the panels and the colour bar
        box = ax.get_tightbbox()  # the panel with its title, tick labels and axis labels
        assert box.x0 >= 0 and box.y0 >= 0 and box.x1 <= width and box.y1 <= height, (ax.get_title(), box)
    legend = fig.legends[0].get_window_extent()
    assert legend.x0 >= 0 and legend.y0 >= 0 and legend.x1 <= width and legend.y1 <= height
    assert not any(legend.overlaps(ax.get_window_extent()) for ax in fig.axes)  # it covers no data
    assert [text.get_text() for text in fig.legends[0].get_texts()] == ["task-relevant", "start", "goal"]


def test_agents_option_draws_only_those_agents(runs, tmp_path, capsys):
    out = tmp_path / "results"
    assert plots.main([f"runs={runs}", f"out={out}", "agents=rf_peg", "marks=7500"]) == 0
    with open(out / "point_umaze_results.csv") as file:
        assert [row["agent"] for row in csv.DictReader(file)] == ["rf_peg"]
    assert not (out / "ablation.csv").exists()  # no morefree among the chosen agents
    capsys.readouterr()
    assert plots.main([f"runs={runs}", f"out={out}", "agents=r3l,ibc"]) == 2
    error = capsys.readouterr().err
    assert error == f"error: no run of r3l, ibc found below {runs} (agents there: morefree, rf_peg)\n"


def test_pick_place_hard_gets_the_side_view_with_its_in_air_share(tmp_path):
    """The paper's XZ heatmap: tasks with a side view draw it from side_visitation_<step>.npy with the
    in-air share in the title; tasks without one (point_umaze) do not."""
    root = tmp_path / "runs"
    for seed, in_air in ((0, 0.25), (1, 0.5)):
        run_dir = root / "pick_place_hard" / "morefree" / f"seed{seed}"
        write_run(run_dir, "pick_place_hard", "morefree", seed, [0.0, 0.1, 0.2])
        with open(run_dir / "metrics.jsonl", "a") as file:
            file.write(json.dumps({"step": STEPS[-1], "visitation/in_air": in_air}) + "\n")
        np.save(run_dir / "plots" / f"side_visitation_{STEPS[-1]:09d}.npy", np.ones((50, 50)))
    write_run(root / "point_umaze" / "morefree" / "seed0", "point_umaze", "morefree", 0, [0.0, 0.0, 0.0])
    out = tmp_path / "results"
    assert plots.main([f"runs={root}", f"out={out}"]) == 0
    names = {path.name for path in out.iterdir()}
    assert {"pick_place_hard_side_visitation.png", "pick_place_hard_visitation.png"} <= names
    assert "point_umaze_side_visitation.png" not in names
    groups = run_groups.group_runs(run_groups.find_runs(root, "pick_place_hard")[0])
    geometry = figures.TaskGeometry("pick_place_hard")
    fig, steps = figures.visitation_figure("pick_place_hard", groups, geometry, view=figures.SIDE_VIEW)
    assert steps == {"morefree": STEPS[-1]}
    title = fig.axes[0].get_title().splitlines()
    assert title == ["morefree", "in the air 37.5%", f"2 seeds, step {STEPS[-1]:,}"]
    # the side view's box is the block's x and height, with the air line inside it
    low_x, high_x, low_z, high_z = geometry.extents["xz"]
    assert low_x < 1.43 < high_x and low_z < geometry.air_height < high_z
