"""Process settings for XLA's CPU runtime, applied by an explicit `configure()` before JAX starts.

Importing `morefree_jax` (or any module of it) changes no process state. A program that trains or
benchmarks calls `morefree_jax.runtime.configure()` first thing, before any JAX computation: the CLIs
(experiments/train.py, evaluate.py, bench*.py) and the test suite's conftest do; in a notebook, call it in
the first cell. `settings()` tells what was applied (mode "unconfigured" if nothing was).

`configure(mode)`, or MOREFREE_JAX_RUNTIME when mode is None, picks them (each chosen by measurement with
experiments/benchmarks/core.py; the figures are in docs/performance.md, "What the runtime settings gain"):

- `standard` (the default): `--xla_cpu_prefer_vector_width=512` on CPUs with AVX-512. XLA's loop fusions
  (ELUs and their derivatives, Adam) then vectorise 512 bits wide instead of 256, and both the `cpu` train
  step and the `paper`-size ensemble get faster.
  On every CPU, `--xla_cpu_copy_insertion_use_region_analysis=true`: XLA's copy insertion then sees that a
  buffer carried through a loop can be updated in place where its default analysis copies it. The
  model-free chunk stores into and samples from its replay in every step of one scan, and by default
  XLA copied a replay field twice per step (docs/performance.md, "The speed bar", for the gain). Only
  copies go: the numbers stay bit for bit the same.
- `large`, for paper-size learners on CPU (`make train PRESET=paper`, the core benchmark's paper row):
  `standard` plus two changes that only pay off when one update moves gigabytes.
  1. Page faults. XLA allocates an execution's temporaries (6.5 GB at `paper`) afresh on every call;
     glibc serves that from a fresh `mmap` (always, for a thread off the main arena) and unmaps it on
     `free`, so every update faults in and zeroes every page again, millions of minor faults per
     exploration update. One malloc arena, no mmap'd chunks and no trimming keep freed memory in the
     process: no faults, and the exploration part nearly twice as fast. The process keeps its peak heap
     (the next update reuses it). With small learners the single arena costs more than it saves (threads
     contend for it: the `cpu` train step about 2x slower), hence not the default.
  2. YNNPACK fusions off (`--xla_cpu_experimental_ynn_fusion_type=`): XLA's own dot emitter runs the
     (33750, 400) x (400, 400) matmuls of the paper-size ensemble faster than YNNPACK does.
     Only for float32 learners (`configure(precision=...)`): with bfloat16 inputs YNNPACK's dots are the
     fast ones (docs/performance.md, "Precision").
- `default`: touch nothing.

XLA flags take effect only if no JAX backend exists yet; flags already in XLA_FLAGS are left as they are.

jemalloc, where installed (Debian/Ubuntu `libjemalloc2`), does better than any glibc setting: per-thread
caches instead of one contended arena, and with purging off (`MALLOC_CONF=JEMALLOC_CONF`) no page is
faulted in twice; both train steps get faster (docs/performance.md, "Learning core"). An allocator is
chosen when a process starts, so it is preloaded by the launchers: `make train/evaluate/bench` run their
command under `allocator_env()` (printed by `print_allocator_env()`), the core benchmark's paper child
process too. With jemalloc loaded,
`large` leaves glibc's malloc alone (it is not used). MOREFREE_JAX_JEMALLOC=0 opts out.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
import warnings

MODE_VARIABLE = "MOREFREE_JAX_RUNTIME"
JEMALLOC_VARIABLE = "MOREFREE_JAX_JEMALLOC"
JEMALLOC_CONF = "retain:true,dirty_decay_ms:-1,muzzy_decay_ms:-1"  # keep freed pages: never purge
MODES = ("standard", "large", "default")
YNN_OFF = "--xla_cpu_experimental_ynn_fusion_type="
WIDE_VECTORS = "--xla_cpu_prefer_vector_width=512"  # only on CPUs with AVX-512
IN_PLACE_LOOPS = "--xla_cpu_copy_insertion_use_region_analysis=true"
_M_TRIM_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -4, -8  # glibc's mallopt parameter numbers


def _keep_freed_memory() -> bool:
    """glibc: one arena, no mmap'd chunks, never trim (-1 reads as SIZE_MAX) -> True if all applied."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    return all(mallopt(param, value) == 1 for param, value in
               ((_M_ARENA_MAX, 1), (_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, -1)))


