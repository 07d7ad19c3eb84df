"""The persistent compilation cache: where it lives, how it is turned off, and that a
second process loads the planner's solver from it instead of compiling."""

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


_PROBE = """
import json, logging
from common import compile_cache
compile_cache.enable()
hits = []
class Hits(logging.Handler):
    def emit(self, record):
        if "cache hit" in record.getMessage() and "solve" in record.getMessage():
            hits.append(record.getMessage())
log = logging.getLogger("jax._src.compiler")
log.setLevel(logging.DEBUG)
log.addHandler(Hits())
import jax.numpy as jnp
from common.config import load_config
from services.planner import mppi
from services.planner.params import PlannerParams
cfg = load_config(None, ["planner.samples=16", "planner.controller=deterministic"])
p = PlannerParams.from_config(cfg)
args = (mppi.initial_state(p, 0), jnp.zeros(6), jnp.zeros(2), jnp.ones(3),
        jnp.zeros((40, 40)), jnp.ones((40, 40)), jnp.zeros(2))
mppi.solver(p).lower(*args, resolution=0.2).compile()
print(json.dumps({"hits": len(hits)}))
"""


@pytest.mark.skipif(sys.platform != "linux", reason="subprocess environment on Linux")
def test_a_second_process_loads_the_solver_from_the_cache(tmp_path):
    env = {**os.environ, "VAMPPI_JAX_CACHE": str(tmp_path / "cache")}
    root = Path(__file__).resolve().parents[1]

    def hits() -> int:
        out = subprocess.run([sys.executable, "-c", _PROBE], env=env, cwd=root, check=True,
                             capture_output=True, text=True, timeout=600)
        return json.loads(out.stdout.strip().splitlines()[-1])["hits"]

    assert hits() == 0                      # compiled, and stored
    assert any("solve" in e.name for e in (tmp_path / "cache").iterdir())
    assert hits() == 1                      # loaded by a fresh process


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
