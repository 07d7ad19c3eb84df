"""The sensor's pure core: a forward depth camera by dense 3D ray casting.

A pinhole camera (square pixels, horizontal FOV `hfov_deg`) mounted
`mount_height_m` above the ground under the CG, `mount_forward_m` ahead of it,
pitched down by `mount_pitch_deg`, yawed with the vehicle (the model is
planar, so no roll or terrain pitch). Every pixel's ray is marched over the
ground-truth heightmap (bilinear surface) in steps of `march_step_m` up to
`range_m` along the ray; the first step below the surface is refined by the
secant between the last two samples. The image holds z-depth (along the
optical axis); 0 marks no return within range or off the map.

Camera frame: x right, y down, z forward (OpenCV). `cam_rotation` maps camera
to world coordinates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache, partial

import jax
import jax.numpy as jnp
import numpy as np

from common.config import SensorConfig, by_name
from common.geometry import bilinear
from services.sensor import native


@dataclass(frozen=True)
class CameraParams:
    """Named as their keys of `[sensor]` (docs/parameters.md), the derived ones commented."""
    width_px: int
    height_px: int
    fx: float                   # derived: the pinhole focal lengths and centre, pixels
    fy: float
    cx: float
    cy: float
    range_m: float
    mount_height_m: float
    mount_forward_m: float
    pitch_rad: float            # derived: mount_pitch_deg
    march_step_m: float
    render_kernel: str = "auto"  # auto | jax | native

    @classmethod
    def from_config(cls, s: SensorConfig) -> CameraParams:
        fx = (s.width_px / 2.0) / math.tan(math.radians(s.hfov_deg) / 2.0)
        return by_name(cls, s, fx=fx, fy=fx, cx=(s.width_px - 1) / 2.0,
                       cy=(s.height_px - 1) / 2.0, pitch_rad=math.radians(s.mount_pitch_deg))

    @property
    def intrinsics(self) -> np.ndarray:
        return np.array([self.fx, self.fy, self.cx, self.cy])


def camera_pose(p: CameraParams, x: float, y: float, z: float, yaw: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """World position (3,) and camera-to-world rotation (3, 3) for a vehicle pose."""
    cy, sy = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(p.pitch_rad), math.sin(p.pitch_rad)
    fwd = np.array([cy * cp, sy * cp, -sp])          # optical axis, pitched down
    right = np.array([sy, -cy, 0.0])                 # vehicle right
    down = np.cross(fwd, right)                      # completes x right, y down, z fwd
    rot = np.stack([right, down, fwd], axis=1)
    pos = np.array([x + p.mount_forward_m * cy, y + p.mount_forward_m * sy,
                    z + p.mount_height_m])
    return pos, rot


@lru_cache(maxsize=8)
def ray_directions(p: CameraParams) -> np.ndarray:
    """Unit ray directions in the camera frame, (H, W, 3) float64 (read-only)."""
    u, v = np.meshgrid(np.arange(p.width_px), np.arange(p.height_px), indexing="xy")
    d = np.stack([(u - p.cx) / p.fx, (v - p.cy) / p.fy, np.ones_like(u, dtype=float)], axis=-1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    d.flags.writeable = False
    return d


REFINE_STEPS = 8     # bisections of the crossing step (0.1 m / 2^8 = 0.4 mm), then a secant


@partial(jax.jit, static_argnames=("p", "resolution"))
def render_depth(p: CameraParams, heightmap: jax.Array, origin: jax.Array, resolution: float,
                 cam_position: jax.Array, cam_rotation: jax.Array) -> jax.Array:
    """Depth image (H, W) float32 of the heightmap seen from the camera pose."""
    dirs_cam = jnp.asarray(ray_directions(p), jnp.float32).reshape(-1, 3)
    dirs = dirs_cam @ jnp.asarray(cam_rotation, jnp.float32).T          # (R, 3) world
    o = jnp.asarray(cam_position, jnp.float32)
    h, w = heightmap.shape
    lo = jnp.asarray(origin, jnp.float32)
    hi = lo + jnp.array([w, h], jnp.float32) * resolution
    n_steps = int(math.ceil(p.range_m / p.march_step_m))

    def height_gap(t):
        pts = o + t[:, None] * dirs
        inside = ((pts[:, 0] >= lo[0]) & (pts[:, 0] < hi[0])
                  & (pts[:, 1] >= lo[1]) & (pts[:, 1] < hi[1]))
        ground = bilinear(heightmap, pts[:, 0], pts[:, 1], lo, resolution, jnp)
        return pts[:, 2] - ground, inside

    def body(carry, i):
        t_prev, gap_prev, t_lo, t_hi = carry
        t = jnp.minimum((i + 1) * p.march_step_m, p.range_m) * jnp.ones_like(t_prev)
        gap, inside = height_gap(t)
        crossing = (gap <= 0.0) & (gap_prev > 0.0) & inside & jnp.isnan(t_hi)
        t_lo = jnp.where(crossing, t_prev, t_lo)       # the first step that ends below
        t_hi = jnp.where(crossing, t, t_hi)
        # once a ray leaves the map it can no longer hit anything
        gap = jnp.where(inside, gap, jnp.inf)
        return (t, gap, t_lo, t_hi), None

    t0 = jnp.zeros(dirs.shape[0], jnp.float32)
    gap0, inside0 = height_gap(t0)
    gap0 = jnp.where(inside0, gap0, jnp.inf)
    nan = jnp.full(dirs.shape[0], jnp.nan, jnp.float32)
    (_, _, t_lo, t_hi), _ = jax.lax.scan(body, (t0, gap0, nan, nan), jnp.arange(n_steps))
    # the crossing bisected inside its step, then the secant across what is left:
    # at a steep face (a block's side is a 0.2 m bilinear ramp) a secant over the
    # whole step is centimetres off; on a plane the final secant is exact
    found = ~jnp.isnan(t_hi)
    t_lo, t_hi = jnp.where(found, t_lo, 0.0), jnp.where(found, t_hi, 0.0)

    def bisect(_, bracket):
        t_lo, t_hi = bracket
        mid = 0.5 * (t_lo + t_hi)
        above = height_gap(mid)[0] > 0.0
        return jnp.where(above, mid, t_lo), jnp.where(above, t_hi, mid)

    # a loop, not unrolled: unrolled, XLA fused each step's lookups with every
    # step before it and a frame took 4.5x longer than the whole march
    t_lo, t_hi = jax.lax.fori_loop(0, REFINE_STEPS, bisect, (t_lo, t_hi))
    g_lo, g_hi = height_gap(t_lo)[0], height_gap(t_hi)[0]
    frac = jnp.clip(g_lo / jnp.maximum(g_lo - g_hi, 1e-12), 0.0, 1.0)
    hit = jnp.where(found, t_lo + frac * (t_hi - t_lo), jnp.nan)
    depth = jnp.where(jnp.isnan(hit), 0.0, hit * dirs_cam[:, 2])
    return depth.reshape(p.height_px, p.width_px).astype(jnp.float32)


def render(p: CameraParams, heightmap: np.ndarray, origin: tuple[float, float], resolution: float,
           x: float, y: float, z: float, yaw: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth (H, W) float32, cam_position, cam_rotation) for a vehicle pose, by the
    native ray caster or the JAX form (`p.render_kernel`)."""
    pos, rot = camera_pose(p, x, y, z, yaw)
    if native.use_native(p.render_kernel):
        depth = native.render_depth(heightmap, np.asarray(origin), resolution, pos, rot,
                                    ray_directions(p).reshape(-1, 3), range_m=p.range_m,
                                    step_m=p.march_step_m, refine=REFINE_STEPS)
        return depth.reshape(p.height_px, p.width_px), pos, rot
    depth = render_depth(p, heightmap, jnp.asarray(origin, jnp.float32), float(resolution),
                         jnp.asarray(pos, jnp.float32), jnp.asarray(rot, jnp.float32))
    return np.asarray(depth), pos, rot


def return_points(p: CameraParams, depth: np.ndarray, pos: np.ndarray, rot: np.ndarray
                  ) -> np.ndarray:
    """World x, y, z (M, 3) of every return of a depth image (0 = no return)."""
    dirs = ray_directions(p).reshape(-1, 3)
    d = np.asarray(depth, dtype=np.float64).reshape(-1)
    hit = d > 0
    t = d[hit] / dirs[hit, 2]                        # z-depth -> distance along the ray
    return pos + (dirs[hit] @ rot.T) * t[:, None]
