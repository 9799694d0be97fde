"""`python -m experiments.benchmarks [only=core,envs] [quick=1] [out=bench/results.json]` (bench.py)."""

import sys

from experiments.benchmarks.bench import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
