"""Planner service: one MPPI solve per control tick, publishes cmd, plan and stats.

The shell of `services.planner.protocol`: states and maps from the bus into it, its
solves onto the bus. At start it asks the plant for the last command it obeyed and, if
this instance sent it, goes on from it (a restart warm-starts where it left off).
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from common.bus import Node, Transport
from common.config import Config
from common.messages import Cmd, Map, Plan, State, Stats, encode
from common.protocol import ACCEPTED
from common.scenarios import scenario_of
from services.planner import mppi, protocol

log = logging.getLogger(__name__)


def main(cfg: Config, instance: str = "0", stop: threading.Event | None = None,
         bus: Transport | None = None) -> None:
    stop = stop or threading.Event()
    p = protocol.PlannerProtocolParams.from_config(cfg, scenario_of(cfg))
    sv = cfg.supervision
    with Node(bus or cfg.bus, cfg.episode.vehicle, "planner", instance, cfg.to_dict(),
              sv.heartbeat_period_s, sv.heartbeat_deadline_s) as node:
        node.role = "active"
        states = node.subscribe("state", State, maxlen=4096 if p.lockstep else 1)
        maps = node.subscribe("map", Map, maxlen=64 if p.lockstep else 1)
        pubs = {"cmd": node.publisher("cmd", Cmd, express=True),
                "plan": node.publisher("plan", Plan), "stats": node.publisher("stats", Stats)}
        n = cfg.mapper.size_cells
        zeros = np.zeros((n, n), np.float32)                     # compile before ready
        mppi.solve(p.mppi, mppi.initial_state(p.mppi, 0), np.zeros(6), np.zeros(2), p.goal,
                   zeros, zeros, np.zeros(2), cfg.mapper.resolution_m)
        run = protocol.PlannerRun(cfg.episode.seed)
        node.hold("state", lambda: None if run.held_state is None else encode(run.held_state))
        node.hold("map", lambda: None if run.held_map is None else encode(run.held_map))
        node.hold("cmd", lambda: pubs["cmd"].latest)
        for cmd in reversed(node.query_latest("cmd", Cmd)):
            if cmd.header.source == node.source:
                run = protocol.recover(p, run, cmd)
                log.info("going on from the command of t=%.2f the plant obeyed", cmd.t0)
                break
        node.ready()
        while not stop.is_set():
            node.progress()
            maps.wait(0.05)
            for st, wall in states.drain():
                run, verdict, outs = protocol.on_state(p, run, st, wall)
                if verdict not in ACCEPTED:
                    node.reject("state", verdict, st)
                for out in outs:                      # a re-offered tick answered again
                    pubs[out.topic].publish_out(out)
            for m, wall in maps.drain():
                run, verdict = protocol.on_map(p, run, m, wall)
                if verdict not in ACCEPTED:
                    node.reject("map", verdict, m)
            job = protocol.due(p, run, time.time())
            if job is None:
                continue
            run, outs = protocol.solve(p, run, job, time.time())
            for out in outs:
                pubs[out.topic].publish_out(out)
            node.progress(job.state.header.stamp, job.episode)
