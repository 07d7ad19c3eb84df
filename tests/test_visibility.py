"""The visibility-aware variance update against a dense float64 reference."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from common.config import load_config
from services.planner import native
from services.planner.costs import OFFSETS
from services.planner.kernels import decayed_variance as batched_decayed_variance
from services.planner.visibility import VisibilityParams, visible_points
from services.plant.dynamics import Reaction

CFG = load_config(overrides=['planner.controller="va"'])
VP = VisibilityParams.from_config(CFG)


def float64_ray_points(vp, state, res):
    """World x, y (rays, points) of one pose's ray points in float64."""
    x, y, psi = (float(v) for v in state[3:6])
    ang = np.linspace(-vp.fov_rad / 2, vp.fov_rad / 2, vp.visibility_rays)[:, None]
    rng = np.linspace(vp.visibility_min_m, vp.visibility_max_m, vp.visibility_points)[None, :]
    bx, by = vp.mount_forward_m + rng * np.cos(ang), rng * np.sin(ang)
    return (x + math.cos(psi) * bx - math.sin(psi) * by,
            y + math.sin(psi) * bx + math.cos(psi) * by)


def reference_visibility(vp, mean, state, rows, cols, res):
    """The 2D-ray rule in float64 on given cells: a ray ends at its first blocker (seen)
    or where it leaves the map (not seen)."""
    n = mean.shape[0]
    vr, vc = int(math.floor(state[4] / res)), int(math.floor(state[3] / res))
    ground = mean[min(max(vr, 0), n - 1), min(max(vc, 0), n - 1)]
    vis = np.zeros(rows.shape, bool)
    for r in range(vp.visibility_rays):
        for k in range(vp.visibility_points):
            row, col = rows[r, k], cols[r, k]
            if not (0 <= row < n and 0 <= col < n):
                break
            vis[r, k] = True
            if mean[row, col] > ground + vp.visibility_height_m:
                break
    return vis


def reference_counted(vp, state, vis):
    """Of the visible points (rays, points), those that count: at least the float64
    reaction distance from the footprint's front edge (all of them without the in-time
    rule), in float64 (`Reaction.distance`; its stopping is checked against an
    integration in test_reveal, its swerve in test_dynamics)."""
    if vp.reaction is None:
        return vis
    v = math.hypot(float(state[0]), float(state[1]))
    stop = float(vp.reaction.distance(np.float64(v), vp.react_s, vp.react_lateral_m))
    stop += vp.react_ahead_m                   # measured from the front edge, not the camera
    ranges = np.linspace(vp.visibility_min_m, vp.visibility_max_m, vp.visibility_points)
    return vis & (ranges >= stop)[None, :]


def reference_decay(vp, variance, seen, rows, cols):
    """Dense float64: count maps of poses 0 .. i-lag, a full 9 x 9 convolution, the decay,
    read at step i's queries. `seen[i]` = (rows, cols) of pose i's visible points."""
    n = variance.shape[0]
    kern = vp.kernel()
    half = vp.splat_size // 2
    raw = np.zeros((n, n))
    out = np.zeros(rows.shape)
    for i in range(rows.shape[0]):
        if i >= vp.visibility_lag_steps:
            np.add.at(raw, seen[i - vp.visibility_lag_steps], vp.count_value)
        padded = np.pad(raw, half)
        splat = np.zeros((n, n))
        for dy in range(-half, half + 1):
            for dx in range(-half, half + 1):
                splat += kern[dy + half, dx + half] * padded[half + dy:half + dy + n,
                                                             half + dx:half + dx + n]
        out[i] = (variance * np.exp(-vp.decay_gamma * splat))[rows[i], cols[i]]
    return out


