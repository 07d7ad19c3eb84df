"""The visibility-aware variance update (the paper's Section "Visibility-Aware
Uncertainty Update"), per trajectory, in JAX.

Along a trajectory, at every pose, 20 horizontal rays across the 72 degree
field of view are sampled at 30 points from 2 m to 25 m over the *mean* map.
A point is visible when no earlier point of its ray stands higher than the
vehicle's ground elevation plus the visibility height h (the 2D-ray-with-a-
threshold approximation of 3D visibility); the first blocking point itself is
seen. Each visible point adds `count_value` c to the trajectory's count map
(Eq. count_increase), which is splatted with a 9 x 9 Gaussian of sigma = 1
cell (Eq. gaussian), and the variance this trajectory meets is
Sigma * exp(-gamma * C) (Eq. uncertainty_update_equation, with the sign that
makes uncertainty shrink).

Causality: the variance the trajectory meets at step i uses only the points
seen from poses 0 .. i-lag; lag = 1 is the paper's remark (what it could have
seen before), a larger lag makes a point seen count only once there is time to
act on it (`planner.visibility_lag_steps`, docs/planner.md). With
`planner.visibility_in_time` (ours, on by default; off is the paper's rule) a point counts
only when the footprint's front edge lies farther from it than the pose needs to react
to it from its speed, with the vehicle's own limits: to stop, or to swerve one vehicle
width aside, whichever is nearer (`services.plant.dynamics.Reaction`); nearer points
still block their rays. A scan over the horizon carries a raw (unsplatted) count map: step i
adds pose i-lag's visible points, then copies the 11 x 11 patch of raw counts
around each of step i's footprint cells; one matmul after the horizon turns
the patches into splatted counts at the five cells. Memory: one padded map per
trajectory processed side by side (`va_chunk`), shared by the trajectories in
turn and cleaned after each, never K full maps; the visible points of every
pose (K x N x 600 indices: 77 MB at K = 800); the patches of one chunk (N x
chunk x P x 121 floats: 2.3 MB).

That is the vectorised (`jax`) form, every backend's. On a CPU the same variances
come by default from a native kernel (services/planner/native, `planner.va_kernel`),
a rollout at a time per thread, about three times faster there (docs/planner.md);
services/planner/kernels.py chooses between the two.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from common.config import Config, by_name
from services.planner import native
from services.plant.dynamics import Reaction, S


@dataclass(frozen=True)
class VisibilityParams:
    """Named as their keys of `[planner]` and `[sensor]` (docs/parameters.md), the derived
    ones commented."""
    visibility_rays: int       # N_theta (Table II): 20
    visibility_points: int     # N_r (Table II): 30
    visibility_min_m: float    # 2 m (text)
    visibility_max_m: float    # 25 m (Table II)
    fov_rad: float             # derived: sensor.hfov_deg, 72 degrees (Table II)
    visibility_height_m: float  # threshold visibility height h
    count_value: float         # c of Eq. count_increase
    splat_size: int            # 9 (text)
    splat_sigma_cells: float   # 1 (text)
    decay_gamma: float         # gamma, 0.3 (Table II)
    mount_forward_m: float     # [sensor]: rays start at the camera
    visibility_lag_steps: int  # step i meets what poses 0 .. i - lag saw (1: the paper's)
    reaction: Reaction | None  # derived: points nearer than the distance to react do not
                               # count; None = off
    react_s: float             # derived: the reaction time of that distance (one control tick)
    react_lateral_m: float     # derived: a swerve's sideways move, the footprint's width
    react_ahead_m: float       # derived: the footprint's front edge ahead of the camera: a
                               # point this much nearer than the reaction distance is reached
    va_chunk: int              # trajectories per chunk (memory bound); 0 = auto
    va_kernel: str             # jax | native: planner.va_kernel resolved (services/planner/
                               # kernels.py)
    va_threads: int            # native kernel threads; 0 = this process's cores

    @classmethod
    def from_config(cls, cfg: Config) -> VisibilityParams:
        p = cfg.planner
        return by_name(cls, p, cfg.sensor, fov_rad=math.radians(cfg.sensor.hfov_deg),
                       va_kernel=native.resolve(p.va_kernel),
                       reaction=reaction_of(cfg), react_s=p.dt_s,
                       react_lateral_m=cfg.vehicle.footprint_width_m + 2 * p.footprint_margin_m,
                       react_ahead_m=cfg.vehicle.footprint_length_m / 2 + p.footprint_margin_m
                       - cfg.sensor.mount_forward_m)

    def ray_grid(self) -> np.ndarray:
        """Body-frame offsets (rays * points, 2) of the ray points from the CG."""
        ang = np.linspace(-self.fov_rad / 2, self.fov_rad / 2, self.visibility_rays)
        a, r = np.meshgrid(ang, self.ranges(), indexing="ij")    # (rays, points)
        pts = np.stack([self.mount_forward_m + r * np.cos(a), r * np.sin(a)], axis=-1)
        return pts.reshape(-1, 2)

    def ranges(self) -> np.ndarray:
        """Distance (points,) of a ray's points from the camera."""
        return np.linspace(self.visibility_min_m, self.visibility_max_m, self.visibility_points)

    def kernel(self) -> np.ndarray:
        """G of Eq. gaussian, (size, size), 1/(2 pi s^2) exp(-(x^2 + y^2) / 2 s^2)."""
        h = self.splat_size // 2
        o = np.arange(-h, h + 1)
        x, y = np.meshgrid(o, o, indexing="xy")
        s2 = self.splat_sigma_cells ** 2
        return np.exp(-(x * x + y * y) / (2 * s2)) / (2 * np.pi * s2)


