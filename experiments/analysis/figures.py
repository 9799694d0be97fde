"""The paper's figures and results tables of grouped run dirs (what `make plots` writes; the CLI is
experiments/plots.py, which lists the files).

    paths = write_task(task, groups, out, stamp_for)        # curves, heatmaps, back starts (PNG and SVG)
    paths = write_table(task, groups, out, marks, stamp_for) # <task>_results.csv / .md
"""

from __future__ import annotations

import pathlib
from typing import NamedTuple

import numpy as np

from experiments.analysis import ablation_summary, run_groups, zero_action
from experiments.analysis.task_geometry import TaskGeometry

CURVES = (("success", "eval/success", run_groups.SUCCESS_ANY),
          ("final_success", "eval/final_success", run_groups.SUCCESS_LAST),
          ("task_relevant", "visitation/task_relevant", "task-relevant share of the replay"))


STAMP_STRIP = 0.04  # the least share of the figure's height kept at the bottom for the stamp (one line)


def _figure(width=6.4, height=4.0, layout="constrained"):
    from matplotlib.figure import Figure  # no pyplot: no global figure state, no GUI backend

    fig = Figure(figsize=(width, height), layout=layout)
    fig.get_layout_engine().set(rect=(0, STAMP_STRIP, 1, 1 - STAMP_STRIP))
    return fig


def _stamp_lines(stamp: str, fits) -> list[str]:
    """The stamp broken between words into lines that each fit (a word longer than a line keeps a line)."""
    lines = []
    for word in stamp.split(" "):
        if lines and fits(f"{lines[-1]} {word}"):
            lines[-1] += f" {word}"
        else:
            lines.append(word)
    return lines


def add_stamp(fig, stamp: str):
    """The stamp in a footer strip, on as many lines as the figure's width needs (a one-panel figure is
    narrower than a stamp listing many commits); the layout leaves the strip that high."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    text = fig.text(0.995, 0.005, stamp, ha="right", va="bottom", fontsize=6, color="0.4")
    renderer = FigureCanvasAgg(fig).get_renderer()
    width = 0.99 * fig.bbox.width

    def fits(line):
        text.set_text(line)
        return text.get_window_extent(renderer).width <= width

    text.set_text("\n".join(_stamp_lines(stamp, fits)))
    strip = max(STAMP_STRIP, (text.get_window_extent(renderer).height + 8) / fig.bbox.height)
    fig.get_layout_engine().set(rect=(0, strip, 1, 1 - strip))
    return text


def save(fig, out: pathlib.Path, name: str, stamp: str) -> list[pathlib.Path]:
    """name.png and name.svg with the stamp in a footer and in the files' metadata (no dates: files change
    only when their content does)."""
    import matplotlib

    add_stamp(fig, stamp)
    paths = [out / f"{name}.png", out / f"{name}.svg"]
    fig.savefig(paths[0], dpi=120, metadata={"Description": stamp, "Software": None})
    with matplotlib.rc_context({"svg.hashsalt": "morefree-jax"}):  # ids from the content, not at random
        fig.savefig(paths[1], metadata={"Description": stamp, "Date": None})
    return paths


def curve_figure(task, groups, key, label):
    fig = _figure()
    axes = fig.add_subplot()
    for (group_task, agent), group in sorted(groups.items()):
        if group_task != task:
            continue
        steps, mean, stderr = run_groups.curve(group, key)
        if not len(steps):
            continue
        line, = axes.plot(steps, mean, label=f"{agent} ({len(group)} seed{'s' * (len(group) > 1)})")
        if len(group) > 1:
            axes.fill_between(steps, mean - stderr, mean + stderr, color=line.get_color(), alpha=0.2)
    axes.set(xlabel="env steps", ylabel=label, title=f"{task}: {label}, mean ± standard error")
    axes.grid(alpha=0.3)
    legend_below(fig, *axes.get_legend_handles_labels(), fontsize=8)
    return fig


def legend_below(fig, handles, labels, fontsize):
    """The legend under the axes, where it covers no data, in as many columns (at most 3) as the figure's
    width holds."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    if not handles:
        return None
    renderer = FigureCanvasAgg(fig).get_renderer()
    for columns in range(min(len(labels), 3), 0, -1):
        legend = fig.legend(handles, labels, loc="outside lower center", ncols=columns, fontsize=fontsize)
        if columns == 1 or legend.get_window_extent(renderer).width <= 0.98 * fig.bbox.width:
            return legend
        legend.remove()


