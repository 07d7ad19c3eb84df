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

d is the straight-line distance to the goal in the paper; ours by default is the length
of the shortest path the vehicle can drive into the goal circle (`goal_distance`).

Readings of the paper's open symbols are in docs/planner.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from common.config import Config, by_name
from common.geometry import footprint_points, goal_path_length, turning_radius, wrap_angle
from services.planner import route
from services.planner.fastmath import FAST
from services.plant.dynamics import Reaction, S, accelerations

TERMS = ("time", "dynamic", "surface", "dist", "acc", "orientation")


@dataclass(frozen=True)
class CostParams:
    """The cost's parameters, named as their keys of `[planner]` (docs/parameters.md), the
    derived ones commented."""
    dt_s: float
    horizon: int
    w_time: float
    w_dynamic: float
    w_surface: float
    w_dist: float
    w_acc: float
    w_orientation: float
    activation_distance_m: float
    time_speed_floor_mps: float
    acc_distance_floor_m: float
    grad_threshold: float          # derived: |gradient| threshold = sqrt(grad_sq_threshold)
    step_threshold: float          # derived: |step| threshold, m = sqrt(step_sq_threshold)
    height_threshold_m: float
    a_roll_mps2: float
    a_max_mps2: float
    beta_max_rad: float
    v_lat_max_mps: float
    footprint: tuple[tuple[float, float], ...]   # derived: (P, 2) body frame, front array first
    footprint_points: int          # points per footprint array, across the width
    surface_estimator: str         # closed_form | monte_carlo
    surface_samples: int           # N_theta of the Monte-Carlo estimate
    crash_variance: float          # absorbing crash on cells known this well; 0 = off
    surface_distance_m: float      # per-step surface weight V dt / this; 0 = off (plain sum)
    turn_radius: float             # derived: the goal distance along a path this tight; 0 =
                                   # straight line (goal_distance)
    turn_radius_speed: bool        # ... or no tighter than V^2 / D g at the pose's speed V
    goal_radius_m: float           # [episode]: ... into the goal circle of this radius
    stop_poses: int                # the surface cost also prices this many poses of the
    stop: Reaction                 # derived: ... way to a stop from the horizon's end; 0 = off
    time_cost: str                 # instants (the paper's d/V at 2, 3, 4 s) | running (every step)
    route: route.RouteParams | None  # derived: goal_distance = "route"'s lattice; None: not that

    @classmethod
    def from_config(cls, cfg: Config) -> CostParams:
        p, v = cfg.planner, cfg.vehicle
        margin = 2.0 * p.footprint_margin_m
        fp = footprint_points(v.footprint_length_m + margin, v.footprint_width_m + margin,
                              p.footprint_points, p.footprint_arrays)
        return by_name(cls, p, cfg.episode,
                       grad_threshold=float(np.sqrt(p.grad_sq_threshold)),
                       step_threshold=float(np.sqrt(p.step_sq_threshold)),
                       footprint=tuple(map(tuple, fp.tolist())),
                       turn_radius=turning_radius(v.lf_m + v.lr_m, v.steer_max_rad)
                       if p.goal_distance != "straight" else 0.0,
                       route=(route.RouteParams.from_config(cfg)
                              if p.goal_distance == "route" else None),
                       stop=Reaction.from_config(v))


def exceed_prob(mean: Any, var: Any, threshold: Any) -> Any:
    """P(|X| > threshold) for X ~ N(mean, var); the plain indicator where var == 0.

    1 + (erf(a) + erf(b)) / 2 with a, b the two tails' standardised distances: XLA
    evaluates erf as a rational polynomial (vector code), erfc (what `ndtr` uses)
    element by element; 3.4x faster on the whole surface cost. Probabilities below
    about 1e-7 round to 0, which a cost does not feel."""
    s = jnp.sqrt(jnp.maximum(var, 0.0))
    inv = jnp.where(s > 0, 1.0 / jnp.where(s > 0, s * np.sqrt(2.0), 1.0), 0.0)
    p = 1.0 + 0.5 * (jax.lax.erf((-threshold - mean) * inv)
                     + jax.lax.erf((mean - threshold) * inv))
    return jnp.where(s > 0, jnp.clip(p, 0.0, 1.0), (jnp.abs(mean) > threshold).astype(mean.dtype))


