"""The planner's native CPU kernels (XLA FFI custom calls), one library:

- va_counts.cc, the visibility-aware variance update. `planner.va_kernel` chooses:
  `jax` (the vectorised form of visibility.py, every backend), `native` (this
  kernel; a CPU backend only) or `auto` (native on a CPU when it builds, else
  jax). Both compute the same variances from the same float32 cells;
  tests/test_visibility.py checks each against the dense float64 reference.
- rollout.cc, the K rollouts of the prediction model (kernels.rollout vmapped),
  chosen the same way by `planner.rollout_kernel`; tests/test_planner.py checks it
  against the JAX form and the plant's float64 model.
- surface.cc, VA-MPPI's expected surface cost (costs.surface_expectation, closed
  form) for all rollouts, used with the native visibility kernel
  (`planner.va_kernel`); tests/test_planner.py checks it against the JAX form. Its
  per-trajectory code (surface.h) also runs fused into va_counts.cc
  (`va_surface`), where the variances then never leave a thread's cache; VA-MPPI's
  iteration takes that form unless it needs the variances (`planner.crash_variance`).

The library (common/native.py builds it) is compiled next to its sources by `make`;
loading never builds it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from common import native as common_native
from common.native import Library, NativeUnavailable

LIBRARY = Library(tuple(Path(__file__).with_name(n)
                        for n in ("va_counts.cc", "rollout.cc", "surface.cc")),
                  tuple(Path(__file__).with_name(n)
                        for n in ("parallel.h", "surface.h", "vecmath.h")))
TARGETS = {"vamppi_va_counts": "VaCounts", "vamppi_rollout": "Rollout",   # FFI name: symbol
           "vamppi_surface": "Surface", "vamppi_va_surface": "VaSurface"}
_WHAT = "the native planner kernels"


@lru_cache(maxsize=1)
def _register() -> None:
    lib = LIBRARY.load()
    for name, symbol in TARGETS.items():
        jax.ffi.register_ffi_target(name, jax.ffi.pycapsule(getattr(lib, symbol)), platform="cpu")


def available() -> bool:
    """Whether the kernels can run here: a CPU backend and a library that builds and loads."""
    return jax.default_backend() == "cpu" and common_native.loads(_register, _WHAT)


def use_native(kernel: str) -> bool:
    """`planner.va_kernel` or `planner.rollout_kernel` resolved on this machine."""
    if kernel != "jax" and jax.default_backend() != "cpu":
        if kernel == "native":
            raise NativeUnavailable(f"a native planner kernel needs a CPU backend, "
                                    f"this one is {jax.default_backend()}")
        return False
    return common_native.use_native(kernel, _register, _WHAT)


def resolve(kernel: str) -> str:
    """A kernel setting (`auto`, `jax`, `native`) as the form that runs here, `jax` or
    `native`: decided once, when the parameters are built (services/planner/kernels.py)."""
    return "native" if use_native(kernel) else "jax"


def threads(requested: int) -> int:
    """`planner.va_threads` (both kernels): 0 = the cores this process may run on."""
    if requested > 0:
        return requested
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        return max(1, os.cpu_count() or 1)


@dataclass(frozen=True)
class SurfaceSpec:
    """What `va_variance` needs to return the expected surface cost instead of the
    variances (the fused kernel): expected_surface's arguments but the variance."""
    outside: Any                  # (K, T, P) 1 where a footprint point is off the map
    h0: Any                       # (K,) the ground under the vehicle now
    grad: float
    step: float
    height: float
    n_across: int


def va_variance(mean: Any, variance: Any, origin: Any, states: Any, skip: Any, rows: Any,
                cols: Any,
                offsets: tuple[tuple[int, int], ...], grid: np.ndarray, weights: np.ndarray, *,
                resolution: float, height: float, gamma: float, rays: int, points: int,
                lag: int, pad: int, n_threads: int, surface: SurfaceSpec | None = None) -> Any:
    """The variance (K, T, Q * P) each trajectory meets at its query cells: the map's
    variance times exp(-gamma C), C the splatted counts; skip (K, T): how many of each
    ray's nearest points do not count (they still block); see va_counts.cc. With
    `surface` (the five queries of costs.OFFSETS), the expected surface cost (K, T, P)
    computed from those variances instead, as `expected_surface` would (one pass)."""
    k, t, p = rows.shape
    _register()
    args = (jnp.asarray(mean, jnp.float32), jnp.asarray(variance, jnp.float32),
            jnp.asarray(origin, jnp.float32), jnp.asarray(states, jnp.float32),
            jnp.asarray(skip, jnp.int32), rows.astype(jnp.int32), cols.astype(jnp.int32),
            jnp.asarray(offsets, jnp.int32), jnp.asarray(grid, jnp.float32),
            jnp.asarray(weights, jnp.float32))
    attrs = dict(resolution=np.float32(resolution), height=np.float32(height),
                 gamma=np.float32(gamma), rays=np.int64(rays), points=np.int64(points),
                 lag=np.int64(lag), pad=np.int64(pad), threads=np.int64(n_threads))
    if surface is None:
        out = jax.ShapeDtypeStruct((k, t, weights.shape[1] * p), jnp.float32)
        return jax.ffi.ffi_call("vamppi_va_counts", out, vmap_method="sequential")(*args, **attrs)
    out = jax.ShapeDtypeStruct((k, t, p), jnp.float32)
    call = jax.ffi.ffi_call("vamppi_va_surface", out, vmap_method="sequential")
    return call(*args, surface.outside.astype(jnp.int32), jnp.asarray(surface.h0, jnp.float32),
                **attrs, **_surface_attrs(resolution, surface.grad, surface.step,
                                          surface.n_across),
                height_threshold=np.float32(surface.height))


