"""The mapper against a float64 reference and the behaviours the issue names."""

import math

import numpy as np

from common.config import load_config
from common.geometry import bilinear
from services.mapper import core
from services.sensor.core import CameraParams, render

CFG = load_config()
P = core.MapperParams.from_config(CFG)
PLAIN = core.MapperParams.from_config(load_config(overrides=["mapper.fill_between_pixels=false"]))
CAM = CameraParams.from_config(CFG.sensor)


def frame(hm, x, y, yaw):
    z = float(bilinear(hm, x, y, (0.0, 0.0), 0.2))
    depth, pos, rot = render(CAM, hm, (0.0, 0.0), 0.2, x, y, z, yaw)
    return depth, pos, rot, np.array([x, y, z, yaw])


def reference_fuse(state, depth, intr, pos, rot, floor=True):
    """Sequential scalar Kalman updates, one pixel at a time, float64. Also returns the
    cells a point within float32 rounding (1e-4 cell) of a cell boundary may fall in:
    there the float32 kernel may rightly pick the neighbour. `floor`: the variance floored
    at `min_variance` (the frame's last update)."""
    mean = state.mean.astype(np.float64)
    var = state.variance.astype(np.float64)
    ambiguous = np.zeros(mean.shape, bool)
    fx, fy, cx, cy = intr
    for v in range(depth.shape[0]):
        for u in range(depth.shape[1]):
            d = float(depth[v, u])
            if d <= 0:
                continue
            pc = np.array([(u - cx) / fx * d, (v - cy) / fy * d, d])
            pw = rot @ pc + pos
            res = P.resolution_m
            col, row = int(math.floor(pw[0] / res)), int(math.floor(pw[1] / res))
            if not (0 <= col < P.size_cells and 0 <= row < P.size_cells):
                continue
            frac = pw[:2] / P.resolution_m
            if (np.abs(frac - np.rint(frac)) < 1e-4).any():
                ambiguous[max(row - 1, 0):row + 2, max(col - 1, 0):col + 2] = True
            s2 = (P.noise_sigma0_m + P.noise_k_per_m * float(np.linalg.norm(pc)) ** 2) ** 2
            k = var[row, col] / (var[row, col] + s2)
            mean[row, col] += k * (pw[2] - mean[row, col])
            var[row, col] *= (1 - k)
    return mean, np.maximum(var, P.min_variance) if floor else var, ambiguous


def test_fusion_matches_sequential_float64_kalman(rng):
    hm = (rng.normal(size=(400, 400)) * 0.05).astype(np.float32) + 0.3
    x, y, yaw = rng.uniform(20, 60), rng.uniform(20, 60), rng.uniform(-3, 3)
    depth, pos, rot, base = frame(hm, x, y, yaw)
    state = core.initial_map(PLAIN, x, y, base[2])
    got = core.fuse_depth(PLAIN, state, depth, CAM.intrinsics, pos, rot)
    mean, var, ambiguous = reference_fuse(state, depth, CAM.intrinsics, pos, rot)
    seen = got.observed & ~state.observed & ~ambiguous
    assert seen.sum() > 500 and ambiguous.sum() < 0.05 * seen.sum()
    np.testing.assert_allclose(got.mean[seen], mean[seen], atol=2e-4)
    np.testing.assert_allclose(got.variance[~ambiguous], var[~ambiguous], rtol=2e-3, atol=1e-7)


def test_flat_plane_converges_and_variance_falls_with_every_observation():
    hm = np.full((400, 400), 0.5, np.float32)
    state = core.initial_map(P, 40.0, 40.0, 0.0)
    history = []
    for i in range(6):
        depth, pos, rot, base = frame(hm, 40.0 + 0.3 * i, 40.0, 0.0)
        state = core.fuse_depth(P, state, depth, CAM.intrinsics, pos, rot)
        history.append(state.variance.copy())
    always = np.ones_like(state.observed)
    for i in range(1, 6):
        always &= history[i] < history[i - 1]   # observed in every frame: fell every time
    assert always.sum() > 200
    start = core.initial_map(P, 40.0, 40.0, 0.0)
    obs = state.observed & ~start.observed
    err = np.abs(state.mean[obs] - 0.5)
    # the Kalman mean keeps var/prior of the prior's (0.0) pull: exact shrinkage bound
    assert (err <= 0.5 * state.variance[obs] / P.prior_variance * 1.01 + 1e-5).all()
    assert (err[state.variance[obs] < 0.01] < 2e-3).all()


