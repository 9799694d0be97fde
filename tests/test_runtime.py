"""Process settings of morefree_jax.runtime, each checked in a fresh interpreter (they act at start-up), and
the promise that importing the library changes none of them."""

import json
import os
import subprocess
import sys

import pytest

from morefree_jax import runtime

# Minor page faults of the second of two malloc / touch / free rounds of 400 MB in a worker thread: what
# XLA does with an execution's temporaries (the thread is off glibc's main arena).
FAULTS = """
import ctypes, json, resource, threading
from morefree_jax import runtime
settings = runtime.configure()
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
size = 400 * 2**20
def use_temporaries():
    block = libc.malloc(size)
    ctypes.memset(block, 1, size)
    libc.free(block)
def in_worker():
    worker = threading.Thread(target=use_temporaries)
    worker.start()
    worker.join()
in_worker()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
in_worker()
print(json.dumps({"faults": resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before,
                  "settings": settings}))
"""


def _python(code: str, mode: str, extra_env: dict | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, runtime.MODE_VARIABLE: mode}
    env.pop("XLA_FLAGS", None)
    env.pop("LD_PRELOAD", None)  # glibc's malloc unless a test asks for jemalloc
    env.update(extra_env or {})
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)


def _last_json(done: subprocess.CompletedProcess) -> dict:
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_large_mode_reuses_freed_memory_instead_of_faulting_it_in_again():
    large, default = _last_json(_python(FAULTS, "large")), _last_json(_python(FAULTS, "default"))
    assert large["settings"]["keep_freed_memory"] and not default["settings"]["keep_freed_memory"]
    # ~100k 4 KB pages of temporaries: faulted in again on every call unless freed memory is kept.
    assert default["faults"] > 50_000
    assert large["faults"] < 5_000


def test_modes_set_their_xla_flags():
    code = ("import json, os; from morefree_jax import runtime; runtime.configure()\n"
            "print(json.dumps(os.environ.get('XLA_FLAGS', '')))")
    flags = {mode: _last_json(_python(code, mode)) for mode in ("large", "standard", "default")}
    assert runtime.YNN_OFF in flags["large"] and runtime.YNN_OFF not in flags["standard"]
    assert runtime.IN_PLACE_LOOPS in flags["large"] and runtime.IN_PLACE_LOOPS in flags["standard"]
    assert flags["default"] == ""
    bf16 = code.replace("runtime.configure()", "runtime.configure(precision='bf16')")
    assert runtime.YNN_OFF not in _last_json(_python(bf16, "large"))  # bf16 dots keep YNNPACK's kernels


def test_flags_are_not_touched_once_jax_has_started():
    code = ("import os, warnings, jax; jax.numpy.ones(1).block_until_ready()\n"
            "with warnings.catch_warnings(record=True) as caught:\n"
            "    warnings.simplefilter('always')\n"
            "    from morefree_jax import runtime; runtime.configure()\n"
            "print(os.environ.get('XLA_FLAGS', ''), '|', [str(w.message) for w in caught])")
    out = _python(code, "large").stdout
    flags, _, warned = out.rpartition("|")
    assert runtime.YNN_OFF not in flags
    assert "call it before any JAX computation" in warned


def test_unknown_mode_is_a_clear_error(monkeypatch):
    monkeypatch.setenv(runtime.MODE_VARIABLE, "fastest")
    with pytest.raises(ValueError, match="standard, large, default"):
        runtime.runtime_mode()


def test_unknown_mode_argument_is_a_clear_error():
    with pytest.raises(ValueError, match="standard, large, default"):
        runtime.configure("fast")


def test_allocator_env_preloads_jemalloc_once_and_only_where_wanted(monkeypatch):
    monkeypatch.setattr(runtime, "find_jemalloc", lambda: "libjemalloc.so.2")
    env = runtime.allocator_env({"LD_PRELOAD": "libother.so"})
    assert env == {"LD_PRELOAD": "libother.so libjemalloc.so.2", "MALLOC_CONF": runtime.JEMALLOC_CONF}
    assert runtime.allocator_env({"MALLOC_CONF": "narenas:2"})["MALLOC_CONF"] == "narenas:2"  # user's wins
    assert runtime.allocator_env({"LD_PRELOAD": "/opt/libjemalloc.so"}) == {}  # already preloaded
    assert runtime.allocator_env({runtime.JEMALLOC_VARIABLE: "0"}) == {}  # opted out
    monkeypatch.setattr(runtime, "find_jemalloc", lambda: None)
    assert runtime.allocator_env({}) == {}  # not installed: glibc, nothing to preload


@pytest.mark.skipif(runtime.find_jemalloc() is None, reason="libjemalloc2 is not installed on this machine")
def test_a_process_started_with_allocator_env_runs_on_jemalloc_and_leaves_glibc_alone():
    code = "import json; from morefree_jax import runtime; print(json.dumps(runtime.configure()))"
    on_jemalloc = _last_json(_python(code, "large", runtime.allocator_env({})))
    assert on_jemalloc["allocator"] == "jemalloc" and not on_jemalloc["keep_freed_memory"]
    on_glibc = _last_json(_python(code, "large"))
    assert on_glibc["allocator"] == "glibc" and on_glibc["keep_freed_memory"]


IMPORT_EVERYTHING = """
import importlib, json, os, pkgutil, sys
before = dict(os.environ)
import morefree_jax, envs_mjx, experiments
from jax._src import xla_bridge
def import_all(package):
    names = [info.name for info in pkgutil.walk_packages(package.__path__, package.__name__ + ".")
             if info.name != "experiments.benchmarks.torch_sac_reference"]  # runs under torch's Python only
    for name in names:
        importlib.import_module(name)
    return names
names = import_all(morefree_jax) + import_all(envs_mjx)
from morefree_jax import runtime
changed = {k: v for k, v in os.environ.items() if before.get(k) != v}
removed = sorted(set(before) - set(os.environ))
names += import_all(experiments)  # the programs: they call runtime.configure() after their imports
print(json.dumps({"modules": names, "changed": changed, "removed": removed, "settings": runtime.settings(),
                  "backend_started": xla_bridge.backends_are_initialized()}))
"""


def test_importing_every_module_changes_no_process_state():
    done = _last_json(_python(IMPORT_EVERYTHING, "large", {"XLA_FLAGS": "--xla_cpu_use_thunk_runtime=true"}))
    assert {"morefree_jax.driver", "morefree_jax.agent", "envs_mjx.point_umaze"} <= set(done["modules"])
    assert done["changed"] == {} and done["removed"] == [], done  # XLA_FLAGS, MALLOC_*, ... untouched
    assert done["settings"]["mode"] == "unconfigured"  # no XLA flag added, no mallopt called
    # nor a JAX computation at import: it starts XLA's backend, after which configure() can set no flag
    assert "experiments.benchmarks.model_free" in done["modules"] and not done["backend_started"]