def random_problem(rng, n=200, steps=12):
    """A random map with obstacles that block rays, a random path over it, and footprint
    cells: half anywhere, half along the path ahead (where counts build up), to the rays'
    far ends (25 m)."""
    mean = (rng.normal(size=(n, n)) * 0.1).astype(np.float32)
    for _ in range(70):
        r, c = rng.integers(5, n - 5, 2)
        mean[r - 2:r + 3, c - 2:c + 3] += rng.uniform(0.5, 3.0)
    variance = rng.uniform(0.5, 3.0, (n, n)).astype(np.float32)
    x = np.cumsum(rng.uniform(0.5, 1.1, steps)) + 3.0
    y = 12.0 + np.cumsum(rng.normal(size=steps) * 0.2)
    psi = np.cumsum(rng.normal(size=steps) * 0.15) + rng.uniform(-0.3, 0.3)
    states = np.zeros((steps, 6), np.float32)
    states[:, 3], states[:, 4], states[:, 5] = x, y, psi
    states[:, 0], states[:, 1] = rng.uniform(0.0, 9.0, steps), rng.normal(size=steps) * 0.3
    rows = rng.integers(1, n - 1, (steps, 8)).astype(np.int32)
    cols = rng.integers(1, n - 1, (steps, 8)).astype(np.int32)
    rows[:, :4] = np.clip((y[:, None] / 0.2 + rng.integers(-20, 20, (steps, 4))), 1, n - 2)
    cols[:, :4] = np.clip((x[:, None] / 0.2 + rng.integers(0, 135, (steps, 4))), 1, n - 2)
    return mean, variance, states, rows, cols


def decayed_variance(vp, mean, variance, origin, resolution, states, rows, cols, offsets):
    """One trajectory through the update in `vp.va_kernel`'s form (services/planner/
    kernels.py): states (N+1, 6), rows/cols (N+1, P)."""
    return batched_decayed_variance(vp, mean, variance, origin, resolution, states[None],
                                    rows[None], cols[None], offsets)[0]


def solve_random_problem(vp, rng, decayed: float = 0.1):
    """A random problem and the update's decayed variance on it; rows and cols are then
    the query cells (the five OFFSETS cells of each footprint cell, offset-major). Drawn
    again (up to 5 times) until more than `decayed` of the queries decay, so that the
    comparison has teeth: about one draw in 40 has its trajectories look past the queried
    cells (5 % decayed at lag 4; 60 seeds: 25-70 %)."""
    for _ in range(5):
        mean, variance, states, rows, cols = random_problem(rng)
        got = np.asarray(decayed_variance(vp, jnp.asarray(mean), jnp.asarray(variance),
                                          jnp.zeros(2), 0.2, jnp.asarray(states),
                                          jnp.asarray(rows), jnp.asarray(cols), OFFSETS))
        rows = np.concatenate([rows + dr for dr, _ in OFFSETS], axis=1)
        cols = np.concatenate([cols + dc for _, dc in OFFSETS], axis=1)
        if (got < variance[rows, cols] * 0.999).mean() > decayed:
            break
    return mean, variance, states, got, rows, cols


def float64_cells(vp, st):
    """Every ray point's float64 cell (rays, points), and which lie within float32 rounding
    (1e-4 cell) of a cell boundary, where a float32 kernel may pick the neighbour."""
    px, py = float64_ray_points(vp, st.astype(np.float64), 0.2)
    ambiguous = ((np.abs(px / 0.2 - np.rint(px / 0.2)) < 1e-4)
                 | (np.abs(py / 0.2 - np.rint(py / 0.2)) < 1e-4))
    return np.floor(py / 0.2).astype(int), np.floor(px / 0.2).astype(int), ambiguous


# (lag, braking): the paper's causality, a longer lag, points counted only beyond the
# distance to stop with the vehicle's brakes
BRAKES = Reaction.from_config(load_config().vehicle)
CAUSALITY = [(1, None), (4, None), (1, BRAKES), (1, Reaction.braking_only(3.6))]


