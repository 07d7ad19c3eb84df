"""Mapper service: fuses each depth frame into the elevation map and publishes it.

The shell of `services.mapper.protocol`. At start it asks the bus for the newest map (the
planner holds the last it accepted) and goes on from it, so a restarted mapper resumes
the map instead of starting an empty one.
"""

from __future__ import annotations

import logging
import threading

import numpy as np

from common.bus import Node, Transport
from common.config import Config
from common.messages import Depth, Map
from common.protocol import ACCEPTED
from common.scenarios import scenario_of
from services.mapper import core, protocol

log = logging.getLogger(__name__)


def main(cfg: Config, instance: str = "0", stop: threading.Event | None = None,
         bus: Transport | None = None) -> None:
    stop = stop or threading.Event()
    scn = scenario_of(cfg)
    p = protocol.MapperProtocolParams.from_config(cfg, scn.origin)
    sv = cfg.supervision
    with Node(bus or cfg.bus, cfg.episode.vehicle, "mapper", instance, cfg.to_dict(),
              sv.heartbeat_period_s, sv.heartbeat_deadline_s, world=scn.digest) as node:
        frames = node.subscribe("depth", Depth, maxlen=64 if p.lockstep else 1)
        map_pub = node.publisher("map", Map, drop=not p.lockstep)
        node.hold("map", lambda: map_pub.latest)
        # compile the fusion before raising the token
        warm = core.initial_map(p.core, 0.0, 0.0, 0.0)
        core.fuse_depth(p.core, warm, np.zeros(p.image_shape, np.float32),
                        np.array([1.0, 1.0, 0.0, 0.0]), np.zeros(3), np.eye(3))
        run = protocol.MapperRun()
        for m in reversed(node.query_latest("map", Map)):
            problem = protocol.map_problem(p, m)
            if not problem:
                run = protocol.restore(p, run, m)
                log.info("resuming from the map of t=%.2f (from %s)", m.header.stamp,
                         m.header.source)
                break
            node.reject("map", problem, m)
        node.ready()
        while not stop.is_set():
            node.progress()
            got = frames.get_received(timeout=0.1)
            if got is None:
                continue
            d, wall = got
            run, verdict, outs = protocol.on_depth(p, run, d, wall)
            if verdict not in ACCEPTED:
                node.reject("depth", verdict, d)
            for out in outs:
                map_pub.publish_out(out)
            node.progress(d.header.stamp, d.header.episode)
