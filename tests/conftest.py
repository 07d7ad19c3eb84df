"""Shared fixtures: fresh random seeds (printed on failure), a VA-MPPI planning problem and a
Zenoh router on loopback. The run has its own JAX compilation cache, and each test process
(`make test` runs two, pytest-xdist) its own configuration home (the certificates `vamppi up`
makes on first use) and runtime dir (where a bus command finds the running `vamppi up`),
never the user's. The tests that make network namespaces (on fixed subnets) must not
overlap: they share one `xdist_group`."""

from __future__ import annotations

import os
import shutil
import tempfile

import numpy as np
import pytest

from common import compile_cache
from common.bus import open_session
from deploy.launch.up import free_port, router_config

_own_cache: str | None = None
_own_home: str | None = None
_own_runtime: str | None = None


def pytest_configure(config):
    """One JAX compilation cache for the whole run, shared with the services the
    tests start (docs/running.md): a fresh directory unless VAMPPI_JAX_CACHE is set."""
    global _own_cache, _own_home, _own_runtime
    _own_home = tempfile.mkdtemp(prefix="vamppi-config-home-")
    os.environ["XDG_CONFIG_HOME"] = _own_home
    _own_runtime = tempfile.mkdtemp(prefix="vamppi-runtime-")
    os.environ["XDG_RUNTIME_DIR"] = _own_runtime
    if compile_cache.ENV not in os.environ:
        _own_cache = tempfile.mkdtemp(prefix="vamppi-jax-cache-")
        os.environ[compile_cache.ENV] = _own_cache
    compile_cache.enable()


def pytest_unconfigure(config):
    for d in (_own_cache, _own_home, _own_runtime):
        if d is not None:
            shutil.rmtree(d, ignore_errors=True)


@pytest.fixture
def rng(request) -> np.random.Generator:
    """A fresh generator each run; its seed is in the test's report on failure."""
    seed = int.from_bytes(os.urandom(4), "little")
    request.node.user_properties.append(("seed", seed))
    print(f"rng seed {seed}")
    return np.random.default_rng(seed)


@pytest.fixture
def va_planning_problem():
    """VA-MPPI's benchmark problem (the offroad map of `deploy.bench.kernels.planner_inputs`) with
    K = 64 rollouts of sampled noise round a zero nominal: (params, map view, states
    (64, N+1, 6))."""
    import jax
    import jax.numpy as jnp

    from common.config import load_config
    from deploy.bench.kernels import planner_inputs
    from services.planner import kernels, mppi
    from services.planner.costs import MapView
    from services.planner.params import PlannerParams
    cfg = load_config(overrides=['planner.controller="va"', "planner.samples=64"])
    x0, u0, _goal, mean, var, origin, res = planner_inputs(cfg)
    params = PlannerParams.from_config(cfg)
    m = MapView(jnp.asarray(mean), jnp.asarray(var), jnp.asarray(origin), res)
    noise = mppi.sample_noise(params, jax.random.PRNGKey(3))
    states = jax.jit(jax.vmap(lambda e: kernels.rollout(params, jnp.asarray(x0), jnp.asarray(u0),
                                                     e)[0]))(noise)
    return params, m, states


@pytest.fixture
def router():
    """A Zenoh router session on a free loopback port; yields its endpoint."""
    port = free_port()
    with open_session(router_config(port)):
        yield f"tcp/127.0.0.1:{port}"
