"""The paper's figures and results tables of grouped run dirs (what `make plots` writes; the CLI is
experiments/plots.py, which lists the files).

    paths = write_task(task, groups, out, stamp_for)        # curves, heatmaps, back starts (PNG and SVG)
    paths = write_table(task, groups, out, marks, stamp_for) # <task>_results.csv / .md
"""

from __future__ import annotations

import pathlib
from typing import NamedTuple

import numpy as np

from experiments.analysis import ablation_summary, run_groups

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
    strip = max(STAMP_STRIP, (text.get_window_extent(renderer).height + 4) / fig.bbox.height)
    fig.get_layout_engine().set(rect=(0, strip, 1, 1 - strip))
    return text


def save(fig, out: pathlib.Path, name: str, stamp: str) -> list[pathlib.Path]:
    """name.png and name.svg with the stamp in a footer and in the files' metadata (no dates: files change
    only when their content does)."""
    add_stamp(fig, stamp)
    paths = [out / f"{name}.png", out / f"{name}.svg"]
    fig.savefig(paths[0], dpi=120, metadata={"Description": stamp, "Software": None})
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
    axes.legend(loc="best", fontsize=8)
    return fig


class TaskGeometry:
    """The task's xy box, samples of its start and goal regions, and walls to draw (PointUMaze); for tasks
    with a side view (envs_mjx.base: side_view_dims) its box, the samples in it and the air height."""

    def __init__(self, task: str, samples: int = 200):
        import jax

        import envs_mjx

        env = envs_mjx.make(task)
        keys = jax.random.split(jax.random.PRNGKey(0), samples)
        starts = np.asarray(jax.vmap(env.initial_states)(keys))
        goals = np.asarray(jax.vmap(env.eval_goals)(keys))
        views = {"xy": env.xy} if env.side_view_dims is None else {"xy": env.xy, "xz": env.side_view}
        self.extents, self.starts, self.goals = {}, {}, {}
        for name, view in views.items():
            low, high = (np.asarray(view(np.asarray(b, np.float32))) for b in env.observation_bounds)
            self.extents[name] = (low[0], high[0], low[1], high[1])
            self.starts[name] = np.asarray(jax.vmap(view)(starts))
            self.goals[name] = np.asarray(jax.vmap(view)(goals))
        self.extent = self.extents["xy"]
        self.air_height = env.air_height
        self.walls = np.zeros((0, 2, 2))
        if task == "point_umaze":
            from envs_mjx.point_umaze import wall_faces

            self.walls = wall_faces(radius=0.0)

    def draw(self, axes, view: str = "xy"):
        if view == "xy":
            for segment in self.walls:
                axes.plot(segment[:, 0], segment[:, 1], color="0.2", linewidth=2)
        else:  # the side view: above the red line the object is in the air
            axes.axhline(self.air_height, color="tab:red", linewidth=1.2, label="in the air above")
        axes.scatter(*self.starts[view].T, marker="o", s=12, facecolors="none", edgecolors="tab:blue",
                     label="start")
        axes.scatter(*self.goals[view].T, marker="*", s=18, color="tab:green", label="goal")
        extent = self.extents[view]
        axes.set(xlim=extent[:2], ylim=extent[2:], aspect="equal")


class HeatmapView(NamedTuple):
    """One visitation heatmap: the files runs save it in (plots/<prefix>_<step>.npy), the share shown in
    the titles and the axes."""

    name: str  # TaskGeometry's view
    prefix: str
    share_key: str
    share_label: str
    axis_labels: tuple[str, str] | None
    legend_loc: str  # where the legend hides the least: the side view's visits lie low


TOP_VIEW = HeatmapView("xy", "visitation", "visitation/task_relevant", "task-relevant", None, "lower right")
SIDE_VIEW = HeatmapView("xz", "side_visitation", "visitation/in_air", "in the air", ("x", "height z"),
                        "upper right")


