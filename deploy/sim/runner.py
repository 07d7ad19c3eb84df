"""The in-process episode: the services' protocol cores composed without a bus.

The nodes wire each service's protocol (`services/<name>/protocol.py`) to the bus; here
the same functions are called in turn, with the messages a publisher would have sent
(`common.protocol.Stamper`): plant state -> sensor frame -> mapper update -> planner
solve -> plant steps for one tick. In lockstep, for the same config and seed, this is
the trajectory the bus pipeline gives, bit for bit.

`planner_link` simulates realtime instead, on a simulated wall clock (the sim time): the
cores run as in realtime, the plant stepping on the newest command and braking when it is
stale, and wherever `planner_link(t)` is False the planner is cut off from the bus (no
state or map reaches it, no command of its reaches the plant): an outage, then the
planner resuming as its node does.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from common.config import Config
from common.messages import Cmd, Depth, Map, State
from common.protocol import Out, Stamper
from common.scenarios import Scenario, scenario_of
from services.mapper import protocol as mapper
from services.planner import protocol as planner
from services.plant import core as plant_core
from services.plant import protocol as plant
from services.plant.dynamics import S
from services.sensor import protocol as sensor

EPISODE = 1                     # the in-process runner's episode name


@dataclass(frozen=True)
class Cores:
    """Every service's protocol parameters for one config: what each node builds at start."""
    cfg: Config
    scenario: Scenario
    plant: plant.PlantProtocolParams
    sensor: sensor.SensorParams
    mapper: mapper.MapperProtocolParams
    planner: planner.PlannerProtocolParams

    @classmethod
    def from_config(cls, cfg: Config) -> Cores:
        scn = scenario_of(cfg)
        return cls(cfg=cfg, scenario=scn,
                   plant=plant.PlantProtocolParams.from_config(
                       cfg, plant_core.PlantParams.from_config(cfg, scn)),
                   sensor=sensor.SensorParams.from_config(cfg, scn),
                   mapper=mapper.MapperProtocolParams.from_config(cfg, scn.origin),
                   planner=planner.PlannerProtocolParams.from_config(cfg, scn))

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
    c = plant_core.collision_of(cores.plant.sim, x)
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
    stale_steps: int = 0                        # plant periods braked for want of a command

    def summary(self, cfg: Config) -> dict[str, Any]:
        return {"scenario": cfg.episode.scenario, "controller": cfg.planner.controller,
                "samples": cfg.planner.samples, "seed": cfg.episode.seed,
                "outcome": self.outcome,
                "time_to_goal_s": None if math.isnan(self.time_to_goal_s) else self.time_to_goal_s,
                "sim_time_s": round(self.sim_time_s, 6), "wall_time_s": round(self.wall_time_s, 3)}


class _Wire:
    """What the bus would carry between the cores: each service's messages stamped as its
    publisher would (seq, boot, source)."""

    def __init__(self) -> None:
        self.stampers = {svc: Stamper(f"{svc}/0", boot=1, wall=lambda: 0.0)
                         for svc in ("plant", "sensor", "mapper", "planner")}

    def message(self, service: str, cls: type, out: Out) -> Any:
        return self.stampers[service].make(cls, out)


