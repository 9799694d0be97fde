"""`make bench`: the benchmark sections (core, envs, loop, model_free, seeds) and their driver (bench.py)."""
