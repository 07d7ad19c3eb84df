"""Geometry shared by the services: angles, grid cells, bilinear lookups.

Functions take `xp` (numpy or jax.numpy) where both the NumPy plant/sensor
references and the JAX planner/mapper need them, so the formula lives once.

Grid convention: a map of shape (H, W) with `origin` = world (x, y) of the
corner of cell (0, 0) and square cells of `resolution` m; row index follows y,
column index follows x; a cell's value is the height at the cell centre.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def wrap_angle(a: Any, xp: Any = np) -> Any:
    """Angle(s) to [-pi, pi)."""
    return (a + xp.pi) % (2.0 * xp.pi) - xp.pi


def world_to_grid(x: Any, y: Any, origin: Any, resolution: float) -> tuple[Any, Any]:
    """Continuous (col, row) coordinates whose integer values are cell centres."""
    return (x - origin[0]) / resolution - 0.5, (y - origin[1]) / resolution - 0.5


def cell_of(x: Any, y: Any, origin: Any, resolution: float, xp: Any = np) -> tuple[Any, Any]:
    """Integer (row, col) of the cell containing (x, y); may be out of range."""
    col = xp.floor((x - origin[0]) / resolution).astype(xp.int32)
    row = xp.floor((y - origin[1]) / resolution).astype(xp.int32)
    return row, col


def bilinear(grid: Any, x: Any, y: Any, origin: Any, resolution: float, xp: Any = np) -> Any:
    """Bilinear interpolation of `grid` at world points, clamped at the border."""
    h, w = grid.shape
    gc, gr = world_to_grid(x, y, origin, resolution)
    gc = xp.clip(gc, 0.0, w - 1.0)
    gr = xp.clip(gr, 0.0, h - 1.0)
    c0 = xp.clip(xp.floor(gc).astype(xp.int32), 0, w - 2)
    r0 = xp.clip(xp.floor(gr).astype(xp.int32), 0, h - 2)
    fc, fr = gc - c0, gr - r0
    v00, v01 = grid[r0, c0], grid[r0, c0 + 1]
    v10, v11 = grid[r0 + 1, c0], grid[r0 + 1, c0 + 1]
    return (v00 * (1 - fc) + v01 * fc) * (1 - fr) + (v10 * (1 - fc) + v11 * fc) * fr


def footprint_points(length: float, width: float, n_across: int, n_arrays: int = 2
                     ) -> np.ndarray:
    """`n_arrays` arrays of `n_across` points spanning the width, evenly spaced from the
    front edge to the rear edge (2: the paper's front and rear arrays), in the body
    frame: shape (n_arrays * n_across, 2) of (forward, left) offsets, array-major."""
    ys = np.linspace(-width / 2.0, width / 2.0, n_across)
    xs = np.linspace(length / 2.0, -length / 2.0, n_arrays)
    return np.concatenate([np.stack([np.full(n_across, x), ys], axis=-1) for x in xs]
                          ).astype(np.float64)


def footprint_grid(length: float, width: float, spacing: float) -> np.ndarray:
    """Points filling the footprint rectangle at about `spacing` m, body frame, (P, 2)."""
    nx = max(2, int(np.ceil(length / spacing)) + 1)
    ny = max(2, int(np.ceil(width / spacing)) + 1)
    gx, gy = np.meshgrid(np.linspace(-length / 2, length / 2, nx),
                         np.linspace(-width / 2, width / 2, ny), indexing="ij")
    return np.stack([gx.ravel(), gy.ravel()], axis=-1)


def body_to_world(points: Any, x: Any, y: Any, yaw: Any, xp: Any = np) -> tuple[Any, Any]:
    """Body-frame (forward, left) points to world x, y; broadcasts over poses."""
    c, s = xp.cos(yaw), xp.sin(yaw)
    px, py = points[..., 0], points[..., 1]
    return x + c * px - s * py, y + s * px + c * py


def turning_radius(wheelbase: float, steer_max: float) -> float:
    """The tightest radius the kinematic bicycle can turn at: wheelbase / tan(steer limit)."""
    return float(wheelbase / np.tan(steer_max))


def _arc(a: Any, xp: Any) -> Any:
    """A turning angle to [0, 2 pi), with the last 1e-4 rad folded to 0: a point dead
    ahead must not cost a full circle because rounding put it a hair to the other side."""
    a = a % (2.0 * xp.pi)
    return xp.where(a > 2.0 * xp.pi - 1e-4, 0.0 * a, a)


def _turn_then_straight(px: Any, py: Any, r: float, xp: Any) -> Any:
    """Length of a left arc then a straight line to the body-frame point (px, py), inf
    where the point lies inside the left turning circle (centre (0, r))."""
    qx, qy = px, py - r
    d2 = qx * qx + qy * qy
    t = xp.sqrt(xp.maximum(d2 - r * r, 0.0))
    theta = _arc(xp.arctan2(qy, qx) - xp.arctan2(t, xp.zeros_like(t) + r) + xp.pi / 2.0, xp)
    return xp.where(d2 >= r * r, r * theta + t, xp.inf)


# the second arc's centre distances `_turn_then_turn` tries (the path it finds is up to
# 1.12 of their spacing, 2 reach / (TURN_DISTANCES - 1), long: tests/test_geometry.py)
TURN_DISTANCES = 17


def _turn_then_turn(px: Any, py: Any, r: float, reach: float, xp: Any,
                    n: int = TURN_DISTANCES) -> Any:
    """Length of a right arc then a left arc until it first comes within `reach` of
    (px, py) (`reach` = 0: until it reaches the point), inf where no such path exists.
    The second arc's centre lies 2 r from the right circle's centre (0, -r) and, for
    it to enter the disk, between r - reach and r + reach from the point: `n` distances
    across that span, each with its two centres, and the shortest of them. The distances
    are a leading axis, not a loop, so that a traced program holds one copy of the
    construction (68 copies took more than half of the planner's compile time)."""
    px, py = xp.asarray(px), xp.asarray(py)
    # (a disk wider than the turn, reach > r: the distances start at 0, not below)
    rho = (np.linspace(max(r - reach, 0.0), r + reach, n) if reach > 0.0 else np.array([r]))
    lead = (len(rho),) + (1,) * px.ndim              # the distances lead: (n, *px.shape)
    dtype = xp.result_type(px, 1.0)
    rho2 = xp.asarray((rho * rho).reshape(lead), dtype)
    with np.errstate(divide="ignore"):
        cos_d = (r * r + rho * rho - reach * reach) / (2.0 * r * rho)
    enter = xp.asarray(np.arccos(np.clip(cos_d, -1.0, 1.0)).reshape(lead), dtype)
    qx, qy = px, py + r
    q = xp.maximum(xp.sqrt(qx * qx + qy * qy), 1e-9)
    gamma = xp.arctan2(qx, qy)
    k = (q * q + 4.0 * r * r - rho2) / (4.0 * r * q)
    spread = xp.arccos(xp.clip(k, -1.0, 1.0))

    def through(a: Any) -> Any:
        sa, ca = xp.sin(a), xp.cos(a)
        cx, cy = 2.0 * r * sa, -r + 2.0 * r * ca           # centre of the second arc
        tau = xp.arctan2(py - cy, px - cx) - xp.arctan2(-ca, -sa)
        b = xp.minimum(_arc(tau - enter, xp), _arc(tau + enter, xp))
        return xp.where(xp.abs(k) <= 1.0, r * (a + b), xp.inf)

    both = xp.minimum(through(_arc(gamma - spread, xp)), through(_arc(gamma + spread, xp)))
    return xp.min(both, axis=0)


def _arc_into(px: Any, py: Any, r: float, reach: float, xp: Any) -> Any:
    """Length of a left arc alone until it first comes within `reach` of (px, py), inf
    where the left turning circle misses that disk."""
    qx, qy = px, py - r
    dc = xp.maximum(xp.sqrt(qx * qx + qy * qy), 1e-9)
    cos_d = (r * r + dc * dc - reach * reach) / (2.0 * r * dc)
    spread = xp.arccos(xp.clip(cos_d, -1.0, 1.0))
    phi = xp.arctan2(qy, qx) + xp.pi / 2.0
    theta = xp.minimum(_arc(phi - spread, xp), _arc(phi + spread, xp))
    return xp.where(xp.abs(cos_d) <= 1.0, r * theta, xp.inf)


def dubins_to_point(dx: Any, dy: Any, yaw: Any, radius: float, xp: Any = np) -> Any:
    """Length of the shortest forward path with curvature at most 1 / `radius` from a pose
    heading `yaw` to the point `(dx, dy)` away from it (world frame), any final heading:
    the least of the four paths that can be shortest (Bui, Soueres, Boissonnat and
    Laumond 1994): a left or right arc then a straight line, or an arc then an arc the
    other way. Equals the straight-line distance for a point dead ahead."""
    c, s = xp.cos(yaw), xp.sin(yaw)
    px, py = c * dx + s * dy, c * dy - s * dx
    return xp.minimum(xp.minimum(_turn_then_straight(px, py, radius, xp),
                                 _turn_then_straight(px, -py, radius, xp)),
                      xp.minimum(_turn_then_turn(px, py, radius, 0.0, xp),
                                 _turn_then_turn(px, -py, radius, 0.0, xp)))


def goal_path_length(dx: Any, dy: Any, yaw: Any, radius: float, reach: float,
                     xp: Any = np) -> Any:
    """The distance to a goal `(dx, dy)` away for a vehicle heading `yaw` that cannot turn
    tighter than `radius`: the length of a forward path into the goal's circle of radius
    `reach`, plus `reach`, so that it is the straight-line distance for a goal dead ahead
    and never less than it. The path is the shortest of: an arc alone, or the shortest
    path to the goal's centre (`dubins_to_point`) cut where it enters the circle (the
    last `reach` of a straight, the last chord `reach` of an arc). Inside the circle it
    is the straight-line distance."""
    c, s = xp.cos(yaw), xp.sin(yaw)
    px, py = c * dx + s * dy, c * dy - s * dx
    straight = xp.minimum(_turn_then_straight(px, py, radius, xp),
                          _turn_then_straight(px, -py, radius, xp)) - reach
    turns = xp.minimum(_turn_then_turn(px, py, radius, reach, xp),
                       _turn_then_turn(px, -py, radius, reach, xp))
    arcs = xp.minimum(_arc_into(px, py, radius, reach, xp), _arc_into(px, -py, radius, reach, xp))
    path = xp.maximum(xp.minimum(xp.minimum(straight, turns), arcs), 0.0)
    euclid = xp.sqrt(px * px + py * py)
    return xp.where(euclid <= reach, euclid, xp.maximum(path + reach, euclid))