def reaction_of(cfg: Config) -> Reaction | None:
    """The in-time rule's reaction: the vehicle's own (`visibility_in_time`), or stopping
    at the fixed `visibility_stop_decel_mps2` (the older form, which the alleyway's tables
    of record ran with); None: the paper's rule."""
    p = cfg.planner
    if p.visibility_in_time:
        return Reaction.from_config(cfg.vehicle)
    if p.visibility_stop_decel_mps2 > 0.0:
        return Reaction.braking_only(p.visibility_stop_decel_mps2)
    return None


def ray_cells(vp: VisibilityParams, origin: Any, resolution: float, states: Any
              ) -> tuple[Any, Any]:
    """Cells (row, col) int (..., M) of the ray points of poses `states` (..., 6);
    M = rays * points, ray-major; unclipped (may lie off the map)."""
    grid = jnp.asarray(vp.ray_grid(), jnp.float32)
    x, y, psi = (states[..., i, None] for i in (S.X, S.Y, S.PSI))
    c, s = jnp.cos(psi), jnp.sin(psi)
    px = x + c * grid[:, 0] - s * grid[:, 1]
    py = y + s * grid[:, 0] + c * grid[:, 1]
    return (jnp.floor((py - origin[1]) / resolution).astype(jnp.int32),
            jnp.floor((px - origin[0]) / resolution).astype(jnp.int32))


def visible_points(vp: VisibilityParams, mean: Any, origin: Any, resolution: float,
                   states: Any) -> tuple[Any, Any, Any]:
    """Ray points of poses `states` (..., 6): (row, col) int (..., M), visible (..., M)
    bool; M = rays * points, ray-major. Vectorised over any leading axes.

    A point blocks its ray when it stands higher than the ground under the pose plus
    h, or lies off the map; a ray's points up to and including its first blocker are
    seen, except off the map."""
    h, w = mean.shape
    row, col = ray_cells(vp, origin, resolution, states)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    flat_mean = mean.reshape(-1)
    elev = jnp.take(flat_mean, jnp.clip(row, 0, h - 1) * w + jnp.clip(col, 0, w - 1))
    x, y = states[..., S.X, None], states[..., S.Y, None]
    vr = jnp.clip(jnp.floor((y - origin[1]) / resolution).astype(jnp.int32), 0, h - 1)
    vc = jnp.clip(jnp.floor((x - origin[0]) / resolution).astype(jnp.int32), 0, w - 1)
    blocker = (elev > jnp.take(flat_mean, vr * w + vc) + vp.visibility_height_m) | ~inside
    blocker = blocker.reshape(blocker.shape[:-1] + (vp.visibility_rays, vp.visibility_points))
    # the first blocker by a min over indices: argmax and cumsum are several times
    # slower on XLA:CPU
    n_r = vp.visibility_points
    first = jnp.min(jnp.where(blocker, jnp.arange(n_r), n_r), axis=-1)
    before = (jnp.arange(n_r) <= first[..., None]).reshape(row.shape)
    return row, col, before & inside


