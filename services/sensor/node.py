"""Sensor service: renders a depth frame from each state on the camera's frame clock."""

from __future__ import annotations

import logging
import math
import threading

import numpy as np

from common.bus import Node, ref_of
from common.config import Config
from common.messages import Depth, State
from common.scenarios import scenario_of
from services.plant.dynamics import S
from services.sensor import core

log = logging.getLogger(__name__)


def main(cfg: Config, instance: str = "0", stop: threading.Event | None = None) -> None:
    stop = stop or threading.Event()
    scn = scenario_of(cfg)
    cam = core.CameraParams.from_config(cfg.sensor)
    period = 1.0 / cfg.sensor.rate_hz
    lockstep = cfg.episode.clock == "lockstep"
    with Node(cfg.bus, cfg.episode.vehicle, "sensor", instance, cfg.to_dict()) as node:
        states = node.subscribe("state", State, maxlen=1024 if lockstep else 1)
        depth_pub = node.publisher("depth", Depth)
        core.render(cam, scn.heightmap, scn.origin, scn.resolution,   # compile before ready
                    scn.start.x, scn.start.y, 0.0, scn.start.yaw)
        node.ready()
        next_frame = 0.0
        while not stop.is_set():
            st = states.get(timeout=0.2)
            if st is None:
                continue
            t = st.header.stamp
            if t < 1e-9:
                next_frame = 0.0    # a new episode restarts the frame clock
            if t < next_frame - 1e-6:
                continue
            x = st.x
            depth, pos, rot = core.render(cam, scn.heightmap, scn.origin, scn.resolution,
                                          x[S.X], x[S.Y], st.z, x[S.PSI])
            depth_pub.publish(t, [ref_of(states.key, st)], depth=depth,
                              intrinsics=cam.intrinsics, cam_position=pos, cam_rotation=rot,
                              base_pose=np.array([x[S.X], x[S.Y], st.z, x[S.PSI]]),
                              range_max=cam.range_m)
            next_frame = (math.floor(t / period + 1e-6) + 1) * period
