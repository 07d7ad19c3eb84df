"""The persistent compilation cache: where it lives, how it is turned off, and that a
second process loads the planner's solver from it (traced and compiled) instead of
tracing and compiling it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from common import compile_cache


def test_cache_dir_follows_the_environment(tmp_path):
    assert compile_cache.cache_dir({"VAMPPI_JAX_CACHE": str(tmp_path)}) == tmp_path
    for off in ("off", "0", "", "OFF", "false"):
        assert compile_cache.cache_dir({"VAMPPI_JAX_CACHE": off}) is None
    assert compile_cache.cache_dir({"XDG_CACHE_HOME": "/x"}) == Path("/x/vamppi/jax")
    assert compile_cache.cache_dir({}) == Path.home() / ".cache" / "vamppi" / "jax"


def test_an_uncreatable_directory_leaves_the_cache_off(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    monkeypatch.setenv("VAMPPI_JAX_CACHE", str(blocker / "jax"))
    assert compile_cache.enable() is None


def test_processes_sharing_a_gpu_neither_preallocate_nor_exceed_their_share():
    from common.memory import GPU_HEADROOM, PIPELINE_PROCESSES, share_device
    env = {}
    share_device(1, env)                                       # a parent's own share ...
    set_ = share_device(PIPELINE_PROCESSES, env)               # ... its children's replace it
    assert set_ and all(env[k] == v for k, v in set_.items())
    assert env["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"
    assert PIPELINE_PROCESSES * float(env["XLA_PYTHON_CLIENT_MEM_FRACTION"]) <= GPU_HEADROOM
    mine = {"XLA_PYTHON_CLIENT_MEM_FRACTION": "0.5"}           # the user's own setting wins
    assert share_device(2, mine) == {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    assert mine["XLA_PYTHON_CLIENT_MEM_FRACTION"] == "0.5"
    assert share_device(4, mine) == {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    assert mine["XLA_PYTHON_CLIENT_MEM_FRACTION"] == "0.5"


_TRACED = """
import hashlib, json, logging, sys
import numpy as np
from common import compile_cache
compile_cache.enable()
warned = []
class Warned(logging.Handler):
    def emit(self, record):
        warned.append(record.getMessage())
logging.getLogger("common.compile_cache").addHandler(Warned())
hits = []
class Hits(logging.Handler):
    def emit(self, record):
        if "cache hit" in record.getMessage():
            hits.append(record.getMessage())
log = logging.getLogger("jax._src.compiler")
log.setLevel(logging.DEBUG)
log.addHandler(Hits())
lowered = []
class Lowered(logging.Handler):
    def emit(self, record):
        if record.getMessage().startswith("Compiling jit(call)"):
            lowered.append(1)
log = logging.getLogger("jax._src.interpreters.pxla")
log.setLevel(logging.DEBUG)
log.addHandler(Lowered())
import jax
from common.config import load_config
from services.planner import mppi
from services.planner.params import PlannerParams
traces = []
_solve = mppi._solve
def counted(*a, **k):
    traces.append(1)
    return _solve(*a, **k)
mppi._solve = counted
rng = np.random.default_rng(int(sys.argv[1]))
cfg = load_config(None, ["planner.samples=16", "planner.controller=va"])
p = PlannerParams.from_config(cfg)
m, v = rng.uniform(0.0, 1.5, (2, 40, 40)).astype(np.float32)
x0 = np.array([3.0, 4.0, 0.3, 2.0, 0.0, 0.0], np.float32)
args = (mppi.initial_state(p, 0), x0, np.array([0.1, 500.0], np.float32),
        np.array([6.0, 5.0, 0.0], np.float32), m, 0.5 * v, np.zeros(2, np.float32))
state, solved = mppi.solve(p, *args, 0.2)
got = jax.tree_util.tree_leaves((state, solved))
mppi.solve(p, state, *args[1:], 0.2)               # a loop's next solve: committed state
out = {"traced": len(traces), "warned": warned, "hits": hits, "lowered": len(lowered),
       "digest": hashlib.sha256(b"".join(np.asarray(x).tobytes() for x in got)).hexdigest()}
if sys.argv[2] == "compare":
    want = mppi.jitted(p)(args[0], *map(jax.numpy.asarray, args[1:]), resolution=0.2)
    out["same"] = all(np.asarray(x).tobytes() == np.asarray(y).tobytes()
                      for x, y in zip(got, jax.tree_util.tree_leaves(want)))
print(json.dumps(out))
"""


@pytest.mark.skipif(sys.platform != "linux", reason="subprocess environment on Linux")
def test_a_second_process_runs_the_traced_solver_without_tracing_bit_for_bit(tmp_path, rng):
    """`mppi.solve` runs the program `Traced` keeps: the first process traces and stores
    it, the next one only deserializes it, a truncated file is traced again with a warning;
    a loop's second solve, on the state the first returned, compiles nothing more;
    every time its results are those of the solver jitted in the process, bit for bit
    (VA-MPPI's solver, with the native kernels where they build, on a fresh random map)."""
    env = {**os.environ, "VAMPPI_JAX_CACHE": str(tmp_path / "cache")}
    root = Path(__file__).resolve().parents[1]
    seed = str(int(rng.integers(2**31)))

    def probe(compare: bool = False) -> dict:
        out = subprocess.run([sys.executable, "-c", _TRACED, seed,
                              "compare" if compare else "-"], env=env, cwd=root,
                             check=True, capture_output=True, text=True, timeout=600)
        return json.loads(out.stdout.strip().splitlines()[-1])

    first = probe(compare=True)
    assert first["traced"] == 1 and first["same"] and first["warned"] == []
    assert first["lowered"] == 1          # the next solve, on the state it returned, too
    (stored,) = (tmp_path / "cache" / "traced").glob("*/*.bin")
    second = probe()
    assert second["traced"] == 0 and second["warned"] == [] and second["lowered"] == 1
    assert [h for h in second["hits"] if "'jit_call'" in h]       # and compiled from the cache
    assert second["digest"] == first["digest"]
    stored.write_bytes(stored.read_bytes()[:1000])
    third = probe()
    assert third["traced"] == 1 and third["digest"] == first["digest"]
    assert len(third["warned"]) == 1 and "does not deserialize" in third["warned"][0]
