"""Runs split by how near their goal a hidden obstacle stands: `vamppi near-goal DIR...`.

A hidden obstacle near the goal hides the ground behind it from the way in, and that
ground may be where the goal lies: VA-MPPI, which will not drive fast onto ground it has
not seen in time, then stands or circles there (docs/analysis.md "VA-MPPI's failures").
This splits an experiment's runs, per controller, into those whose scenario has a hidden
obstacle's footprint within `within_m` of the goal and the rest, and compares their
successes by Fisher's exact test.
"""

from __future__ import annotations

from typing import Any

from common.config import Config
from common.scenarios import Scenario

WITHIN_M = 12.0         # a hidden obstacle's footprint this near the goal counts as near


def hidden_to_goal_m(scn: Scenario) -> float | None:
    """The distance from the goal to the nearest hidden obstacle's footprint (None: no
    hidden obstacle)."""
    d = [float(o.distance(scn.goal.x, scn.goal.y)) for o in scn.obstacles if o.hidden]
    return min(d) if d else None


def split(cfg: Config, runs: list[dict[str, Any]], within_m: float = WITHIN_M
          ) -> list[dict[str, Any]]:
    """Per controller: runs, successes and collisions near (a hidden obstacle within
    `within_m` of the goal) and far (the rest, scenarios without one included), the worlds
    on each side, and Fisher's p for successes near against far."""
    from deploy.analysis.summary import fisher_exact
    from deploy.sim.experiment import run_scenario
    scenarios: dict[tuple[str, int, int], Any] = {}
    by: dict[str, dict[str, Any]] = {}
    for r in runs:
        d = hidden_to_goal_m(run_scenario(cfg, r, scenarios))
        side = "near" if d is not None and d < within_m else "far"
        row = by.setdefault(r["controller"], {f"{s}_{k}": 0 for s in ("near", "far")
                                              for k in ("runs", "success", "collision")}
                            | {"near_worlds": set(), "far_worlds": set()})
        row[f"{side}_runs"] += 1
        row[f"{side}_success"] += r["outcome"] == "success"
        row[f"{side}_collision"] += r["outcome"] == "collision"
        row[f"{side}_worlds"].add(r["scenario"])
    out = []
    for controller, row in sorted(by.items()):
        ns, nf = row["near_success"], row["far_success"]
        out.append({"controller": controller, **{k: v for k, v in row.items()
                                                  if not k.endswith("worlds")},
                    "near_worlds": len(row["near_worlds"]), "far_worlds": len(row["far_worlds"]),
                    "p": fisher_exact(ns, row["near_runs"] - ns, nf, row["far_runs"] - nf)
                    if row["near_runs"] and row["far_runs"] else None})
    return out


def _side(r: dict[str, Any], s: str) -> str:
    n = r[f"{s}_runs"]
    rate = f" ({100.0 * r[f'{s}_success'] / n:.0f} %)" if n else ""
    return f"{r[f'{s}_worlds']}, {r[f'{s}_success']} of {n}{rate}, {r[f'{s}_collision']}"


def table(rows: list[dict[str, Any]], within_m: float = WITHIN_M) -> str:
    lines = [f"| controller | hidden obstacle within {within_m:g} m of the goal: worlds, "
             "success, collisions | the rest: worlds, success, collisions | Fisher p |",
             "|---|---|---|---|"]
    for r in rows:
        p = "" if r["p"] is None else f"{r['p']:.2g}"
        lines.append(f"| {r['controller']} | {_side(r, 'near')} | {_side(r, 'far')} | {p} |")
    return "\n".join(lines)
