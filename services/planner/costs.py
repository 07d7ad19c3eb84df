"""The paper's cost terms for one rollout (JAX, vmapped over samples by the caller).

Terms, by the paper's equation labels:
  time_cost    S_t = w_t (d20/(4 V20) + d30/(2 V30) + dN/VN)
  S_dynamic    indicators of lateral accel > a_roll, total accel > a_max,
               |side slip| > beta_max, |lateral velocity| > v_max
  occupied     the expected surface cost: at every footprint point, the
               probability, under the per-cell Gaussian map, of each of the five
               indicators (x and y gradient, x and y step change, height against
               the CG); with zero variance it is the indicator itself
  distance     S_dist = w_dist (dN/d0 + 2 phi_G dN/d0)
  stop         S_acc = w_acc V_N^2 |V_N| / (2 d_N)
  direction    S_orientation = w_o phi_G sum_i |Psi_i - Psi_G| psi_i

Readings of the paper's open symbols are in docs/planner.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from common.config import Config
from common.geometry import body_to_world, footprint_points, wrap_angle
from services.plant.dynamics import S, accelerations

TERMS = ("time", "dynamic", "surface", "dist", "acc", "orientation")


@dataclass(frozen=True)
class CostParams:
    dt: float
    horizon: int
    w_time: float
    w_dynamic: float
    w_surface: float
    w_dist: float
    w_acc: float
    w_orientation: float
    activation_distance_m: float
    time_speed_floor: float
    acc_distance_floor: float
    grad_threshold: float          # |gradient| threshold = sqrt(grad_sq_threshold)
    step_threshold: float          # |step| threshold, m = sqrt(step_sq_threshold)
    height_threshold: float
    a_roll: float
    a_max: float
    beta_max: float
    v_lat_max: float
    footprint: tuple[tuple[float, float], ...]   # (P, 2) body frame: front array, rear array
    n_across: int

    @classmethod
    def from_config(cls, cfg: Config) -> CostParams:
        p, v = cfg.planner, cfg.vehicle
        fp = footprint_points(v.footprint_length_m, v.footprint_width_m, p.footprint_points)
        return cls(p.dt_s, p.horizon, p.w_time, p.w_dynamic, p.w_surface, p.w_dist, p.w_acc,
                   p.w_orientation, p.activation_distance_m, p.time_speed_floor_mps,
                   p.acc_distance_floor_m, float(np.sqrt(p.grad_sq_threshold)),
                   float(np.sqrt(p.step_sq_threshold)), p.height_threshold_m, p.a_roll_mps2,
                   p.a_max_mps2, p.beta_max_rad, p.v_lat_max_mps,
                   tuple(map(tuple, fp.tolist())), p.footprint_points)


def exceed_prob(mean: Any, var: Any, threshold: float) -> Any:
    """P(|X| > threshold) for X ~ N(mean, var); the plain indicator where var == 0."""
    s = jnp.sqrt(jnp.maximum(var, 0.0))
    safe = jnp.where(s > 0, s, 1.0)
    p = (jax.scipy.special.ndtr((-threshold - mean) / safe)
         + jax.scipy.special.ndtr((mean - threshold) / safe))
    return jnp.where(s > 0, p, (jnp.abs(mean) > threshold).astype(mean.dtype))


@dataclass(frozen=True)
class MapView:
    """What the cost sees of the map: mean and variance grids (H, W) and placement."""
    mean: Any
    variance: Any
    origin: Any          # (2,)
    resolution: float


def footprint_world(c: CostParams, states: Any) -> tuple[Any, Any]:
    """World x, y of the footprint points along a rollout: (N+1, P) each."""
    fp = jnp.asarray(c.footprint, jnp.float32)
    return body_to_world(fp, states[:, S.X, None], states[:, S.Y, None], states[:, S.PSI, None],
                         jnp)


def surface_expectation(c: CostParams, m: MapView, px: Any, py: Any, variance_at: Any) -> Any:
    """Expected number of tripped indicators at each footprint point, (N+1, P).

    `px, py` (N+1, P) are the footprint points; `variance_at(row, col)` gives the
    variance the rollout meets there (the map's, or a visibility-updated one).
    """
    h, w = m.mean.shape
    col = jnp.floor((px - m.origin[0]) / m.resolution).astype(jnp.int32)
    row = jnp.floor((py - m.origin[1]) / m.resolution).astype(jnp.int32)
    outside = (col < 1) | (col > w - 2) | (row < 1) | (row > h - 2)
    col = jnp.clip(col, 1, w - 2)
    row = jnp.clip(row, 1, h - 2)
    mu, var = m.mean, variance_at
    mu_c, var_c = mu[row, col], var(row, col)
    # axis gradients by central differences over neighbouring cells (independent cells)
    two_res = 2.0 * m.resolution
    gx_m = (mu[row, col + 1] - mu[row, col - 1]) / two_res
    gx_v = (var(row, col + 1) + var(row, col - 1)) / two_res ** 2
    gy_m = (mu[row + 1, col] - mu[row - 1, col]) / two_res
    gy_v = (var(row + 1, col) + var(row - 1, col)) / two_res ** 2
    # step changes: temporally along the horizon (X), across each footprint array (Y)
    zero_row = jnp.zeros_like(mu_c[:1])
    sx_m = jnp.concatenate([zero_row, mu_c[1:] - mu_c[:-1]])
    sx_v = jnp.concatenate([zero_row, var_c[1:] + var_c[:-1]])
    n = c.n_across
    first = (jnp.arange(mu_c.shape[1]) % n) == 0
    prev_m = jnp.roll(mu_c, 1, axis=1)
    prev_v = jnp.roll(var_c, 1, axis=1)
    sy_m = jnp.where(first, 0.0, mu_c - prev_m)
    sy_v = jnp.where(first, 0.0, var_c + prev_v)
    # height against the CG's ground now (x_0): the cell under the vehicle at i = 0
    h0 = mu[jnp.clip(jnp.floor((jnp.mean(px[0]) - m.origin[0]) / m.resolution).astype(jnp.int32),
                     0, w - 1),
            jnp.clip(jnp.floor((jnp.mean(py[0]) - m.origin[1]) / m.resolution).astype(jnp.int32),
                     0, h - 1)]
    total = (exceed_prob(gx_m, gx_v, c.grad_threshold)
             + exceed_prob(gy_m, gy_v, c.grad_threshold)
             + exceed_prob(sx_m, sx_v, c.step_threshold)
             + exceed_prob(sy_m, sy_v, c.step_threshold)
             + exceed_prob(mu_c - h0, var_c, c.height_threshold))
    return jnp.where(outside, 5.0, total)


def rollout_cost(c: CostParams, states: Any, xdots: Any, goal: Any, m: MapView,
                 variance_at: Any) -> Any:
    """Cost terms (6,) of one rollout: states (N+1, 6), dx/dt (N, 6), goal (3,).

    `variance_at(row, col)` gives the variance this rollout meets at those
    cells (the map's own for deterministic/prescient; the visibility-updated one
    for VA-MPPI).
    """
    n = c.horizon
    d = jnp.hypot(states[:, S.X] - goal[0], states[:, S.Y] - goal[1])
    V = states[:, S.V]
    i2, i3 = int(round(2.0 / c.dt)), int(round(3.0 / c.dt))
    vf = c.time_speed_floor
    s_time = c.w_time * (d[i2] / (4 * jnp.maximum(V[i2], vf)) + d[i3] / (2 * jnp.maximum(V[i3], vf))
                         + d[n] / jnp.maximum(V[n], vf))

    _, a_y, a_tot = accelerations(states[:-1], xdots, jnp)
    beta = jnp.arctan2(states[:-1, S.v], jnp.maximum(states[:-1, S.V], 0.5))
    s_dyn = c.w_dynamic * jnp.sum(
        (jnp.abs(a_y) >= c.a_roll).astype(jnp.float32) + (a_tot >= c.a_max)
        + (jnp.abs(beta) >= c.beta_max) + (jnp.abs(states[:-1, S.v]) >= c.v_lat_max))

    px, py = footprint_world(c, states)
    s_surf = c.w_surface * jnp.sum(surface_expectation(c, m, px, py, variance_at))

    d0 = d[0]
    phi = jax.nn.sigmoid(2.0 * (c.activation_distance_m - d0))
    ratio = d[n] / jnp.maximum(d0, 1e-3)
    s_dist = c.w_dist * (ratio + 2.0 * phi * ratio)
    s_acc = c.w_acc * V[n] ** 2 * jnp.abs(V[n]) / (2.0 * jnp.maximum(d[n], c.acc_distance_floor))
    psi_w = jnp.arange(n + 1, dtype=jnp.float32) / n
    s_or = c.w_orientation * phi * jnp.sum(
        jnp.abs(wrap_angle(states[:, S.PSI] - goal[2], jnp)) * psi_w)
    return jnp.stack([s_time, s_dyn, s_surf, s_dist, s_acc, s_or])
