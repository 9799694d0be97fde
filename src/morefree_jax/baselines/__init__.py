"""Model-free baselines of the paper (docs/baselines.md): the SAC learner they share (sac/learner.py,
with its replay, learned rewards and stream in sac/) and one subpackage per baseline over it: oracle_sac/,
r3l/, medal/ and ibc/. Their settings are in baseline_config.py."""
