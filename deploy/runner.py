"""The in-process lockstep episode: the services' cores composed without a bus.

This is the same sequence the bus pipeline runs in lockstep (plant state ->
sensor frame -> mapper update -> planner solve -> plant steps for one tick),
so for the same config and seed it gives the same trajectory, bit for bit.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from common.config import Config
from common.scenarios import Scenario, scenario_of
from services.mapper import core as mapper
from services.planner import mppi
from services.plant import core as plant
from services.plant.dynamics import S
from services.sensor import core as sensor


@dataclass(frozen=True)
class Cores:
    """Every service's parameters for one config: what each node builds at start."""
    cfg: Config
    scenario: Scenario
    plant: plant.PlantParams
    camera: sensor.CameraParams
    mapper: mapper.MapperParams
    planner: mppi.PlannerParams

    @classmethod
    def from_config(cls, cfg: Config) -> Cores:
        scn = scenario_of(cfg)
        return cls(cfg, scn, plant.PlantParams.from_config(cfg, scn),
                   sensor.CameraParams.from_config(cfg.sensor),
                   mapper.MapperParams.from_config(cfg, scn.origin),
                   mppi.PlannerParams.from_config(cfg))

    @property
    def goal(self) -> np.ndarray:
        g = self.scenario.goal
        return np.array([g.x, g.y, g.yaw])


# an obstacle counts as mapped once one of its cells is observed (variance below this
# fraction of the prior) with a mean standing plant.obstacle_height_m above the bare terrain
MAPPED_VARIANCE_FRACTION = 0.5


def mapped_obstacles(cells: tuple[np.ndarray, ...], mean: np.ndarray, variance: np.ndarray,
                     terrain: np.ndarray, min_height: float, max_variance: float) -> np.ndarray:
    """(n_obstacles,) bool: which obstacles the map shows, from their flat cell indices
    (`Scenario.obstacle_cells`): some cell observed (variance below `max_variance`) whose
    mean stands `min_height` or more above the bare terrain."""
    m, v, g = mean.ravel(), variance.ravel(), terrain.ravel()
    return np.array([bool(np.any((v[c] < max_variance) & (m[c] - g[c] >= min_height)))
                     for c in cells], dtype=bool)


def collision_record(cores: Cores, x: np.ndarray, t: float,
                     mapped_at: dict[int, float]) -> dict[str, Any] | None:
    """What a colliding state is on, for the run record: each obstacle with its place, its
    `hidden` flag and when the map first showed it (null: never before the collision);
    and when the map first showed each of the scenario's hidden obstacles, hit or not (a
    collision with a wall just after one appeared is the swerve it caused)."""
    c = plant.collision_of(cores.plant, x)
    if c is None:
        return None
    obs = []
    for i in c.obstacles:
        ob = cores.scenario.obstacles[i]
        seen = mapped_at.get(i)
        obs.append({"index": i, "kind": ob.kind, "x": ob.x, "y": ob.y, "hidden": ob.hidden,
                    "mapped_at_s": None if seen is None else round(seen, 3),
                    "mapped_for_s": None if seen is None else round(t - seen, 3)})
    hidden = [{"index": i, "x": ob.x, "y": ob.y,
               "mapped_at_s": None if mapped_at.get(i) is None else round(mapped_at[i], 3)}
              for i, ob in enumerate(cores.scenario.obstacles) if ob.hidden]
    return {"t_s": round(t, 3), "x": round(float(x[S.X]), 3), "y": round(float(x[S.Y]), 3),
            "heading_rad": round(float(x[S.PSI]), 4),
            "speed_mps": round(math.hypot(x[S.V], x[S.v]), 3),
            "off_map": c.off_map, "obstacles": obs, "hidden": hidden}