@pytest.mark.parametrize(("lag", "decel"), CAUSALITY)
def test_decayed_variance_matches_the_dense_float64_reference(rng, lag, decel):
    """The vectorised JAX form: every ray point's cell and visibility checked, then the
    decayed variance at every query against the dense float64 computation."""
    vp = dataclasses.replace(VP, visibility_lag_steps=lag, reaction=decel, va_kernel="jax")
    mean, variance, states, got, rows, cols = solve_random_problem(vp, rng)
    seen = []
    for st in states:
        grid = (vp.visibility_rays, vp.visibility_points)
        k_row, k_col, k_vis = (np.asarray(a).reshape(grid) for a in visible_points(
            vp, jnp.asarray(mean), jnp.zeros(2), 0.2, jnp.asarray(st)))
        # every ray point checked: the kernel's cell is the float64 cell, except for points
        # within float32 rounding of a cell boundary
        f_row, f_col, ambiguous = float64_cells(vp, st)
        assert ((k_col == f_col) & (k_row == f_row) | ambiguous).all()
        # visibility: the float64 rule on those cells
        ref_vis = reference_visibility(vp, mean.astype(np.float64), st.astype(np.float64),
                                       k_row, k_col, 0.2)
        np.testing.assert_array_equal(k_vis, ref_vis)
        counted = reference_counted(vp, st, k_vis)
        seen.append((k_row[counted], k_col[counted]))
    ref = reference_decay(vp, variance.astype(np.float64), seen, rows, cols)
    np.testing.assert_allclose(got[:lag], variance[rows[:lag], cols[:lag]])   # nothing seen yet
    # the test has teeth: many queries decayed (the problem is drawn so)
    assert (ref < variance[rows, cols] * 0.999).mean() > 0.1
    np.testing.assert_allclose(got, ref, rtol=2e-4, atol=1e-6)


@pytest.mark.skipif(not native.available(), reason="the native kernel does not build here")
# splat 17: patches of 19 cells, wider than a 16-lane row (the general path)
@pytest.mark.parametrize(("lag", "decel", "splat"),
                         [(*c, 9) for c in CAUSALITY] + [(1, None, 7), (1, None, 17)])
def test_native_kernel_matches_the_dense_float64_reference(rng, lag, decel, splat):
    """The C++ kernel (services/planner/native): its cells are not exposed, so the reference
    is built wholly in float64 (cells, visibility, counts, splat, decay); queries within the
    splat's reach of a ray point that lies within float32 rounding of a cell boundary are
    left out (and of the rest of its ray, where the two cells differ in blocking it). The
    paper's 9 x 9 splat takes the kernel's compile-time path, 7 x 7 its general one."""
    vp = dataclasses.replace(VP, visibility_lag_steps=lag, reaction=decel, splat_size=splat,
                             va_kernel="native")
    mean, variance, states, got, rows, cols = solve_random_problem(vp, rng)
    seen, doubtful = [], np.zeros(mean.shape, bool)
    half = vp.splat_size // 2
    for st in states:
        f_row, f_col, ambiguous = float64_cells(vp, st)
        vis = reference_visibility(vp, mean.astype(np.float64), st.astype(np.float64),
                                   f_row, f_col, 0.2)
        counted = reference_counted(vp, st, vis)
        seen.append((f_row[counted], f_col[counted]))
        px, py = float64_ray_points(vp, st.astype(np.float64), 0.2)
        ground = mean[int(st[4] / 0.2), int(st[3] / 0.2)] + vp.visibility_height_m
        for r, k in np.argwhere(ambiguous):
            # the point may count in the neighbouring cell; if the two cells differ in
            # blocking the ray, the rest of the ray may be seen or not
            cells = {(int(np.floor((py[r, k] + dy) / 0.2)), int(np.floor((px[r, k] + dx) / 0.2)))
                     for dy in (-2e-5, 2e-5) for dx in (-2e-5, 2e-5)}
            blocks = {not (0 <= a < mean.shape[0] and 0 <= b < mean.shape[1])
                      or mean[a, b] > ground for a, b in cells}
            for j in range(k, vp.visibility_points if len(blocks) > 1 else k + 1):
                r0, c0 = f_row[r, j], f_col[r, j]
                doubtful[max(r0 - half - 1, 0):r0 + half + 2,
                         max(c0 - half - 1, 0):c0 + half + 2] = True
    ref = reference_decay(vp, variance.astype(np.float64), seen, rows, cols)
    keep = ~doubtful[rows, cols]
    assert keep.mean() > 0.7
    np.testing.assert_allclose(got[:lag], variance[rows[:lag], cols[:lag]])   # nothing seen yet
    assert (ref[keep] < variance[rows, cols][keep] * 0.999).mean() > 0.1   # the test has teeth
    np.testing.assert_allclose(got[keep], ref[keep], rtol=2e-4, atol=1e-6)