def uncounted_points(vp: VisibilityParams, states: Any) -> Any:
    """How many of each ray's nearest points do not count, int32 (...) for poses
    `states` (..., 6): those the footprint's front edge is nearer to than the distance
    to react from the pose's speed (`reaction`; None = off: none)."""
    if vp.reaction is None:
        return jnp.zeros(states.shape[:-1], jnp.int32)
    v = jnp.hypot(states[..., S.V], states[..., S.v])
    stop = vp.reaction.distance(v, vp.react_s, vp.react_lateral_m, jnp) + vp.react_ahead_m
    ranges = jnp.asarray(vp.ranges(), jnp.float32)
    return jnp.sum(ranges < stop[..., None], axis=-1).astype(jnp.int32)


def offset_kernels(vp: VisibilityParams, offsets: tuple[tuple[int, int], ...]) -> np.ndarray:
    """(S*S, len(offsets)) matrix: a patch of S = splat_size + 2 max|offset| raw counts
    around a footprint cell, times column k, is the splatted count at cell + offsets[k]."""
    reach = max(max(abs(a), abs(b)) for a, b in offsets)
    size = vp.splat_size + 2 * reach
    kern = vp.kernel()
    out = np.zeros((size, size, len(offsets)))
    for k, (dr, dc) in enumerate(offsets):
        r0, c0 = reach + dr, reach + dc              # the kernel centred on cell + offset
        out[r0:r0 + vp.splat_size, c0:c0 + vp.splat_size, k] = kern
    return out.reshape(size * size, len(offsets))


def count_inputs(vp: VisibilityParams, offsets: tuple[tuple[int, int], ...], states: Any
                 ) -> tuple[np.ndarray, int, Any]:
    """What both forms of the update start from: the splat weights (S * S, len(offsets))
    times c, the padding of a count map (half the splat plus the offsets' reach) and each
    pose's uncounted points (K, N+1)."""
    reach = max(max(abs(a), abs(b)) for a, b in offsets)
    return (offset_kernels(vp, offsets) * vp.count_value, vp.splat_size // 2 + reach,
            uncounted_points(vp, states))


