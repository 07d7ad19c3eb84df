"""Shared fixtures: fresh random seeds (printed on failure) and a Zenoh router on loopback."""

from __future__ import annotations

import os
import shutil
import tempfile

import numpy as np
import pytest

from common import compile_cache
from common.bus import open_session
from deploy.launch import free_port, router_config

_own_cache: str | None = None


def pytest_configure(config):
    """One JAX compilation cache for the whole run, shared with the services the
    tests start (docs/running.md): a fresh directory unless VAMPPI_JAX_CACHE is set."""
    global _own_cache
    if compile_cache.ENV not in os.environ:
        _own_cache = tempfile.mkdtemp(prefix="vamppi-jax-cache-")
        os.environ[compile_cache.ENV] = _own_cache
    compile_cache.enable()


def pytest_unconfigure(config):
    if _own_cache is not None:
        shutil.rmtree(_own_cache, ignore_errors=True)


@pytest.fixture
def rng(request) -> np.random.Generator:
    """A fresh generator each run; its seed is in the test's report on failure."""
    seed = int.from_bytes(os.urandom(4), "little")
    request.node.user_properties.append(("seed", seed))
    print(f"rng seed {seed}")
    return np.random.default_rng(seed)


@pytest.fixture
def router():
    """A Zenoh router session on a free loopback port; yields its endpoint."""
    port = free_port()
    with open_session(router_config(port)):
        yield f"tcp/127.0.0.1:{port}"
