"""The goal distance along a route over the map (ours, `planner.goal_distance = "route"`).

The analytic goal distance (`geometry.goal_path_length`: the shortest forward path into
the goal circle at the vehicle's tightest turn) knows nothing of the map. Where an
occluder hides the goal it points a rollout at ground the camera has never seen, often
beside the vehicle where the camera cannot look, and VA-MPPI, which may not drive fast
where it has not seen in time, waits at the edge of what it has seen (docs/analysis.md,
"The creep").

With the route, the goal distance is that analytic one plus a *detour*: how much dearer
the route to the goal circle is on the map than on empty ground, both on one lattice of
poses (x, y, heading): `route_cell_m` apart, 16 headings, each move an arc of 22.5
degrees at the vehicle's tightest turn or a straight piece as long. A move costs its
length times the mean cost per metre of the lattice cells it crosses:

- closed (infinite) where the map shows an obstacle (an axis gradient or a step to a
  neighbour past Eq. occupied's thresholds, grown by half the footprint's width less half
  a lattice cell and the one map cell the gradient marks beside a face, on more than a
  quarter of the cell) and within half the footprint's length of the map's edge;
- for VA-MPPI only, on ground the map has never observed (variance at the prior):
  `route_unseen_factor` driven straight, `route_unseen_turn_factor` turning (a vehicle
  that drives straight onto unseen ground has seen it ahead first; one that turns onto it
  meets it beside itself, out of the camera's view). The deterministic and prescient
  controllers take their map as certain, as they plan (`mppi.map_view`);
- 1 elsewhere.

The detour is capped at `route_cap_m` (also where the map shows no route). On open
ground it is zero, and the lattice's rounding, the same in both routes, cancels.

The map's route is found by value iteration from a lower bound, the empty lattice's
cost-to-go; that depends on the goal only through its cell, so one empty field twice the
map's size and a margin, computed once, serves every goal. Each of `route_sweeps` sweeps
relaxes every pose over its three moves: after k sweeps a pose's value is exact for
routes of up to k moves and a lower bound beyond (k = 40: 83 m). All of it is JAX, traced
into the solve; tests/test_route.py holds it to a float64 Dijkstra over the same lattice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from common.config import Config, by_name
from common.geometry import turning_radius
from services.plant.dynamics import S

HEADINGS = 16


@dataclass(frozen=True)
class RouteParams:
    """Named as their keys of `[planner]` (docs/parameters.md), the derived ones commented."""
    route_cell_m: float             # lattice spacing (a multiple of the map's resolution)
    route_unseen_factor: float      # cost per metre of unseen ground driven straight (VA-MPPI)
    route_unseen_turn_factor: float  # ... turning on it
    route_cap_m: float              # the longest detour priced
    route_sweeps: int               # value-iteration sweeps
    radius_m: float                 # derived: the tightest turn, (lf + lr) / tan(steer_max)
    goal_radius_m: float            # [episode]
    half_width_m: float             # derived: obstacles grown by half the footprint's width
    half_length_m: float            # derived: the map's edge, by half the footprint's length
    grad_threshold: float           # derived: Eq. occupied's |gradient| threshold
    step_threshold: float           # derived: Eq. occupied's |step| threshold, m
    unseen_variance: float          # [mapper] prior_variance: a cell never observed

    @classmethod
    def from_config(cls, cfg: Config) -> RouteParams:
        p, v = cfg.planner, cfg.vehicle
        return by_name(cls, p, radius_m=turning_radius(v.lf_m + v.lr_m, v.steer_max_rad),
                       goal_radius_m=cfg.episode.goal_radius_m,
                       half_width_m=v.footprint_width_m / 2 + p.footprint_margin_m,
                       half_length_m=v.footprint_length_m / 2 + p.footprint_margin_m,
                       grad_threshold=float(np.sqrt(p.grad_sq_threshold)),
                       step_threshold=float(np.sqrt(p.step_sq_threshold)),
                       unseen_variance=cfg.mapper.prior_variance)


def _step(p: RouteParams) -> float:
    return p.radius_m * 2.0 * math.pi / HEADINGS


@lru_cache(maxsize=8)
def moves(p: RouteParams) -> tuple[tuple[tuple[int, int, int, tuple[tuple[int, int], ...]],
                                         ...], ...]:
    """Per heading bin h (heading h 2 pi / 16 from +x), its three moves (straight, left,
    right): (end heading bin, end row offset, end column offset, the cells at a quarter,
    half, three quarters and all of the move), in lattice cells."""
    dth = 2.0 * math.pi / HEADINGS
    fr = np.array([0.25, 0.5, 0.75, 1.0])
    out = []
    for h in range(HEADINGS):
        th = h * dth
        row = []
        for turn in (0, 1, -1):
            if turn == 0:
                dx, dy = fr * _step(p) * math.cos(th), fr * _step(p) * math.sin(th)
            else:
                a = turn * fr * dth
                dx = turn * p.radius_m * (np.sin(th + a) - math.sin(th))
                dy = -turn * p.radius_m * (np.cos(th + a) - math.cos(th))
            cells = tuple(zip(np.round(dy / p.route_cell_m).astype(int).tolist(),
                              np.round(dx / p.route_cell_m).astype(int).tolist(), strict=True))
            row.append(((h + turn) % HEADINGS, cells[-1][0], cells[-1][1], cells))
        out.append(tuple(row))
    return tuple(out)


def _reach(p: RouteParams) -> int:
    return max(max(abs(r), abs(c)) for row in moves(p) for _, _, _, cs in row for r, c in cs)


def _shift(a: Any, dr: int, dc: int, reach: int) -> Any:
    """From `a` padded by `reach` on every side, the unpadded size shifted by (dr, dc):
    b[..., i, j] = a[..., reach + i + dr, reach + j + dc]."""
    n, m = a.shape[-2] - 2 * reach, a.shape[-1] - 2 * reach
    return a[..., reach + dr:reach + dr + n, reach + dc:reach + dc + m]


def edge_costs(p: RouteParams, cost: Any, turn_cost: Any, xp: Any = jnp) -> Any:
    """(16, 3, n, n): each move's length times the mean cost per metre of the cells it
    crosses; `cost`, `turn_cost` (n, n) per metre for straight moves and arcs."""
    r = _reach(p)
    pads = [xp.pad(c, r, constant_values=np.inf) for c in (cost, turn_cost)]
    return xp.stack([xp.stack([
        sum(_shift(pads[min(a, 1)], dr, dc, r) for dr, dc in cells) * (_step(p) / len(cells))
        for a, (_, _, _, cells) in enumerate(row)]) for row in moves(p)])


def relax(p: RouteParams, vp: Any, edges: Any, target: Any, xp: Any = jnp) -> Any:
    """One value-iteration sweep: every pose's cost-to-go (16, n, n) over its best move, 0 on
    target, from the field `vp` padded by `_reach` with inf (off the lattice)."""
    r = _reach(p)
    best = []
    for h, row in enumerate(moves(p)):
        m = None
        for a, (h2, dr, dc, _) in enumerate(row):
            x = edges[h, a] + _shift(vp[h2], dr, dc, r)
            m = x if m is None else xp.minimum(m, x)
        best.append(m)
    return xp.where(target, 0.0, xp.stack(best))


def target_cells(p: RouteParams, n: int, goal_cell: Any, xp: Any = jnp) -> Any:
    """(n, n) bool: lattice cells whose centre lies in the goal circle drawn round the
    centre of the goal's cell."""
    i = xp.arange(n)
    di = (i[:, None] - goal_cell[0]) * p.route_cell_m
    dj = (i[None, :] - goal_cell[1]) * p.route_cell_m
    return di * di + dj * dj <= max(p.goal_radius_m, 0.5 * p.route_cell_m) ** 2


