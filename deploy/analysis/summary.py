"""What an experiment's runs show: summary.json, summary-kinds.json, summary.md and the
plots beside runs.jsonl (deploy.sim.experiment), and the statistics behind them.

  summary.json   per scenario/controller/samples: counts of each outcome and the
                 time to goal over successful runs
  summary-kinds.json  the same per world kind and over the whole set, where the
                 runs span more than one world
  summary.md     the same as markdown tables, the paper's figures beside ours; then
                 what each collision was on (deploy.analysis.collisions)
  *.png          the plots of deploy.analysis.plots
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from common.config import Config
from deploy.analysis import collisions
from services.plant.core import OUTCOMES

log = logging.getLogger(__name__)


def group_of(r: dict[str, Any], by: str) -> str:
    """The row a record is summarised in: its scenario, its world's kind, or "all"."""
    if by == "scenario":
        return r["scenario"]
    if by == "kind":
        return r.get("kind") or r["scenario"]
    return "all"


def summarize(runs: Iterable[dict[str, Any]], by: str = "scenario") -> list[dict[str, Any]]:
    """Per group (`by`: scenario, kind or all) x controller x samples: the count of each
    outcome and the time to goal over the successful runs (mean, std, median); the
    median of the per-run ratios to the prescient controller's time on the same world and
    seed, where both succeeded; Fisher's exact test of the collision counts against each
    other controller's in the group."""
    runs = list(runs)
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for r in runs:
        groups.setdefault((group_of(r, by), r["controller"], r["samples"]), []).append(r)
    prescient = {(r["scenario"], r["samples"], r["seed"]): r["time_to_goal_s"] for r in runs
                 if r["controller"] == "prescient" and r["outcome"] == "success"}
    out = []
    for (group, controller, samples), rs in sorted(groups.items()):
        ttg = [r["time_to_goal_s"] for r in rs if r["outcome"] == "success"]
        row: dict[str, Any] = {by: group, "controller": controller, "samples": samples,
                               "runs": len(rs)}
        if by != "scenario":
            row["worlds"] = len({r["scenario"] for r in rs})
        row.update({o: sum(r["outcome"] == o for r in rs) for o in OUTCOMES})
        row["time_to_goal_mean_s"] = round(float(np.mean(ttg)), 3) if ttg else None
        row["time_to_goal_std_s"] = round(float(np.std(ttg)), 3) if ttg else None
        row["time_to_goal_median_s"] = round(float(np.median(ttg)), 3) if ttg else None
        ratios = [r["time_to_goal_s"] / prescient[key] for r in rs if r["outcome"] == "success"
                  and (key := (r["scenario"], r["samples"], r["seed"])) in prescient]
        row["ratio_to_prescient_median"] = (round(float(np.median(ratios)), 3) if ratios
                                            and controller != "prescient" else None)
        out.append(row)
    for row in out:
        mine = (row[by], row["samples"])
        row["collision_p"] = {
            o["controller"]: round(fisher_exact(row["collision"], row["runs"] - row["collision"],
                                                o["collision"], o["runs"] - o["collision"]), 6)
            for o in out if (o[by], o["samples"]) == mine and o is not row}
    return out


def fisher_exact(a: int, b: int, c: int, d: int) -> float:
    """Two-sided p of Fisher's exact test on the table [[a, b], [c, d]]: the probability,
    with the margins fixed, of a table no more likely than this one."""
    from math import comb
    n1, k, n = a + b, a + c, a + b + c + d
    total = comb(n, k)

    def prob(x: int) -> float:
        return comb(n1, x) * comb(n - n1, k - x) / total
    p0 = prob(a)
    lo, hi = max(0, k - (n - n1)), min(k, n1)
    return min(1.0, sum(p for x in range(lo, hi + 1) if (p := prob(x)) <= p0 * (1 + 1e-7)))


# The paper's reported figures (Section "Results and Discussion"): failure percentage
# of 100 runs and how many of those failures were collisions; time to goal mean
# and std over successful runs, s. A key is absent where the paper gives no number.
PAPER: dict[tuple[str, str, int], dict[str, Any]] = {
    ("offroad", "deterministic", 400): {"failure_pct": 92, "collision_pct": 92},
    ("offroad", "prescient", 400): {"failure_pct": 6, "collision_pct": 0,
                                    "time_to_goal": (12.2, 0.5)},
    ("offroad", "va", 400): {"failure_pct": 16, "collision_pct": 0, "time_to_goal": (13.3, 0.4)},
    ("alleyway", "deterministic", 400): {"failure_pct": 95, "collision_pct": 95},
    ("alleyway", "prescient", 400): {"failure_pct": 3, "time_to_goal": (12.5, 0.5)},
    ("alleyway", "va", 400): {"failure_pct": 9, "collision_pct": 4, "time_to_goal": (12.8, 0.4)},
    ("alleyway", "va", 1000): {"failure_pct": 8, "collision_pct": 2},
    ("alleyway", "va", 4000): {"failure_pct": 7, "collision_pct": 0},
    ("alleyway", "deterministic", 4000): {"failure_pct": 100, "collision_pct": 100},
    ("offroad", "deterministic", 4000): {"failure_pct": 100, "collision_pct": 100},
}


