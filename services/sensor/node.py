"""Sensor service: renders a depth frame from each state on the camera's frame clock.

The shell of `services.sensor.protocol`: states from the bus into `on_state`, its
frames onto the bus. At start it asks the bus for the newest state (the plant holds
its pending one), so a restarted sensor answers at once.
"""

from __future__ import annotations

import logging
import threading
import time

from common.bus import Node, Transport
from common.config import Config
from common.messages import Depth, State, encode
from common.protocol import ACCEPTED
from common.scenarios import scenario_of
from services.sensor import core, protocol

log = logging.getLogger(__name__)


def main(cfg: Config, instance: str = "0", stop: threading.Event | None = None,
         bus: Transport | None = None) -> None:
    stop = stop or threading.Event()
    scn = scenario_of(cfg)
    p = protocol.SensorParams.from_config(cfg, scn)
    sv = cfg.supervision
    with Node(bus or cfg.bus, cfg.episode.vehicle, "sensor", instance, cfg.to_dict(),
              sv.heartbeat_period_s, sv.heartbeat_deadline_s, world=scn.digest) as node:
        states = node.subscribe("state", State, maxlen=1024 if p.lockstep else 1)
        depth_pub = node.publisher("depth", Depth, drop=not p.lockstep)
        core.render(p.camera, scn.heightmap, scn.origin, scn.resolution,   # compile first
                    scn.start.x, scn.start.y, 0.0, scn.start.yaw)
        run = protocol.SensorRun()
        node.hold("depth", lambda: depth_pub.latest)
        node.hold("state", lambda: None if run.held_state is None else encode(run.held_state))
        node.ready()
        pending = [(m, time.time()) for m in node.query_latest("state", State)[-1:]]
        while not stop.is_set():
            node.progress()
            if not pending:
                got = states.get_received(timeout=0.1)
                pending = [got] if got is not None else []
            for msg, wall in pending:
                run, verdict, outs = protocol.on_state(p, run, msg, wall)
                if verdict not in ACCEPTED:
                    node.reject("state", verdict, msg)
                for out in outs:
                    depth_pub.publish_out(out)
                node.progress(msg.header.stamp, msg.header.episode)
            pending = []
