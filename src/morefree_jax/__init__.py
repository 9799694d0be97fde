"""morefree-jax: reset-free model-based RL (MoReFree, PEG, LEXA/DreamerV2) in JAX.

Importing the package changes no process state. For the tuned CPU runtime (XLA flags, and in the `large`
mode the allocator), call `morefree_jax.runtime.configure()` before the first JAX computation; the CLIs
and benchmarks do.
"""
