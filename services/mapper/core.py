"""The mapper's pure core: a stochastic 2.5D elevation map fused from depth images.

Per cell a Gaussian N(mean, variance) of the ground elevation.

- Start: every cell at the prior variance (3.0 in the paper) with the
  free-space mean (the robot's elevation); cells within `known_radius_m` of the
  robot at `known_variance` ("no uncertainty near the robot", the paper).
- Fusion (`fuse_depth`, JAX): each depth pixel is back-projected to a world
  point; its height is a measurement of its cell with standard deviation
  sigma0 + k * range^2 (stereo/ToF-like growth with range). All measurements of
  a frame are fused per cell in information form, which is exactly the
  sequential scalar Kalman update: 1/var' = 1/var + sum 1/s_i,
  mean' = var' (mean/var + sum z_i/s_i). Variance never drops below
  `min_variance`.
- Inpainting (`inpaint_occluded`, OpenCV Telea): cells inside the camera's
  field of view (range and angle) that have never been observed, i.e. occluded,
  get their mean inpainted from the ground around them (occluders excluded)
  and keep the prior variance.

See docs/mapper.md for the noise model and the choices.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import partial

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from common.config import Config, by_name


@dataclass(frozen=True)
class MapperParams:
    """Named as their keys of `[mapper]` and `[sensor]` (docs/parameters.md), the derived
    ones commented."""
    size_cells: int
    resolution_m: float
    origin: tuple[float, float]       # derived: the scenario's map origin
    prior_variance: float
    known_radius_m: float
    known_variance: float
    noise_sigma0_m: float
    noise_k_per_m: float
    min_variance: float
    inpaint_radius_cells: int
    occluder_height_m: float
    fill_between_pixels: bool
    ground_step_m: float              # derived: the most ground rises from cell to cell, the
                                      # steepest slope Eq. occupied takes for ground
                                      # (planner.grad_sq_threshold) over one cell
    hfov_rad: float                   # derived: sensor.hfov_deg
    range_m: float                    # [sensor]

    @classmethod
    def from_config(cls, cfg: Config, origin: tuple[float, float] = (0.0, 0.0)) -> MapperParams:
        return by_name(cls, cfg.mapper, cfg.sensor, origin=origin,
                       ground_step_m=math.sqrt(cfg.planner.grad_sq_threshold)
                       * cfg.mapper.resolution_m,
                       hfov_rad=math.radians(cfg.sensor.hfov_deg))


@dataclass(frozen=True)
class MapState:
    mean: np.ndarray          # (n, n) float32
    variance: np.ndarray      # (n, n) float32
    observed: np.ndarray      # (n, n) bool: measured at least once; always variance < prior
                              # (a fused variance is below the one before, the known disc's
                              # below the prior), so the map message alone restores it


def cell_centres(p: MapperParams) -> tuple[np.ndarray, np.ndarray]:
    c = (np.arange(p.size_cells) + 0.5) * p.resolution_m
    return np.meshgrid(c + p.origin[0], c + p.origin[1], indexing="xy")


def initial_map(p: MapperParams, x: float, y: float, z: float) -> MapState:
    """Prior map around a robot standing at (x, y) on ground elevation z."""
    xx, yy = cell_centres(p)
    near = (xx - x) ** 2 + (yy - y) ** 2 <= p.known_radius_m ** 2
    mean = np.full((p.size_cells, p.size_cells), z, np.float32)
    var = np.where(near, p.known_variance, p.prior_variance).astype(np.float32)
    return MapState(mean, var, near)


def restore(p: MapperParams, mean: np.ndarray, variance: np.ndarray) -> MapState:
    """The map state a published (mean, variance) pair is: what a restarted mapper goes
    on from."""
    return MapState(mean, variance, variance < np.float32(p.prior_variance))


def measurement_variance(p: MapperParams, rng: jax.Array) -> jax.Array:
    """Range-dependent measurement variance, (sigma0 + k r^2)^2."""
    s = p.noise_sigma0_m + p.noise_k_per_m * rng * rng
    return s * s


def flat_cells(p: MapperParams, x: jax.Array, y: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The flat index row * n + col of the cells under world points (x, y), and whether
    each lies on the map (the index is meaningless where it does not)."""
    n = p.size_cells
    col = jnp.floor((x - p.origin[0]) / p.resolution_m).astype(jnp.int32)
    row = jnp.floor((y - p.origin[1]) / p.resolution_m).astype(jnp.int32)
    return row * n + col, (col >= 0) & (col < n) & (row >= 0) & (row < n)


