"""MEDAL (agent.py), with its demonstrations (demos.py, demo_rollouts.py)."""