class HeatmapView(NamedTuple):
    """One visitation heatmap: the files runs save it in (plots/<prefix>_<step>.npy), the share shown in
    the titles and the axes."""

    name: str  # TaskGeometry's view
    prefix: str
    share_key: str
    share_label: str
    axis_labels: tuple[str, str] | None


TOP_VIEW = HeatmapView("xy", "visitation", "visitation/task_relevant", "task-relevant", None)
SIDE_VIEW = HeatmapView("xz", "side_visitation", "visitation/in_air", "in the air", ("x", "height z"))


def _panels(count):
    # "compressed": the constrained layout for fixed-aspect axes (maps, heatmaps); the plain one lets their
    # two-line titles run off the top of a row of panels.
    fig = _figure(3.2 * count + 1.0, 3.9, layout="compressed")  # + the colour bar; the legend below
    return fig, [fig.add_subplot(1, count, i + 1) for i in range(count)]


def visitation_figure(task, groups, geometry: TaskGeometry, cap: int | None = None, view=TOP_VIEW):
    """Per agent: the view's histogram summed over seeds, as shares of the visits, at the latest step all
    its seeds have saved (at or below `cap` when given, to compare agents at one step), on one log colour
    scale with a colour bar; the step is in each panel's title, the legend under the panels. Agents that
    ran for different lengths each show their latest. (figure, {agent: step}); (None, {}) if none."""
    steps = {}
    for (t, agent), group in sorted(groups.items()):
        if t != task:
            continue
        common = set.intersection(*(r.saved_views(view.prefix) for r in group))
        eligible = [step for step in common if cap is None or step <= cap]
        if eligible:
            steps[agent] = max(eligible)
    if not steps:
        return None, {}
    from matplotlib.colors import LogNorm

    shares = {agent: visit_shares(groups[task, agent], view.prefix, step) for agent, step in steps.items()}
    visited = np.concatenate([share[share > 0] for share in shares.values()])
    # One scale for every panel, so that colours compare across agents; unvisited cells stay blank.
    norm = LogNorm(vmin=visited.min(), vmax=visited.max()) if visited.size else None
    fig, axes = _panels(len(steps))
    for ax, (agent, step) in zip(axes, steps.items(), strict=True):
        group = groups[task, agent]
        share = np.mean([r.steps.get(step, {}).get(view.share_key, np.nan) for r in group])
        image = ax.imshow(np.ma.masked_equal(shares[agent].T, 0), origin="lower", norm=norm,
                          extent=geometry.extents[view.name], cmap="viridis")
        geometry.draw(ax, view.name)
        if view.axis_labels:
            ax.set(xlabel=view.axis_labels[0], ylabel=view.axis_labels[1])
        seeds = f"{len(group)} seed{'s' * (len(group) > 1)}"
        ax.set_title(f"{agent}\n{view.share_label} {run_groups.percent(share)}\n{seeds}, step {step:,}",
                     fontsize=9)
    fig.colorbar(image, ax=axes, shrink=0.8, label="share of visits per cell")
    legend_below(fig, *axes[0].get_legend_handles_labels(), fontsize=7)
    return fig, steps


def heatmap_panels(fig) -> list:
    """The panels of a heatmap figure (its axes but the colour bar's)."""
    return [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]


def visit_shares(group, prefix: str, step: int) -> np.ndarray:
    """The seeds' histograms at `step` summed, as shares of all their visits (agents with 3 and 5 seeds
    compare)."""
    histogram = sum(run.histogram(prefix, step) for run in group)
    return histogram / max(histogram.sum(), 1)


def rest_density(trajectory: np.ndarray, radius: float) -> np.ndarray:
    """(100,) share of the trajectory's points within `radius` of each point (NaN points: 0)."""
    distances = np.linalg.norm(trajectory[:, None] - trajectory[None], axis=-1)
    return np.nansum(distances < radius, axis=1) / len(trajectory)