def _margin(p: RouteParams) -> int:
    """Lattice cells round the empty field's window within which a pose may not be able to
    turn back before the field's edge: two turning circles and a move."""
    return int(math.ceil(2.0 * p.radius_m / p.route_cell_m)) + _reach(p) + 1


@lru_cache(maxsize=8)
def empty_field(p: RouteParams, n: int) -> np.ndarray:
    """Cost-to-go (16, 2 (n + margin) - 1, ...) float32 on an empty lattice to a goal at its
    centre cell, exact (swept to convergence, float64). Any n x n window that holds the
    centre cell lies `_margin` cells inside its edges, so no pose of it is cut off."""
    size = 2 * (n + _margin(p)) - 1
    c = n + _margin(p) - 1
    target = target_cells(p, size, (c, c), np)
    ones = np.ones((size, size))
    edges = edge_costs(p, ones, ones, np)
    r = _reach(p)
    vp = np.full((HEADINGS, size + 2 * r, size + 2 * r), np.inf)
    v = vp[:, r:-r, r:-r]
    v[...] = np.where(target, 0.0, np.inf)
    # relax's sweep, min(v, relax(p, vp, edges, target, np)), in place: the same sums and
    # minima (so the same bits; tests/test_route.py), 1.4-1.9 times as fast without
    # its temporaries. Every process that plans with the route pays it once, at its start
    new, tmp = np.empty_like(v), np.empty((size, size))
    while True:
        for h, row in enumerate(moves(p)):
            np.copyto(new[h], v[h])
            for a, (h2, dr, dc, _) in enumerate(row):
                np.add(edges[h, a], _shift(vp[h2], dr, dc, r), out=tmp)
                np.minimum(new[h], tmp, out=new[h])
        new[:, target] = 0.0
        if np.array_equal(new, v):
            return v.astype(np.float32)
        v[...] = new


