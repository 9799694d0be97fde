"""`make bench`: compile times and steady-state throughput of every jitted entry point.

Runs every section module of experiments/benchmarks/ (SECTIONS; each exposes `run(quick) -> list[row]`, a
row being {"section", "name", "value", "unit", "note"}), prints one table and writes bench/results.json
together with the machine and the package versions. Speed is measured here, never asserted in tests.

    python -m experiments.benchmarks                       # everything (minutes)
    python -m experiments.benchmarks only=envs,core        # some sections
    python -m experiments.benchmarks quick=1               # tiny sizes: checks that every section runs
    python -m experiments.benchmarks out=bench/results.json
"""

from __future__ import annotations

import importlib
import json
import os
import pathlib
import platform
import sys
import time

from experiments.cli import KeyValueError, parse_keys

# modules of this package with run(quick)
SECTIONS = ("core", "envs", "loop", "model_free", "seeds", "whole_run")


def parse_args(argv=None) -> dict:
    """{"sections", "quick", "out"}; a bad argument is a one-line KeyValueError naming the valid ones."""
    args = parse_keys(list(argv or []), {"only": "", "quick": False, "out": "bench/results.json"})
    args["sections"] = [s for s in args["only"].split(",") if s] or list(SECTIONS)
    unknown = [s for s in args["sections"] if s not in SECTIONS]
    if unknown:
        raise KeyValueError(f"unknown section(s) {unknown}; valid sections: {', '.join(SECTIONS)}")
    return args


def machine_info() -> dict:
    import jax

    versions = {}
    for name in ("jax", "jaxlib", "flax", "optax", "mujoco", "brax"):
        try:
            versions[name] = importlib.import_module(name).__version__
        except (ImportError, AttributeError):
            versions[name] = "?"
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = float("nan")
    return {"python": platform.python_version(), "cpu_count": os.cpu_count(), "machine": platform.machine(),
            "device": str(jax.devices()[0]), "load_average_1min": load, "versions": versions,
            "date": time.strftime("%Y-%m-%d %H:%M:%S")}


def format_table(rows: list[dict]) -> str:
    lines = [f"{'section':<10} {'name':<52} {'value':>12} {'unit':<10} note"]
    for row in rows:
        value = row["value"]
        shown = f"{value:12.4g}" if isinstance(value, float) else f"{value!s:>12}"
        note = row.get("note", "")
        lines.append(f"{row['section']:<10} {row['name']:<52} {shown} {row['unit']:<10} {note}")
    return "\n".join(lines)


def main(argv=None) -> int:
    from morefree_jax import runtime

    try:
        args = parse_args(argv)
    except KeyValueError as error:
        print(f"bench: {error}", file=sys.stderr)
        return 2
    runtime.configure()  # before any JAX computation: the tuned runtime the runs use
    rows: list[dict] = []
    for section in args["sections"]:
        started = time.perf_counter()
        module = importlib.import_module(f"experiments.benchmarks.{section}")
        section_rows = module.run(quick=args["quick"])
        rows.extend(section_rows)
        print(format_table(section_rows), flush=True)
        print(f"# section {section}: {time.perf_counter() - started:.1f} s\n", flush=True)
    out = pathlib.Path(args["out"])
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"machine": machine_info(), "quick": args["quick"], "rows": rows}, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
