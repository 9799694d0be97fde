#!/usr/bin/env bash
# On a CUDA machine (no network needed beyond the package index): install the CUDA build of the pinned JAX,
# then measure the `paper` train step (1 and 2 seeds; one seed at f32 and bf16) and the 1- and 3-seed `cpu`
# chunk at both precisions, in about 10 minutes.
#
#     bash experiments/benchmarks/gpu_check.sh [OUT_DIR]      # rows printed and written to OUT_DIR/gpu_bench.json
#
# CUDA=13 picks the CUDA 13 wheels (default 12). Nothing here is needed on a CPU machine.
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-bench}"
mkdir -p "$out"
make install CUDA="${CUDA:-12}" >/dev/null
.venv/bin/python - "$out" <<'PY'
import json, sys, time

from morefree_jax import runtime

runtime.configure()
import jax

from experiments.benchmarks import core as bench_core
from experiments.benchmarks import seeds as bench_seeds

print("devices:", jax.devices(), flush=True)
rows, started = [], time.perf_counter()
peak = bench_core.matmul_peak()
rows.append(bench_seeds._row("matmul_peak", peak / 1e9, "GFLOP/s", str(jax.devices()[0])))
rows += bench_seeds.paper_rows(peak)
for precision in ("f32", "bf16"):
    rows += bench_core.bench_train("paper", 3, peak, precision)
for precision, num_seeds in (("f32", 1), ("bf16", 1), ("f32", 3), ("bf16", 3)):
    result = bench_seeds.run_throughput(num_seeds, "auto", chunks=4, precision=precision)
    rows.append(bench_seeds._row(f"cpu_run/{precision}_{num_seeds}_seeds_steps_per_s",
                                 bench_seeds._steps_per_s(result), "steps/s",
                                 f"compile {result['compile_s']:.0f} s; collect {result['collect_s']:.2f} s, "
                                 f"train {result['train_s']:.2f} s per chunk"))
for row in rows:
    print(f"{row['name']:52} {row['value']:10.3f} {row['unit']:8} {row['note']}", flush=True)
print(f"total {time.perf_counter() - started:.0f} s")
json.dump({"device": str(jax.devices()[0]), "rows": rows}, open(f"{sys.argv[1]}/gpu_bench.json", "w"), indent=1)
PY
