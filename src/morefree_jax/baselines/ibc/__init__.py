"""IBC: learners (learner.py), its stream of segments (segments.py), curriculum, hindsight replay, tasks."""
