"""Mapper service: fuses each depth frame into the elevation map and publishes it."""

from __future__ import annotations

import logging
import threading

import numpy as np

from common.bus import Node, ref_of
from common.config import Config
from common.messages import Depth, Map
from services.mapper import core

log = logging.getLogger(__name__)


def main(cfg: Config, instance: str = "0", stop: threading.Event | None = None) -> None:
    stop = stop or threading.Event()
    params = core.MapperParams.from_config(cfg)
    lockstep = cfg.episode.clock == "lockstep"
    with Node(cfg.bus, cfg.episode.vehicle, "mapper", instance, cfg.to_dict()) as node:
        frames = node.subscribe("depth", Depth, maxlen=64 if lockstep else 1)
        map_pub = node.publisher("map", Map)
        # compile the fusion before raising the token
        warm = core.initial_map(params, 0.0, 0.0, 0.0)
        core.fuse_depth(params, warm, np.zeros((cfg.sensor.height_px, cfg.sensor.width_px),
                                               np.float32), np.array([1.0, 1.0, 0.0, 0.0]),
                        np.zeros(3), np.eye(3))
        node.ready()
        state: core.MapState | None = None
        origin = np.asarray(params.origin, dtype=np.float64)
        while not stop.is_set():
            d = frames.get(timeout=0.2)
            if d is None:
                continue
            bx, by, bz, _ = d.base_pose
            if state is None or d.header.stamp < 1e-9:
                state = core.initial_map(params, bx, by, bz)
            state = core.update(params, state, d.depth, d.intrinsics, d.cam_position,
                                d.cam_rotation, d.base_pose)
            map_pub.publish(d.header.stamp, [ref_of(frames.key, d)], mean=state.mean,
                            variance=state.variance, origin=origin,
                            resolution=params.resolution)