def test_blocked_rays_stop_at_the_first_blocker():
    mean = np.zeros((200, 200), np.float32)
    mean[90:110, 110:115] = 2.0                  # a wall 2 m tall, 4 m ahead of a pose at x=18
    state = jnp.asarray([0, 0, 0, 18.0, 20.0, 0.0], jnp.float32)
    row, col, vis = (np.asarray(a) for a in visible_points(VP, jnp.asarray(mean), jnp.zeros(2),
                                                           0.2, state))
    centre_rays = np.abs(np.linspace(-36, 36, VP.visibility_rays)) < 10
    vis = vis.reshape(VP.visibility_rays, VP.visibility_points)
    col = col.reshape(VP.visibility_rays, VP.visibility_points)
    for r in np.nonzero(centre_rays)[0]:
        seen = col[r][vis[r]]
        assert seen.max() <= 114 and (seen >= 110).any()   # the wall is seen, nothing behind
    assert vis[0].all() and vis[-1].all()                  # the edge rays pass beside it


@pytest.mark.parametrize("backend", ["jax", "native"])
def test_batched_update_equals_one_trajectory_at_a_time(rng, backend):
    """The count map is shared by the trajectories in turn and cleaned after each:
    nothing of one may leak into the next, whatever the chunking (jax) or the split of
    the trajectories over threads (native)."""

    if backend == "native" and not native.available():
        pytest.skip("the native kernel does not build here")
    n, k, steps = 100, 5, 8
    mean = (rng.normal(size=(n, n)) * 0.1).astype(np.float32)
    mean[40:45, 60:64] += 2.0
    variance = rng.uniform(0.5, 3.0, (n, n)).astype(np.float32)
    states = np.zeros((k, steps, 6), np.float32)
    states[:, :, 3] = 4.0 + np.cumsum(rng.uniform(0.3, 1.0, (k, steps)), axis=1)
    states[:, :, 4] = 9.0 + rng.normal(size=(k, 1)) + np.cumsum(rng.normal(size=(k, steps)) * 0.1,
                                                               axis=1)
    states[:, :, 5] = rng.normal(size=(k, 1)) * 0.2
    rows = np.clip(states[:, :, 4:5] / 0.2 + rng.integers(-8, 8, (k, steps, 6)), 1, n - 2)
    cols = np.clip(states[:, :, 3:4] / 0.2 + rng.integers(0, 40, (k, steps, 6)), 1, n - 2)
    rows, cols = rows.astype(np.int32), cols.astype(np.int32)
    args = (jnp.asarray(mean), jnp.asarray(variance), jnp.zeros(2), 0.2)
    vp1 = dataclasses.replace(VP, va_kernel=backend, va_threads=1)
    one = np.stack([np.asarray(decayed_variance(vp1, *args, jnp.asarray(states[j]),
                                                jnp.asarray(rows[j]), jnp.asarray(cols[j]),
                                                OFFSETS)) for j in range(k)])
    prior = np.concatenate([variance[rows + dr, cols + dc] for dr, dc in OFFSETS], axis=-1)
    assert (one < prior * 0.5).mean() > 0.05                  # the trajectories did see
    variants = ([dataclasses.replace(vp1, va_chunk=c) for c in (1, 2, 8)] if backend == "jax"
                else [dataclasses.replace(vp1, va_threads=t) for t in (1, 2, 3)])
    for vp in variants:
        got = np.asarray(batched_decayed_variance(vp, *args, jnp.asarray(states),
                                                  jnp.asarray(rows), jnp.asarray(cols), OFFSETS))
        # float32 sums of the count C in another order move the exponent gamma C by a few
        # ulps, so ln(variance) by up to 8.6e-7 (1 + gamma C) over 200 seeds (relative
        # errors reach 2.3e-5 where gamma C = 30); a leak would move it by O(1)
        exponent = np.log(prior / one)
        assert np.all(np.abs(np.log(got / one)) <= 1.2e-6 * (1 + np.abs(exponent)))


@pytest.mark.skipif(not native.available(), reason="the native kernel does not build here")
def test_native_and_jax_forms_agree_on_a_planning_problem(va_planning_problem):
    """Both forms on one VA-MPPI problem (K = 64 rollouts on the offroad map): equal except
    where a ray point sits within float32 rounding of a cell boundary (their sines and
    cosines may differ in the last bit), which leaves only a few of the 200 k queries."""
    from services.planner import kernels
    params, m, states = va_planning_problem
    out = {}
    for backend in ("jax", "native"):
        p = dataclasses.replace(params, visibility=dataclasses.replace(params.visibility,
                                                                       va_kernel=backend))
        out[backend] = np.asarray(jax.jit(lambda s, p=p: kernels.query_variance(p, m, s))(states))
    a, b = out["jax"], out["native"]
    assert (a < 0.5 * np.asarray(m.variance).max()).mean() > 0.3      # much was seen
    close = np.isclose(a, b, rtol=1e-4, atol=1e-7)
    assert close.mean() > 0.999, close.mean()


