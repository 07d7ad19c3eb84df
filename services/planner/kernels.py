"""The planner's kernels, each exposed once, its form chosen here and nowhere else.

    rollouts        K rollouts of the prediction model (the plant's own model)
    query_variance  the variance each rollout meets at its cost's query cells: VA-MPPI's
                    visibility-aware update (zero for the other two controllers)
    surface_terms   that variance and VA-MPPI's expected surface cost, together

Each has two forms that compute the same numbers from the same float32 inputs: `jax`
(vectorised JAX, every backend: rollout vmapped, visibility.batched_decayed_variance,
costs.surface_expectation) and `native` (services/planner/native: C++ through XLA FFI on
a CPU). The settings `planner.rollout_kernel` and `planner.va_kernel` say `auto`, `jax` or
`native`; `native.resolve` turns them into a form when the parameters are built
(PlannerParams.from_config, VisibilityParams.from_config), so nothing is decided, loaded or
built while a solve is traced. What remains for trace time are the shapes the native
kernels take (`native_variance`), and which of the expected surface cost's forms runs
(`surface_form`). mppi.py calls these functions without knowing which form runs;
tests/test_planner.py and tests/test_visibility.py hold each form to a float64 reference
and to the other.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from services.planner import native
from services.planner.costs import OFFSETS, MapView, footprint_cells, ground_now, priced_poses
from services.planner.fastmath import FAST
from services.planner.params import PlannerParams
from services.planner.visibility import (
    VisibilityParams,
    batched_decayed_variance,
    count_inputs,
)
from services.plant.dynamics import clamp_control, derivatives, rk4_step


# ----------------------------------------------------------------------------- rollouts
def rollout(params: PlannerParams, x0: jax.Array, u_prev: jax.Array, controls: jax.Array
            ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """One sample, the JAX form: states (N+1, 6), applied controls (N, 2), dx/dt at each
    step (N, 6). The plant's own model, with vectorisable arctan/sin/cos (`fastmath.FAST`)."""
    def body(carry, v):
        x, u_last = carry
        u = clamp_control(v, u_last, params.limits, params.dt_s, jnp)
        xdot = derivatives(params.vehicle, x, u, FAST)
        x_next = jax.lax.fori_loop(0, params.substeps,
                                   lambda _, x: rk4_step(params.vehicle, x, u, h, FAST), x)
        return (x_next, u), (x_next, u, xdot)

    # the plant's `integrate`, its substeps as a loop: one copy of the model in the
    # program instead of `substeps` (compiling took 4 s longer with them unrolled)
    h = params.dt_s / params.substeps

    _, (xs, us, xdots) = jax.lax.scan(body, (x0, u_prev), controls)
    return jnp.concatenate([x0[None], xs]), us, xdots