BETWEEN_SAMPLES = 16      # points on the line between two pixel rows' hits: gaps to 16 cells


def between_rows(p: MapperParams, pw, rng, valid, cam_position, shape: tuple[int, int]):
    """Measurements of the ground between vertically neighbouring pixels (`fill_between_pixels`):
    (flat cell index, precision, height), each (h-1, w, BETWEEN_SAMPLES), precision 0 where
    there is none.

    A pixel row lands on the ground farther than the row below it, and at range the two
    hits lie cells apart (1.9 m at 25 m with 128 x 72 pixels), leaving stripes of cells
    no pixel hits. The farther pixel's ray passed over them, so nothing stands on them
    higher than that ray. Where the two hits lie on one ground slope (they rise no more
    than Eq. occupied's steepest ground, `ground_step_m` a cell, and lie more than a cell
    and at most BETWEEN_SAMPLES cells apart), the line between them is a measurement of
    every cell it crosses: height on the line, standard deviation the farther pixel's
    noise plus that ray's height above the line there (nothing taller could stand there
    unseen), about one measurement a cell. The hits' own cells are left to the hits. A
    step (an obstacle's face, a wall's foot) is steeper than ground and is not bridged."""
    h, w = shape
    s = BETWEEN_SAMPLES
    pts = pw.reshape(h, w, 3)
    ok = valid.reshape(h, w)
    r = rng.reshape(h, w)
    a, b = pts[:-1], pts[1:]
    da = jnp.hypot(a[..., 0] - cam_position[0], a[..., 1] - cam_position[1])
    db = jnp.hypot(b[..., 0] - cam_position[0], b[..., 1] - cam_position[1])
    a_far = da >= db
    far = jnp.where(a_far[..., None], a, b)
    near = jnp.where(a_far[..., None], b, a)
    d_far = jnp.maximum(da, db)
    r_far = jnp.where(a_far, r[:-1], r[1:])
    gap = jnp.hypot(far[..., 0] - near[..., 0], far[..., 1] - near[..., 1])
    res = p.resolution_m
    use = (ok[:-1] & ok[1:] & (gap > res) & (gap <= s * res)
           & (jnp.abs(far[..., 2] - near[..., 2]) <= p.ground_step_m / res * gap))
    t = (jnp.arange(s, dtype=jnp.float32) + 1.0) / (s + 1.0)            # near -> far
    q = near[..., None, :] + t[:, None] * (far - near)[..., None, :]     # (h-1, w, s, 3)
    dq = jnp.hypot(q[..., 0] - cam_position[0], q[..., 1] - cam_position[1])
    ray_z = cam_position[2] + (far[..., None, 2] - cam_position[2]) * dq / d_far[..., None]
    clear = jnp.maximum(ray_z - q[..., 2], 0.0)
    sigma = p.noise_sigma0_m + p.noise_k_per_m * r_far[..., None] ** 2 + clear
    weight = jnp.minimum(gap / ((s + 1.0) * res), 1.0)[..., None]
    cell, inside = flat_cells(p, q[..., 0], q[..., 1])
    c_near, _ = flat_cells(p, near[..., 0], near[..., 1])
    c_far, _ = flat_cells(p, far[..., 0], far[..., 1])
    keep = use[..., None] & inside & (cell != c_near[..., None]) & (cell != c_far[..., None])
    return (jnp.where(keep, cell, 0), jnp.where(keep, weight / (sigma * sigma), 0.0),
            q[..., 2])


