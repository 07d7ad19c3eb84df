"""MPPI pieces against float64 references, and the controller's behaviour."""

import dataclasses
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from common.config import load_config
from services.planner import kernels, mppi, native
from services.planner.costs import MapView, absorbing_crash, exceed_prob, rollout_cost
from services.planner.params import PlannerParams
from services.plant.dynamics import S, clamp_control, integrate

CFG = load_config(overrides=["planner.samples=256"])
PP = PlannerParams.from_config(CFG)


def test_rollout_matches_the_float64_model(rng):
    x0 = np.array([rng.uniform(0, 10), 0, 0, 40.0, 40.0, rng.uniform(-3, 3)])
    controls = np.stack([rng.uniform(-0.6, 0.6, PP.horizon),
                         rng.uniform(-6000, 5000, PP.horizon)], -1).astype(np.float32)
    states, applied, _ = kernels.rollout(PP, jnp.asarray(x0, jnp.float32), jnp.zeros(2), controls)
    x, u_prev = x0.copy(), np.zeros(2)
    for i in range(PP.horizon):
        u = clamp_control(controls[i].astype(np.float64), u_prev, PP.limits, PP.dt_s)
        np.testing.assert_allclose(np.asarray(applied[i]), u, rtol=1e-5, atol=1e-3)
        x = integrate(PP.vehicle, x, u, PP.dt_s, PP.substeps)
        u_prev = u
        np.testing.assert_allclose(np.asarray(states[i + 1, S.X:S.Y + 1]), x[S.X:S.Y + 1],
                                   atol=5e-3)


@pytest.mark.skipif(not native.available(), reason="the native kernels do not build here")
def test_the_native_model_vector_is_named_entry_by_entry_as_rollout_cc_reads_it(tmp_path):
    """native.MODEL against rollout.cc's enum Model, name for name and in order; each
    entry a field of the vehicle or of its control limits, every value where MODEL says."""
    assert native.model_enum() == [name for name, _ in native.MODEL]
    vec = native.model_vector(PP.vehicle, PP.limits)
    assert vec.shape == (len(native.MODEL),)
    for (name, what), x in zip(native.MODEL, vec, strict=True):
        field, _, i = what.partition(".")
        want = getattr(PP.limits, field)[int(i)] if i else getattr(PP.vehicle, field)
        assert x == np.float32(want), name
    swapped = tmp_path / "rollout.cc"           # two entries swapped: the check sees it
    source = Path(native.__file__).with_name("rollout.cc").read_text()
    swapped.write_text(source.replace("kLf, kLr,", "kLr, kLf,"))
    assert native.model_enum(swapped) != [name for name, _ in native.MODEL]