def _panels(count):
    # "compressed": the constrained layout for fixed-aspect axes (maps, heatmaps); the plain one lets their
    # two-line titles run off the top of a row of panels.
    fig = _figure(3.2 * count + 0.4, 3.4, layout="compressed")
    return fig, [fig.add_subplot(1, count, i + 1) for i in range(count)]


def _saved_visitation_steps(run, prefix: str = "visitation") -> set[int]:
    return {int(p.stem.rsplit("_", 1)[1]) for p in (run.run_dir / "plots").glob(f"{prefix}_*.npy")}


def visitation_figure(task, groups, geometry: TaskGeometry, cap: int | None = None, view=TOP_VIEW):
    """Per agent: the view's histogram summed over seeds at the latest step all its seeds have saved (at or
    below `cap` when given, to compare agents at one step); the step is in each panel's title. Agents
    that ran for different lengths each show their latest. (figure, {agent: step}); (None, {}) if none."""
    steps = {}
    for (t, agent), group in sorted(groups.items()):
        if t != task:
            continue
        common = set.intersection(*(_saved_visitation_steps(r, view.prefix) for r in group))
        eligible = [step for step in common if cap is None or step <= cap]
        if eligible:
            steps[agent] = max(eligible)
    if not steps:
        return None, {}
    fig, axes = _panels(len(steps))
    for ax, (agent, step) in zip(axes, steps.items(), strict=True):
        group = groups[task, agent]
        histogram = sum(np.load(r.run_dir / "plots" / f"{view.prefix}_{step:09d}.npy") for r in group)
        share = np.mean([r.steps.get(step, {}).get(view.share_key, np.nan) for r in group])
        ax.imshow(np.log1p(histogram.T), origin="lower", extent=geometry.extents[view.name], cmap="viridis")
        geometry.draw(ax, view.name)
        if view.axis_labels:
            ax.set(xlabel=view.axis_labels[0], ylabel=view.axis_labels[1])
        seeds = f"{len(group)} seed{'s' * (len(group) > 1)}"
        ax.set_title(f"{agent}: {view.share_label} {100 * share:.1f}%\n({seeds}, step {step:,})", fontsize=9)
    axes[0].legend(loc=view.legend_loc, fontsize=7)
    return fig, steps


def rest_density(trajectory: np.ndarray, radius: float) -> np.ndarray:
    """(100,) share of the trajectory's points within `radius` of each point (NaN points: 0)."""
    distances = np.linalg.norm(trajectory[:, None] - trajectory[None], axis=-1)
    return np.nansum(distances < radius, axis=1) / len(trajectory)


def _load_back_starts(path) -> tuple[np.ndarray, int]:
    """(xy (n, 100, 2), the step the file was saved at): each seed keeps its newest successful back chunks."""
    with np.load(path) as data:
        return data["xy"], int(data["step"])


def back_starts_figure(task, groups, geometry: TaskGeometry):
    agents = []
    for (t, agent), group in sorted(groups.items()):
        files = [r.run_dir / "plots" / "back_starts.npz" for r in group]
        if t == task and any(f.exists() for f in files):
            agents.append((agent, [_load_back_starts(f) for f in files if f.exists()]))
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


def write_window(task, groups, out, window, stamp_for) -> list[pathlib.Path]:
    """<task>_window.csv and .md: mean success over the evaluations in the window (run_groups.window_rows)."""
    task_groups = {key: group for key, group in groups.items() if key[0] == task}
    rows = run_groups.window_rows(task_groups, *window)
    commits = sorted({c for group in task_groups.values() for r in group for c in r.commits})
    paths = [out / f"{task}_window.csv", out / f"{task}_window.md"]
    paths[0].write_text(run_groups.csv_text(rows, run_groups.WINDOW_COLUMNS))
    paths[1].write_text(run_groups.window_markdown(rows) + f"\n{stamp_for(commits)}\n")
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
