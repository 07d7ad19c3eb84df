"""The planner's kernels in their JAX forms against their C++ forms, whole: one VA-MPPI
solve and a short lockstep episode with each (docs/planner.md "Kernel forms"; each kernel
is held to a float64 reference apart, in test_planner.py and test_visibility.py)."""

import numpy as np
import pytest

from common.config import load_config
from deploy.sim.runner import Cores, run_episode
from services.planner import mppi, native

CFG = load_config(overrides=["planner.samples=256", 'episode.scenario="alleyway"',
                             "episode.timeout_s=2.0"])
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

    # 20 ticks of VA-MPPI at K = 256: the states agree to float32 rounding (1.3e-6 seen;
    # the trajectories part, as any two float32 orders of summation do, some 6 s in)
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
    # seen: here controls equal, optimal 1.5e-8 m apart, costs 1e-7 relative; on the
    # planner benchmark's problem (offroad, K = 256) controls 1.2e-6 of their size apart,
    # optimal 4.8e-7
    scale = np.abs(n.controls).max(axis=0)              # steering rad, force N
    assert (np.abs(n.controls - j.controls) <= 3e-6 * scale).all()
    assert np.abs(n.optimal - j.optimal).max() < 1e-6
    np.testing.assert_allclose(j.rollout_costs, n.rollout_costs, rtol=3e-7)
    np.testing.assert_allclose(j.terms, n.terms, rtol=3e-7, atol=1e-6)


def jax_tree_np(out):
    return type(out)(*(np.asarray(x, np.float64) for x in out))