def back_starts_figure(task, groups, geometry: TaskGeometry):
    agents = []
    for (t, agent), group in sorted(groups.items()):
        saved = [r.back_starts() for r in group] if t == task else []
        if any(back is not None for back in saved):  # each seed keeps its newest successful back chunks
            agents.append((agent, [back for back in saved if back is not None]))
    if not agents:
        return None
    fig, axes = _panels(len(agents))
    radius = 0.03 * np.hypot(geometry.extent[1] - geometry.extent[0], geometry.extent[3] - geometry.extent[2])
    for ax, (agent, loaded) in zip(axes, agents, strict=True):
        per_seed, saved = [xy for xy, _ in loaded], sorted({step for _, step in loaded})
        trajectories = np.concatenate(per_seed)
        points = trajectories.reshape(-1, 2)
        density = np.concatenate([rest_density(t, radius) for t in trajectories])
        keep = np.isfinite(points).all(axis=1)
        order = np.argsort(density[keep])  # the longest rests drawn on top
        ax.scatter(*points[keep][order].T, c=density[keep][order], cmap="Reds", vmin=0, vmax=1, s=4)
        geometry.draw(ax)  # after the points, so that the start and goal markers stay visible
        seeds = f"{len(per_seed)} seed{'s' * (len(per_seed) > 1)}"
        # Seeds save at their own latest evaluation: the title says which steps the chunks run up to.
        at = f"{saved[0]:,}" if len(saved) == 1 else f"{saved[0]:,}-{saved[-1]:,}"
        ax.set_title(f"{agent}: {len(trajectories)} successful back chunks\n(100 steps before each, "
                     f"{seeds}, up to step {at})", fontsize=9)
    return fig


def write_task(task, groups, out, stamp_for, visitation_cap: int | None = None) -> list[pathlib.Path]:
    written = []
    commits = sorted({c for (t, _), g in groups.items() if t == task for r in g for c in r.commits})
    stamp = stamp_for(commits)
    for name, key, label in CURVES:
        written += save(curve_figure(task, groups, key, label), out, f"{task}_{name}", stamp)
    geometry = TaskGeometry(task)
    for view in (v for v in (TOP_VIEW, SIDE_VIEW) if v.name in geometry.extents):  # the task's views
        fig, _ = visitation_figure(task, groups, geometry, visitation_cap, view)
        if fig is not None:
            written += save(fig, out, f"{task}_{view.prefix}", stamp)
    fig = back_starts_figure(task, groups, geometry)
    if fig is not None:
        written += save(fig, out, f"{task}_back_starts", stamp)
    return written


def write_table(task, groups, out, marks, stamp_for) -> list[pathlib.Path]:
    """<task>_results.csv and .md: success at the step marks (default: 4 evenly spaced evaluated steps)."""
    task_groups = {key: group for key, group in groups.items() if key[0] == task}
    rows = run_groups.results_rows(task_groups, {task: marks or run_groups.default_marks(task_groups, task)})
    commits = sorted({c for group in task_groups.values() for r in group for c in r.commits})
    paths = [out / f"{task}_results.csv", out / f"{task}_results.md"]
    paths[0].write_text(run_groups.csv_text(rows))
    paths[1].write_text(run_groups.markdown_table(rows) + f"\n{stamp_for(commits)}\n")
    return paths


def write_window(task, groups, out, window, stamp_for, chance: dict | None = None) -> list[pathlib.Path]:
    """<task>_window.csv and .md: mean success over the evaluations in the window (run_groups.window_rows);
    under the markdown table the task's chance level where one is given (zero_action.py)."""
    task_groups = {key: group for key, group in groups.items() if key[0] == task}
    rows = run_groups.window_rows(task_groups, *window)
    commits = sorted({c for group in task_groups.values() for r in group for c in r.commits})
    paths = [out / f"{task}_window.csv", out / f"{task}_window.md"]
    paths[0].write_text(run_groups.csv_text(rows, run_groups.WINDOW_COLUMNS))
    chance_line = f"\n{zero_action.markdown_line(chance)}\n" if chance else ""
    paths[1].write_text(run_groups.window_markdown(rows) + chance_line + f"\n{stamp_for(commits)}\n")
    return paths


def write_ablation(groups, out, stamp_for) -> list[pathlib.Path]:
    """ablation.{png,svg,csv,md} when some task has morefree and an ablation variant (ablation_summary)."""
    rows = ablation_summary.task_rows(groups)
    if not rows:
        return []
    summary = ablation_summary.summary_rows(rows)
    commits = sorted({c for row in rows for c in row["commits"].split()})
    stamp = stamp_for(commits)
    paths = save(ablation_summary.figure(rows, summary, _figure), out, "ablation", stamp)
    paths += [out / "ablation.csv", out / "ablation.md"]
    paths[2].write_text(run_groups.csv_text(rows, ablation_summary.TASK_COLUMNS))
    paths[3].write_text(ablation_summary.markdown(rows, summary) + f"\n{stamp}\n")
    return paths
