"""Planner service: one MPPI solve per control tick, publishes cmd, plan and stats.

lockstep: each map is matched with the state of the same stamp; one solve per
map. realtime: one solve per new map, on the newest state (at most one per half
tick); without new maps, one per tick on the last map.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from common.bus import Node, ref_of
from common.config import Config
from common.messages import Cmd, Map, Plan, State, Stats
from common.scenarios import scenario_of
from services.planner import mppi
from services.planner.costs import TERMS

log = logging.getLogger(__name__)


def main(cfg: Config, instance: str = "0", stop: threading.Event | None = None) -> None:
    stop = stop or threading.Event()
    params = mppi.PlannerParams.from_config(cfg)
    scn = scenario_of(cfg)
    goal = np.array([scn.goal.x, scn.goal.y, scn.goal.yaw])
    lockstep = cfg.episode.clock == "lockstep"
    dt = params.dt
    with Node(cfg.bus, cfg.episode.vehicle, "planner", instance, cfg.to_dict()) as node:
        states = node.subscribe("state", State, maxlen=4096 if lockstep else 1)
        maps = node.subscribe("map", Map, maxlen=64 if lockstep else 1)
        cmd_pub = node.publisher("cmd", Cmd, express=True)
        plan_pub = node.publisher("plan", Plan)
        stats_pub = node.publisher("stats", Stats)
        qs = mppi.initial_state(params, cfg.episode.seed)
        n = cfg.mapper.size_cells
        mppi.solve(params, qs, np.zeros(6), np.zeros(2), goal, np.zeros((n, n), np.float32),
                   np.zeros((n, n), np.float32), np.zeros(2), cfg.mapper.resolution_m)  # JIT
        node.ready()
        last_t: float | None = None
        m: Map | None = None
        while not stop.is_set():
            if lockstep:
                m = maps.get(timeout=0.2)
                if m is None:
                    continue
                st = states.get_where(lambda s, t=m.header.stamp: abs(s.header.stamp - t) < 1e-6,
                                      timeout=30.0)
                if st is None:
                    log.warning("no state for map stamp %.2f", m.header.stamp)
                    continue
            else:
                # a solve as soon as a new map is in, on the newest state (the map of a
                # tick arrives a frame's render and fusion after the tick); no new map in
                # 1.5 ticks: a solve on the last one, once a tick
                fresh = maps.get(timeout=1.5 * dt if m is not None else 0.2)
                if fresh is not None:
                    m = fresh
                st = states.peek_latest()
                if st is None or m is None:
                    continue
                if not realtime_due(last_t, st.header.stamp, fresh is not None, dt):
                    continue
            t = st.header.stamp
            if last_t is None or t < last_t - 1e-9:        # first tick, or a new episode
                qs = mppi.initial_state(params, cfg.episode.seed)
            else:
                qs = mppi.advance(qs, int(round((t - last_t) / dt)))
            last_t = t
            mean, var = mppi.planning_map(params, scn.heightmap, m.mean, m.variance)
            t_solve = time.perf_counter()
            qs, out = mppi.solve(params, qs, st.x, st.u_applied, goal, mean, var, m.origin,
                                 m.resolution)
            controls = np.asarray(out.controls)
            solve_ms = (time.perf_counter() - t_solve) * 1e3
            inputs = [ref_of(states.key, st), ref_of(maps.key, m)]
            cmd_pub.publish(t, inputs, t0=t, dt=dt, controls=controls)
            plan_pub.publish(t, inputs, controller=params.controller,
                             optimal=np.asarray(out.optimal), nominal=controls,
                             rollouts=np.asarray(out.rollouts_xy),
                             rollout_costs=np.nan_to_num(np.asarray(out.rollout_costs, np.float32),
                                                           posinf=np.finfo(np.float32).max))
            stats_pub.publish(t, inputs, controller=params.controller, samples=params.samples,
                              solve_ms=solve_ms, cost_min=_finite(out.cost_min),
                              cost_mean=_finite(out.cost_mean),
                              terms=dict(zip(TERMS, map(float, np.asarray(out.terms)),
                                             strict=True)))


def realtime_due(last_t: float | None, t: float, fresh_map: bool, dt: float) -> bool:
    """Whether a realtime solve is due on the newest state (stamp t): the first, the first
    of a new episode (t went back), half a tick after the last on a new map, a tick after
    it on the last map."""
    if last_t is None or t < last_t - 1e-9:
        return True
    return t >= last_t + (0.5 if fresh_map else 1.0) * dt - 1e-6


def _finite(v) -> float:
    """A cost for the stats message: inf (every rollout invalid) becomes float max."""
    return float(np.nan_to_num(float(v), posinf=np.finfo(np.float32).max))