def run_episode(cfg: Config, cores: Cores | None = None,
                snapshot_ticks: frozenset[int] = frozenset(),
                planner_link: Callable[[float], bool] | None = None) -> EpisodeResult:
    """One episode in this process (lockstep; simulated realtime with `planner_link`, see
    the module's docstring). At each tick in `snapshot_ticks` the map, the state and the
    planned trajectory are kept (for the visibility plots)."""
    realtime = planner_link is not None
    if realtime:
        cfg = cfg.replace(**{"episode.clock": "realtime"})
        cores = Cores.from_config(cfg)
    elif cfg.episode.clock != "lockstep":
        cfg = cfg.replace(**{"episode.clock": "lockstep"})
        cores = None
    cores = cores or Cores.from_config(cfg)
    wall0 = time.monotonic()
    wire = _Wire()
    pr, outs = plant.start(cores.plant, EPISODE, 0.0)
    sr, mr = sensor.SensorRun(), mapper.MapperRun()
    qr = planner.PlannerRun(cfg.episode.seed, boot=1)        # the wire's planner process
    rows = [np.concatenate([[pr.sim.t], pr.sim.x])]
    solve_ms: list[float] = []
    snapshots: list[dict[str, Any]] = []
    obstacle_cells = cores.scenario.obstacle_cells(cores.cfg.plant.obstacle_height_m)
    max_var = MAPPED_VARIANCE_FRACTION * cores.mapper.core.prior_variance
    mapped_at: dict[int, float] = {}
    # the map on the scenario's grid (the default): when it is not, no obstacle counts as mapped
    track = cores.mapper.core.size_cells == cores.scenario.heightmap.shape[0]
    tick = 0
    while not pr.done:
        wall = pr.sim.t                                 # the simulated wall clock
        linked = planner_link is None or planner_link(wall)
        states = [wire.message("plant", State, o) for o in outs if o.topic == "state"]
        m = None
        for st in states:
            sr, _, frames = sensor.on_state(cores.sensor, sr, st, wall)
            if linked:
                qr, _, _ = planner.on_state(cores.planner, qr, st, wall)
            for f in frames:
                mr, _, maps = mapper.on_depth(cores.mapper, mr, wire.message("sensor", Depth, f),
                                              wall)
                for mo in maps:
                    m = wire.message("mapper", Map, mo)
                    if linked:
                        qr, _ = planner.on_map(cores.planner, qr, m, wall)
        if m is not None and track:
            shown = mapped_obstacles(obstacle_cells, m.mean, m.variance, cores.scenario.terrain,
                                     cores.cfg.plant.obstacle_height_m, max_var)
            for i in np.flatnonzero(shown):
                mapped_at.setdefault(int(i), pr.sim.t)
        outs = ()
        job = planner.due(cores.planner, qr, wall) if linked else None
        if job is not None:
            qr, answer = planner.solve(cores.planner, qr, job, wall)
            cmd_out, plan_out, stats_out = answer
            solve_ms.append(stats_out.fields["solve_ms"])
            if tick in snapshot_ticks:
                snapshots.append({"t": pr.sim.t, "x": pr.sim.x.copy(),
                                  "mean": job.map.mean.copy(),
                                  "variance": job.map.variance.copy(),
                                  "origin": np.asarray(job.map.origin).copy(),
                                  "resolution": job.map.resolution,
                                  "optimal": plan_out.fields["optimal"],
                                  "terms": np.array(list(stats_out.fields["terms"].values()),
                                                    np.float32),
                                  "controls": cmd_out.fields["controls"].copy(),
                                  "u_prev": np.asarray(pr.sim.u_applied).copy()})
            pr, verdict, outs = plant.on_cmd(cores.plant, pr,
                                             wire.message("planner", Cmd, cmd_out), wall)
            if verdict != "new":
                raise RuntimeError(f"the plant rejected the planner's command: {verdict}")
        if realtime:
            stepped: tuple[Out, ...] = ()
            for _ in range(cores.plant.sim.steps_per_tick):
                pr, o = plant.realtime_step(cores.plant, pr)
                stepped += o
                if pr.done:
                    break
            outs += stepped
        elif job is None:
            raise RuntimeError(f"lockstep: no solve for t={pr.sim.t:.2f}")
        rows += [np.concatenate([[o.stamp], o.fields["x"]]) for o in outs if o.topic == "state"]
        tick += 1
    collision = (collision_record(cores, pr.sim.x, pr.sim.t, mapped_at)
                 if pr.sim.outcome == "collision" else None)
    return EpisodeResult(pr.sim.outcome, pr.sim.time_to_goal_s, pr.sim.t,
                         time.monotonic() - wall0, np.array(rows), solve_ms, snapshots,
                         collision, pr.stale_steps)
