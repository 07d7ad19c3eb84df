"""How each run that neither reached its goal nor collided ended: `vamppi timeouts DIR`.

Such a run timed out (30 s, never in the goal region) or reached the goal region and
never stopped there (`stopping`). Its record's path (t, X, Y, V[, psi] at 10 Hz) tells
which of two ways it ended: **standing** (slower than `STAND_MPS` at the end, a creep
included; since when) or still **driving**; how far from the goal it ended, how near it
came and when, and how far it drove. docs/analysis.md sorts VA-MPPI's failures
this way.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from common.config import Config

STAND_MPS = 0.3        # slower than this at the end counts as standing (a creep included)
FAILED = ("timeout", "stopping")


def ending(path: Any, goal_xy: tuple[float, float]) -> dict[str, Any]:
    """How a recorded path (t, X, Y, V[, psi]) ended, against the goal at `goal_xy`:
    `how` "standing" (slower than STAND_MPS from `standing_since_s` to the end) or
    "driving" (its speed at the end); the distance from the goal at the end
    and at the nearest (and when); the length driven."""
    p = np.asarray(path, float)
    if p.ndim != 2 or p.shape[0] < 2 or p.shape[1] < 4 or not np.all(np.isfinite(p[:, :4])):
        raise ValueError("a path needs two or more finite rows of (t, X, Y, V[, psi])")
    t, x, y, v = p[:, 0], p[:, 1], p[:, 2], np.abs(p[:, 3])
    d = np.hypot(x - goal_xy[0], y - goal_xy[1])
    moving = np.flatnonzero(v >= STAND_MPS)
    since = float(t[0]) if moving.size == 0 else (
        None if moving[-1] == len(t) - 1 else float(t[moving[-1] + 1]))
    standing = since is not None
    i = int(np.argmin(d))
    return {"how": "standing" if standing else "driving",
            "standing_since_s": round(since, 2) if standing else None,
            "end_speed_mps": round(float(v[-1]), 2),
            "end_from_goal_m": round(float(d[-1]), 2),
            "nearest_m": round(float(d[i]), 2), "nearest_at_s": round(float(t[i]), 2),
            "driven_m": round(float(np.sum(np.hypot(np.diff(x), np.diff(y)))), 1)}


def endings(cfg: Config, runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per run of `runs` (experiment records) that timed out or never stopped in
    the goal region: its keys and `ending`, the goal from its scenario; a record without a
    path says so (`how`: "no path")."""
    from deploy.sim.experiment import KEY_FIELDS, run_scenario
    scenarios: dict[tuple[str, int, int], Any] = {}
    rows = []
    for r in runs:
        if r["outcome"] not in FAILED:
            continue
        row = {k: r[k] for k in (*KEY_FIELDS, "outcome")}
        row["world"] = r.get("world", r["scenario"])
        if not r.get("path"):
            rows.append({**row, "how": "no path"})
            continue
        goal = run_scenario(cfg, r, scenarios).goal
        rows.append({**row, **ending(r["path"], (goal.x, goal.y))})
    return rows


def counts(rows: list[dict[str, Any]]) -> dict[str, dict[str, int]]:
    """Per controller, how many ended each way."""
    out: dict[str, dict[str, int]] = {}
    for r in rows:
        by = out.setdefault(r["controller"], {})
        by[r["how"]] = by.get(r["how"], 0) + 1
    return out


def table(rows: list[dict[str, Any]]) -> str:
    lines = ["| world | controller | K | seed | outcome | ended | from the goal at the end "
             "| nearest to the goal | driven |", "|" + "---|" * 9]
    for r in sorted(rows, key=lambda r: (r["scenario"], r["controller"], r["samples"],
                                         r["seed"])):
        head = (f"| {r.get('world', r['scenario'])} | {r['controller']} | {r['samples']} "
                f"| {r['seed']} "
                f"| {r['outcome']} ")
        if r["how"] == "no path":
            lines.append(head + "| no path recorded | | | |")
            continue
        ended = (f"standing from {r['standing_since_s']:.1f} s" if r["how"] == "standing"
                 else f"driving, {r['end_speed_mps']:.1f} m/s")
        lines.append(head + f"| {ended} | {r['end_from_goal_m']:.1f} m "
                     f"| {r['nearest_m']:.1f} m at {r['nearest_at_s']:.1f} s "
                     f"| {r['driven_m']:.0f} m |")
    return "\n".join(lines)