def find_jemalloc() -> str | None:
    """The jemalloc shared library's name if the system has one (LD_PRELOAD accepts the bare name)."""
    return ctypes.util.find_library("jemalloc") if sys.platform.startswith("linux") else None


def _file_contains(path: str, text: str) -> bool:
    """Whether a (/proc) file holds `text`; False where the file cannot be read (not Linux)."""
    try:
        with open(path) as file:
            return text in file.read()
    except OSError:
        return False


def jemalloc_loaded() -> bool:
    """Whether this process runs on jemalloc (preloaded: it replaces malloc for every library)."""
    return _file_contains("/proc/self/maps", "libjemalloc")


def allocator_env(environ: dict | None = None) -> dict[str, str]:
    """Environment additions that start a process on jemalloc: {} if it is missing, already preloaded, or
    disabled with MOREFREE_JAX_JEMALLOC=0."""
    environ = os.environ if environ is None else environ
    preload = environ.get("LD_PRELOAD", "")
    library = find_jemalloc()
    if environ.get(JEMALLOC_VARIABLE, "1") == "0" or library is None or "jemalloc" in preload:
        return {}
    return {"LD_PRELOAD": " ".join(filter(None, [preload, library])),
            "MALLOC_CONF": environ.get("MALLOC_CONF", JEMALLOC_CONF)}


def _has_avx512() -> bool:
    return _file_contains("/proc/cpuinfo", " avx512f")


def _add_xla_flags(wanted: list[str]) -> list[str]:
    """Adds the wanted flags the user did not set to XLA_FLAGS while no JAX backend exists yet."""
    from jax._src import xla_bridge  # private: the only way to know whether flags can still apply

    flags = os.environ.get("XLA_FLAGS", "")
    added = [flag for flag in wanted if flag.split("=")[0] not in flags]
    if added and xla_bridge.backends_are_initialized():
        warnings.warn(f"morefree_jax.runtime.configure() was called after JAX started, too late for "
                      f"XLA_FLAGS {added}: train steps on CPU run slower; call it before any JAX computation",
                      stacklevel=3)
        return []
    os.environ["XLA_FLAGS"] = " ".join([flags, *added]).strip()
    return added


def runtime_mode() -> str:
    return _checked(os.environ.get(MODE_VARIABLE, "standard") or "standard")


def _checked(mode: str) -> str:
    if mode not in MODES:
        raise ValueError(f"{MODE_VARIABLE}={mode!r} is not one of {', '.join(MODES)}")
    return mode


_applied: dict | None = None  # what configure() applied in this process (None: not called)


def configure(mode: str | None = None, precision: str = "f32") -> dict:
    """Applies the settings of `mode` (default: $MOREFREE_JAX_RUNTIME or standard) -> what was applied.
    precision: the learner's agent.precision (precision.py; f32, its default), which decides `large`'s dot
    emitter.
    Call it before the first JAX computation (XLA reads its flags when its backend starts); a second call
    returns the first call's settings."""
    global _applied
    mode = _checked(mode) if mode else runtime_mode()
    if _applied is not None:
        if mode != _applied["mode"]:
            warnings.warn(f"runtime already configured as {_applied['mode']!r}; {mode!r} ignored",
                          stacklevel=2)
        return _applied
    allocator = "jemalloc" if jemalloc_loaded() else "glibc"
    if mode == "default":
        _applied = {"mode": mode, "allocator": allocator, "keep_freed_memory": False, "xla_flags": []}
        return _applied
    from morefree_jax.precision import cpu_precision  # no JAX: safe before the backend starts

    float32_dots = cpu_precision(precision) == "f32"
    wanted = [IN_PLACE_LOOPS, *([YNN_OFF] if mode == "large" and float32_dots else []),
              *([WIDE_VECTORS] if _has_avx512() else [])]
    keep = _keep_freed_memory() if mode == "large" and allocator == "glibc" else False
    _applied = {"mode": mode, "allocator": allocator, "keep_freed_memory": keep,
                "xla_flags": _add_xla_flags(wanted)}
    return _applied


def settings() -> dict:
    """What configure() applied in this process; mode "unconfigured" when it was not called."""
    if _applied is not None:
        return _applied
    allocator = "jemalloc" if jemalloc_loaded() else "glibc"
    return {"mode": "unconfigured", "allocator": allocator, "keep_freed_memory": False, "xla_flags": []}


def print_allocator_env() -> None:
    """Prints the allocator_env() assignments for a shell's `env` (the Makefile's launchers use it)."""
    print(" ".join(f"{name}={value}" for name, value in allocator_env().items()))
