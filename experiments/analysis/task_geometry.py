"""What the heatmaps draw over the visits: the task's box, samples of its start and goal regions, the
region that counts as task-relevant, and PointUMaze's walls.

    geometry = TaskGeometry("push_hard")
    geometry.draw(axes)            # walls, the task-relevant outline, start (o) and goal (*) samples
"""

from __future__ import annotations

import numpy as np

RELEVANT_CELLS = 160  # the task-relevant outline's grid per axis (finer than the 50-bin heatmap)
RELEVANT_BASES = 24  # initial states and evaluation goals whose other coordinates the outline uses
MARKERS = 30  # start and goal samples drawn


def xy_dims(env, obs) -> np.ndarray:
    """The two observation entries env.xy reads (every task's xy is two entries of the observation),
    found from its Jacobian; ValueError for an xy that mixes entries."""
    import jax

    jacobian = np.asarray(jax.jacobian(env.xy)(obs))
    dims = np.abs(jacobian).argmax(axis=1)
    if not np.array_equal(np.abs(jacobian) > 0, np.eye(obs.size, dtype=bool)[dims]):
        raise ValueError(f"{env.name}.xy is not two entries of the observation")
    return dims


def relevant_mask(env, bases: np.ndarray, extent, cells: int = RELEVANT_CELLS) -> np.ndarray:
    """(cells, cells) bool, [y, x] over `extent`: where env.task_relevant holds for an observation of
    `bases` with its xy moved there (the start and goal observations give the other coordinates: a Fetch
    block on the table at its start, in the air at a Pick&Place goal). The region the task-relevant
    share counts, seen from above."""
    import jax
    import jax.numpy as jnp

    dims = xy_dims(env, jnp.asarray(bases[0]))
    xs = np.linspace(extent[0], extent[1], cells)
    ys = np.linspace(extent[2], extent[3], cells)
    grid = jnp.asarray(np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2), jnp.float32)

    @jax.jit
    def relevant_at(base):
        observations = jnp.broadcast_to(base, (grid.shape[0], base.size)).at[:, dims].set(grid)
        return jax.vmap(env.task_relevant)(observations)

    mask = np.zeros(len(grid), bool)
    for base in bases:
        mask |= np.asarray(relevant_at(jnp.asarray(base, jnp.float32)))
    return mask.reshape(cells, cells)


class TaskGeometry:
    """The task's xy box, samples of its start and goal regions, the task-relevant region, and walls to
    draw (PointUMaze); for tasks with a side view (envs_mjx.base: side_view_dims) its box, the samples in
    it and the air height."""

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
        half = RELEVANT_BASES // 2
        self.relevant = relevant_mask(env, np.concatenate([starts[:half], goals[:half]]), self.extent)
        self.air_height = env.air_height
        self.walls = np.zeros((0, 2, 2))
        if task == "point_umaze":
            from envs_mjx.point_umaze import wall_faces

            self.walls = wall_faces(radius=0.0)

    def draw(self, axes, view: str = "xy"):
        if view == "xy":
            for segment in self.walls:
                axes.plot(segment[:, 0], segment[:, 1], color="0.2", linewidth=2)
            if self.relevant.any():
                axes.contour(self.relevant.astype(float), levels=[0.5], extent=self.extent, colors="tab:red",
                             linewidths=1.0, linestyles="--")
                axes.plot([], [], color="tab:red", linewidth=1.0, linestyle="--", label="task-relevant")
        else:  # the side view: above the red line the object is in the air
            axes.axhline(self.air_height, color="tab:red", linewidth=1.2, label="in the air above")
        # A few hollow markers, so that the visits under them stay visible (the outline shows the regions).
        shown = slice(0, MARKERS)
        axes.scatter(*self.starts[view][shown].T, marker="o", s=14, facecolors="none", edgecolors="tab:blue",
                     linewidths=0.8, label="start")
        axes.scatter(*self.goals[view][shown].T, marker="*", s=22, facecolors="none", edgecolors="tab:green",
                     linewidths=0.6, label="goal")
        extent = self.extents[view]
        axes.set(xlim=extent[:2], ylim=extent[2:], aspect="equal")
