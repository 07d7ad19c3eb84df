"""The planner's vectorisable float32 transcendental functions against NumPy float64."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from services.planner import fastmath as fm


def _f32(a):
    return jnp.asarray(np.asarray(a, np.float32))


def _edges():
    return np.array([0.0, -0.0, 1e-30, -1e-30, 0.41421357, 2.4142137, 1.0, -1.0, 1e6, -1e6,
                     np.pi / 4, np.pi / 2, np.pi, -np.pi, 3 * np.pi / 4], np.float32)


def test_arctan(rng):
    x = np.concatenate([rng.normal(0, 1, 20000), rng.normal(0, 100, 5000), _edges()])
    x = x.astype(np.float32)
    got = np.asarray(jax.jit(fm.arctan)(_f32(x)), np.float64)
    assert np.max(np.abs(got - np.arctan(x.astype(np.float64)))) <= 2.5e-7


def test_arctan2_in_every_quadrant_and_on_the_axes(rng):
    y = np.concatenate([rng.normal(0, 3, 20000), _edges(), _edges() * 0, np.zeros(15)])
    x = np.concatenate([rng.normal(0, 3, 20000), _edges()[::-1], _edges(), -_edges()])
    y, x = y.astype(np.float32), x.astype(np.float32)
    got = np.asarray(jax.jit(fm.arctan2)(_f32(y), _f32(x)), np.float64)
    want = np.arctan2(y.astype(np.float64), x.astype(np.float64))
    assert np.max(np.abs(got - want)) <= 3e-7         # XLA's own arctan2: 2.5e-7


def test_arccos_over_its_domain_and_at_its_ends(rng):
    x = np.concatenate([rng.uniform(-1, 1, 20000), 1 - rng.uniform(0, 1e-3, 2000),
                        -1 + rng.uniform(0, 1e-3, 2000), [-1.0, 0.0, -0.0, 1.0]])
    x = x.astype(np.float32)
    got = np.asarray(jax.jit(fm.arccos)(_f32(x)), np.float64)
    assert np.max(np.abs(got - np.arccos(x.astype(np.float64)))) <= 3e-7    # seen: 2.7e-7


@pytest.mark.parametrize("scale", [1.0, 10.0, 1000.0])
def test_sin_cos(rng, scale):
    x = np.concatenate([rng.uniform(-scale, scale, 20000), _edges()[:9]]).astype(np.float32)
    x64 = x.astype(np.float64)
    s = np.asarray(jax.jit(fm.sin)(_f32(x)), np.float64)
    c = np.asarray(jax.jit(fm.cos)(_f32(x)), np.float64)
    assert np.max(np.abs(s - np.sin(x64))) <= 5e-7
    assert np.max(np.abs(c - np.cos(x64))) <= 5e-7


def test_tan_over_steering_angles(rng):
    x = rng.uniform(-1.4, 1.4, 20000).astype(np.float32)
    got = np.asarray(jax.jit(fm.tan)(_f32(x)), np.float64)
    want = np.tan(x.astype(np.float64))
    assert np.max(np.abs(got - want) / np.maximum(1.0, np.abs(want))) <= 1e-6


def test_fast_namespace_is_jax_numpy_otherwise():
    assert fm.FAST.tanh is jnp.tanh and fm.FAST.stack is jnp.stack
    assert fm.FAST.arctan2 is fm.arctan2 and fm.FAST.arccos is fm.arccos