@dataclass(frozen=True)
class MapView:
    """What the cost sees of the map: mean and variance grids (H, W) and placement, and the
    detour (16, n, n) of `goal_distance = "route"` on it (`route.detour`; None: none)."""
    mean: Any
    variance: Any
    origin: Any          # (2,)
    resolution: float
    detour: Any = None


def footprint_world(c: CostParams, states: Any) -> tuple[Any, Any]:
    """World x, y of the footprint points along a rollout: (N+1, P) each."""
    fp = jnp.asarray(c.footprint, jnp.float32)
    psi = states[:, S.PSI]
    # cos and sin materialised, one per step: XLA:CPU otherwise fuses their polynomials into
    # every consumer and evaluates them again for each of the 5 P cells a step reads (2.8 of
    # the deterministic iteration's 20.7 ms at K = 800, measured when this was written).
    # Multiplying by the identity is exact and is a dot, which no elementwise fusion crosses
    # (XLA:CPU expands optimization_barrier before fusing).
    cs = jnp.dot(jnp.stack([FAST.cos(psi), FAST.sin(psi)], axis=-1), jnp.eye(2, dtype=jnp.float32),
                 precision=jax.lax.Precision.HIGHEST)
    cos, sin = cs[:, 0, None], cs[:, 1, None]
    px, py = fp[:, 0], fp[:, 1]
    return (states[:, S.X, None] + cos * px - sin * py,
            states[:, S.Y, None] + sin * px + cos * py)


# the five cells read per footprint point: centre, +x, -x, +y, -y (row, col offsets)
OFFSETS = ((0, 0), (0, 1), (0, -1), (1, 0), (-1, 0))


def footprint_cells(c: CostParams, m: MapView, states: Any) -> tuple[Any, Any, Any]:
    """The cells of the footprint points along a rollout: row, col (N+1, P) int, kept
    one cell inside the map, and `outside` (N+1, P), points off the map."""
    h, w = m.mean.shape
    px, py = footprint_world(c, states)
    col = jnp.floor((px - m.origin[0]) / m.resolution).astype(jnp.int32)
    row = jnp.floor((py - m.origin[1]) / m.resolution).astype(jnp.int32)
    outside = (col < 1) | (col > w - 2) | (row < 1) | (row > h - 2)
    return jnp.clip(row, 1, h - 2), jnp.clip(col, 1, w - 2), outside


def five_cells(grid: Any, row: Any, col: Any) -> Any:
    """grid at the five cells of every footprint point (`OFFSETS`), (..., 5 P) offset-major,
    from the points' own cells row, col (..., P) (`footprint_cells`), kept one cell inside
    the grid. One gather of five neighbours stacked per cell, not five gathers:
    XLA:CPU pays per gathered index, so this is the same values at about a fifth of the
    cost."""
    h, w = grid.shape
    padded = jnp.pad(grid, 1, mode="edge")
    stacked = jnp.stack([padded[1 + dr:1 + dr + h, 1 + dc:1 + dc + w] for dr, dc in OFFSETS],
                        axis=-1)
    vals = stacked[row, col]                                  # (..., P, 5)
    return jnp.reshape(jnp.swapaxes(vals, -1, -2), vals.shape[:-2] + (5 * vals.shape[-2],))


def _split5(a: Any, n_pts: int) -> list[Any]:
    return [a[:, k * n_pts:(k + 1) * n_pts] for k in range(5)]


def indicator_quantities(c: CostParams, m: MapView, h: Any, n_pts: int, h0: Any) -> list[Any]:
    """The five quantities of Eq. occupied from cell values `h` (..., N+1, 5 P):
    x and y gradient, x (temporal) and y (across-array) step, height against x_0."""
    h_c, h_px, h_mx, h_py, h_my = (h[..., k * n_pts:(k + 1) * n_pts] for k in range(5))
    two_res = 2.0 * m.resolution
    zero = jnp.zeros_like(h_c[..., :1, :])
    first = (jnp.arange(n_pts) % c.footprint_points) == 0
    return [(h_px - h_mx) / two_res, (h_py - h_my) / two_res,
            jnp.concatenate([zero, h_c[..., 1:, :] - h_c[..., :-1, :]], axis=-2),
            jnp.where(first, 0.0, h_c - jnp.roll(h_c, 1, axis=-1)), h_c - h0]


