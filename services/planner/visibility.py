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
seen from poses 0 .. i-1. A scan over the horizon carries the trajectory's raw
(unsplatted) count map: step i adds pose i-1's visible points, then reads the
splatted count at step i's query cells (a 9 x 9 window per cell). Memory: one
padded map per trajectory of a chunk (`va_chunk`), never K full maps at once,
plus the visible points of every pose (K x (N+1) x 600 indices).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from common.config import Config
from services.plant.dynamics import S


@dataclass(frozen=True)
class VisibilityParams:
    rays: int                  # N_theta (Table II): 20
    points: int                # N_r (Table II): 30
    ray_min_m: float           # 2 m (text)
    ray_max_m: float           # 25 m (Table II)
    fov_rad: float             # 72 degrees (Table II)
    height_m: float            # threshold visibility height h
    count_value: float         # c of Eq. count_increase
    splat_size: int            # 9 (text)
    splat_sigma_cells: float   # 1 (text)
    gamma: float               # 0.3 (Table II)
    mount_forward_m: float     # rays start at the camera
    chunk: int                 # trajectories per chunk (memory bound); 0 = auto

    @classmethod
    def from_config(cls, cfg: Config) -> VisibilityParams:
        p = cfg.planner
        return cls(p.visibility_rays, p.visibility_points, p.visibility_min_m,
                   p.visibility_max_m, math.radians(cfg.sensor.hfov_deg), p.visibility_height_m,
                   p.count_value, p.splat_size, p.splat_sigma_cells, p.decay_gamma,
                   cfg.sensor.mount_forward_m, p.va_chunk)

    def ray_grid(self) -> np.ndarray:
        """Body-frame offsets (rays * points, 2) of the ray points from the CG."""
        ang = np.linspace(-self.fov_rad / 2, self.fov_rad / 2, self.rays)
        rng = np.linspace(self.ray_min_m, self.ray_max_m, self.points)
        a, r = np.meshgrid(ang, rng, indexing="ij")            # (rays, points)
        pts = np.stack([self.mount_forward_m + r * np.cos(a), r * np.sin(a)], axis=-1)
        return pts.reshape(-1, 2)

    def kernel(self) -> np.ndarray:
        """G of Eq. gaussian, (size, size), 1/(2 pi s^2) exp(-(x^2 + y^2) / 2 s^2)."""
        h = self.splat_size // 2
        o = np.arange(-h, h + 1)
        x, y = np.meshgrid(o, o, indexing="xy")
        s2 = self.splat_sigma_cells ** 2
        return np.exp(-(x * x + y * y) / (2 * s2)) / (2 * np.pi * s2)


def visible_points(vp: VisibilityParams, mean: Any, origin: Any, resolution: float,
                   state: Any) -> tuple[Any, Any, Any]:
    """Ray points of one pose: (row, col) int (M,), visible (M,) bool; M = rays * points."""
    h, w = mean.shape
    grid = jnp.asarray(vp.ray_grid(), jnp.float32)
    c, s = jnp.cos(state[S.PSI]), jnp.sin(state[S.PSI])
    px = state[S.X] + c * grid[:, 0] - s * grid[:, 1]
    py = state[S.Y] + s * grid[:, 0] + c * grid[:, 1]
    col = jnp.floor((px - origin[0]) / resolution).astype(jnp.int32)
    row = jnp.floor((py - origin[1]) / resolution).astype(jnp.int32)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    elev = mean[jnp.clip(row, 0, h - 1), jnp.clip(col, 0, w - 1)]
    vr = jnp.clip(jnp.floor((state[S.Y] - origin[1]) / resolution).astype(jnp.int32), 0, h - 1)
    vc = jnp.clip(jnp.floor((state[S.X] - origin[0]) / resolution).astype(jnp.int32), 0, w - 1)
    blocker = (elev > mean[vr, vc] + vp.height_m) | ~inside      # off the map blocks too
    blocker = blocker.reshape(vp.rays, vp.points)
    before = jnp.cumsum(blocker, axis=1) - blocker                # blockers strictly before
    visible = (before == 0).reshape(-1) & inside
    return row, col, visible


def batched_decayed_variance(vp: VisibilityParams, mean: Any, variance: Any, origin: Any,
                             resolution: float, states: Any, rows: Any, cols: Any) -> Any:
    """Variance K trajectories meet at their query cells: states (K, N+1, 6), rows/cols
    (K, N+1, Q) int, step-major; step i's queries see the points of poses 0 .. i-1 only.

    Every pose's visible points are found at once, vectorised over K and N. Then,
    per trajectory, a scan over the horizon carries its raw count map: step i adds
    pose i-1's points, then reads step i's query cells through a 9 x 9 window
    (splat on read). Adding before reading lets XLA update the carried map in
    place (reading first made it copy the map every step). Trajectories go
    `chunk` at a time (`lax.map` over chunks, `vmap` within).
    """
    h, w = mean.shape
    pad = vp.splat_size // 2
    wp = w + 2 * pad
    kern = jnp.asarray(vp.kernel(), jnp.float32)
    off = jnp.arange(-pad, pad + 1)
    window = off[:, None] * wp + off[None, :]                    # (size, size) flat offsets

    row, col, vis = jax.vmap(jax.vmap(
        lambda st: visible_points(vp, mean, origin, resolution, st)))(states)   # (K, N+1, M)
    flat = (row + pad) * wp + col + pad
    add = jnp.where(vis, jnp.float32(vp.count_value), 0.0)
    flat = jnp.concatenate([jnp.zeros_like(flat[:, :1]), flat[:, :-1]], axis=1)  # pose i-1
    add = jnp.concatenate([jnp.zeros_like(add[:, :1]), add[:, :-1]], axis=1)
    qr, qc = jnp.clip(rows, 0, h - 1), jnp.clip(cols, 0, w - 1)
    centre = (qr + pad) * wp + qc + pad
    prior = variance[qr, qc]

    def one(fl, ad, ce, q):
        def step(counts, inp):
            f1, a1, c1 = inp
            counts = counts.at[f1].add(a1, mode="drop")
            return counts, jnp.sum(counts[c1[:, None, None] + window] * kern, axis=(1, 2))

        _, c_splat = jax.lax.scan(step, jnp.zeros(((h + 2 * pad) * wp,), jnp.float32),
                                  (fl, ad, ce))
        return q * jnp.exp(-vp.gamma * c_splat)

    k = states.shape[0]
    chunk = vp.chunk or (1 if jax.default_backend() == "cpu" else 256)
    chunk = max(1, min(chunk, k))
    n_chunks = -(-k // chunk)

    def split(a):
        extra = n_chunks * chunk - k
        a = jnp.concatenate([a, jnp.repeat(a[-1:], extra, axis=0)]) if extra else a
        return a.reshape((n_chunks, chunk) + a.shape[1:])

    out = jax.lax.map(lambda args: jax.vmap(one)(*args),
                      (split(flat), split(add), split(centre), split(prior)))
    return out.reshape((n_chunks * chunk,) + out.shape[2:])[:k]


def decayed_variance(vp: VisibilityParams, mean: Any, variance: Any, origin: Any,
                     resolution: float, states: Any, rows: Any, cols: Any) -> Any:
    """`batched_decayed_variance` for one trajectory: states (N+1, 6), rows/cols (N+1, Q)."""
    return batched_decayed_variance(vp, mean, variance, origin, resolution, states[None],
                                    rows[None], cols[None])[0]