def batched_decayed_variance(vp: VisibilityParams, mean: Any, variance: Any, origin: Any,
                             resolution: float, states: Any, rows: Any, cols: Any,
                             offsets: tuple[tuple[int, int], ...]) -> Any:
    """Variance K trajectories meet at the cells around their footprint points, the JAX
    form (services/planner/kernels.py chooses between it and va_counts.cc).

    states (K, N+1, 6); rows/cols (K, N+1, P) int, the footprint points' cells
    (at least `max|offset|` inside the map); returns (K, N+1, len(offsets) * P),
    offset-major: block k is the cells rows + offsets[k][0], cols + offsets[k][1].
    Step i sees the points of poses 0 .. i-lag only (steps before lag: the prior);
    of each ray, the points before `uncounted_points` block it but do not count.

    The visible points of poses 0 .. N-lag are found at once, vectorised over K and
    N. Then raw count maps (visible points per cell, unsplatted; `chunk`
    trajectories side by side) go through the trajectories in turn (`lax.scan`):
    for each, a scan over the horizon adds pose i-lag's points and copies out the
    S x S patch of raw counts around each footprint cell (S = splat size + 2
    max|offset|: a slice of S contiguous rows, not S*S single lookups). After the
    horizon, one matmul turns every patch into the splatted counts at the five
    cells (splat on read). Adding before reading lets XLA update the carried maps
    in place; after the horizon the trajectories' cells are set back to zero, so
    the maps are never cleared whole.
    """
    h, w = mean.shape
    k_traj = rows.shape[0]
    reach = max(max(abs(a), abs(b)) for a, b in offsets)
    weights, pad, skip = count_inputs(vp, offsets, states)       # skip: (K, N+1)
    size = 2 * pad + 1                                           # patch side S
    hp, wp = h + 2 * pad, w + 2 * pad
    lag = vp.visibility_lag_steps
    n_steps = rows.shape[1] - 1

    qr = jnp.concatenate([rows + dr for dr, _ in offsets], axis=-1)
    qc = jnp.concatenate([cols + dc for _, dc in offsets], axis=-1)
    prior = jnp.take(variance.reshape(-1), jnp.clip(qr, 0, h - 1) * w + jnp.clip(qc, 0, w - 1))
    if lag > n_steps:                                            # nothing seen in time
        return prior

    # the patch around a footprint cell starts at the cell itself in padded coordinates
    pr = jnp.clip(rows, reach, h - 1 - reach)
    pc = jnp.clip(cols, reach, w - 1 - reach)
    weights = jnp.asarray(weights, jnp.float32)

    # poses 0 .. N-lag, read at steps lag .. N
    row, col, vis = visible_points(vp, mean, origin, resolution, states[:, :n_steps - lag + 1])
    if vp.reaction is not None:                                    # nearer points: not counted
        # point index along its ray
        k_pt = jnp.tile(jnp.arange(vp.visibility_points), vp.visibility_rays)
        vis = vis & (k_pt >= skip[:, :n_steps - lag + 1, None])
    flat = jnp.where(vis, (row + pad) * wp + col + pad, hp * wp)   # unseen: dropped

    chunk = vp.va_chunk or (8 if jax.default_backend() == "cpu" else 256)
    chunk = max(1, min(chunk, k_traj))
    n_chunks = -(-k_traj // chunk)

    def split(a):
        extra = n_chunks * chunk - k_traj
        a = jnp.concatenate([a, jnp.repeat(a[-1:], extra, axis=0)]) if extra else a
        return a.reshape((n_chunks, chunk) + a.shape[1:])

    def patches(m2, r, c):
        """The S x S patches of one padded map (hp, wp) at corners (r, c), each (P,)."""
        return jax.vmap(lambda r1, c1: jax.lax.dynamic_slice(m2, (r1, c1), (size, size)))(r, c)

    def per_chunk(maps, inp):
        """`chunk` trajectories: fl (chunk, N-lag+1, M) their poses' points, r/c
        (chunk, N+1, P)."""
        fl, r, c = inp

        def step(m, x):
            f1, r1, c1 = x                                       # (chunk, M), (chunk, P)
            m = jax.vmap(lambda mm, ff: mm.at[ff].add(1.0, mode="drop"))(m, f1)
            return m, jax.vmap(patches)(m.reshape(chunk, hp, wp), r1, c1)

        maps, pts = jax.lax.scan(step, maps, (jnp.swapaxes(fl, 0, 1),
                                              jnp.swapaxes(r[:, lag:], 0, 1),
                                              jnp.swapaxes(c[:, lag:], 0, 1)))
        n, _, n_pts = pts.shape[:3]
        # HIGHEST: exact float32 everywhere (no TF32 on a GPU), and on XLA:CPU 1.7x faster
        cnt = jnp.matmul(pts.reshape(n, chunk, n_pts, size * size), weights,
                         precision=jax.lax.Precision.HIGHEST)           # (N, chunk, P, 5)
        cnt = jnp.transpose(cnt, (1, 0, 3, 2)).reshape(chunk, n, -1)   # offset-major
        maps = jax.vmap(lambda mm, ff: mm.at[ff.reshape(-1)].set(0.0, mode="drop"))(maps, fl)
        # steps 0 .. lag-1 have seen nothing yet
        return maps, jnp.concatenate([jnp.zeros((chunk, lag) + cnt.shape[2:], cnt.dtype), cnt],
                                     axis=1)

    maps = jnp.zeros((chunk, hp * wp), jnp.float32)
    _, c = jax.lax.scan(per_chunk, maps, (split(flat), split(pr), split(pc)))
    c = c.reshape((n_chunks * chunk,) + c.shape[2:])[:k_traj]
    return prior * jnp.exp(-vp.decay_gamma * c)
