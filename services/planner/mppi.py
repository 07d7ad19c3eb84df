"""MPPI (Williams et al., information-theoretic update) in JAX, pieces kept apart.

One iteration: sample K control sequences around the nominal (sample 0 is the
nominal itself), roll each out through the plant's own model (`kernels.rollouts`),
let the controller supply the variance each rollout meets (`kernels.surface_terms`:
where VA-MPPI's visibility-aware update comes in), price every rollout
(`costs.rollout_cost`; these three are `price`), weight by exp(-(J - J_min) / lambda)
and move the nominal by the weighted noise. The kernels' forms (JAX or C++) are
services/planner/kernels.py's to choose; nothing here knows which runs.

    step(params, state, inputs) -> (state, outputs)

Randomness is state: the PRNG key lives in `PlannerState` and is split each
iteration, so a run is reproducible from its seed.
"""

from __future__ import annotations

import math
from functools import lru_cache, partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from common import compile_cache
from services.planner import native, route
from services.planner.costs import MapView, rollout_cost
from services.planner.kernels import query_variance, rollouts, surface_terms
from services.planner.params import PlannerParams
from services.plant.dynamics import S, U, effective_force


class PlannerState(NamedTuple):
    nominal: jax.Array                 # (N, 2) float32, the mean control sequence
    key: jax.Array                     # PRNG key


jax.export.register_namedtuple_serialization(PlannerState, serialized_name="vamppi.PlannerState")


class SolveOutput(NamedTuple):
    controls: jax.Array                # (N, 2) the nominal, as the plant would apply it
    optimal: jax.Array                 # (N+1, 6) its rollout
    terms: jax.Array                   # (6,) its cost terms, costs.TERMS
    rollouts_xy: jax.Array             # (R, N+1, 2) some sampled rollouts
    rollout_costs: jax.Array           # (R,)
    cost_min: jax.Array
    cost_mean: jax.Array


jax.export.register_namedtuple_serialization(SolveOutput, serialized_name="vamppi.SolveOutput")


def initial_state(params: PlannerParams, seed: int) -> PlannerState:
    return PlannerState(jnp.zeros((params.horizon, 2), jnp.float32), jax.random.PRNGKey(seed))


def planning_map(params: PlannerParams, truth: Any, mean: Any, variance: Any
                 ) -> tuple[Any, Any]:
    """The (mean, variance) the controller plans on: the scenario's true heightmap for
    prescient, the mapper's map otherwise. Only VA-MPPI reads the variance
    (`query_variance`): deterministic and prescient plan as if every cell were certain."""
    return (truth, variance) if params.controller == "prescient" else (mean, variance)


def map_view(params: PlannerParams, mean: Any, variance: Any, origin: Any, resolution: float,
             goal: Any) -> MapView:
    """The planning map as the cost sees it, with `goal_distance = "route"`'s detour on it
    (services/planner/route.py): VA-MPPI's over its variance, the others' over the map
    taken as certain, as they plan."""
    r = params.cost.route
    detour = None if r is None else route.detour(
        r, mean, variance if params.controller == "va" else None, origin, resolution, goal)
    return MapView(mean, variance, origin, resolution, detour)


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


def felt(params: PlannerParams, states: jax.Array, applied: jax.Array) -> jax.Array:
    """The controls (K, N, 2) the update averages: with `effective_update` (ours) each
    step's force as the vehicle felt it at the step's start speed (`effective_force`: a
    brake on a stopped vehicle is none), else as commanded (the paper's). Commanded, a
    nominal that brakes a stopped vehicle never leaves it: every sample around it whose
    force stays below zero has the same rollout and cost, and the update keeps their mean;
    felt, their mean is zero, and a sample that drives can pull the nominal forward."""
    if not params.effective_update:
        return applied
    f = effective_force(params.vehicle, states[:, :-1, S.V], applied[..., U.FXT], jnp)
    return applied.at[..., U.FXT].set(f)