@partial(jax.jit, static_argnames=("p",))
def _fuse(p: MapperParams, mean, var, observed, depth, intrinsics, cam_position, cam_rotation):
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    h, w = depth.shape
    u, v = jnp.meshgrid(jnp.arange(w, dtype=jnp.float32), jnp.arange(h, dtype=jnp.float32),
                        indexing="xy")
    d = depth
    pc = jnp.stack([(u - cx) / fx * d, (v - cy) / fy * d, d], axis=-1).reshape(-1, 3)
    pw = pc @ cam_rotation.T + cam_position
    rng = jnp.linalg.norm(pc, axis=-1)
    cell, inside = flat_cells(p, pw[:, 0], pw[:, 1])
    n_side = p.size_cells
    valid = (d.reshape(-1) > 0) & inside
    prec = jnp.where(valid, 1.0 / measurement_variance(p, rng), 0.0)
    flat = jnp.where(valid, cell, 0)
    z = pw[:, 2]
    if p.fill_between_pixels:
        b_flat, b_prec, b_z = between_rows(p, pw, rng, valid, cam_position, (h, w))
        flat = jnp.concatenate([flat, b_flat.reshape(-1)])
        prec = jnp.concatenate([prec, b_prec.reshape(-1)])
        z = jnp.concatenate([z, b_z.reshape(-1)])
    n = n_side * n_side
    prec_sum = jnp.zeros(n, jnp.float32).at[flat].add(prec).reshape(n_side, n_side)
    z_sum = jnp.zeros(n, jnp.float32).at[flat].add(prec * z).reshape(n_side, n_side)
    seen = prec_sum > 0
    post_prec = 1.0 / var + prec_sum
    new_mean = jnp.where(seen, (mean / var + z_sum) / post_prec, mean)
    new_var = jnp.where(seen, jnp.maximum(1.0 / post_prec, p.min_variance), var)
    return new_mean, new_var.astype(jnp.float32), observed | seen


def fuse_depth(p: MapperParams, state: MapState, depth: np.ndarray, intrinsics: np.ndarray,
               cam_position: np.ndarray, cam_rotation: np.ndarray) -> MapState:
    """Kalman-fuse one depth frame into the map."""
    mean, var, obs = _fuse(p, jnp.asarray(state.mean), jnp.asarray(state.variance),
                           jnp.asarray(state.observed), jnp.asarray(depth, jnp.float32),
                           jnp.asarray(intrinsics, jnp.float32),
                           jnp.asarray(cam_position, jnp.float32),
                           jnp.asarray(cam_rotation, jnp.float32))
    return MapState(np.asarray(mean), np.asarray(var), np.asarray(obs))


def cell_of(p: MapperParams, x: float, y: float) -> tuple[int, int]:
    """The (row, col) of the cell under (x, y)."""
    return int((y - p.origin[1]) / p.resolution_m), int((x - p.origin[0]) / p.resolution_m)


def fov_mask(p: MapperParams, x: float, y: float, yaw: float) -> tuple[np.ndarray, slice, slice]:
    """Cells inside the camera's horizontal field of view and range, on the window
    (rows, cols) around the robot that contains them."""
    r = int(math.ceil(p.range_m / p.resolution_m)) + 2
    ri, ci = cell_of(p, x, y)
    rows = slice(max(ri - r, 0), min(ri + r + 1, p.size_cells))
    cols = slice(max(ci - r, 0), min(ci + r + 1, p.size_cells))
    cy = (np.arange(rows.start, rows.stop) + 0.5) * p.resolution_m + p.origin[1]
    cx = (np.arange(cols.start, cols.stop) + 0.5) * p.resolution_m + p.origin[0]
    xx, yy = np.meshgrid(cx - x, cy - y, indexing="xy")
    bearing = np.arctan2(yy, xx) - yaw
    bearing = (bearing + np.pi) % (2 * np.pi) - np.pi
    inside = (xx * xx + yy * yy <= p.range_m ** 2) & (np.abs(bearing) <= p.hfov_rad / 2)
    return inside, rows, cols


