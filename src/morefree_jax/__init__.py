"""morefree_jax: reset-free model-based RL (MoReFree, PEG, LEXA, DreamerV2) in JAX/Flax."""
