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

    rows = plans(cfg, at_s=20.0)       # cfg: scenario, controller, samples, seed as for `run`
    print(table(rows))

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


def plans(cfg: Config, at_s: float, shifts: tuple[int, ...] = SHIFTS,
          tails: tuple[int, ...] = TAILS) -> list[dict[str, Any]]:
    """The rows of `table`: the plan sent at the tick of `at_s` and its `variants`, each with
    its cost terms, total, speed at 2, 3 and 4 s and distance covered; first a row `solver`
    with the terms the planner reported for its plan (the same plan priced in the solve)."""
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

    @jax.jit
    def price(mean, variance, origin, x0, u_prev, goal, candidates):
        return mppi.price(params, mppi.map_view(params, mean, variance, origin, res, goal), x0,
                          u_prev, goal, candidates, jax.random.PRNGKey(0))

    mean, variance = mppi.planning_map(params, cores.planner.truth, snap["mean"],
                                       snap["variance"])       # the true map for prescient
    states, _, terms = price(*(jnp.asarray(a, jnp.float32) for a in (
        mean, variance, snap["origin"], snap["x"], snap["u_prev"], cores.goal,
        np.stack([c for _, c in named]))))
    states, terms = np.asarray(states), np.asarray(terms, np.float64)
    at = [int(round(t / dt)) for t in (2.0, 3.0)] + [states.shape[1] - 1]
    rows = [{"plan": "solver", "t_s": round(float(snap["t"]), 2),
             "total": float(np.sum(snap["terms"])),
             **{t: float(v) for t, v in zip(TERMS, snap["terms"], strict=True)}}]
    for (name, _), st, tm in zip(named, states, terms, strict=True):
        rows.append({"plan": name, "total": float(tm.sum()),
                     **{t: float(v) for t, v in zip(TERMS, tm, strict=True)},
                     "speed_2_3_4_s": [round(float(st[i, S.V]), 2) for i in at],
                     "moved_m": round(float(np.hypot(*(st[-1, [S.X, S.Y]] - st[0, [S.X, S.Y]]))),
                                      2)})
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    """Markdown: a row per plan, cheapest variant first after the nominal."""
    head = ["plan", "total", *TERMS, "V at 2, 3, 4 s", "moved, m"]
    first, rest = rows[:2], sorted(rows[2:], key=lambda r: r["total"])
    body = [[r["plan"], f"{r['total']:.2f}", *(f"{r[t]:.2f}" for t in TERMS),
             ", ".join(f"{v:.2f}" for v in r.get("speed_2_3_4_s", [])),
             "" if "moved_m" not in r else f"{r['moved_m']:.2f}"] for r in first + rest]
    return markdown_table(f"The plan at {rows[0]['t_s']} s and the same plan carried out sooner "
                          "(variants k steps sooner, cheapest first)", head, body)