def ground_reached(p: MapperParams, mean: np.ndarray, observed: np.ndarray,
                   robot: tuple[int, int]) -> np.ndarray:
    """Cells (bool, the window's shape) the robot's cell `robot` (row, col) reaches over
    ground: through observed cells, none of which differs from a 4-neighbour by more than
    `ground_step_m`. Far ground is seen by every other pixel row, so an unobserved cell
    beside observed ones counts at their mean. A wall's face breaks the way (the cells on
    both sides of the step are left out), so the top of a box is not reached; a slope is.
    Nothing where the robot's own cell is not such a cell."""
    seen = observed.astype(np.float32)
    count = cv2.boxFilter(seen, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    total = cv2.boxFilter(mean * seen, -1, (3, 3), normalize=False,
                          borderType=cv2.BORDER_CONSTANT)
    known = count > 0
    mean = np.where(observed, mean, total / np.maximum(count, 1.0))
    across = known[1:] & known[:-1] & (np.abs(np.diff(mean, axis=0)) > p.ground_step_m)
    along = known[:, 1:] & known[:, :-1] & (np.abs(np.diff(mean, axis=1)) > p.ground_step_m)
    rough = ~known
    rough[1:] |= across
    rough[:-1] |= across
    rough[:, 1:] |= along
    rough[:, :-1] |= along
    r, c = robot
    inside = 0 <= r < mean.shape[0] and 0 <= c < mean.shape[1]
    if not inside or rough[r, c]:
        return np.zeros_like(observed)
    _, labels = cv2.connectedComponents((~rough).astype(np.uint8), connectivity=4)
    return labels == labels[r, c]


def inpaint_occluded(p: MapperParams, state: MapState, x: float, y: float, z: float, yaw: float
                     ) -> MapState:
    """Telea-inpaint the mean of never-observed cells inside the field of view.

    Occluders (observed cells more than `occluder_height_m` above the robot's
    ground z that are not `ground_reached`) are not sources: their height says
    nothing about what stands behind them, so they enter Telea at the free-space
    value z and the shadow is filled from the ground around it. A hill's crest
    is ground, however high: the shadow behind it continues the hill instead of
    dropping to z, which would put a cliff at the crest. The window is padded by
    replication (so Telea has context at its edge) and any non-finite value is filled
    before inpainting (NaNs would leak). Variance is left at the prior:
    inpainting is a guess, not an observation.
    """
    inside, rows, cols = fov_mask(p, x, y, yaw)
    mask = inside & ~state.observed[rows, cols]
    if not mask.any():
        return state
    window = np.array(state.mean[rows, cols], dtype=np.float32)
    bad = ~np.isfinite(window)
    if bad.any():
        window[bad] = np.nanmedian(np.where(bad, np.nan, window)) if (~bad).any() else z
    observed = state.observed[rows, cols]
    high = observed & (window > z + p.occluder_height_m)
    if high.any():
        ri, ci = cell_of(p, x, y)
        high &= ~ground_reached(p, window, observed, (ri - rows.start, ci - cols.start))
    source = np.where(high, np.float32(z), window)
    # OpenCV's float32 Telea returns garbage (4.14 and 5.0 alike, docs/mapper.md):
    # inpaint a uint16 quantisation over the window's own range instead.
    lo, hi = float(source.min()), float(source.max())
    scale = max(hi - lo, 1e-6) / 65535.0
    q = np.clip(np.rint((source - lo) / scale), 0, 65535).astype(np.uint16)
    pad = p.inpaint_radius_cells + 1
    src = cv2.copyMakeBorder(q, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    m8 = cv2.copyMakeBorder(mask.astype(np.uint8), pad, pad, pad, pad, cv2.BORDER_CONSTANT,
                            value=0)
    q_filled = cv2.inpaint(src, m8, p.inpaint_radius_cells, cv2.INPAINT_TELEA)[pad:-pad, pad:-pad]
    filled = (lo + q_filled.astype(np.float32) * scale).astype(np.float32)
    mean = state.mean.copy()
    mean[rows, cols] = np.where(mask, filled, window)
    return replace(state, mean=mean)


def update(p: MapperParams, state: MapState, depth: np.ndarray, intrinsics: np.ndarray,
           cam_position: np.ndarray, cam_rotation: np.ndarray, base_pose: np.ndarray) -> MapState:
    """One frame: fuse, then inpaint the occluded part of the field of view."""
    fused = fuse_depth(p, state, depth, intrinsics, cam_position, cam_rotation)
    return inpaint_occluded(p, fused, float(base_pose[0]), float(base_pose[1]),
                            float(base_pose[2]), float(base_pose[3]))
