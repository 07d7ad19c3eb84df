"""MPPI (Williams et al., information-theoretic update) in JAX, pieces kept apart.

One iteration: sample K control sequences around the nominal (sample 0 is the
nominal itself), roll each out through the plant's own model (`rollout`,
written for one sample and vmapped), let the controller supply the variance
each rollout meets (`query_variance`: where VA-MPPI's visibility-aware update
comes in), price every rollout (`costs.rollout_cost`), weight by
exp(-(J - J_min) / lambda) and move the nominal by the weighted noise.

    step(params, state, inputs) -> (state, outputs)

Randomness is state: the PRNG key lives in `PlannerState` and is split each
iteration, so a run is reproducible from its seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache, partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from common.config import Config, VehicleConfig
from services.planner import native
from services.planner.costs import (
    OFFSETS,
    CostParams,
    MapView,
    footprint_cells,
    ground_now,
    priced_poses,
    rollout_cost,
)
from services.planner.fastmath import FAST
from services.planner.visibility import VisibilityParams, batched_decayed_variance, native_applies
from services.plant.dynamics import ControlLimits, clamp_control, derivatives, rk4_step


@dataclass(frozen=True)
class PlannerParams:
    controller: str                    # deterministic | prescient | va
    samples: int                       # K (J in the paper)
    horizon: int                       # N
    dt: float
    substeps: int
    iterations: int
    temperature: float                 # lambda
    noise_std: tuple[float, float]     # delta, f_xt
    noise_correlation: float           # rho of the AR(1) noise along the horizon; 0 = white
    brake_samples: int                 # samples replaced by full braking (0: the paper's MPPI)
    swerve_samples: int                # ... and by full-lock swerves (0: the paper's MPPI)
    advance_samples: int               # ... and by the nominal done sooner (0: the paper's)
    rollouts_published: int
    rollout_kernel: str                # auto | jax | native (services/planner/native)
    threads: int                       # native kernels' threads; 0 = this process's cores
    vehicle: VehicleConfig
    limits: ControlLimits
    cost: CostParams
    visibility: VisibilityParams

    @classmethod
    def from_config(cls, cfg: Config) -> PlannerParams:
        p = cfg.planner
        return cls(p.controller, p.samples, p.horizon, p.dt_s, p.substeps, p.iterations,
                   p.temperature, (p.noise_steer_rad, p.noise_force_n), p.noise_correlation,
                   min(p.brake_samples, p.samples - 1),
                   min(p.swerve_samples, max(0, p.samples - 1 - p.brake_samples)),
                   min(p.advance_samples,
                       max(0, p.samples - 1 - p.brake_samples - p.swerve_samples)),
                   min(p.rollouts_published, p.samples), p.rollout_kernel, p.va_threads,
                   cfg.vehicle,
                   ControlLimits.from_config(cfg.vehicle), CostParams.from_config(cfg),
                   VisibilityParams.from_config(cfg))


class PlannerState(NamedTuple):
    nominal: jax.Array                 # (N, 2) float32, the mean control sequence
    key: jax.Array                     # PRNG key


class SolveOutput(NamedTuple):
    controls: jax.Array                # (N, 2) the nominal, as the plant would apply it
    optimal: jax.Array                 # (N+1, 6) its rollout
    terms: jax.Array                   # (6,) its cost terms, costs.TERMS
    rollouts_xy: jax.Array             # (R, N+1, 2) some sampled rollouts
    rollout_costs: jax.Array           # (R,)
    cost_min: jax.Array
    cost_mean: jax.Array


def initial_state(params: PlannerParams, seed: int) -> PlannerState:
    return PlannerState(jnp.zeros((params.horizon, 2), jnp.float32), jax.random.PRNGKey(seed))


def planning_map(params: PlannerParams, truth: Any, mean: Any, variance: Any
                 ) -> tuple[Any, Any]:
    """The (mean, variance) the controller plans on: the scenario's true heightmap for
    prescient, the mapper's map otherwise. Only VA-MPPI reads the variance
    (`query_variance`): deterministic and prescient plan as if every cell were certain."""
    return (truth, variance) if params.controller == "prescient" else (mean, variance)


@jax.jit
def _shift(nominal: jax.Array, ticks: jax.Array) -> jax.Array:
    """The nominal shifted by `ticks` steps, the last control repeated: one compiled
    gather for every shift (eager slicing compiled anew for each count, 0.1 s the first
    time a standby took over after a gap of two ticks)."""
    n = nominal.shape[0]
    return nominal[jnp.minimum(jnp.arange(n) + ticks, n - 1)]


def advance(state: PlannerState, ticks: int) -> PlannerState:
    """Warm start: shift the nominal by `ticks` steps, repeating the last control."""
    if ticks <= 0:
        return state
    ticks = min(ticks, state.nominal.shape[0])
    return state._replace(nominal=_shift(state.nominal, jnp.int32(ticks)))


def rollout(params: PlannerParams, x0: jax.Array, u_prev: jax.Array, controls: jax.Array
            ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """One sample: states (N+1, 6), applied controls (N, 2), dx/dt at each step (N, 6).
    The plant's own model, with vectorisable arctan/sin/cos (`fastmath.FAST`)."""
    def body(carry, v):
        x, u_last = carry
        u = clamp_control(v, u_last, params.limits, params.dt, jnp)
        xdot = derivatives(params.vehicle, x, u, FAST)
        x_next = jax.lax.fori_loop(0, params.substeps,
                                   lambda _, x: rk4_step(params.vehicle, x, u, h, FAST), x)
        return (x_next, u), (x_next, u, xdot)

    # the plant's `integrate`, its substeps as a loop: one copy of the model in the
    # program instead of `substeps` (compiling took 4 s longer with them unrolled)
    h = params.dt / params.substeps

    _, (xs, us, xdots) = jax.lax.scan(body, (x0, u_prev), controls)
    return jnp.concatenate([x0[None], xs]), us, xdots


