"""The run functions compiled for a group of seeds: `compile_programs(fns, num_seeds) -> Programs`.

Every program takes and returns states with a leading seed axis: one compiled collect and one compiled
train call advance every seed of the group, each with its own stream, replay, agent, planner, keys and goal
schedule. How the seeds share the program (`seed_axis`):

  "map"   a loop over the seeds inside the program (lax.map): each seed runs exactly the single-seed
          computation, bit for bit, and its branches (the goal search) run only where that seed needs
          them. On a CPU, where one seed's learner already keeps the cores busy, this loses nothing.
  "vmap"  the seeds batched (jax.vmap): on an accelerator each kernel serves all seeds at once. The
          numbers equal the single-seed run's to float rounding (~1e-7), but XLA's batched kernels round
          differently, and a contact-rich stream amplifies that over tens of steps, so seed k's trajectory
          is a valid run of seed k but not the single-seed one. Branches that differ per seed stay lazy
          (batching.lazy_cond: the goal search runs when any seed needs it).
  "auto"  map on CPU, vmap on GPU/TPU.

A single seed always runs the plain unbatched functions behind a free reshape to a seed axis of 1.

When the process sees more than one device (GPUs, or CPU devices forced with
XLA_FLAGS=--xla_force_host_platform_device_count=N) and the seed count divides among them, the seed axis
is sharded over a 1-D mesh (jax.shard_map): each device runs its own seeds, with no change to the code.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from morefree_jax.run import RunFns

SEED_AXIS = "seeds"
SEED_AXIS_MODES = ("auto", "map", "vmap")


class Programs(NamedTuple):
    """Jitted run functions over a seed axis (see RunFns for each function's unbatched signature)."""

    fns: RunFns
    num_seeds: int
    seed_axis: str  # "map" or "vmap" (resolved)
    sharding: NamedSharding | None
    init: Callable  # keys (S, 2) -> RunState (S, ...)
    prefill: Callable
    collect: Callable
    train_updates: Callable | None
    evaluate: Callable  # (AgentState (S, ...), keys (S, 2)) -> (metrics (S,), EvalResult (S, ...))
    visitation: Callable


def seed_sharding(num_seeds: int, devices=None) -> NamedSharding | None:
    """The seed axis split over all devices (a 1-D mesh), or None with one device or an uneven split."""
    devices = jax.devices() if devices is None else devices
    if len(devices) < 2 or num_seeds % len(devices):
        return None
    return NamedSharding(Mesh(np.asarray(devices), (SEED_AXIS,)), PartitionSpec(SEED_AXIS))


def resolve_seed_axis(seed_axis: str) -> str:
    if seed_axis not in SEED_AXIS_MODES:
        raise ValueError(f"unknown seed_axis {seed_axis!r}; valid: {', '.join(SEED_AXIS_MODES)}")
    if seed_axis == "auto":
        return "map" if jax.default_backend() == "cpu" else "vmap"
    return seed_axis


def _over_seeds(fn: Callable, num_seeds: int, seed_axis: str) -> Callable:
    """fn over a leading seed axis of every argument and output (module docstring)."""
    if num_seeds == 1:
        def single(*args):
            return jax.tree.map(lambda x: x[None], fn(*jax.tree.map(lambda x: x[0], args)))

        return single
    if seed_axis == "vmap":
        return jax.vmap(fn)
    return lambda *args: jax.lax.map(lambda per_seed: fn(*per_seed), args)


def compile_programs(fns: RunFns, num_seeds: int, sharding: NamedSharding | None = None,
                     seed_axis: str = "auto") -> Programs:
    """jit of every run function over the seed axis; states are donated. Compiles on first call."""
    if num_seeds < 1:
        raise ValueError(f"num_seeds must be >= 1, got {num_seeds}")
    seed_axis = resolve_seed_axis(seed_axis)

    options = compiler_options(fns)

    def program(fn, donate: bool = False):
        if fn is None:  # a run function the agent does not have (model-free: no train_updates)
            return None
        if sharding is None:
            over_seeds = _over_seeds(fn, num_seeds, seed_axis)
        else:  # each device runs its own share of the seeds
            local = num_seeds // sharding.mesh.size
            spec = PartitionSpec(SEED_AXIS)
            over_seeds = jax.shard_map(_over_seeds(fn, local, seed_axis), mesh=sharding.mesh, in_specs=spec,
                                       out_specs=spec, check_vma=False)
        return jax.jit(over_seeds, donate_argnums=0 if donate else (), compiler_options=options)

    return Programs(fns, num_seeds, seed_axis, sharding, program(fns.init),
                    program(fns.prefill, donate=True), program(fns.collect, donate=True),
                    program(fns.train_updates, donate=True), program(fns.evaluate),
                    program(fns.visitation))


def compiler_options(fns: RunFns) -> dict | None:
    """XLA options of every program of a run: run.codegen "fast" sets XLA's backend optimisation level 0
    (config.RunConfig); None leaves XLA's defaults."""
    return {"xla_backend_optimization_level": 0} if fns.config.run.codegen == "fast" else None


def seed_slice(tree, index: int):
    """Seed `index` of a tree with a leading seed axis (host-side, for checkpoints and logs)."""
    return jax.tree.map(lambda x: x[index], tree)


def stack_seeds(trees: list, sharding: NamedSharding | None = None):
    """Per-seed trees -> one tree with a leading seed axis (placed by `sharding` when given)."""
    stacked = jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *trees)
    return jax.device_put(stacked, sharding) if sharding is not None else jax.device_put(stacked)


def jit_run_fns(fns: RunFns) -> RunFns:
    """The run functions jitted one seed at a time, states donated (notebooks, benchmarks, tests)."""
    options = compiler_options(fns)
    donated = {name: jax.jit(getattr(fns, name), donate_argnums=0, compiler_options=options)
               for name in ("prefill", "collect", "train_updates") if getattr(fns, name) is not None}
    return fns._replace(init=jax.jit(fns.init, compiler_options=options),
                        evaluate=jax.jit(fns.evaluate, compiler_options=options),
                        visitation=jax.jit(fns.visitation, compiler_options=options), **donated)