def test_unseen_cells_keep_the_prior():
    hm = np.zeros((400, 400), np.float32)
    state = core.initial_map(P, 40.0, 40.0, 0.25)
    depth, pos, rot, base = frame(hm, 40.0, 40.0, 0.0)
    after = core.update(P, state, depth, CAM.intrinsics, pos, rot, base)
    behind = np.zeros_like(after.observed)
    behind[:, :150] = True           # everything behind the camera (x < 30 m)
    assert (after.variance[behind] == P.prior_variance).all()
    assert (after.mean[behind] == np.float32(0.25)).all()
    assert (after.variance[state.observed] <= P.known_variance).all()  # the known disc


def test_occluded_cells_in_view_are_inpainted_from_the_ground_and_stay_uncertain():
    hm = np.zeros((400, 400), np.float32)
    hm[180:220, 240:250] = 2.0       # a wall 8 m ahead, 8 m wide, hides what is behind it
    hm[195:205, 280:290] = 1.0       # hidden obstacle behind it
    state = core.initial_map(P, 40.0, 40.0, 0.0)
    depth, pos, rot, base = frame(hm, 40.0, 40.0, 0.0)
    fused = core.fuse_depth(P, state, depth, CAM.intrinsics, pos, rot)
    out = core.inpaint_occluded(P, fused, 40.0, 40.0, 0.0, 0.0)
    shadow = (slice(195, 205), slice(255, 275))      # behind the wall, inside the FOV
    assert not fused.observed[shadow].any()
    assert np.isfinite(out.mean).all()
    assert (out.variance[shadow] == P.prior_variance).all()
    # the wall is an occluder, not a source: the shadow is filled from the ground around
    assert np.abs(out.mean[shadow]).max() < 0.15      # the face's lowest mixed pixels remain
    # a low occluded step (below occluder_height_m) is a source
    low = fused.mean.copy()
    low[fused.observed & (low > 1.0)] = 0.3
    out_low = core.inpaint_occluded(P, core.MapState(low, fused.variance, fused.observed),
                                    40.0, 40.0, 0.0, 0.0)
    assert (out_low.mean[195:205, 251:254] > 0.1).all()
    assert (out.mean[shadow] <= 2.0 + 1e-3).all()
    assert (out.mean[fused.observed] == fused.mean[fused.observed]).all()


