"""R3L (agent.py)."""
