"""Planner service: one MPPI solve per control tick, publishes cmd, plan and stats.

The shell of `services.planner.protocol`: states, maps and the authority's commands from
the bus into it, its solves onto the bus. At start it asks the plant for the last command
it obeyed and, if this instance sent it, goes on from it (a restart warm-starts where it
left off). Its role (docs/hotswap.md):

- `active`: commands while the plant names it;
- `standby`: follows the authority, takes over when the plant promotes it;
- `candidate`: follows and solves in shadow (plans on the `shadow` topic) for
  `take_over_after_s` and until the episode reaches `take_over_at_s`, then asks for the
  authority with a Handover; once granted it is active. The planner it replaced
  retires (exits) or, without `retire`, stands by;
- `replay`: commands every tick (`vamppi replay --feed`).

It beats five times per `supervision.planner_deadline_s` (0.15 s) and states that
deadline, so that a stopped or dead authority is replaced within a few control periods;
it is declared stalled (wedged while its threads run) only after the main loop has made
no progress for `supervision.heartbeat_deadline_s`, which no solve lasts.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import replace

import numpy as np

from common.bus import Node, Transport
from common.config import Config
from common.messages import Cmd, Handover, Map, Plan, State, Stats, encode
from common.protocol import ACCEPTED
from common.scenarios import scenario_of
from services.planner import mppi, protocol

log = logging.getLogger(__name__)

ROLES = ("active", "standby", "candidate", "replay")
REQUEST_EVERY_S = 0.5        # a candidate asks again until it is granted


def main(cfg: Config, instance: str = "0", stop: threading.Event | None = None,
         bus: Transport | None = None, role: str = "active",
         take_over_after_s: float = 0.0, retire: bool = True,
         take_over_at_s: float = 0.0) -> str:
    stop = stop or threading.Event()
    scn = scenario_of(cfg)
    p = protocol.PlannerProtocolParams.from_config(cfg, scn)
    sv = cfg.supervision
    floor = sv.planner_deadline_s
    with Node(bus or cfg.bus, cfg.episode.vehicle, "planner", instance, cfg.to_dict(),
              floor / 5, floor, sv.heartbeat_deadline_s, world=scn.digest) as node:
        node.role = role
        fifo = p.lockstep
        states = node.subscribe("state", State, maxlen=4096 if fifo else 1)
        maps = node.subscribe("map", Map, maxlen=64 if fifo else 1)
        cmds = node.subscribe("cmd", Cmd, maxlen=64 if fifo else 2)
        handovers = node.subscribe("handover", Handover, maxlen=16)
        drop = not p.lockstep        # realtime: a stopped subscriber must not push back
        pubs = {"cmd": node.publisher("cmd", Cmd, express=True, drop=drop),
                "plan": node.publisher("plan", Plan, drop=drop),
                "stats": node.publisher("stats", Stats, drop=drop),
                "shadow": node.publisher("shadow", Plan, drop=drop),
                "handover": node.publisher("handover", Handover)}
        n = cfg.mapper.size_cells
        zeros = np.zeros((n, n), np.float32)                     # compile before ready
        qs0 = mppi.initial_state(p.mppi, 0)
        mppi.solve(p.mppi, qs0, np.zeros(6), np.zeros(2), p.goal, zeros, zeros, np.zeros(2),
                   cfg.mapper.resolution_m)
        for u in (np.zeros(2), np.array([1.0, 1e5])):   # the warm start's eager operations
            protocol.warm_start(p, qs0, 0.0, p.dt, u)  # too: a standby's first solve is fast
        run = protocol.PlannerRun(cfg.episode.seed, source=node.source, boot=node.boot,
                                  role=role)
        node.hold("state", lambda: None if run.held_state is None else encode(run.held_state))
        node.hold("map", lambda: None if run.held_map is None else encode(run.held_map))
        node.hold("cmd", lambda: pubs["cmd"].latest)
        for cmd in reversed(node.query_latest("cmd", Cmd)):
            if cmd.header.source == node.source:
                run = protocol.recover(p, run, cmd)
                log.info("going on from the command of t=%.2f the plant obeyed", cmd.t0)
                break
        node.ready()
        ready_at, asked_at = time.monotonic(), 0.0
        replaced: dict[int, bool] = {}            # epoch granted to another -> retire
        became_active: float | None = None
        waits: list[float] = []
        while not stop.is_set():
            node.progress()
            node.wait_any(0.05)
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
            for cmd, wall in cmds.drain():
                run, _ = protocol.on_cmd(p, run, cmd, wall)
            for h, _ in handovers.drain():
                if h.current == node.source and h.to != node.source:
                    replaced[h.epoch + 1] = h.retire
            was = run.role
            run = _role(run, node, replaced)
            if run.role == "active" and was != "active":
                became_active = time.monotonic()
            if run.role == "retired":
                log.info("retired: another planner has the authority")
                break
            cur = run.episodes.current()
            sim_t = None if cur is None else cur[1].states.newest_stamp()
            if (run.role == "candidate" and time.monotonic() - ready_at >= take_over_after_s
                    and sim_t is not None and sim_t >= take_over_at_s
                    and time.monotonic() - asked_at >= REQUEST_EVERY_S):
                req = protocol.handover_request(run, retire=retire)
                if req is not None:
                    pubs["handover"].publish_out(req)
                    asked_at = time.monotonic()
            job = protocol.due(p, run, time.time())
            if job is None:
                if run.role == "active" and became_active is not None:
                    waits.append(time.monotonic())
                continue
            if run.role == "active" and became_active is not None:
                log.info("first command as the authority: solving on t=%.2f, %.0f ms after "
                         "the plant named it (%d idle loops)", job.state.header.stamp,
                         1e3 * (time.monotonic() - became_active), len(waits))
                became_active, waits = None, []
            run, outs = protocol.solve(p, run, job, time.time())
            for out in outs:
                pubs[out.topic].publish_out(out)
            node.progress(job.state.header.stamp, job.episode)
        if run.role == "retired":
            node.role, node.detail = "retired", "replaced by a swap"
            node.retire()
    return run.role


def _role(run: protocol.PlannerRun, node: Node, replaced: dict[int, bool]
          ) -> protocol.PlannerRun:
    """The role after the newest state: named by the plant -> active; replaced by a granted
    handover -> retired or standby; lost the authority otherwise -> standby."""
    cur = run.episodes.current()
    if cur is None or run.role == "replay":
        return run
    src, _, epoch = cur[1].authority
    role = run.role
    if run.names_me(cur[1].authority):
        role = "active"
    elif role in ("active", "standby") and src and replaced.get(epoch, False):
        role = "retired"        # (the Handover may arrive after the state that names its heir)
    elif role == "active" and src:
        role = "standby"
    if role != run.role:
        log.info("role %s -> %s (authority %s epoch %d)", run.role, role, src, epoch)
        node.role = role if role != "retired" else node.role
    return replace(run, role=role)
