"""Plots of an experiment, like the paper's figures (matplotlib, Agg backend).

failures.png          failures per controller and sample count, collision / stopping / timeout
time_to_goal.png      time-to-goal box plots over successful runs
trajectories_<s>.png  every run's path over the scenario, coloured by speed
solve_time.png        histogram of planner solve times
visibility_<s>.png    one VA-MPPI run: the map variance, the vehicle and its plan over time

and `plot_scenario`, a scenario's top-down picture (`vamppi scenario --plot`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from common.config import Config  # noqa: E402
from common.scenarios import label, scenario_of  # noqa: E402

log = logging.getLogger(__name__)
CONTROLLER_COLORS = {"deterministic": "tab:red", "prescient": "tab:green", "va": "tab:blue"}


def save_figure(fig, path: Path, dpi: int = 120, tight: bool = True, title: str = "") -> Path:
    """Write `fig` to `path` (laid out tight unless not `tight`), titled `title` above its
    own titles (what it shows: the recording or experiment, controllers, K), and close it."""
    if title:
        old = fig.get_suptitle()
        fig.suptitle(f"{title}: {old}" if old else title, fontsize=9)
    if tight:
        fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def _groups(summary: list[dict[str, Any]], scenario: str) -> list[dict[str, Any]]:
    return [r for r in summary if r["scenario"] == scenario]


def plot_failures(summary: list[dict[str, Any]], out: Path, title: str = "") -> Path:
    scenarios = sorted({r["scenario"] for r in summary})
    fig, axes = plt.subplots(1, len(scenarios), figsize=(6 * len(scenarios), 4), squeeze=False)
    for ax, scenario in zip(axes[0], scenarios, strict=True):
        rows = _groups(summary, scenario)
        labels = [f"{r['controller']}\n{r['samples']}" for r in rows]
        x = np.arange(len(rows))
        bottom = np.zeros(len(rows))
        for outcome, color in (("collision", "tab:red"), ("stopping", "tab:orange"),
                               ("timeout", "tab:gray")):
            pct = np.array([100.0 * r[outcome] / r["runs"] for r in rows])
            ax.bar(x, pct, bottom=bottom, color=color, label=outcome)
            bottom += pct
        ax.set_xticks(x, labels, fontsize=8)
        ax.set_ylabel("failures, % of runs")
        ax.set_ylim(0, 100)
        ax.set_title(scenario)
        ax.legend(fontsize=8)
    return save_figure(fig, out / "failures.png", title=title)


def plot_time_to_goal(runs: list[dict[str, Any]], out: Path, title: str = "") -> Path:
    scenarios = sorted({r["scenario"] for r in runs})
    fig, axes = plt.subplots(1, len(scenarios), figsize=(6 * len(scenarios), 4), squeeze=False)
    for ax, scenario in zip(axes[0], scenarios, strict=True):
        keys = sorted({(r["controller"], r["samples"]) for r in runs if r["scenario"] == scenario})
        data, labels = [], []
        for c, k in keys:
            t = [r["time_to_goal_s"] for r in runs if r["scenario"] == scenario
                 and r["controller"] == c and r["samples"] == k and r["outcome"] == "success"]
            data.append(t)
            labels.append(f"{c}\n{k}\n(n={len(t)})")
        ax.boxplot([d if d else [np.nan] for d in data])
        ax.set_xticks(np.arange(1, len(labels) + 1), labels, fontsize=8)
        ax.set_ylabel("time to goal, s (successful runs)")
        ax.set_title(scenario)
    return save_figure(fig, out / "time_to_goal.png", title=title)


def _scenario_background(ax, cfg: Config, scenario: str) -> None:
    scn = scenario_of(cfg.replace(**{"episode.scenario": scenario}))
    h, w = scn.heightmap.shape
    extent = (0, w * scn.resolution, 0, h * scn.resolution)
    ax.imshow(scn.heightmap, origin="lower", extent=extent, cmap="Greys", vmin=-0.5, vmax=4.0)
    ax.plot(scn.start.x, scn.start.y, "k^", ms=7)
    ax.add_patch(plt.Circle((scn.goal.x, scn.goal.y), cfg.episode.goal_radius_m, fill=False,
                            color="k", lw=1.2))


def plot_scenario(cfg: Config, scenario: str, path: Path) -> Path:
    """Top-down picture: terrain and obstacles (height above the bare ground), the
    start (triangle, heading) and the goal region, each obstacle numbered as listed
    by `vamppi scenario`."""
    scn = scenario_of(cfg.replace(**{"episode.scenario": scenario}))
    h, w = scn.heightmap.shape
    extent = (0, w * scn.resolution, 0, h * scn.resolution)
    fig, ax = plt.subplots(figsize=(7, 6.2))
    im = ax.imshow(scn.heightmap, origin="lower", extent=extent, cmap="terrain", vmin=-1.0,
                   vmax=5.0)
    fig.colorbar(im, ax=ax, label="elevation, m", shrink=0.8)
    for i, ob in enumerate(scn.obstacles):
        if ob.height < 4.0 or ob.hidden:     # the tree trunks are too many to number
            ax.annotate(str(i), (ob.x, ob.y), color="r" if ob.hidden else "k", fontsize=7,
                        ha="center", va="center", fontweight="bold" if ob.hidden else None)
    ax.annotate("", (scn.start.x + 4 * np.cos(scn.start.yaw), scn.start.y
                     + 4 * np.sin(scn.start.yaw)), (scn.start.x, scn.start.y),
                arrowprops={"arrowstyle": "->", "color": "k", "lw": 2})
    ax.plot(scn.start.x, scn.start.y, "k^", ms=8, label="start")
    ax.add_patch(plt.Circle((scn.goal.x, scn.goal.y), cfg.episode.goal_radius_m, fill=False,
                            color="r", lw=1.5, label=f"goal region: within "
                            f"{cfg.episode.goal_radius_m:g} m of the goal, below "
                            f"{cfg.episode.goal_speed_mps:g} m/s"))
    ax.plot([], [], " ", label="n: obstacle n as `vamppi scenario` lists it")
    if any(ob.hidden for ob in scn.obstacles):
        ax.plot([], [], " ", label="red n: hidden from the approach (behind an occluder)")
    ax.set_title(f"{scenario} (layout {scn.layout}): {scn.description}", fontsize=8, wrap=True)
    ax.set_xlabel("x, m")
    ax.set_ylabel("y, m")
    ax.legend(fontsize=8, loc="lower right")
    return save_figure(fig, path)


def plot_trajectories(cfg: Config, runs: list[dict[str, Any]], scenario: str, out: Path,
                      title: str = "") -> Path:
    controllers = sorted({r["controller"] for r in runs if r["scenario"] == scenario})
    fig, axes = plt.subplots(1, len(controllers), figsize=(5.5 * len(controllers), 5),
                             squeeze=False)
    vmax = max((r["max_speed_mps"] for r in runs if r["scenario"] == scenario), default=1.0)
    line = None
    for ax, c in zip(axes[0], controllers, strict=True):
        _scenario_background(ax, cfg, scenario)
        mine = [r for r in runs if r["scenario"] == scenario and r["controller"] == c]
        for r in mine:
            p = np.asarray(r["path"])
            line = ax.scatter(p[:, 1], p[:, 2], c=p[:, 3], s=2, cmap="viridis", vmin=0,
                              vmax=vmax)
            if r["outcome"] == "collision":
                ax.plot(p[-1, 1], p[-1, 2], "rx", ms=6)
        hits = sum(r["outcome"] == "collision" for r in mine)
        ks = ", ".join(str(k) for k in sorted({r["samples"] for r in mine}))
        ax.set_title(f"{scenario}, {c}, K = {ks}: {len(mine)} runs, {hits} collisions (x)",
                     fontsize=10)
        ax.set_xlabel("x, m")
        ax.set_ylabel("y, m")
    if line is not None:
        fig.colorbar(line, ax=axes[0].tolist(), label="speed, m/s")
    return save_figure(fig, out / f"trajectories_{label(scenario)}.png", tight=False,
                       title=title)


def plot_solve_time(runs: list[dict[str, Any]], out: Path, title: str = "") -> Path:
    fig, ax = plt.subplots(figsize=(7, 4))
    keys = sorted({(r["controller"], r["samples"]) for r in runs})
    for c, k in keys:
        t = np.concatenate([np.asarray(r["solve_ms"][1:], dtype=float) for r in runs
                            if r["controller"] == c and r["samples"] == k] or [np.zeros(0)])
        if t.size:
            ax.hist(t, bins=40, alpha=0.5, label=f"{c} K={k} (median {np.median(t):.0f} ms)")
    ax.axvline(100.0, color="k", ls="--", lw=1, label="10 Hz")
    ax.set_xlabel("solve time per control tick, ms (first tick, with compilation, excluded)")
    ax.set_ylabel("ticks")
    ax.legend(fontsize=8)
    return save_figure(fig, out / "solve_time.png", title=title)


def plot_visibility(cfg: Config, scenario: str, samples: int, seed: int, out: Path,
                    title: str = "") -> Path:
    """One VA-MPPI run: the map variance and the plan at four moments."""
    from deploy.sim.runner import run_episode
    run_cfg = cfg.replace(**{"episode.scenario": scenario, "planner.controller": "va",
                             "planner.samples": samples, "episode.seed": seed})
    ticks = frozenset(range(0, int(run_cfg.episode.timeout_s / run_cfg.planner.dt_s), 15))
    result = run_episode(run_cfg, snapshot_ticks=ticks)
    snaps = result.snapshots[:: max(1, len(result.snapshots) // 4)][:4]
    fig, axes = plt.subplots(2, len(snaps), figsize=(4.5 * len(snaps), 8), squeeze=False)
    res = run_cfg.mapper.resolution_m
    extent = (0, snaps[0]["variance"].shape[1] * res, 0, snaps[0]["variance"].shape[0] * res)
    for j, s in enumerate(snaps):
        for i, (layer, cmap, title) in enumerate((("variance", "magma", "variance"),
                                                  ("mean", "terrain", "mean"))):
            ax = axes[i][j]
            ax.imshow(s[layer], origin="lower", extent=extent, cmap=cmap)
            ax.plot(s["optimal"][:, 3], s["optimal"][:, 4], "c-", lw=1.5)
            ax.plot(s["x"][3], s["x"][4], "wo", ms=4)
            ax.set_title(f"{title}, t = {s['t']:.1f} s, surface cost {s['terms'][2]:.0f}, "
                         f"f_xt {s['controls'][0][1]:.0f} N", fontsize=8)
    fig.suptitle(f"{scenario}, VA-MPPI K={samples}, seed {seed}: {result.outcome}")
    return save_figure(fig, out / f"visibility_{label(scenario)}.png", dpi=110, title=title)


PER_SCENARIO_PLOTS = 6       # trajectories and visibility pictures only for this few scenarios


def plot_all(cfg: Config, runs: list[dict[str, Any]], summary: list[dict[str, Any]],
             out: Path, visibility: bool = True) -> list[Path]:
    if not runs:
        return []
    title = f"experiment {out.name}"
    paths = [plot_failures(summary, out, title), plot_time_to_goal(runs, out, title),
             plot_solve_time(runs, out, title)]
    scenarios = sorted({r["scenario"] for r in runs})
    if len(scenarios) > PER_SCENARIO_PLOTS:
        log.info("plots: %d scenarios, no per-scenario plots (at most %d)", len(scenarios),
                 PER_SCENARIO_PLOTS)
        scenarios = []
    for scenario in scenarios:
        paths.append(plot_trajectories(cfg, runs, scenario, out, title))
        va = [r for r in runs if r["scenario"] == scenario and r["controller"] == "va"]
        if visibility and va:
            paths.append(plot_visibility(cfg, scenario, min(r["samples"] for r in va),
                                         min(r["seed"] for r in va), out, title))
    log.info("plots: %s", ", ".join(p.name for p in paths))
    return paths
