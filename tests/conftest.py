"""Shared fixtures: fresh random seeds (printed on failure) and a Zenoh router on loopback."""

from __future__ import annotations

import os

import numpy as np
import pytest

from common.bus import open_session
from deploy.launch import free_port, router_config


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