def test_the_shadow_behind_a_hill_continues_the_hill_and_a_box_top_stays_an_occluder():
    """A ridge 1.2 m high (a raised cosine 12 m wide across the map, 14 m ahead) is ground
    the robot reaches over gentle slopes: its crest is a source, and the shadow behind it
    continues from the crest instead of dropping to the robot's height (a cliff at the
    crest that Eq. occupied would take for an obstacle). A box 1.2 m high whose top the
    camera sees is reached over no such slope: its top is not a source."""
    x = (np.arange(400) + 0.5) * 0.2
    d = np.abs(x - 54.0)
    ridge = np.where(d < 6.0, 0.6 * (1.0 + np.cos(2.0 * np.pi * d / 12.0)), 0.0)
    hm = np.tile(ridge[None, :], (400, 1)).astype(np.float32)
    state = core.initial_map(P, 40.0, 40.0, 0.0)
    depth, pos, rot, _ = frame(hm, 40.0, 40.0, 0.0)
    fused = core.fuse_depth(P, state, depth, CAM.intrinsics, pos, rot)
    out = core.inpaint_occluded(P, fused, 40.0, 40.0, 0.0, 0.0)
    row = out.mean[200]
    last = 220 + np.flatnonzero(fused.observed[200, 220:330])[-1]   # the shadow starts after
    assert not fused.observed[200, last + 1:last + 30].any()
    crest = row[last]
    assert crest > 1.0                            # seen up to near the crest, 14 m ahead
    # no step past Eq. occupied's threshold where the seen crest meets the shadow
    assert np.abs(np.diff(row[last - 3:last + 10])).max() < P.ground_step_m
    assert row[last + 1:last + 30].min() > 0.8 * crest

    box = np.zeros((400, 400), np.float32)
    box[190:210, 230:250] = 1.2          # lower than the camera (1.8 m): its top is seen
    depth, pos, rot, _ = frame(box, 40.0, 40.0, 0.0)
    fused = core.fuse_depth(P, state, depth, CAM.intrinsics, pos, rot)
    top = fused.observed & (fused.mean > 1.0)
    assert top.sum() > 20
    reached = core.ground_reached(P, fused.mean, fused.observed, (200, 200))
    assert reached[200, 200] and not (reached & top).any()
    out = core.inpaint_occluded(P, fused, 40.0, 40.0, 0.0, 0.0)
    shadow = ~fused.observed[195:205, 252:270]
    assert shadow.any() and np.abs(out.mean[195:205, 252:270][shadow]).max() < 0.15


FILL = core.MapperParams.from_config(load_config(overrides=["mapper.fill_between_pixels=true"]))


def reference_between(depth, intr, pos, rot):
    """The measurements between vertically neighbouring pixels, float64, pair by pair:
    [(x, y, z, variance)], and the cells within float32 rounding of one's boundary."""
    fx, fy, cx, cy = intr
    res, s = FILL.resolution_m, core.BETWEEN_SAMPLES
    out, ambiguous = [], set()

    def world(v, u):
        d = float(depth[v, u])
        pc = np.array([(u - cx) / fx * d, (v - cy) / fy * d, d])
        return rot @ pc + pos, float(np.linalg.norm(pc))

    def cell(p):
        return int(math.floor(p[1] / res)), int(math.floor(p[0] / res))

    for v in range(depth.shape[0] - 1):
        for u in range(depth.shape[1]):
            if depth[v, u] <= 0 or depth[v + 1, u] <= 0:
                continue
            (a, ra), (b, rb) = world(v, u), world(v + 1, u)
            if not all(0 <= c < FILL.size_cells for c in (*cell(a), *cell(b))):
                continue
            da, db = (float(np.hypot(*(p[:2] - pos[:2]))) for p in (a, b))
            far, near, r_far, d_far = (a, b, ra, da) if da >= db else (b, a, rb, db)
            gap = float(np.hypot(*(far[:2] - near[:2])))
            slack = FILL.ground_step_m / res * gap - abs(far[2] - near[2])
            # a pair within float32 rounding of a condition may rightly go either way
            close = min(abs(slack), abs(gap - res), abs(gap - s * res), abs(da - db)) < 1e-4
            if not (res < gap <= s * res and slack >= 0):
                if close:
                    ambiguous.update(cell(near + (k + 1) / (s + 1) * (far - near))
                                     for k in range(s))
                continue
            for k in range(s):
                q = near + (k + 1) / (s + 1) * (far - near)
                frac = q[:2] / res
                if close or (np.abs(frac - np.rint(frac)) < 1e-4).any():
                    ambiguous.add(cell(q))
                if cell(q) in (cell(near), cell(far)):
                    continue
                ray = pos[2] + (far[2] - pos[2]) * float(np.hypot(*(q[:2] - pos[:2]))) / d_far
                sigma = FILL.noise_sigma0_m + FILL.noise_k_per_m * r_far ** 2 + max(ray - q[2], 0)
                out.append((q[0], q[1], q[2], sigma ** 2 / min(gap / ((s + 1) * res), 1.0)))
    return out, ambiguous