def lattice_costs(p: RouteParams, mean: Any, variance: Any | None, resolution: float
                  ) -> tuple[Any, Any]:
    """Cost per metre (n, n) of each lattice cell for straight moves and for arcs."""
    k = int(round(p.route_cell_m / resolution))
    h, w = mean.shape
    n = min(h, w) // k
    t_g, t_s = p.grad_threshold, p.step_threshold
    gx = jnp.abs(mean[:, 2:] - mean[:, :-2]) > 2.0 * resolution * t_g
    gy = jnp.abs(mean[2:] - mean[:-2]) > 2.0 * resolution * t_g
    sx = jnp.abs(jnp.diff(mean, axis=1)) > t_s
    sy = jnp.abs(jnp.diff(mean, axis=0)) > t_s
    closed = (jnp.pad(gx, ((0, 0), (1, 1))) | jnp.pad(gy, ((1, 1), (0, 0)))
              | jnp.pad(sx, ((0, 0), (1, 0))) | jnp.pad(sy, ((1, 0), (0, 0))))
    closed = closed.astype(jnp.float32)
    # grown by the half width less what the marking and the lattice already add: the
    # central gradient marks the ground cell beside a face, and a lattice cell is shut
    # when a quarter of it is, so the whole half width shut passages the footprint fits
    # through (docs/planner.md). An octagon, the union of a (2g+1) x (2d+1) box and its
    # transpose, each a max over rows then over columns (a box's max is separable; with
    # 2-D windows this function took 4.6 times as long)
    g = int(round(max(p.half_width_m - 0.5 * p.route_cell_m - resolution, 0.0) / resolution))
    d = int(round(g / math.sqrt(2.0)))

    def run_max(a: Any, n: int, axis: int) -> Any:
        window = (2 * n + 1, 1) if axis == 0 else (1, 2 * n + 1)
        return jax.lax.reduce_window(a, 0.0, jax.lax.max, window, (1, 1), "SAME")
    grown = jnp.maximum(run_max(run_max(closed, g, 0), d, 1),
                        run_max(run_max(closed, d, 0), g, 1))
    shut = grown[:n * k, :n * k].reshape(n, k, n, k).mean(axis=(1, 3)) > 0.25
    # a pose nearer the map's edge than half the footprint's length has it off the map
    e = int(math.ceil(p.half_length_m / p.route_cell_m - 0.5))
    i = jnp.arange(n)
    rim = (i < e) | (i >= n - e)
    base = jnp.where(shut | rim[:, None] | rim[None, :], jnp.inf, 1.0)
    if variance is None:
        return base, base
    unseen = (variance[:n * k, :n * k] >= p.unseen_variance).reshape(n, k, n, k).mean(
        axis=(1, 3)) > 0.5
    return (jnp.where(unseen, base * p.route_unseen_factor, base),
            jnp.where(unseen, base * p.route_unseen_turn_factor, base))


