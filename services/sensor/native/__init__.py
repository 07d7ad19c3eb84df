"""The sensor's native CPU ray caster (render.cc, a plain C function called with ctypes).

`sensor.render_kernel` chooses: `jax` (render_depth in core.py, every backend), `native`
(this kernel) or `auto` (native where it builds, else jax). Both march the same float32
rays over the same bilinear heightmap; tests/test_sensor.py checks each against a float64
brute-force march and the two against each other.
"""

from __future__ import annotations

import ctypes
from functools import lru_cache
from pathlib import Path

import numpy as np

from common import native as common_native
from common.native import Library

LIBRARY = Library((Path(__file__).with_name("render.cc"),))

_F32P = np.ctypeslib.ndpointer(np.float32, flags="C_CONTIGUOUS")


@lru_cache(maxsize=1)
def _function() -> ctypes._CFuncPtr:
    f = LIBRARY.load().vamppi_render_depth
    f.restype = ctypes.c_int
    f.argtypes = [_F32P, ctypes.c_int64, ctypes.c_int64, _F32P, ctypes.c_float, _F32P, _F32P,
                  _F32P, ctypes.c_int64, ctypes.c_float, ctypes.c_float, ctypes.c_int64, _F32P]
    return f


def available() -> bool:
    """Whether the kernel builds and loads here (tried once per process)."""
    return common_native.loads(_function, "the native ray caster")


def use_native(kernel: str) -> bool:
    """`sensor.render_kernel` resolved on this machine."""
    return common_native.use_native(kernel, _function, "the native ray caster")


def render_depth(heightmap: np.ndarray, origin: np.ndarray, resolution: float,
                 cam_position: np.ndarray, cam_rotation: np.ndarray, dirs_cam: np.ndarray, *,
                 range_m: float, step_m: float, refine: int) -> np.ndarray:
    """z-depth (R,) float32 of each camera-frame ray `dirs_cam` (R, 3); 0 = no return."""
    f32 = lambda a: np.ascontiguousarray(a, np.float32)   # noqa: E731
    hm, dirs = f32(heightmap), f32(dirs_cam)
    depth = np.empty(dirs.shape[0], np.float32)
    rc = _function()(hm, hm.shape[0], hm.shape[1], f32(origin), resolution, f32(cam_position),
                     f32(cam_rotation), dirs, dirs.shape[0], range_m, step_m, refine, depth)
    if rc != 0:
        raise ValueError(f"render_depth: bad arguments (heightmap {hm.shape}, step {step_m}, "
                         f"range {range_m}, refine {refine})")
    return depth
