"""morefree-jax: reset-free model-based RL (MoReFree, PEG, LEXA/DreamerV2) in JAX.

Importing the package tunes the process for XLA's CPU runtime before JAX starts: XLA flags, and in the
`large` mode the allocator (see `morefree_jax.runtime`; MOREFREE_JAX_RUNTIME=default opts out).
`RUNTIME_SETTINGS` records what was applied.
"""

from morefree_jax.runtime import tune_cpu_runtime

RUNTIME_SETTINGS = tune_cpu_runtime()