def surface_expectation(c: CostParams, m: MapView, row: Any, col: Any, outside: Any,
                        query_var: Any, h0: Any, key: Any = None) -> Any:
    """Expected number of tripped indicators at each footprint point, (N+1, P).

    `row, col, outside` (N+1, P) from `footprint_cells`; `query_var` (N+1, 5 P) the
    variance the rollout meets at each point's five cells (`five_cells`; zero for the
    deterministic and prescient controllers, visibility-decayed for VA-MPPI); `h0` the
    ground under the vehicle now. Cells are independent Gaussians. `closed_form`: each
    quantity is a difference of independent Gaussians, P(|X| > t) from the normal CDF.
    `monte_carlo` (the paper's N_theta samples, needs `key`): every looked-up cell drawn
    independently, the indicators averaged.
    """
    n_pts = outside.shape[1]
    mu = five_cells(m.mean, row, col)
    thresholds = (c.grad_threshold, c.grad_threshold, c.step_threshold, c.step_threshold,
                  c.height_threshold_m)
    if c.surface_estimator == "monte_carlo":
        batch = 50

        def draw(total, k):
            z = jax.random.normal(k, (batch,) + mu.shape, mu.dtype)
            q = indicator_quantities(c, m, mu + jnp.sqrt(query_var) * z, n_pts, h0)
            hits = sum((jnp.abs(x) > t).astype(jnp.float32)
                       for x, t in zip(q, thresholds, strict=True))
            return total + jnp.sum(hits, axis=0), None

        keys = jax.random.split(key, -(-c.surface_samples // batch))
        total, _ = jax.lax.scan(draw, jnp.zeros(outside.shape, jnp.float32), keys)
        expected = total / (keys.shape[0] * batch)
    else:
        means = indicator_quantities(c, m, mu, n_pts, h0)
        v_c, v_px, v_mx, v_py, v_my = _split5(query_var, n_pts)
        two_res2 = (2.0 * m.resolution) ** 2
        zero = jnp.zeros_like(v_c[:1])
        first = (jnp.arange(n_pts) % c.footprint_points) == 0
        variances = [(v_px + v_mx) / two_res2, (v_py + v_my) / two_res2,
                     jnp.concatenate([zero, v_c[1:] + v_c[:-1]]),
                     jnp.where(first, 0.0, v_c + jnp.roll(v_c, 1, axis=1)), v_c]
        expected = sum(exceed_prob(mq, vq, t)
                       for mq, vq, t in zip(means, variances, thresholds, strict=True))
    return jnp.where(outside, 5.0, expected)


def absorbing_crash(c: CostParams, expected: Any, query_var: Any) -> Any:
    """A collision ends the rollout (not in the paper; `crash_variance`, docs/planner.md).

    `expected` (N+1, P) from `surface_expectation`, `query_var` (N+1, 5 P). A step
    crashes where some footprint point expects at least half an indicator on a
    cell whose variance is below `crash_variance` (a known obstacle, not fog);
    from the first crash on, every step pays all 5 P indicators, as a vehicle
    stopped by the obstacle would for the rest of the horizon. Off (the paper's
    plain sum over steps) when `crash_variance` is 0.
    """
    if c.crash_variance <= 0.0:
        return expected
    n_pts = expected.shape[1]
    known = query_var[:, :n_pts] < c.crash_variance       # the centre cells, OFFSETS[0]
    hit = jnp.any((expected >= 0.5) & known, axis=1)
    steps = jnp.arange(hit.shape[0])                  # a min, not a cumsum (slow on XLA:CPU)
    crashed = steps >= jnp.min(jnp.where(hit, steps, hit.shape[0]))
    return jnp.where(crashed[:, None], 5.0, expected)


def priced_poses(c: CostParams, states: Any) -> Any:
    """The poses the surface cost prices, (..., N+1+B, 6): the rollout's, then `stop_poses`
    = B poses along the way it would brake to a stop from its last one (straight on, the
    model's stopping distance after one control tick: `Reaction.stopping`), at 1/B, 2/B,
    ... of that distance, with the speed braking leaves there. A rollout may then not end
    the horizon faster than the ground it has seen lets it stop; without them nothing
    past the horizon's end is priced (docs/planner.md)."""
    b = c.stop_poses
    if b <= 0:
        return states
    last = states[..., -1:, :]
    v = jnp.maximum(last[..., S.V], 0.0)
    frac = jnp.arange(1, b + 1, dtype=jnp.float32) / b
    along = c.stop.stopping(v, c.dt_s, jnp) * frac
    psi = last[..., S.PSI]
    ext = jnp.broadcast_to(last, last.shape[:-2] + (b, last.shape[-1]))
    ext = ext.at[..., S.X].set(last[..., S.X] + along * jnp.cos(psi))
    ext = ext.at[..., S.Y].set(last[..., S.Y] + along * jnp.sin(psi))
    ext = ext.at[..., S.V].set(v * jnp.sqrt(1.0 - frac))
    return jnp.concatenate([states, ext], axis=-2)


def goal_distance(c: CostParams, states: Any, goal: Any, xp: Any = jnp,
                  m: MapView | None = None) -> Any:
    """d of the time, distance and stop terms at poses `states` (..., 6): the straight
    line to the goal (the paper's), or with `turn_radius` the length of the shortest
    forward path into the goal circle at that radius (`geometry.goal_path_length`): a
    goal beside or behind the vehicle is as far as the turn it takes to get there (with
    `turn_radius_speed` the turn the tyres allow at the pose's speed, the radius and the
    goal circle scaled by k = max(1, V^2 / (D g turn_radius)): k times the path at
    `turn_radius` to a goal k times nearer); with
    `route` and a map `m` with its detour, that plus the detour the map asks for
    (services/planner/route.py)."""
    dx, dy = goal[0] - states[..., S.X], goal[1] - states[..., S.Y]
    if c.turn_radius <= 0.0:
        return xp.sqrt(dx * dx + dy * dy)
    if c.turn_radius_speed:
        # the tightest turn's path scaled by k: a path of radius k R (its goal circle k times
        # as wide too), the same length for a goal dead ahead
        v = states[..., S.V]
        k = xp.maximum(v * v / (c.stop.lateral_accel_mps2 * c.turn_radius), 1.0)
        d = k * goal_path_length(dx / k, dy / k, states[..., S.PSI], c.turn_radius,
                                 c.goal_radius_m, xp)
    else:
        d = goal_path_length(dx, dy, states[..., S.PSI], c.turn_radius, c.goal_radius_m, xp)
    if c.route is None or m is None or m.detour is None:
        return d
    return d + route.lookup(c.route, m.detour, m.origin, states)


RUNNING_KNOT_STEPS = 4         # the running time cost's d: every 4th step (0.4 s), linear between


def _running_knots(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The steps where the running time cost evaluates d (every `RUNNING_KNOT_STEPS`-th and
    the last, n) and the (n + 1, knots) weights of the linear interpolation between them."""
    knots = np.unique(np.append(np.arange(0, n + 1, RUNNING_KNOT_STEPS), n))
    steps = np.arange(n + 1)
    weights = np.stack([np.interp(steps, knots, np.eye(len(knots))[k])
                        for k in range(len(knots))], axis=1)
    return knots, weights.astype(np.float32)


def time_cost(c: CostParams, states: Any, goal: Any, m: MapView) -> tuple[Any, Any, Any]:
    """Eq. time_cost of one rollout (N+1, 6), and d now and at the horizon's end (the
    distance and stop terms read them). `instants`, the paper's: w_t (d20/(4 V20) +
    d30/(2 V30) + dN/VN). `running` (ours): w_t 7/4 mean(d_i / V_i) over steps 1 .. N, the
    same total weight spread evenly. At 2, 3 and 4 s only, a plan that stands now and
    drives later pays nothing for standing, and its speed at 4 s is what counts: where the
    ground it may drive on in time ends a few metres on, the cheapest plan waits so that it
    reaches that edge fast, and a receding horizon waits again every tick (docs/analysis.md,
    "The creep"). Every step's d/V makes standing cost d/V_floor a step, more where the goal
    is farther. V below `time_speed_floor_mps` counts as that floor. The running cost
    takes d at every `RUNNING_KNOT_STEPS`-th step and the last, linear between, with the
    vectorised trig (`FAST`): d at all N + 1 steps was two thirds of a K = 1000 solve."""
    n = c.horizon
    V = jnp.maximum(states[:, S.V], c.time_speed_floor_mps)
    if c.time_cost == "running":
        knots, weights = _running_knots(n)
        d = jnp.dot(jnp.asarray(weights), goal_distance(c, states[knots], goal, FAST, m),
                    precision=jax.lax.Precision.HIGHEST)
        return c.w_time * 1.75 * jnp.mean(d[1:] / V[1:]), d[0], d[n]
    i2, i3 = int(round(2.0 / c.dt_s)), int(round(3.0 / c.dt_s))
    d0, d2, d3, dn = goal_distance(c, states[jnp.array([0, i2, i3, n])], goal, m=m)
    return c.w_time * (d2 / (4 * V[i2]) + d3 / (2 * V[i3]) + dn / V[n]), d0, dn


def per_metre_weight(c: CostParams, V: Any, xp: Any = jnp) -> Any:
    """The weight of each step's expected surface indicators when `surface_distance` > 0:
    the distance the vehicle covers in the step, |V| dt, over that length (docs/planner.md)."""
    return xp.abs(V) * (c.dt_s / c.surface_distance_m)


def ground_now(m: MapView, states: Any) -> Any:
    """x_0 of Eq. occupied: the mean elevation of the cell under the CG now (i = 0)."""
    h, w = m.mean.shape
    r = jnp.clip(jnp.floor((states[0, S.Y] - m.origin[1]) / m.resolution).astype(jnp.int32),
                 0, h - 1)
    c = jnp.clip(jnp.floor((states[0, S.X] - m.origin[0]) / m.resolution).astype(jnp.int32),
                 0, w - 1)
    return m.mean[r, c]


def rollout_cost(c: CostParams, states: Any, xdots: Any, goal: Any, m: MapView,
                 query_var: Any, key: Any = None, expected: Any = None) -> Any:
    """Cost terms (6,) of one rollout: states (N+1, 6), dx/dt (N, 6), goal (3,),
    `query_var` (T, 5 P) the variance met at the cells of `five_cells` on the T =
    N+1+B `priced_poses` (None when
    `expected` is given and `crash_variance` is 0: nothing reads it); `key` for the
    Monte-Carlo surface estimate; `expected` (T, P) the surface expectation where the
    caller has it already (VA-MPPI's native kernels), else computed here."""
    n = c.horizon
    V = states[:, S.V]
    s_time, d0, dn = time_cost(c, states, goal, m)

    _, a_y, a_tot = accelerations(states[:-1], xdots, jnp)
    beta = FAST.arctan2(states[:-1, S.v], jnp.maximum(states[:-1, S.V], 0.5))
    s_dyn = c.w_dynamic * jnp.sum(
        (jnp.abs(a_y) >= c.a_roll_mps2).astype(jnp.float32) + (a_tot >= c.a_max_mps2)
        + (jnp.abs(beta) >= c.beta_max_rad) + (jnp.abs(states[:-1, S.v]) >= c.v_lat_max_mps))

    priced = priced_poses(c, states)
    if expected is None:
        row, col, outside = footprint_cells(c, m, priced)
        expected = surface_expectation(c, m, row, col, outside, query_var,
                                       ground_now(m, states), key)
    per_step = absorbing_crash(c, expected, query_var)
    if c.surface_distance_m > 0.0:
        # a cell priced per metre crossed: a slower or stopped rollout does not pay again
        # for every tenth of a second it spends on the same cells
        per_step = per_step * per_metre_weight(c, priced[:, S.V])[:, None]
    s_surf = c.w_surface * jnp.sum(per_step)

    phi = jax.nn.sigmoid(2.0 * (c.activation_distance_m - d0))
    ratio = dn / jnp.maximum(d0, 1e-3)
    s_dist = c.w_dist * (ratio + 2.0 * phi * ratio)
    s_acc = c.w_acc * V[n] ** 2 * jnp.abs(V[n]) / (2.0 * jnp.maximum(dn, c.acc_distance_floor_m))
    psi_w = jnp.arange(n + 1, dtype=jnp.float32) / n
    s_or = c.w_orientation * phi * jnp.sum(
        jnp.abs(wrap_angle(states[:, S.PSI] - goal[2], jnp)) * psi_w)
    return jnp.stack([s_time, s_dyn, s_surf, s_dist, s_acc, s_or])
