"""Model-free baselines of the paper (reference/baselines.md): the SAC learner they share (sac.py)."""