def price(params: PlannerParams, m: MapView, x0: jax.Array, u_prev: jax.Array, goal: jax.Array,
          candidates: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Control sequences (C, N, 2) rolled out from x0 and priced as an iteration prices its
    samples: states (C, N+1, 6), the controls as applied (C, N, 2) and the cost terms (C, 6)
    (`costs.TERMS`); `key` for the Monte-Carlo surface estimate (deploy/analysis/plans.py
    prices a plan's variants with it)."""
    states, applied, xdots = rollouts(params, x0, u_prev, candidates)
    qvar, expected = surface_terms(params, m, states)
    terms = jax.vmap(rollout_cost, in_axes=(None, 0, 0, None, None,
                                            None if qvar is None else 0, 0,
                                            None if expected is None else 0))(
        params.cost, states, xdots, goal, m, qvar,
        jax.random.split(key, candidates.shape[0]), expected)
    return states, applied, terms


def _iteration(params: PlannerParams, state: PlannerState, x0, u_prev, goal, m: MapView):
    key, sub, mc = jax.random.split(state.key, 3)
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
    states, applied, terms = price(params, m, x0, u_prev, goal, candidates, mc)
    cost = jnp.sum(terms, axis=-1)
    finite = jnp.isfinite(cost)
    cost = jnp.where(finite, cost, jnp.inf)
    j_min = jnp.min(cost)
    # a rollout with a non-finite cost gets no weight; if none is finite the nominal stays
    w = jnp.where(finite, jnp.exp(-(cost - jnp.where(finite.any(), j_min, 0.0))
                                  / params.temperature), 0.0)
    total = jnp.sum(w)
    w = jnp.where(total > 0, w / jnp.where(total > 0, total, 1.0), 0.0)
    nominal = state.nominal + jnp.einsum("k,kni->ni", w, felt(params, states, applied)
                                         - state.nominal[None])
    r = params.rollouts_published
    j_mean = jnp.sum(jnp.where(finite, cost, 0.0)) / jnp.maximum(jnp.sum(finite), 1)
    info = (states[:r, :, 3:5], cost[:r], j_min, j_mean)
    return PlannerState(nominal, key), info


def _solve(params: PlannerParams, state: PlannerState, x0, u_prev, goal, mean, variance,
           origin, resolution) -> tuple[PlannerState, SolveOutput]:
    m = map_view(params, mean, variance, origin, resolution, goal)
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
def jitted(params: PlannerParams):
    """The jitted solve for these (static) parameters (`lower` it to inspect the program)."""
    return jax.jit(partial(_solve, params), static_argnames=("resolution",))


@lru_cache(maxsize=8)
def solver(params: PlannerParams, resolution: float):
    """The solve for these (static) parameters, traced once per machine and code
    (common.compile_cache.Traced): a process starts in about 3.7 s less. What the trace
    bakes in besides `params`: the native kernels' thread count and whether they load
    (which also registers them, as tracing would)."""
    loads = native.available() if "native" in (params.rollout_kernel,
                                              params.visibility.va_kernel) else False
    salt = f"{params!r} resolution={resolution!r} threads={native.threads(params.va_threads)}" \
           f" native={loads}"
    return compile_cache.Traced("planner-solve",
                                jax.jit(partial(_solve, params, resolution=resolution)),
                                salt, tuple(native.TARGETS))


def solve(params: PlannerParams, state: PlannerState, x0: Any, u_prev: Any, goal: Any,
          mean: Any, variance: Any, origin: Any, resolution: float
          ) -> tuple[PlannerState, SolveOutput]:
    """One control tick: `iterations` MPPI updates from the current nominal.

    x0 (6,), u_prev (2,) the control applied now, goal (3,) = (x, y, yaw),
    mean/variance (H, W) float32 map, origin (2,), resolution (m).
    """
    f = solver(params, float(resolution))
    return f(state, jnp.asarray(x0, jnp.float32), jnp.asarray(u_prev, jnp.float32),
             jnp.asarray(goal, jnp.float32), jnp.asarray(mean, jnp.float32),
             jnp.asarray(variance, jnp.float32), jnp.asarray(origin, jnp.float32))

