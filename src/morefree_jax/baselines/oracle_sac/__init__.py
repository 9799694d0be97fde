"""Oracle SAC (agent.py)."""
