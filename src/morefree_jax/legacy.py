"""Config keys added after run dirs were written without them, with the value those runs computed with.
A stored config that lacks one reads as having that value: it compares so on resume (checkpoint.py), and
plots label it so (experiments/analysis/run_groups.py). No JAX here."""

LEGACY_VALUES = {"agent.precision": "f32", "run.update_cadence": "chunk"}


def stored_value(config: dict, dotted: str):
    """The value of a dotted key of a stored config dict, its legacy value where the dict lacks it."""
    section, key = dotted.split(".")
    return config.get(section, {}).get(key, LEGACY_VALUES[dotted])