def detour(p: RouteParams, mean: Any, variance: Any | None, origin: Any, resolution: float,
           goal: Any) -> Any:
    """How much longer (16, n, n) float32 than on empty ground the route from each lattice
    pose to the goal circle is on this map (`variance` None: unseen ground as seen),
    between 0 and `route_cap_m`; pose (h, i, j) is heading h 2 pi / 16 at the centre of
    cell (i, j), `route_cell_m` square from `origin`."""
    cost, turn_cost = lattice_costs(p, mean, variance, resolution)
    n = cost.shape[0]
    goal_cell = jnp.floor((goal[1::-1] - origin[::-1]) / p.route_cell_m).astype(jnp.int32)
    goal_cell = jnp.clip(goal_cell, 0, n - 1)
    c = n + _margin(p) - 1
    free = jax.lax.dynamic_slice(jnp.asarray(empty_field(p, n)),
                                 (0, c - goal_cell[0], c - goal_cell[1]), (HEADINGS, n, n))
    target = target_cells(p, n, goal_cell)
    edges = edge_costs(p, cost, turn_cost)
    bound = free + p.route_cap_m
    r = _reach(p)

    def body(_, vp):
        return vp.at[:, r:r + n, r:r + n].set(jnp.minimum(relax(p, vp, edges, target), bound))

    vp = jax.lax.fori_loop(0, p.route_sweeps, body,
                           jnp.pad(free, ((0, 0), (r, r), (r, r)), constant_values=np.inf))
    return jnp.clip(vp[:, r:r + n, r:r + n] - free, 0.0, p.route_cap_m)


def lookup(p: RouteParams, field: Any, origin: Any, states: Any) -> Any:
    """The detour at poses `states` (..., 6): bilinear over the lattice cells' centres,
    linear between the two nearest heading bins."""
    n = field.shape[-1]
    fx = (states[..., S.X] - origin[0]) / p.route_cell_m - 0.5
    fy = (states[..., S.Y] - origin[1]) / p.route_cell_m - 0.5
    fh = jnp.mod(states[..., S.PSI] * (HEADINGS / (2.0 * math.pi)), HEADINGS)
    x0 = jnp.clip(jnp.floor(fx), 0, n - 2)
    y0 = jnp.clip(jnp.floor(fy), 0, n - 2)
    h0 = jnp.floor(fh)
    ax, ay, ah = jnp.clip(fx - x0, 0.0, 1.0), jnp.clip(fy - y0, 0.0, 1.0), fh - h0
    x0, y0 = x0.astype(jnp.int32), y0.astype(jnp.int32)
    h0 = h0.astype(jnp.int32) % HEADINGS

    def plane(h):
        return ((1 - ay) * ((1 - ax) * field[h, y0, x0] + ax * field[h, y0, x0 + 1])
                + ay * ((1 - ax) * field[h, y0 + 1, x0] + ax * field[h, y0 + 1, x0 + 1]))

    return (1 - ah) * plane(h0) + ah * plane((h0 + 1) % HEADINGS)
