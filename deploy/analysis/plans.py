"""`vamppi plans`: the planner's plan at one instant of an episode, priced beside the same
plan carried out sooner.

Why a plan waits (docs/analysis.md "The creep"): the episode is run in-process and lockstep
(`deploy.sim.runner.run_episode`, the same cores as the services) up to the tick at `--at`
seconds, where the runner keeps the map, the state and the plan the planner sent. That plan
(the nominal) is then priced with `mppi.price`, the pricing every MPPI iteration applies to
its samples, beside its variants: the same controls carried out k steps sooner (the last
control held to fill the horizon), and each of those with the force cut to zero (coasting)
or to the brake limit from a given step on. A variant that costs less than the nominal is
one MPPI could move to; none cheaper means the wait is the cost's own optimum.

With `steady` the same state also prices plans made by hand, not from the nominal: each
steering angle of `STEERS` (fractions of the steering limit, + left) held with each force
of `FORCES` (the brake limit, none, fractions of the drive limit), and braking at the
limit for each of `BRAKE_STEPS` steps before a steering angle of `STEERS` is held with the
force cut. They ask whether any way out, a turn into unseen ground or a loop away from
the goal, is cheaper than what the planner does, and which term stops it. With `alt` (a
second configuration) every plan is priced again under it, at the same state, on the
same map: what a change of the cost would say there, without a new episode.

    rows = plans(cfg, at_s=20.0)       # cfg: scenario, controller, samples, seed as for `run`
    print(table(rows))
    rows = plans(cfg, 25.0, steady=True, alt=load_config(overrides=[...], base=cfg))

The episode stops at the tick after `at_s` (`episode.timeout_s`), so a probe costs only the
time up to it.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from common.config import Config
from deploy.bench.device import markdown_table
from services.planner import mppi
from services.planner.costs import TERMS
from services.planner.params import PlannerParams
from services.plant.dynamics import S, U

SHIFTS = (1, 2, 4, 8)           # steps sooner
TAILS = (20, 30)                # steps from which a variant coasts or brakes
STEERS = (-1.0, -0.5, 0.0, 0.5, 1.0)   # steady plans: fractions of the steering limit
FORCES = ("brake", 0.0, 0.1, 0.25, 0.5)  # ... the brake limit, or fractions of the drive limit
BRAKE_STEPS = (5, 10, 15)       # brake-then-turn plans: steps at the brake limit first


def variants(nominal: np.ndarray, brake_force: float, shifts: tuple[int, ...] = SHIFTS,
             tails: tuple[int, ...] = TAILS) -> list[tuple[str, np.ndarray]]:
    """(name, controls (N, 2)): the nominal, then per k in `shifts` the nominal k steps sooner
    (its last control held), and that with the force 0 or `brake_force` from each step of
    `tails` on."""
    n = nominal.shape[0]
    out = [("nominal", nominal)]
    for k in shifts:
        adv = nominal[np.minimum(np.arange(n) + k, n - 1)]
        out.append((f"{k} sooner", adv))
        for s in tails:
            for what, force in (("coasting", 0.0), ("braking", brake_force)):
                v = adv.copy()
                v[s:, U.FXT] = force
                out.append((f"{k} sooner, {what} from {s}", v))
    return out


def steady_plans(n: int, lo: np.ndarray, hi: np.ndarray, steers: tuple[float, ...] = STEERS,
                 forces: tuple[Any, ...] = FORCES, brake_steps: tuple[int, ...] = BRAKE_STEPS
                 ) -> list[tuple[str, np.ndarray]]:
    """(name, controls (n, 2)) made by hand from the control limits `lo`, `hi`: each steering
    fraction of `steers` held with each force of `forces` ("brake": the brake limit, a
    number: that fraction of the drive limit), then for each k of `brake_steps` the brake
    limit for k steps and each steering fraction held after it, the force cut. (The
    rollout applies the controls' rate limits, as to every sample.)"""
    out = []
    for f in forces:
        force = lo[U.FXT] if f == "brake" else f * hi[U.FXT]
        label = "braking" if f == "brake" else ("coasting" if f == 0 else f"force {force:.0f} N")
        for s in steers:
            u = np.zeros((n, 2), np.float32)
            u[:, U.DELTA], u[:, U.FXT] = s * hi[U.DELTA], force
            out.append((f"steer {s:+.2f}, {label}", u))
    for k in brake_steps:
        for s in steers:
            u = np.zeros((n, 2), np.float32)
            u[:k, U.FXT] = lo[U.FXT]
            u[k:, U.DELTA] = s * hi[U.DELTA]
            out.append((f"brake {k} steps, then steer {s:+.2f}", u))
    return out


def plans(cfg: Config, at_s: float, shifts: tuple[int, ...] = SHIFTS,
          tails: tuple[int, ...] = TAILS, steady: bool = False,
          alt: Config | None = None) -> list[dict[str, Any]]:
    """The rows of `table`: the plan sent at the tick of `at_s` and its `variants` (and with
    `steady` the `steady_plans`), each with its cost terms, total, speed at 2, 3 and 4 s,
    distance covered, and distance from the goal at the horizon's end and at its nearest;
    first a row `solver` with the terms the planner reported for its plan (the same plan
    priced in the solve). With `alt` each plan's row also holds `alt`: its terms and total
    under that configuration (its planner parameters; same state, map and goal)."""
    from deploy.sim.runner import Cores, run_episode
    dt = cfg.planner.dt_s
    tick = int(round(at_s / dt))
    cfg = cfg.replace(**{"episode.timeout_s": (tick + 1) * dt + 1e-6})
    cores = Cores.from_config(cfg)
    result = run_episode(cfg, cores, snapshot_ticks=frozenset({tick}))
    if not result.snapshots:
        raise ValueError(f"the episode ended ({result.outcome}) at {result.sim_time_s:.1f} s, "
                         f"before {at_s} s")
    snap = result.snapshots[0]
    params = PlannerParams.from_config(cfg)
    res = float(snap["resolution"])
    nominal = np.asarray(snap["controls"], np.float32)
    named = variants(nominal, float(params.limits.lo[U.FXT]), shifts, tails)
    if steady:
        named += steady_plans(nominal.shape[0], np.asarray(params.limits.lo),
                              np.asarray(params.limits.hi))
    candidates = np.stack([c for _, c in named])

    def priced(p: PlannerParams) -> tuple[np.ndarray, np.ndarray]:
        @jax.jit
        def price(mean, variance, origin, x0, u_prev, goal, candidates):
            return mppi.price(p, mppi.map_view(p, mean, variance, origin, res, goal), x0,
                              u_prev, goal, candidates, jax.random.PRNGKey(0))

        mean, variance = mppi.planning_map(p, cores.planner.truth, snap["mean"],
                                           snap["variance"])   # the true map for prescient
        states, _, terms = price(*(jnp.asarray(a, jnp.float32) for a in (
            mean, variance, snap["origin"], snap["x"], snap["u_prev"], cores.goal,
            candidates)))
        return np.asarray(states), np.asarray(terms, np.float64)

    states, terms = priced(params)
    alt_terms = None if alt is None else priced(PlannerParams.from_config(alt))[1]
    to_goal = np.hypot(states[..., S.X] - cores.goal[0], states[..., S.Y] - cores.goal[1])
    at = [int(round(t / dt)) for t in (2.0, 3.0)] + [states.shape[1] - 1]
    rows = [{"plan": "solver", "t_s": round(float(snap["t"]), 2),
             "total": float(np.sum(snap["terms"])),
             **{t: float(v) for t, v in zip(TERMS, snap["terms"], strict=True)}}]
    for j, ((name, _), st, tm) in enumerate(zip(named, states, terms, strict=True)):
        row = {"plan": name, "total": float(tm.sum()),
               **{t: float(v) for t, v in zip(TERMS, tm, strict=True)},
               "speed_2_3_4_s": [round(float(st[i, S.V]), 2) for i in at],
               "moved_m": round(float(np.hypot(*(st[-1, [S.X, S.Y]] - st[0, [S.X, S.Y]]))), 2),
               "to_goal_end_m": round(float(to_goal[j, -1]), 2),
               "to_goal_nearest_m": round(float(to_goal[j].min()), 2)}
        if alt_terms is not None:
            row["alt"] = {"total": float(alt_terms[j].sum()),
                          **{t: float(v) for t, v in zip(TERMS, alt_terms[j], strict=True)}}
        rows.append(row)
    return rows


def table(rows: list[dict[str, Any]], limit: int | None = None) -> str:
    """Markdown: a row per plan, cheapest first after the nominal (at most `limit` of them),
    with the total under the second configuration where the rows have one."""
    alt = any("alt" in r for r in rows)
    head = ["plan", "total", *TERMS, "V at 2, 3, 4 s", "moved, m", "to goal: end, nearest, m",
            *(["total, second config"] if alt else [])]
    first, rest = rows[:2], sorted(rows[2:], key=lambda r: r["total"])[:limit]
    body = [[r["plan"], f"{r['total']:.2f}", *(f"{r[t]:.2f}" for t in TERMS),
             ", ".join(f"{v:.2f}" for v in r.get("speed_2_3_4_s", [])),
             "" if "moved_m" not in r else f"{r['moved_m']:.2f}",
             "" if "to_goal_end_m" not in r else
             f"{r['to_goal_end_m']:.2f}, {r['to_goal_nearest_m']:.2f}",
             *([f"{r['alt']['total']:.2f}" if "alt" in r else ""] if alt else [])]
            for r in first + rest]
    return markdown_table(f"The plan at {rows[0]['t_s']} s, the same plan carried out sooner "
                          "(variants k steps sooner) and other plans, cheapest first", head, body)