def _surface_attrs(resolution: float, grad: float, step: float, n_across: int
                   ) -> dict[str, Any]:
    two_res = 2.0 * resolution                        # as costs.indicator_quantities has it
    return dict(two_res=np.float32(two_res), two_res2=np.float32(two_res ** 2),
                grad=np.float32(grad), step=np.float32(step), n_across=np.int64(n_across))


def expected_surface(mean: Any, rows: Any, cols: Any, outside: Any, variance: Any, h0: Any,
                     *, resolution: float, grad: float, step: float, height: float,
                     n_across: int, n_threads: int) -> Any:
    """costs.surface_expectation's closed form for K trajectories at once: the expected
    tripped indicators (K, T, P) at footprint cells rows, cols (K, T, P) and `outside`
    (costs.footprint_cells), `variance` (K, T, 5 P) met at their five query cells, h0 (K,)
    the ground under the vehicle now; see surface.cc."""
    out = jax.ShapeDtypeStruct(rows.shape, jnp.float32)
    _register()
    call = jax.ffi.ffi_call("vamppi_surface", out, vmap_method="sequential")
    return call(jnp.asarray(mean, jnp.float32), rows.astype(jnp.int32), cols.astype(jnp.int32),
                outside.astype(jnp.int32), jnp.asarray(variance, jnp.float32),
                jnp.asarray(h0, jnp.float32), height=np.float32(height),
                threads=np.int64(n_threads),
                **_surface_attrs(resolution, grad, step, n_across))


# rollout.cc's `enum Model`, entry by entry: its name there and what it holds, a field of
# the VehicleConfig or of the ControlLimits (`lo.0`: lo[0], delta; `.1`: f_xt). The one
# statement of the order: `model_enum` reads the C++ side's, and tests/test_planner.py
# checks the two name for name.
MODEL = (("kMass", "mass_kg"), ("kLf", "lf_m"), ("kLr", "lr_m"), ("kTrack", "track_m"),
         ("kB", "pacejka_b"), ("kC", "pacejka_c"), ("kD", "pacejka_d"), ("kE", "pacejka_e"),
         ("kCd", "drag_coefficient"), ("kAf", "frontal_area_m2"), ("kRho", "air_density"),
         ("kCr", "rolling_coefficient"), ("kG", "gravity"), ("kCgHeight", "cg_height_m"),
         ("kIz", "yaw_inertia_kgm2"), ("kKinBelow", "kinematic_below_mps"),
         ("kDynAbove", "dynamic_above_mps"), ("kTau", "kinematic_tau_s"),
         ("kSlipFloor", "slip_speed_floor_mps"), ("kBrakeEps", "brake_speed_eps_mps"),
         ("kSteerLo", "lo.0"), ("kForceLo", "lo.1"), ("kSteerHi", "hi.0"),
         ("kForceHi", "hi.1"), ("kSteerRate", "rate.0"), ("kForceRate", "rate.1"))


def model_enum(source: Path | None = None) -> list[str]:
    """The entries of rollout.cc's `enum Model`, in order, its closing kModelSize left out."""
    import re
    text = (source or Path(__file__).with_name("rollout.cc")).read_text()
    body = re.search(r"enum Model \{(.*?)\};", text, re.S)
    if body is None:
        raise ValueError("rollout.cc has no `enum Model { ... };`")
    names = [n.strip() for n in body[1].split(",") if n.strip()]
    if names[-1] != "kModelSize":
        raise ValueError("rollout.cc's enum Model does not end with kModelSize")
    return names[:-1]


def model_vector(vehicle: Any, limits: Any) -> np.ndarray:
    """The (26,) float32 parameters rollout.cc reads, in MODEL's order."""
    def value(what: str) -> float:
        name, _, i = what.partition(".")
        return getattr(limits, name)[int(i)] if i else getattr(vehicle, name)
    return np.asarray([value(what) for _, what in MODEL], np.float32)


def rollouts(model: np.ndarray, x0: Any, u_prev: Any, controls: Any, *, dt: float,
             substeps: int, n_threads: int) -> tuple[Any, Any, Any]:
    """K rollouts of the prediction model (rollout.cc): controls (K, N, 2) -> states
    (K, N+1, 6), applied controls (K, N, 2), dx/dt (K, N, 6), as kernels.rollout vmapped."""
    k, n, _ = controls.shape
    out = (jax.ShapeDtypeStruct((k, n + 1, 6), jnp.float32),
           jax.ShapeDtypeStruct((k, n, 2), jnp.float32),
           jax.ShapeDtypeStruct((k, n, 6), jnp.float32))
    _register()
    call = jax.ffi.ffi_call("vamppi_rollout", out, vmap_method="sequential")
    return call(jnp.asarray(model, jnp.float32), jnp.asarray(x0, jnp.float32),
                jnp.asarray(u_prev, jnp.float32), jnp.asarray(controls, jnp.float32),
                dt=np.float32(dt), substeps=np.int64(substeps), threads=np.int64(n_threads))