@pytest.mark.parametrize("k", [1, 37])
def test_native_rollouts_match_the_jax_form_and_the_float64_model(rng, k):
    """rollout.cc against `rollout` vmapped (the same float32 arithmetic, so within
    rounding) and against the plant's float64 model; K = 37 leaves a short last block of
    vector lanes; from standstill to 10 m/s (the kinematic blend), controls past the
    limits (the clamps), one thread or three (the same numbers)."""
    x0 = np.array([rng.uniform(0, 10), rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3),
                   40.0, 40.0, rng.uniform(-3, 3)], np.float32)
    u0 = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-6000, 5000)], np.float32)
    controls = np.stack([rng.uniform(-0.8, 0.8, (k, PP.horizon)),
                         rng.uniform(-8000, 7000, (k, PP.horizon))], -1).astype(np.float32)
    model = native.model_vector(PP.vehicle, PP.limits)
    got = [native.rollouts(model, x0, u0, controls, dt=PP.dt_s, substeps=PP.substeps,
                           n_threads=n) for n in (1, 3)]
    for a, b in zip(*got, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    ref = jax.vmap(kernels.rollout, in_axes=(None, None, None, 0))(
        PP, jnp.asarray(x0), jnp.asarray(u0), jnp.asarray(controls))
    (states, applied, xdots), (s_ref, a_ref, x_ref) = got[0], ref
    np.testing.assert_allclose(np.asarray(applied), np.asarray(a_ref), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(np.asarray(states), np.asarray(s_ref), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(np.asarray(xdots), np.asarray(x_ref), rtol=1e-3, atol=1e-3)
    x, u_prev = x0.astype(np.float64), u0.astype(np.float64)
    for i in range(PP.horizon):                       # the last sample, in float64
        u = clamp_control(controls[-1, i].astype(np.float64), u_prev, PP.limits, PP.dt_s)
        x = integrate(PP.vehicle, x, u, PP.dt_s, PP.substeps)
        u_prev = u
        np.testing.assert_allclose(np.asarray(states[-1, i + 1, S.X:S.Y + 1]), x[S.X:S.Y + 1],
                                   atol=5e-3)


def test_exceedance_probability_closed_form(rng):
    mean = rng.normal(size=200) * 0.5
    var = rng.uniform(0, 0.3, 200) ** 2
    thr = 0.3
    got = np.asarray(exceed_prob(jnp.asarray(mean, jnp.float32), jnp.asarray(var, jnp.float32),
                                 thr))
    phi = lambda z: 0.5 * (1 + math.erf(z / math.sqrt(2)))  # noqa: E731
    ref = np.array([1 - (phi((thr - m) / math.sqrt(v)) - phi((-thr - m) / math.sqrt(v)))
                    for m, v in zip(mean, var, strict=True)])
    # float32: 1 - (Phi(a) - Phi(b)) loses digits where both are near 1; 3000 seeds gave at
    # most 1.3e-5 absolute, always inside atol 2e-6 + rtol 1e-4 (atol alone failed in CI)
    np.testing.assert_allclose(got, ref, rtol=2e-4, atol=2e-6)
    det = np.asarray(exceed_prob(jnp.asarray(mean, jnp.float32), jnp.zeros(200), thr))
    np.testing.assert_array_equal(det, (np.abs(mean.astype(np.float32)) > thr).astype(np.float32))


def flat_map(n=400):
    return MapView(jnp.zeros((n, n), jnp.float32), jnp.zeros((n, n), jnp.float32),
                   jnp.zeros(2), 0.2)


P_POINTS = CFG.planner.footprint_arrays * CFG.planner.footprint_points
T_PRICED = PP.horizon + 1 + PP.cost.stop_poses          # the rollout's poses, then the stop's
ZERO_VAR = jnp.zeros((T_PRICED, 5 * P_POINTS), jnp.float32)


def test_surface_cost_sees_a_wall_and_nothing_on_flat_ground():
    x0 = jnp.asarray([8.0, 0, 0, 20.0, 40.0, 0.0], jnp.float32)
    go = jnp.tile(jnp.asarray([0.0, 1000.0], jnp.float32), (PP.horizon, 1))
    states, _, xd = kernels.rollout(PP, x0, jnp.zeros(2), go)
    goal = jnp.asarray([60.0, 40.0, 0.0])
    flat = rollout_cost(PP.cost, states, xd, goal, flat_map(), ZERO_VAR)
    assert float(flat[2]) == 0.0
    m = flat_map()
    wall = MapView(m.mean.at[150:250, 200:205].set(2.0), m.variance, m.origin, m.resolution)
    hit = rollout_cost(PP.cost, states, xd, goal, wall, ZERO_VAR)
    assert float(hit[2]) > 10 * PP.cost.w_surface


def test_a_middle_array_and_a_margin_see_a_corner_at_the_vehicles_side():
    """The paper's two arrays (front and rear edge) leave the sides unpriced: a post
    beside the vehicle's middle costs nothing. A middle array sees a post reaching the
    side; a margin sees one just clear of it."""
    from common.geometry import footprint_points
    fp = footprint_points(4.0, 2.0, 5, 3)
    assert fp.shape == (15, 2) and sorted(set(fp[:, 0])) == [-2.0, 0.0, 2.0]
    np.testing.assert_array_equal(footprint_points(4.0, 2.0, 5), fp[[*range(5), *range(10, 15)]])
    x0 = jnp.asarray([0.0, 0, 0, 40.1, 40.1, 0.0], jnp.float32)        # standing still
    states, _, xd = kernels.rollout(PP, x0, jnp.zeros(2), jnp.zeros((PP.horizon, 2)))
    goal = jnp.asarray([60.0, 40.0, 0.0])
    m = flat_map()

    def surface(post_rows, arrays, margin):
        cfg = CFG.replace(**{"planner.footprint_arrays": arrays,
                             "planner.footprint_margin_m": margin})
        cp = PlannerParams.from_config(cfg).cost
        post = MapView(m.mean.at[post_rows, 199:202].set(2.0), m.variance, m.origin, 0.2)
        zero = jnp.zeros((T_PRICED, 5 * arrays * 5), jnp.float32)
        return float(rollout_cost(cp, states, xd, goal, post, zero)[2])

    touching = slice(204, 207)           # y 40.8-41.4: into the left side (y <= 41.1)
    clear = slice(207, 209)              # y 41.4-41.8: beyond the side's cells and their
    #                                      neighbours (read by the gradient indicators)
    assert surface(touching, 2, 0.0) == 0.0
    assert surface(touching, 3, 0.0) > 0.0
    assert surface(clear, 3, 0.0) == 0.0 and surface(clear, 3, 0.2) > 0.0


def test_every_post_the_plants_footprint_meets_is_priced(rng):
    """The plant counts a collision wherever a point of its footprint (a 0.1 m grid over the
    whole rectangle) lies on an obstacle cell. The planner prices footprint points only,
    each reading its cell and four neighbours; nine arrays, 0.5 m apart as the 5 points
    across the width are, leave no obstacle unpriced that the plant's footprint meets:
    round posts of radius 0.3-1.0 m anywhere round a standing vehicle (one pose, the true
    map, no variance). With three arrays, 2 m apart (the default before nine), one such
    post in five costs nothing; with five one in 170, with seven one in 1000 of radius 0.3-0.5 m
    (docs/analysis.md "Posts between the footprint's points")."""
    from dataclasses import replace

    from common.scenarios import build_scenario
    from services.planner.costs import footprint_cells, surface_expectation
    from services.plant import core as plant
    scn = build_scenario("open-field", 0)
    pp = replace(plant.PlantParams.from_config(CFG, scn), obstacle_mask=None)
    cost = PlannerParams.from_config(CFG.replace(**{"planner.footprint_arrays": 9})).cost
    n, res = scn.heightmap.shape[0], scn.resolution
    centres = np.asarray(scn.origin)[:, None, None] + (np.mgrid[0:n, 0:n][::-1] + 0.5) * res
    m = flat_map(n)
    m = MapView(m.mean, m.variance, jnp.asarray(scn.origin, jnp.float32), res)

    @jax.jit
    def priced(mean, pose):
        view = MapView(mean, m.variance, m.origin, res)
        row, col, outside = footprint_cells(cost, view, pose[None])
        return surface_expectation(cost, view, row, col, outside,
                                   jnp.zeros((1, 5 * row.shape[1]), jnp.float32),
                                   jnp.float32(0.0)).sum()

    met = 0
    for _ in range(300):
        x = np.zeros(6)
        x[S.X], x[S.Y], x[S.PSI] = n * res / 2, n * res / 2, rng.uniform(-np.pi, np.pi)
        r = rng.uniform(0.3, 1.0)
        along, across = rng.uniform(-2.0 - r, 2.0 + r), rng.uniform(-1.0 - r, 1.0 + r)
        c, s = math.cos(x[S.PSI]), math.sin(x[S.PSI])
        cx, cy = x[S.X] + c * along - s * across, x[S.Y] + s * along + c * across
        post = (centres[0] - cx) ** 2 + (centres[1] - cy) ** 2 <= r * r
        if not plant.collides(replace(pp, obstacle_mask=post), x):
            continue
        met += 1
        paid = float(priced(jnp.asarray(post * 2.0, jnp.float32), jnp.asarray(x, jnp.float32)))
        assert paid > 0.0, (r, along, across, x[S.PSI])
    assert met > 200


def test_absorbing_crash_against_a_loop(rng):
    """From the first step with >= 0.5 expected indicators on a well-known cell on,
    every step costs 5 P; fog (variance above crash_variance) never crashes; 0 = off."""
    cp = PlannerParams.from_config(CFG.replace(**{"planner.crash_variance": 0.01})).cost
    n1, p = PP.horizon + 1, P_POINTS
    for _ in range(20):
        expected = (rng.uniform(0, 0.6, (n1, p)) * (rng.uniform(size=(n1, p)) < 0.1)
                    ).astype(np.float32)
        qvar = rng.choice([0.0, 0.005, 0.02, 3.0], (n1, 5 * p)).astype(np.float32)
        got = np.asarray(absorbing_crash(cp, jnp.asarray(expected), jnp.asarray(qvar)))
        ref, crashed = expected.copy(), False
        for i in range(n1):
            crashed = crashed or any(expected[i, j] >= 0.5 and qvar[i, j] < 0.01
                                     for j in range(p))
            if crashed:
                ref[i] = 5.0
        np.testing.assert_array_equal(got, ref)
    fog = np.full((n1, 5 * p), 3.0, np.float32)
    high = np.full((n1, p), 4.0, np.float32)
    np.testing.assert_array_equal(np.asarray(absorbing_crash(cp, high, fog)), high)
    np.testing.assert_array_equal(np.asarray(absorbing_crash(PP.cost, high, fog * 0)), high)

    # a wall the rollout drives into: the crash cost charges the steps after the hit too
    x0 = jnp.asarray([8.0, 0, 0, 20.0, 40.0, 0.0], jnp.float32)
    go = jnp.tile(jnp.asarray([0.0, 1000.0], jnp.float32), (PP.horizon, 1))
    states, _, xd = kernels.rollout(PP, x0, jnp.zeros(2), go)
    m = flat_map()
    wall = MapView(m.mean.at[150:250, 200:205].set(2.0), m.variance, m.origin, m.resolution)
    goal = jnp.asarray([60.0, 40.0, 0.0])
    plain = float(rollout_cost(PP.cost, states, xd, goal, wall, ZERO_VAR)[2])
    crash = float(rollout_cost(cp, states, xd, goal, wall, ZERO_VAR)[2])
    first = int(np.argmax(np.asarray(states[:, S.X]) + 2.0 >= 40.0))    # front edge at x = 40
    assert crash >= cp.w_surface * 5 * p * (n1 - first - 1) > 2 * plain > 0


def test_surface_cost_per_metre_against_a_loop(rng):
    """`surface_distance_m` > 0: step i's expected indicators weigh |V_i| dt / that length
    (a float64 loop over random expectations and speeds); a rollout standing still on
    fog pays nothing for it, where the paper's sum charges every step; a rollout that
    stops before a wall pays less than one that drives on through it."""
    ref_m = 0.5
    cp = PlannerParams.from_config(
        CFG.replace(**{"planner.surface_distance_m": ref_m})).cost
    loop = dataclasses.replace(cp, stop_poses=0)     # the loop's poses are the rollout's
    n1, p = PP.horizon + 1, P_POINTS
    goal = jnp.asarray([60.0, 40.0, 0.0])
    m = flat_map()
    for _ in range(10):
        states = np.zeros((n1, 6), np.float32)
        states[:, S.V] = rng.uniform(-1.0, 10.0, n1)
        states[:, S.X], states[:, S.Y] = 20.0, 40.0
        expected = (rng.uniform(0, 5, (n1, p)) * (rng.uniform(size=(n1, p)) < 0.2)
                    ).astype(np.float32)
        xd = jnp.zeros((PP.horizon, 6), jnp.float32)
        got = float(rollout_cost(loop, jnp.asarray(states), xd, goal, m, None,
                                 expected=jnp.asarray(expected))[2])
        want = cp.w_surface * sum(abs(float(states[i, S.V])) * PP.dt_s / ref_m
                                  * float(np.sum(expected[i], dtype=np.float64))
                                  for i in range(n1))
        assert got == pytest.approx(want, rel=1e-5)

    # standing on fog: the plain sum charges every step, per metre nothing
    still = jnp.tile(jnp.asarray([0.0, 0, 0, 20.0, 40.0, 0.0], jnp.float32), (n1, 1))
    fog = MapView(m.mean, jnp.full_like(m.variance, 3.0), m.origin, m.resolution)
    fog_var = jnp.full((T_PRICED, 5 * p), 3.0, jnp.float32)
    xd = jnp.zeros((PP.horizon, 6), jnp.float32)
    assert float(rollout_cost(PP.cost, still, xd, goal, fog, fog_var)[2]) > 0.0
    assert float(rollout_cost(cp, still, xd, goal, fog, fog_var)[2]) == 0.0

    # a wall ahead: braking to a stop before it costs less than driving through it
    x0 = jnp.asarray([6.0, 0, 0, 20.0, 40.0, 0.0], jnp.float32)
    wall = MapView(m.mean.at[150:250, 175:177].set(2.0), m.variance, m.origin, m.resolution)
    costs = {}
    for name, force in (("on", 0.0), ("brake", -6000.0)):
        u = jnp.tile(jnp.asarray([0.0, force], jnp.float32), (PP.horizon, 1))
        states, _, xd = kernels.rollout(PP, x0, jnp.zeros(2), u)
        costs[name] = float(rollout_cost(cp, states, xd, goal, wall, ZERO_VAR)[2])
    assert costs["on"] > costs["brake"] >= 0.0


def test_mppi_is_reproducible_and_moves_toward_the_goal():
    m = flat_map()
    goal = np.array([60.0, 40.0, 0.0])
    x0 = np.array([0, 0, 0, 20.0, 40.0, 0.0])

    def run():
        qs = mppi.initial_state(PP, 7)
        outs = []
        for _ in range(5):
            qs, out = mppi.solve(PP, qs, x0, np.zeros(2), goal, m.mean, m.variance, m.origin, 0.2)
            outs.append(out)
            qs = mppi.advance(qs, 0)
        return outs

    a, b = run(), run()
    for oa, ob in zip(a, b, strict=True):
        np.testing.assert_array_equal(np.asarray(oa.controls), np.asarray(ob.controls))
    first, last = a[0], a[-1]
    assert float(last.controls[:10, 1].mean()) > 1000.0         # drives forward
    assert float(np.sum(last.terms)) < float(np.sum(first.terms))
    assert float(last.optimal[-1, S.X]) > 30.0


def test_advance_shifts_the_nominal():
    qs = mppi.initial_state(PP, 0)
    nom = jnp.arange(PP.horizon * 2, dtype=jnp.float32).reshape(PP.horizon, 2)
    s = mppi.advance(qs._replace(nominal=nom), 3)
    np.testing.assert_array_equal(np.asarray(s.nominal[0]), np.asarray(nom[3]))
    np.testing.assert_array_equal(np.asarray(s.nominal[-3:]), np.tile(np.asarray(nom[-1]), (3, 1)))


@pytest.mark.parametrize("controller", ["deterministic", "prescient"])
def test_in_process_episode_reaches_the_goal(controller):
    from deploy.sim.runner import run_episode
    cfg = load_config(overrides=["planner.samples=256", f'planner.controller="{controller}"'])
    r = run_episode(cfg)
    assert r.outcome == "success", r.summary(cfg)
    assert r.time_to_goal_s < 15.0


def test_monte_carlo_surface_cost_agrees_with_the_closed_form(rng):
    from services.planner.costs import CostParams, surface_expectation
    c_cf = CostParams.from_config(CFG)
    c_mc = CostParams.from_config(CFG.replace(**{"planner.surface_estimator": "monte_carlo",
                                                 "planner.surface_samples": 4000}))
    n, steps, p = 60, PP.horizon + 1, P_POINTS
    mean = jnp.asarray(rng.normal(size=(n, n)) * 0.4, jnp.float32)
    m = MapView(mean, jnp.zeros((n, n)), jnp.zeros(2), 0.2)
    rows = jnp.asarray(rng.integers(1, n - 1, (steps, p)), jnp.int32)
    cols = jnp.asarray(rng.integers(1, n - 1, (steps, p)), jnp.int32)
    outside = jnp.zeros((steps, p), bool)
    qvar = jnp.asarray(rng.uniform(0, 0.4, (steps, 5 * p)) ** 2, jnp.float32)
    cf = np.asarray(surface_expectation(c_cf, m, rows, cols, outside, qvar, 0.0))
    mc = np.asarray(surface_expectation(c_mc, m, rows, cols, outside, qvar, 0.0,
                                        jax.random.PRNGKey(int(rng.integers(1 << 30)))))
    # a sum of five Bernoulli frequencies over 4000 draws: standard error <= sqrt(5/4/4000)
    se = np.sqrt(5 * 0.25 / 4000)
    assert np.abs(mc - cf).max() < 5 * se
    assert abs(mc.mean() - cf.mean()) < 5 * se / np.sqrt(cf.size)
    assert 0.2 < cf.mean() < 4.8                 # neither all-0 nor all-5: the test has teeth


@pytest.mark.skipif(not native.available(), reason="the native kernels do not build here")
def test_native_expected_surface_matches_the_closed_form(rng):
    """surface.cc against costs.surface_expectation's closed form on a random map, for
    K = 7 random rollouts partly off the map, variances from 0 (the plain indicators:
    the same bits) through seen to unseen (3.0); one thread or three give the same."""
    from services.planner.costs import (
        CostParams,
        footprint_cells,
        ground_now,
        surface_expectation,
    )
    c = CostParams.from_config(CFG)
    n, k, steps, p = 80, 7, PP.horizon + 1, P_POINTS
    mean = jnp.asarray(rng.normal(size=(n, n)) * 0.4, jnp.float32)
    m = MapView(mean, jnp.zeros((n, n)), jnp.zeros(2), 0.2)
    states = np.zeros((k, steps, 6), np.float32)
    states[..., S.X] = rng.uniform(-1.0, 17.0, (k, steps))       # the map is 16 m across
    states[..., S.Y] = rng.uniform(-1.0, 17.0, (k, steps))
    states[..., S.PSI] = rng.uniform(-4.0, 4.0, (k, steps))
    states = jnp.asarray(states)
    scale = rng.choice([0.0, 0.05, 0.5, np.sqrt(3.0)], (k, steps, 5 * p))
    qvar = jnp.asarray((scale * rng.uniform(0.2, 1.0, scale.shape)) ** 2, jnp.float32)
    rows, cols, outside = jax.vmap(footprint_cells, in_axes=(None, None, 0))(c, m, states)
    h0 = jax.vmap(ground_now, in_axes=(None, 0))(m, states)

    def reference(var):
        def one(st, v, g):
            return surface_expectation(c, m, *footprint_cells(c, m, st), v, g)
        return np.asarray(jax.vmap(one)(states, var, h0))

    def kernel(var, threads):
        return np.asarray(native.expected_surface(
            mean, rows, cols, outside, var, h0, resolution=0.2, grad=c.grad_threshold,
            step=c.step_threshold, height=c.height_threshold_m, n_across=c.footprint_points,
            n_threads=threads))

    got = kernel(qvar, 1)
    np.testing.assert_array_equal(got, kernel(qvar, 3))
    ref = reference(qvar)
    # erfc (A&S 7.1.26, |error| < 1.5e-7) against XLA's erf, five probabilities a point
    np.testing.assert_allclose(got, ref, rtol=0, atol=5e-6)
    assert np.asarray(outside).any() and not np.asarray(outside).all()
    assert 0.2 < ref[~np.asarray(outside)].mean() < 4.8     # neither all-0 nor all-5
    zero = jnp.zeros_like(qvar)
    np.testing.assert_array_equal(kernel(zero, 1), reference(zero))


@pytest.mark.skipif(not native.available(), reason="the native kernels do not build here")
def test_fused_surface_kernel_equals_the_update_then_the_surface(monkeypatch,
                                                                 va_planning_problem):
    """VA-MPPI's iteration takes the expected surface cost from the variance update fused
    with surface.h (va_counts.cc, `vamppi_va_surface`); on a planning problem (K = 64
    rollouts on the offroad map) it is bit for bit the two kernels one after the other
    (va_counts.cc, then surface.cc), with one thread or three."""
    params, m, states = va_planning_problem

    def terms(p):
        return jax.jit(lambda s: kernels.surface_terms(p, m, s))(states)

    def threads(n):
        return dataclasses.replace(params, va_threads=n,
                                   visibility=dataclasses.replace(params.visibility, va_threads=n))

    qvar, fused = terms(threads(3))
    assert qvar is None
    np.testing.assert_array_equal(np.asarray(terms(threads(1))[1]), np.asarray(fused))
    monkeypatch.setattr(kernels, "surface_form", lambda *a: "native")
    qvar, split = terms(params)
    assert qvar is not None
    np.testing.assert_array_equal(np.asarray(split), np.asarray(fused))
    fused = np.asarray(fused)
    assert 0.01 < fused.mean() < 4.0 and (fused > 0.5).any()   # a cost with something in it


def test_non_finite_costs_get_no_weight_and_never_poison_the_nominal():
    m = flat_map()
    nan_map = MapView(m.mean.at[:, :].set(jnp.nan), m.variance, m.origin, m.resolution)
    qs = mppi.initial_state(PP, 0)
    nom = jnp.full((PP.horizon, 2), 0.1, jnp.float32)
    qs = qs._replace(nominal=nom)
    qs2, out = mppi.solve(PP, qs, np.array([3.0, 0, 0, 20, 40, 0]), np.zeros(2),
                          np.array([60.0, 40.0, 0.0]), nan_map.mean, nan_map.variance,
                          nan_map.origin, 0.2)
    assert np.isfinite(np.asarray(out.controls)).all()
    assert np.isfinite(np.asarray(qs2.nominal)).all()


@pytest.mark.parametrize("rho", [0.0, 0.9])
def test_sampling_noise_has_the_configured_std_and_correlation(rho):
    """AR(1) noise along the horizon: every step keeps the configured std, neighbouring
    steps correlate by rho (a float64 estimate over many samples); rho = 0 is the
    white noise of the paper's sampler, bit for bit."""
    params = dataclasses.replace(PP, samples=20000, noise_correlation=rho)
    key = jax.random.PRNGKey(7)
    eps = np.asarray(mppi.sample_noise(params, key), np.float64)
    std = np.asarray(params.noise_std)
    per_step = eps.std(axis=0) / std                                  # (N, 2)
    assert np.all(np.abs(per_step - 1.0) < 0.04), per_step
    z = eps / std
    lag1 = np.mean(z[:, 1:] * z[:, :-1], axis=(0, 1))
    lag5 = np.mean(z[:, 5:] * z[:, :-5], axis=(0, 1))
    assert np.all(np.abs(lag1 - rho) < 0.02), lag1
    assert np.all(np.abs(lag5 - rho ** 5) < 0.02), lag5
    if rho == 0.0:
        white = jax.random.normal(key, (params.samples, params.horizon, 2), jnp.float32)
        np.testing.assert_array_equal(eps, np.asarray(white * jnp.asarray(std, jnp.float32)))


def test_brake_samples_find_the_stop_that_random_samples_miss():
    """A wall across the whole road appears 12 m ahead of a vehicle at 7 m/s whose
    nominal accelerates: full braking stops it short, the random samples around the
    nominal (force std 1500 N, the brake limit 6 stds below) all hit. The braking
    samples carry the brake limit over the horizon around the nominal's steering."""
    mean = jnp.zeros((400, 400), jnp.float32).at[50:350, 170:175].set(2.0)   # x 34-35 m
    m = MapView(mean, jnp.zeros_like(mean), jnp.zeros(2), 0.2)
    x0 = np.array([7.0, 0, 0, 20.0, 40.0, 0.0])
    u_prev = np.array([0.0, 3000.0])
    goal = np.array([70.0, 40.0, 0.0])
    hit = {}
    for b in (0, 3):
        params = dataclasses.replace(PP, brake_samples=b, swerve_samples=0)
        qs = mppi.initial_state(params, 0)
        qs = qs._replace(nominal=jnp.tile(jnp.asarray([0.0, 3000.0], jnp.float32),
                                          (PP.horizon, 1)))
        if b:
            seqs = np.asarray(mppi.brake_sequences(params, qs.nominal))
            assert seqs.shape == (3, PP.horizon, 2)
            np.testing.assert_allclose(seqs[:, :, 1], CFG.vehicle.force_min_n)
            np.testing.assert_allclose(seqs[:, 0, 0], [-0.3, 0.0, 0.3], atol=1e-6)
        for _ in range(3):
            qs, out = mppi.solve(params, qs, x0, u_prev, goal, m.mean, m.variance, m.origin,
                                 0.2)
        hit[b] = float(out.terms[2])
        front = np.asarray(out.optimal)[:, S.X] + CFG.vehicle.footprint_length_m / 2
        if b:
            assert float(out.controls[:10, 1].min()) < -4000.0         # braking hard
            assert front.max() < 34.0 and hit[b] == 0.0                # and stops short
    assert hit[0] > 0.0                                               # the test has teeth


def test_priced_poses_walk_the_models_stopping_distance_straight_on(rng):
    """The B poses past the horizon's end lie straight on along its heading at 1/B ... 1
    of the stopping distance (one control tick at speed, the force's ramp, then the brake
    limit: float64, integrated in 0.1 ms steps), with the speed braking leaves there."""
    from services.planner.costs import priced_poses
    c = PP.cost
    assert c.stop_poses == 3
    states = rng.normal(size=(5, PP.horizon + 1, 6)).astype(np.float32)
    states[:, -1, S.V] = rng.uniform(0.0, 12.0, 5)
    states[:, -1, S.X:] = rng.uniform(-3.0, 3.0, (5, 3)) * [10.0, 10.0, 1.0]
    got = np.asarray(priced_poses(c, jnp.asarray(states)))
    assert got.shape == (5, PP.horizon + 4, 6)
    np.testing.assert_array_equal(got[:, :PP.horizon + 1], states)
    v_cfg = CFG.vehicle
    a, rate = -v_cfg.force_min_n / v_cfg.mass_kg, v_cfg.force_rate_max_nps / v_cfg.mass_kg
    for k in range(5):
        v, s, t, h = float(states[k, -1, S.V]), 0.0, 0.0, 1e-4
        while v > 0.0:                      # the reference: walk the stop
            dec = 0.0 if t < c.dt_s else min(a, rate * (t - c.dt_s))
            s, v, t = s + v * h - 0.5 * dec * h * h, v - dec * h, t + h
        last = states[k, -1]
        for j, f in enumerate((1 / 3, 2 / 3, 1.0)):
            pose = got[k, PP.horizon + 1 + j]
            np.testing.assert_allclose(pose[S.X], last[S.X] + f * s * np.cos(last[S.PSI]),
                                       atol=2e-3)
            np.testing.assert_allclose(pose[S.Y], last[S.Y] + f * s * np.sin(last[S.PSI]),
                                       atol=2e-3)
            np.testing.assert_allclose(pose[S.V], last[S.V] * np.sqrt(1.0 - f), atol=1e-5)


def test_a_wall_just_past_the_horizon_is_priced_by_the_stopping_poses():
    """A rollout that ends at 8 m/s 3 m short of a wall: it could not stop before it. The
    stopping poses price the wall; without them (the paper's horizon) it costs nothing."""
    mean = jnp.zeros((400, 400), jnp.float32).at[:, 250:255].set(2.0)        # x 50-51 m
    m = MapView(mean, jnp.zeros_like(mean), jnp.zeros(2), 0.2)
    n = PP.horizon
    states = np.zeros((n + 1, 6), np.float32)
    states[:, S.V] = 8.0
    states[:, S.X] = np.linspace(15.0, 47.0 - CFG.vehicle.footprint_length_m / 2, n + 1)
    states[:, S.Y] = 40.0
    xdots = np.zeros((n, 6), np.float32)
    goal = jnp.asarray([70.0, 40.0, 0.0])
    surface = {}
    for b in (0, 3):
        c = dataclasses.replace(PP.cost, stop_poses=b)
        surface[b] = float(rollout_cost(c, jnp.asarray(states), jnp.asarray(xdots), goal, m,
                                        jnp.zeros((n + 1 + b, 5 * len(c.footprint))))[2])
    assert surface[0] == 0.0 and surface[3] > 0.0


def test_advanced_nominals_leave_a_plan_that_puts_off_its_start():
    """A standing vehicle whose nominal waits 2 s before it drives off on open ground, with
    small sampling noise (0.02 rad, 100 N): the noise alone leaves the wait in place, the
    nominal done sooner (by 2 and 4 steps) costs less and MPPI takes it."""
    m = flat_map()
    goal = np.array([60.0, 40.0, 0.0])
    x0 = np.array([0, 0, 0, 20.0, 40.0, 0.0])
    wait = np.zeros((PP.horizon, 2), np.float32)
    wait[20:, 1] = 3000.0
    moved = {}
    for a in (0, 2):
        params = dataclasses.replace(PP, advance_samples=a, noise_std=(0.02, 100.0))
        qs = mppi.initial_state(params, 0)._replace(nominal=jnp.asarray(wait))
        if a:
            seqs = np.asarray(mppi.advance_sequences(params, qs.nominal))
            np.testing.assert_array_equal(seqs[0], np.concatenate([wait[2:]] + [wait[-1:]] * 2))
            np.testing.assert_array_equal(seqs[1, :16], wait[4:20])
        qs, out = mppi.solve(params, qs, x0, np.zeros(2), goal, m.mean, m.variance, m.origin,
                             0.2)
        moved[a] = float(np.asarray(out.controls)[:20, 1].mean())
    # advanced by 4 steps: 4 of the first 20 at 3000 N, 600 N on average
    assert moved[0] < 50.0 and moved[2] > 450.0, moved


def test_the_felt_force_is_the_model_s_on_random_speeds_and_forces(rng):
    """`mppi.felt` against float64: a drive force in full, a brake times tanh(V / eps) at
    each step's start speed, the steering untouched; the paper's update keeps the commands."""
    k, n = 64, PP.horizon
    states = np.zeros((k, n + 1, 6), np.float32)
    states[..., S.V] = rng.uniform(0.0, 1.0, (k, n + 1)) ** 2          # many near standstill
    applied = np.stack([rng.uniform(-0.6, 0.6, (k, n)),
                        rng.uniform(-6000.0, 5000.0, (k, n))], axis=-1).astype(np.float32)
    got = np.asarray(mppi.felt(PP, jnp.asarray(states), jnp.asarray(applied)))
    v, f = states[:, :-1, S.V].astype(np.float64), applied[..., 1].astype(np.float64)
    want = np.where(f >= 0.0, f, f * np.tanh(v / CFG.vehicle.brake_speed_eps_mps))
    np.testing.assert_array_equal(got[..., 0], applied[..., 0])
    np.testing.assert_allclose(got[..., 1], want, rtol=4e-7, atol=1e-3)   # 3e-7 seen
    paper = dataclasses.replace(PP, effective_update=False)
    np.testing.assert_array_equal(np.asarray(mppi.felt(paper, jnp.asarray(states),
                                                       jnp.asarray(applied))), applied)


def test_a_nominal_that_brakes_a_stopped_vehicle_is_left_by_the_felt_update():
    """A stopped vehicle on open, known ground, the goal 40 m ahead, its nominal braking at
    the limit (offroad's VA-MPPI stood 16 s with one at -3500 N): every sample whose force
    stays below zero has the same rollout, so the paper's update (commanded forces) keeps
    braking tick after tick; averaging the forces felt, the nominal drives off within a few
    ticks."""
    m = flat_map()
    goal = np.array([60.0, 40.0, 0.0])
    x0 = np.array([0, 0, 0, 20.0, 40.0, 0.0])
    brake = np.tile([0.0, CFG.vehicle.force_min_n], (PP.horizon, 1)).astype(np.float32)
    first = {}
    for felt in (False, True):
        params = dataclasses.replace(PP, effective_update=felt)
        qs = mppi.initial_state(params, 0)._replace(nominal=jnp.asarray(brake))
        u = brake[0]
        for _ in range(5):                    # five ticks, the vehicle held where it stands
            qs, out = mppi.solve(params, qs, x0, u, goal, m.mean, m.variance, m.origin, 0.2)
            u = np.asarray(out.controls)[0]                 # the command the plant applies
        first[felt] = float(u[1])
    assert first[False] < -4000.0 and first[True] > 0.0, first
