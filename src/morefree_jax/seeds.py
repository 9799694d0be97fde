"""Seed lists of multi-seed runs: parsing, checking, and one config (and run dir) per seed.

Imports no JAX, so the CLI can reject bad input before anything heavy loads.
"""

from __future__ import annotations

import dataclasses

from morefree_jax.config import MAX_SEED, Config, ConfigError


def check_seeds(seeds) -> tuple[int, ...]:
    """The seeds as a tuple of distinct non-negative ints, else a one-line ConfigError."""
    seeds = tuple(seeds)
    if not seeds:
        raise ConfigError("seeds is empty; give one or more distinct integers >= 0, e.g. seeds=0,1,2")
    if any(isinstance(s, bool) or not isinstance(s, int) or not 0 <= s <= MAX_SEED for s in seeds):
        raise ConfigError(f"seeds must be integers in 0..{MAX_SEED}, got {list(seeds)}")
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"seeds must be distinct, got {list(seeds)}")
    return seeds


def parse_seeds(text: str) -> tuple[int, ...]:
    """'0,1,2' -> (0, 1, 2), with one-line errors for empty, repeated, negative or non-integer entries."""
    parts = [part.strip() for part in text.split(",")] if text.strip() else []
    try:
        seeds = tuple(int(part) for part in parts)
    except ValueError:
        raise ConfigError(f"seeds must be comma-separated integers >= 0 (e.g. seeds=0,1,2), got {text!r}") \
            from None
    return check_seeds(seeds)


def seed_configs(config: Config, seeds: tuple[int, ...]) -> list[Config]:
    """One config per seed. Run dirs: runs/<env>/<agent>/seed<k>, or <run_dir>/seed<k> when a run_dir is
    given for several seeds (a single seed keeps the run_dir as given)."""
    base = config.run.run_dir
    configs = []
    for seed in seeds:
        run_dir = f"{base}/seed{seed}" if base and len(seeds) > 1 else base
        configs.append(dataclasses.replace(config, run=dataclasses.replace(config.run, seed=seed,
                                                                           run_dir=run_dir)))
    return configs
