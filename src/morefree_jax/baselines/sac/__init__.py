"""What the model-free baselines share: the SAC learner, replay, learned rewards, the stream (stream.py)."""