@dataclass
class EpisodeResult:
    outcome: str
    time_to_goal_s: float
    sim_time_s: float
    wall_time_s: float
    trajectory: np.ndarray                  # (steps+1, 7): t, V, v, r, X, Y, Psi
    solve_ms: list[float] = field(default_factory=list)
    snapshots: list[dict[str, Any]] = field(default_factory=list)
    collision: dict[str, Any] | None = None     # `collision_record` where the outcome is one

    def summary(self, cfg: Config) -> dict[str, Any]:
        return {"scenario": cfg.episode.scenario, "controller": cfg.planner.controller,
                "samples": cfg.planner.samples, "seed": cfg.episode.seed,
                "outcome": self.outcome,
                "time_to_goal_s": None if math.isnan(self.time_to_goal_s) else self.time_to_goal_s,
                "sim_time_s": round(self.sim_time_s, 6), "wall_time_s": round(self.wall_time_s, 3)}


def run_episode(cfg: Config, cores: Cores | None = None,
                snapshot_ticks: frozenset[int] = frozenset()) -> EpisodeResult:
    """One lockstep episode in this process. At each tick in `snapshot_ticks` the map,
    the state and the planned trajectory are kept (for the visibility plots)."""
    cores = cores or Cores.from_config(cfg)
    wall0 = time.monotonic()
    ps = plant.initial_state(cores.plant)
    z0 = plant.ground_z(cores.plant, ps.x[S.X], ps.x[S.Y])
    m = mapper.initial_map(cores.mapper, ps.x[S.X], ps.x[S.Y], z0)
    qs = mppi.initial_state(cores.planner, cfg.episode.seed)
    rows = [np.concatenate([[ps.t], ps.x])]
    solve_ms: list[float] = []
    snapshots: list[dict[str, Any]] = []
    obstacle_cells = cores.scenario.obstacle_cells(cores.cfg.plant.obstacle_height_m)
    max_var = MAPPED_VARIANCE_FRACTION * cores.mapper.prior_variance
    mapped_at: dict[int, float] = {}
    # the map on the scenario's grid (the default): when it is not, no obstacle counts as mapped
    track = m.mean.shape == cores.scenario.heightmap.shape
    tick = 0
    while not ps.done:
        x, z = ps.x, plant.ground_z(cores.plant, ps.x[S.X], ps.x[S.Y])
        depth, pos, rot = sensor.render(cores.camera, cores.scenario.heightmap,
                                        cores.scenario.origin, cores.scenario.resolution,
                                        x[S.X], x[S.Y], z, x[S.PSI])
        m = mapper.update(cores.mapper, m, depth, cores.camera.intrinsics, pos, rot,
                          np.array([x[S.X], x[S.Y], z, x[S.PSI]]))
        if track:
            shown = mapped_obstacles(obstacle_cells, np.asarray(m.mean), np.asarray(m.variance),
                                     cores.scenario.terrain, cores.cfg.plant.obstacle_height_m,
                                     max_var)
            for i in np.flatnonzero(shown):
                mapped_at.setdefault(int(i), ps.t)
        mean, var = mppi.planning_map(cores.planner, cores.scenario.heightmap, m.mean,
                                      m.variance)
        if tick > 0:
            qs = mppi.advance(qs, 1)
        t_solve = time.perf_counter()
        qs, out = mppi.solve(cores.planner, qs, x, ps.u_applied, cores.goal, mean, var,
                             cores.mapper.origin, cores.mapper.resolution)
        controls = np.asarray(out.controls)
        solve_ms.append((time.perf_counter() - t_solve) * 1e3)
        if tick in snapshot_ticks:
            snapshots.append({"t": ps.t, "x": ps.x.copy(), "mean": m.mean.copy(),
                              "variance": m.variance.copy(),
                              "optimal": np.asarray(out.optimal), "terms": np.asarray(out.terms),
                              "controls": controls.copy(),
                              "u_prev": np.asarray(ps.u_applied).copy()})
        t0 = ps.t
        for _ in range(cores.plant.steps_per_tick):
            u = plant.control_at(ps.t, t0, cores.plant.tick_s, controls)
            ps = plant.plant_step(cores.plant, ps, u)
            rows.append(np.concatenate([[ps.t], ps.x]))
            if ps.done:
                break
        tick += 1
    collision = (collision_record(cores, ps.x, ps.t, mapped_at)
                 if ps.outcome == "collision" else None)
    return EpisodeResult(ps.outcome, ps.time_to_goal_s, ps.t, time.monotonic() - wall0,
                         np.array(rows), solve_ms, snapshots, collision)