def test_the_ground_between_pixel_rows_matches_a_float64_reference(rng):
    """Waves and a wall: every measurement, hits and lines between rows, fused one at a
    time in float64 against the kernel's one scatter."""
    yy, xx = np.mgrid[0:400, 0:400] * 0.2
    a, b, c = rng.uniform(0.1, 0.4, 3)
    hm = (a * np.sin(xx / rng.uniform(4, 9)) * np.cos(yy / rng.uniform(4, 9))
          + b * np.sin((xx + yy) / 7.0) + c).astype(np.float32)
    x, y, yaw = rng.uniform(25, 55), rng.uniform(25, 55), rng.uniform(-3, 3)
    wx, wy = x + 9 * math.cos(yaw), y + 9 * math.sin(yaw)
    hm[int(wy / 0.2) - 10:int(wy / 0.2) + 10, int(wx / 0.2) - 10:int(wx / 0.2) + 10] += 1.5
    depth, pos, rot, base = frame(hm, x, y, yaw)
    state = core.initial_map(FILL, x, y, base[2])
    got = core.fuse_depth(FILL, state, depth, CAM.intrinsics, pos, rot)
    mean, var, ambiguous = reference_fuse(state, depth, CAM.intrinsics, pos, rot, floor=False)
    lines, amb_lines = reference_between(depth, CAM.intrinsics, pos.astype(np.float64),
                                         rot.astype(np.float64))
    for qx, qy, qz, s2 in lines:
        r, c = int(math.floor(qy / 0.2)), int(math.floor(qx / 0.2))
        k = var[r, c] / (var[r, c] + s2)
        mean[r, c] += k * (qz - mean[r, c])
        var[r, c] *= 1 - k
    var = np.maximum(var, FILL.min_variance)
    for r, c in amb_lines:
        ambiguous[max(r - 1, 0):r + 2, max(c - 1, 0):c + 2] = True
    plain = core.fuse_depth(PLAIN, state, depth, CAM.intrinsics, pos, rot)
    added = got.observed & ~plain.observed & ~ambiguous
    assert len(lines) > 2000 and added.sum() > 300, (len(lines), added.sum())
    ok = ~ambiguous
    err_m = np.abs(got.mean - mean)[ok & got.observed]
    err_v = np.abs(got.variance - var)[ok] / var[ok]
    # seen over 12 draws: 8.9e-7 and 1.6e-5
    assert err_m.max() < 1.5e-6 and err_v.max() < 3e-5, (err_m.max(), err_v.max())


def test_between_rows_the_stripes_are_measured_and_a_wall_s_foot_is_not_raised():
    hm = np.zeros((400, 400), np.float32)
    hm[180:220, 300:305] = 2.0                  # a wall 20 m ahead, 8 m wide
    state = core.initial_map(PLAIN, 40.0, 40.0, 0.0)
    depth, pos, rot, base = frame(hm, 40.0, 40.0, 0.0)
    plain = core.fuse_depth(PLAIN, state, depth, CAM.intrinsics, pos, rot)
    filled = core.fuse_depth(FILL, state, depth, CAM.intrinsics, pos, rot)
    ahead = (slice(190, 210), slice(240, 290))   # 8-18 m ahead, 4 m wide: ground only
    assert plain.observed[ahead].mean() < 0.8 and filled.observed[ahead].all()
    assert np.abs(filled.mean[ahead]).max() < 0.05
    assert (filled.variance[ahead] < 0.15).all()           # a ray at most 0.3 m above
    foot = (slice(185, 215), slice(290, 300))    # the 2 m before the face: the lines add
    new = filled.observed[foot] & ~plain.observed[foot]     # none raised (the hits' own
    assert new.sum() > 20 and np.abs(filled.mean[foot][new]).max() < 0.1   # mixed pixels
    behind = (slice(190, 210), slice(306, 330))  # the wall's shadow stays unseen
    assert not filled.observed[behind].any()