@pytest.mark.skipif(not native.available(), reason="the native kernel does not build here")
def test_native_kernel_clips_cells_off_the_map_like_the_jax_form(rng):
    """Footprint cells at and beyond the map's edges: the kernel clips the query cells to
    the map and the patches inside it as the JAX form does (no stray read), and refuses
    inconsistent shapes with an error."""
    from services.planner.visibility import offset_kernels
    n = 50
    mean = jnp.asarray(rng.normal(size=(n, n)) * 0.1, jnp.float32)
    variance = jnp.asarray(rng.uniform(0.5, 3.0, (n, n)), jnp.float32)
    states = np.zeros((2, 6, 6), np.float32)
    states[:, :, 3] = np.linspace(1.0, 9.0, 6)
    states[:, :, 4] = [[0.5], [9.5]]
    rows = np.stack([np.full((6, 4), v) for v in (-3, n + 4)]).astype(np.int32)
    rows[:, :, 1] = [[0], [n - 1]]
    cols = np.tile(np.array([-7, 3, 25, n + 2], np.int32), (2, 6, 1))
    out = {}
    for backend in ("jax", "native"):
        vp = dataclasses.replace(VP, va_kernel=backend)
        out[backend] = np.asarray(batched_decayed_variance(
            vp, mean, variance, jnp.zeros(2), 0.2, jnp.asarray(states), jnp.asarray(rows),
            jnp.asarray(cols), OFFSETS))
    assert (out["jax"] < 0.9 * np.asarray(variance).min()).any()    # something was seen
    np.testing.assert_allclose(out["native"], out["jax"], rtol=1e-5)
    w = offset_kernels(VP, OFFSETS)
    with pytest.raises(Exception, match="inconsistent shapes"):
        np.asarray(native.va_variance(mean, variance, jnp.zeros(2), jnp.asarray(states),
                                      jnp.zeros((2, 6), jnp.int32), jnp.asarray(rows),
                                      jnp.asarray(cols), OFFSETS[:3],
                                      VP.ray_grid(), w, resolution=0.2, height=1.0, gamma=0.3,
                                      rays=VP.visibility_rays, points=VP.visibility_points,
                                      lag=1, pad=5,
                                      n_threads=2))


@pytest.mark.skipif(not native.available(), reason="the native kernel does not build here")
def test_native_kernel_separable_and_general_paths_agree(rng):
    """The paper's splat is an outer product, which the kernel's compile-time path uses
    (rows combined first); weights nudged off rank one take the general path (the full
    S x S products). On the same problem the two agree to float32 rounding and the nudge."""
    from services.planner.visibility import offset_kernels
    mean, variance, states, rows, cols = random_problem(rng)
    w = offset_kernels(VP, OFFSETS) * VP.count_value
    nudged = w.copy()
    nudged[0, 0] += 2e-6 * w.max()   # a corner: off rank one by twice the kernel's 1e-6 tolerance
    out = []
    for weights in (w, nudged):
        out.append(np.asarray(native.va_variance(
            jnp.asarray(mean), jnp.asarray(variance), jnp.zeros(2), jnp.asarray(states[None]),
            jnp.zeros((1, states.shape[0]), jnp.int32), jnp.asarray(rows[None]),
            jnp.asarray(cols[None]), OFFSETS, VP.ray_grid(), weights.astype(np.float32),
            resolution=0.2, height=VP.visibility_height_m, gamma=VP.decay_gamma,
            rays=VP.visibility_rays,
            points=VP.visibility_points, lag=1, pad=VP.splat_size // 2 + 1, n_threads=1)))
    seen = out[0] < 0.5 * variance.max()
    assert seen.mean() > 0.1                                    # the test has teeth
    np.testing.assert_allclose(out[1], out[0], rtol=1e-4, atol=1e-7)