def rollouts(params: PlannerParams, x0: jax.Array, u_prev: jax.Array, controls: jax.Array
             ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """`rollout` for K samples, controls (K, N, 2): states (K, N+1, 6), applied (K, N, 2),
    dx/dt (K, N, 6); native: rollout.cc (the same model and arithmetic, W samples per
    vector instruction)."""
    if params.rollout_kernel == "native":
        return native.rollouts(native.model_vector(params.vehicle, params.limits), x0, u_prev,
                               controls, dt=params.dt_s, substeps=params.substeps,
                               n_threads=native.threads(params.va_threads))
    return jax.vmap(rollout, in_axes=(None, None, None, 0))(params, x0, u_prev, controls)


# ----------------------------------------------------------------------------- visibility
def native_variance(vp: VisibilityParams, t_len: int) -> bool:
    """Whether the variance update of T = t_len poses runs in C++ (va_counts.cc): its form
    native, a lag inside the horizon, and at most 65 535 ray points a rollout (its raw
    counts are uint16)."""
    points = t_len * vp.visibility_rays * vp.visibility_points
    return vp.va_kernel == "native" and vp.visibility_lag_steps < t_len and points < 2 ** 16


def decayed_variance(vp: VisibilityParams, mean: Any, variance: Any, origin: Any,
                     resolution: float, states: Any, rows: Any, cols: Any,
                     offsets: tuple[tuple[int, int], ...],
                     surface: native.SurfaceSpec | None = None) -> Any:
    """visibility.batched_decayed_variance (K trajectories: states (K, N+1, 6), footprint
    cells rows, cols (K, N+1, P); (K, N+1, len(offsets) * P) out), in the form
    `native_variance` says; with `surface` (native only), the expected surface cost
    (K, N+1, P) computed from those variances instead (va_counts.cc fused with surface.h)."""
    if not native_variance(vp, rows.shape[1]):
        if surface is not None:
            raise ValueError("the fused surface cost needs the native variance kernel")
        return batched_decayed_variance(vp, mean, variance, origin, resolution, states, rows,
                                        cols, offsets)
    weights, pad, skip = count_inputs(vp, offsets, states)
    return native.va_variance(mean, variance, origin, states, skip, rows, cols, offsets,
                              vp.ray_grid(), weights, resolution=resolution,
                              height=vp.visibility_height_m, gamma=vp.decay_gamma,
                              rays=vp.visibility_rays, points=vp.visibility_points,
                              lag=vp.visibility_lag_steps, pad=pad,
                              n_threads=native.threads(vp.va_threads), surface=surface)


def query_variance(params: PlannerParams, m: MapView, states: jax.Array) -> jax.Array:
    """The variance each rollout meets at its cost's query cells, (K, N+1, 5 P).

    deterministic plans on the mean map and prescient on the true map, both as
    certain (zero variance); VA-MPPI decays the map variance by what each rollout
    would have seen before each step (services.planner.visibility).
    """
    states = priced_poses(params.cost, states)
    rows, cols, _ = jax.vmap(footprint_cells, in_axes=(None, None, 0))(params.cost, m, states)
    if params.controller != "va":
        return jnp.zeros(rows.shape[:-1] + (len(OFFSETS) * rows.shape[-1],), jnp.float32)
    return decayed_variance(params.visibility, m.mean, m.variance, m.origin, m.resolution,
                            states, rows, cols, OFFSETS)


# ----------------------------------------------------------------------------- surface cost
def surface_form(params: PlannerParams, t_len: int) -> str:
    """Which form prices the surface cost of rollouts of T = t_len priced poses:

    certain  deterministic, prescient: the indicator cost on zero variance (costs, JAX)
    jax      VA-MPPI whose surface expectation is the Monte-Carlo estimate, or whose
             variance kernel is JAX: costs.surface_expectation on query_variance
    fused    VA-MPPI, closed form, native variance kernel, nothing else needing the
             variances (crash_variance 0): one C++ pass, the variances never leave a
             thread's cache (va_counts.cc with surface.h)
    native   VA-MPPI, closed form, native, otherwise: query_variance, then surface.cc
    """
    c = params.cost
    if params.controller != "va":
        return "certain"
    if c.surface_estimator != "closed_form" or params.visibility.va_kernel != "native":
        return "jax"
    if c.crash_variance <= 0.0 and native_variance(params.visibility, t_len):
        return "fused"
    return "native"


def surface_terms(params: PlannerParams, m: MapView, states: jax.Array
                  ) -> tuple[jax.Array | None, jax.Array | None]:
    """The query variance (K, N+1, 5 P) and the expected surface cost (K, N+1, P) of every
    rollout, either None where the form (`surface_form`) does without it: the variance in
    `fused`, the expected cost in `certain` and `jax` (costs.rollout_cost computes it)."""
    c = params.cost
    priced = priced_poses(c, states)
    form = surface_form(params, priced.shape[1])
    if form in ("certain", "jax"):
        return query_variance(params, m, states), None
    h0 = jax.vmap(ground_now, in_axes=(None, 0))(m, states)
    rows, cols, outside = jax.vmap(footprint_cells, in_axes=(None, None, 0))(c, m, priced)
    if form == "fused":
        spec = native.SurfaceSpec(outside, h0, c.grad_threshold, c.step_threshold,
                                  c.height_threshold_m, c.footprint_points)
        return None, decayed_variance(params.visibility, m.mean, m.variance, m.origin,
                                      m.resolution, priced, rows, cols, OFFSETS, spec)
    qvar = query_variance(params, m, states)
    return qvar, native.expected_surface(m.mean, rows, cols, outside, qvar, h0,
                                         resolution=m.resolution, grad=c.grad_threshold,
                                         step=c.step_threshold, height=c.height_threshold_m,
                                         n_across=c.footprint_points,
                                         n_threads=native.threads(params.va_threads))