def markdown_table(summary: list[dict[str, Any]], by: str = "scenario") -> str:
    """A summary (`summarize(runs, by)`) as a markdown table; per scenario, the paper's
    figures beside ours."""
    def pct(n: int, runs: int) -> str:
        return f"{100.0 * n / runs:.0f} %"

    paper_cols = by == "scenario"
    head = (f"| {by} | controller | K | runs | success | collision | stopping | timeout "
            "| time to goal, s | median, s | × prescient |")
    lines = [head + (" paper: failures (collisions) | paper: time to goal, s |"
                     if paper_cols else ""),
             "|---" * (11 + 2 * paper_cols) + "|"]
    for r in summary:
        n = r["runs"]
        ttg = "—"
        if r["time_to_goal_mean_s"] is not None:
            ttg = (f"{r['time_to_goal_mean_s']:.2f} ± {r['time_to_goal_std_s']:.2f}"
                   if r["success"] > 1 else f"{r['time_to_goal_mean_s']:.2f}")
        med = "—" if r.get("time_to_goal_median_s") is None else f"{r['time_to_goal_median_s']:.2f}"
        ratio = ("—" if r.get("ratio_to_prescient_median") is None
                 else f"{r['ratio_to_prescient_median']:.3f}")
        line = (f"| {r[by]} | {r['controller']} | {r['samples']} | {n} | {pct(r['success'], n)} "
                f"| {pct(r['collision'], n)} | {pct(r['stopping'], n)} | {pct(r['timeout'], n)} "
                f"| {ttg} | {med} | {ratio} |")
        if paper_cols:
            paper = PAPER.get((r["scenario"], r["controller"], r["samples"]), {})
            p_fail = (f"{paper['failure_pct']} %" + (f" ({paper['collision_pct']} %)"
                                                     if "collision_pct" in paper else "")
                      if "failure_pct" in paper else "—")
            p_ttg = ("{} ± {}".format(*paper["time_to_goal"]) if "time_to_goal" in paper
                     else "—")
            line += f" {p_fail} | {p_ttg} |"
        lines.append(line)
    return "\n".join(lines) + "\n"


def fisher_lines(summary: list[dict[str, Any]], by: str) -> str:
    """Fisher's exact test of each controller's collisions against the others'."""
    rows = [f"- {r[by]}, K = {r['samples']}: {r['controller']} against "
            + ", ".join(f"{c} p = {p:.3g}" for c, p in sorted(r["collision_p"].items()))
            for r in summary if r["controller"] == "va" and r["collision_p"]]
    return ("\nCollisions, Fisher's exact test (two-sided):\n\n" + "\n".join(rows) + "\n"
            if rows else "")


def summary_markdown(runs: list[dict[str, Any]]) -> tuple[str, dict[str, Any]]:
    """summary.md's tables (overall and per world kind where the runs span more than one
    world, then per scenario) and the summaries they show."""
    per = {"scenario": summarize(runs)}
    text = ""
    if len({r["scenario"] for r in runs}) > 1:
        for by in ("all", "kind"):
            per[by] = summarize(runs, by)
            text += f"By {by if by == 'kind' else 'set'}:\n\n" + markdown_table(per[by], by) \
                + fisher_lines(per[by], by) + "\n"
        text += "By scenario:\n\n"
    return text + markdown_table(per["scenario"]), per


def collisions_section(cfg: Config, runs: list[dict[str, Any]], out: Path) -> str:
    """summary.md's second table, what each collision was on (deploy/analysis/collisions.py; records
    older than the `collision` field as `vamppi collisions DIR --rerun` left them); "" when
    no run collided."""
    if not any(r["outcome"] == "collision" for r in runs):
        return ""
    try:
        saved = collisions.load_saved(out)
    except ValueError as exc:
        log.warning("%s", exc)
        saved = []
    rows = collisions.attribute(cfg, runs, saved=saved)
    return ("\nWhat the collisions were on (`vamppi collisions DIR`):\n\n"
            + collisions.table(rows) + "\n")


def write_summary(cfg: Config, runs: list[dict[str, Any]], out: Path, plots: bool = True
                  ) -> list[dict[str, Any]]:
    """Write what `runs` (an experiment's, in `out`) show; the per-scenario summary."""
    text, per = summary_markdown(runs)
    summary = per["scenario"]
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    if len(per) > 1:
        (out / "summary-kinds.json").write_text(json.dumps(per["kind"] + per["all"], indent=2)
                                                + "\n")
    (out / "summary.md").write_text(text + collisions_section(cfg, runs, out))
    if plots:
        from deploy.analysis import plots as plotting
        plotting.plot_all(cfg, runs, summary, out)
    return summary
