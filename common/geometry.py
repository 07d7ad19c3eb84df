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