def rollouts(params: PlannerParams, x0: jax.Array, u_prev: jax.Array, controls: jax.Array
             ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """`rollout` for K samples, controls (K, N, 2): states (K, N+1, 6), applied (K, N, 2),
    dx/dt (K, N, 6). On a CPU by default the native kernel (rollout.cc: the same model
    and arithmetic, W samples per vector instruction), else `rollout` vmapped."""
    if native.use_native(params.rollout_kernel):
        return native.rollouts(native.model_vector(params.vehicle, params.limits), x0, u_prev,
                               controls, dt=params.dt, substeps=params.substeps,
                               n_threads=native.threads(params.threads))
    return jax.vmap(rollout, in_axes=(None, None, None, 0))(params, x0, u_prev, controls)


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
    return batched_decayed_variance(params.visibility, m.mean, m.variance, m.origin,
                                    m.resolution, states, rows, cols, OFFSETS)


def surface_terms(params: PlannerParams, m: MapView, states: jax.Array
                  ) -> tuple[jax.Array | None, jax.Array | None]:
    """The query variance (K, N+1, 5 P) and VA-MPPI's expected surface cost (K, N+1, P)
    of every rollout, either None. The expected cost comes from the native kernels
    (closed form, on a CPU: `planner.va_kernel`), fused into the variance update when
    nothing else needs the variances (`crash_variance` 0), the variance then None;
    otherwise it is None and `rollout_cost` computes it in JAX (the deterministic and
    prescient controllers' indicators, the Monte-Carlo estimate, an accelerator)."""
    c = params.cost
    if (params.controller != "va" or c.estimator != "closed_form"
            or not native.use_native(params.visibility.backend)):
        return query_variance(params, m, states), None
    h0 = jax.vmap(ground_now, in_axes=(None, 0))(m, states)
    priced = priced_poses(c, states)
    rows, cols, outside = jax.vmap(footprint_cells, in_axes=(None, None, 0))(c, m, priced)
    if c.crash_variance <= 0.0 and native_applies(params.visibility, priced.shape[1]):
        spec = native.SurfaceSpec(outside, h0, c.grad_threshold, c.step_threshold,
                                  c.height_threshold, c.n_across)
        return None, batched_decayed_variance(params.visibility, m.mean, m.variance, m.origin,
                                              m.resolution, priced, rows, cols, OFFSETS, spec)
    qvar = query_variance(params, m, states)
    return qvar, native.expected_surface(m.mean, rows, cols, outside, qvar, h0,
                                         resolution=m.resolution, grad=c.grad_threshold,
                                         step=c.step_threshold, height=c.height_threshold,
                                         n_across=c.n_across,
                                         n_threads=native.threads(params.threads))


def sample_noise(params: PlannerParams, key: jax.Array) -> jax.Array:
    """(K, N, 2) perturbations of the nominal, std `noise_std` at every step. With
    rho = `noise_correlation` > 0 each sample is an AR(1) sequence along the horizon,
    eps_i = rho eps_(i-1) + sqrt(1 - rho^2) eta_i (stationary: eps_0 = eta_0), so a
    sample holds a steering or force offset for about 1 / (1 - rho) steps instead of
    flipping sign every step against the steering-rate limit."""
    k, n = params.samples, params.horizon
    std = jnp.asarray(params.noise_std, jnp.float32)
    eta = jax.random.normal(key, (k, n, 2), jnp.float32)
    rho = params.noise_correlation
    if rho > 0.0:
        a = math.sqrt(1.0 - rho * rho)

        def ar(prev, e):
            cur = rho * prev + a * e
            return cur, cur

        _, rest = jax.lax.scan(ar, eta[:, 0], jnp.swapaxes(eta[:, 1:], 0, 1))
        eta = jnp.concatenate([eta[:, :1], jnp.swapaxes(rest, 0, 1)], axis=1)
    return eta * std


def brake_sequences(params: PlannerParams, nominal: jax.Array) -> jax.Array:
    """(B, N, 2) full-braking candidates: the brake limit over the whole horizon, the
    nominal's steering shifted by B offsets spread over +-half the steering limit (one
    sample: the nominal's own). Random samples around a nominal that accelerates almost
    never brake hard (the limit is some 6 force stds below), so without them MPPI can miss
    the one safe choice when an obstacle appears late (docs/planner.md)."""
    b = params.brake_samples
    half = 0.5 * params.limits.hi[0]
    offs = jnp.linspace(-half, half, b) if b > 1 else jnp.zeros((1,))
    steer = nominal[None, :, 0] + offs[:, None].astype(jnp.float32)
    force = jnp.full(steer.shape, params.limits.lo[1], jnp.float32)
    return jnp.stack([steer, force], axis=-1)


def swerve_sequences(params: PlannerParams, nominal: jax.Array) -> jax.Array:
    """(W, N, 2) swerves: the steering limit held over the whole horizon (reached at the
    steering-rate limit), alternately left and right, the first of each side at the
    nominal's force, the next at half of it, ...; the way round an obstacle that appears
    too late to stop for, which white steering noise (0.15 rad a step, flipping sign
    against the rate limit) almost never holds (docs/planner.md)."""
    w = params.swerve_samples
    side = jnp.where(jnp.arange(w) % 2 == 0, 1.0, -1.0).astype(jnp.float32)
    scale = (0.5 ** (jnp.arange(w) // 2)).astype(jnp.float32)
    steer = jnp.broadcast_to(side[:, None] * params.limits.hi[0], (w, nominal.shape[0]))
    force = scale[:, None] * nominal[None, :, 1]
    return jnp.stack([steer, force], axis=-1)


def advance_sequences(params: PlannerParams, nominal: jax.Array) -> jax.Array:
    """(A, N, 2) the nominal advanced by 2, 4, ... 2 A steps, its last control held: the
    same plan carried out sooner. A nominal that puts off its start (a stopped vehicle
    whose plan accelerates only later) is only ever perturbed by white noise that averages
    out over a few steps, so MPPI keeps putting it off even when doing it now costs less
    (docs/planner.md)."""
    n = nominal.shape[0]
    shifts = 2 * jnp.arange(1, params.advance_samples + 1)
    return nominal[jnp.minimum(jnp.arange(n)[None] + shifts[:, None], n - 1)]


def _iteration(params: PlannerParams, state: PlannerState, x0, u_prev, goal, m: MapView):
    key, sub, mc = jax.random.split(state.key, 3)
    k = params.samples
    eps = sample_noise(params, sub)
    eps = eps.at[0].set(0.0)                          # sample 0: the nominal itself
    candidates = state.nominal[None] + eps
    b = params.brake_samples
    if b:                                             # samples 1 .. B: full braking
        candidates = candidates.at[1:1 + b].set(brake_sequences(params, state.nominal))
    if params.swerve_samples:                         # then W swerves
        candidates = candidates.at[1 + b:1 + b + params.swerve_samples].set(
            swerve_sequences(params, state.nominal))
    a0 = 1 + b + params.swerve_samples
    if params.advance_samples:                        # then A advanced nominals
        candidates = candidates.at[a0:a0 + params.advance_samples].set(
            advance_sequences(params, state.nominal))
    states, applied, xdots = rollouts(params, x0, u_prev, candidates)

    qvar, expected = surface_terms(params, m, states)
    terms = jax.vmap(rollout_cost, in_axes=(None, 0, 0, None, None,
                                            None if qvar is None else 0, 0,
                                            None if expected is None else 0))(
        params.cost, states, xdots, goal, m, qvar, jax.random.split(mc, k), expected)
    cost = jnp.sum(terms, axis=-1)
    finite = jnp.isfinite(cost)
    cost = jnp.where(finite, cost, jnp.inf)
    j_min = jnp.min(cost)
    # a rollout with a non-finite cost gets no weight; if none is finite the nominal stays
    w = jnp.where(finite, jnp.exp(-(cost - jnp.where(finite.any(), j_min, 0.0))
                                  / params.temperature), 0.0)
    total = jnp.sum(w)
    w = jnp.where(total > 0, w / jnp.where(total > 0, total, 1.0), 0.0)
    nominal = state.nominal + jnp.einsum("k,kni->ni", w, applied - state.nominal[None])
    r = params.rollouts_published
    j_mean = jnp.sum(jnp.where(finite, cost, 0.0)) / jnp.maximum(jnp.sum(finite), 1)
    info = (states[:r, :, 3:5], cost[:r], j_min, j_mean)
    return PlannerState(nominal, key), info


def _solve(params: PlannerParams, state: PlannerState, x0, u_prev, goal, mean, variance,
           origin, resolution) -> tuple[PlannerState, SolveOutput]:
    m = MapView(mean, variance, origin, resolution)
    info = None
    for _ in range(params.iterations):
        state, info = _iteration(params, state, x0, u_prev, goal, m)
    states, applied, xdots = (a[0] for a in rollouts(params, x0, u_prev, state.nominal[None]))
    terms = rollout_cost(params.cost, states, xdots, goal, m,
                         query_variance(params, m, states[None])[0], state.key)
    xy, costs, j_min, j_mean = info
    state = state._replace(nominal=applied)
    return state, SolveOutput(applied, states, terms, xy, costs, j_min, j_mean)


@lru_cache(maxsize=8)
def solver(params: PlannerParams):
    """The jitted solve for these (static) parameters."""
    return jax.jit(partial(_solve, params), static_argnames=("resolution",))


def solve(params: PlannerParams, state: PlannerState, x0: Any, u_prev: Any, goal: Any,
          mean: Any, variance: Any, origin: Any, resolution: float
          ) -> tuple[PlannerState, SolveOutput]:
    """One control tick: `iterations` MPPI updates from the current nominal.

    x0 (6,), u_prev (2,) the control applied now, goal (3,) = (x, y, yaw),
    mean/variance (H, W) float32 map, origin (2,), resolution (m).
    """
    f = solver(params)
    return f(state, jnp.asarray(x0, jnp.float32), jnp.asarray(u_prev, jnp.float32),
             jnp.asarray(goal, jnp.float32), jnp.asarray(mean, jnp.float32),
             jnp.asarray(variance, jnp.float32), jnp.asarray(origin, jnp.float32),
             resolution=float(resolution))

