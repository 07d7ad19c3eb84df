"""The planner's kernels in their JAX forms against their C++ forms, whole: one VA-MPPI
solve and a short lockstep episode with each (docs/planner.md "Kernel forms"; each kernel
is held to a float64 reference apart, in test_planner.py and test_visibility.py)."""

import numpy as np
import pytest

from common.config import load_config
from deploy.sim.runner import Cores, run_episode
from services.planner import mppi, native

CFG = load_config(overrides=["planner.samples=256", 'episode.scenario="alleyway"',
                             "episode.timeout_s=1.2"])
SNAPSHOT = 10                    # the tick whose planning problem both forms solve again


def forced(form):
    return CFG.replace(**{"planner.va_kernel": form, "planner.rollout_kernel": form})


@pytest.mark.skipif(not native.available(), reason="the native kernels do not build here")
def test_the_jax_forms_solve_and_drive_as_the_native_kernels():
    cores = {f: Cores.from_config(forced(f)) for f in ("native", "jax")}
    for f, c in cores.items():
        assert (c.planner.mppi.rollout_kernel, c.planner.mppi.visibility.va_kernel) == (f, f)
    runs = {f: run_episode(forced(f), c, snapshot_ticks=frozenset({SNAPSHOT}))
            for f, c in cores.items()}

    # 12 ticks of VA-MPPI at K = 256: the states agree to float32 rounding (1.5e-6 seen).
    # Then the two forms' solves part (7.9e-5 m at tick 13, under the defaults), the maps
    # next differ in single cells, and the trajectories part as any two float32 orders of
    # summation do (1.6e-2 m at 2 s; under the previous defaults some 6 s in)
    a, b = runs["native"].trajectory, runs["jax"].trajectory
    assert a.shape == b.shape and runs["native"].outcome == runs["jax"].outcome
    assert np.abs(a - b).max() < 4e-6

    # one solve of the same problem (the native run's map and state at the snapshot)
    snap = runs["native"].snapshots[0]
    out = {}
    for f, c in cores.items():
        p = c.planner.mppi
        _, out[f] = mppi.solve(p, mppi.initial_state(p, 0), snap["x"], snap["u_prev"],
                               c.goal, snap["mean"], snap["variance"], snap["origin"],
                               snap["resolution"])
    n, j = (jax_tree_np(out["native"]), jax_tree_np(out["jax"]))
    # seen: controls 4.5e-6 (steering) and 2.3e-6 (force) of their size apart, optimal
    # 9.5e-7 m, rollout costs 1.3e-7 relative: the costs' float32 rounding (about 1e-5 of
    # costs near 100) moves the exponential weights by as much
    scale = np.abs(n.controls).max(axis=0)              # steering rad, force N
    assert (np.abs(n.controls - j.controls) <= 6e-6 * scale).all()
    assert np.abs(n.optimal - j.optimal).max() < 1.5e-6
    np.testing.assert_allclose(j.rollout_costs, n.rollout_costs, rtol=3e-7)
    np.testing.assert_allclose(j.terms, n.terms, rtol=3e-7, atol=1e-6)


def jax_tree_np(out):
    return type(out)(*(np.asarray(x, np.float64) for x in out))
