"""The mapper's protocol: which depth frames it fuses, and what it answers, as pure functions.

    on_depth(params, run, depth, wall) -> (run, verdict, outputs)
    restore(params, run, map) -> run

A frame is checked against what the mapper expects (common.protocol.check; the image size,
intrinsics and range of the configured camera) before it changes the map. Only a frame
newer than the last one fused is fused: one with the same stamp (the plant re-offering a
tick, the sensor answering it again) is answered in lockstep with the map already
published for it, so nothing is fused twice. A restarted mapper `restore`s the newest map
on the bus (the planner holds the last it accepted) and goes on from there: a map message
is the whole of the mapper's state (a cell is observed exactly when its variance is below
the prior, services.mapper.core), so the resumed maps are those it would have made.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from common.config import Config
from common.messages import Depth, Map
from common.protocol import (
    ACCEPTED,
    EPS,
    NEW,
    REPEAT,
    Episodes,
    Order,
    Out,
    after_rejection,
    context,
    judge,
    ref,
)
from common.topics import topic_key
from services.mapper import core
from services.sensor.core import CameraParams


@dataclass(frozen=True)
class MapperProtocolParams:
    core: core.MapperParams
    lockstep: bool
    ahead_s: float                    # a frame may run ahead of the last accepted one by this
    image_shape: tuple[int, int]      # (H, W) of the configured camera
    intrinsics: tuple[float, ...]
    range_m: float
    depth_key: str

    @classmethod
    def from_config(cls, cfg: Config, origin: tuple[float, float]) -> MapperProtocolParams:
        cam = CameraParams.from_config(cfg.sensor)
        return cls(core=core.MapperParams.from_config(cfg, origin),
                   lockstep=cfg.episode.clock == "lockstep",
                   ahead_s=max(cfg.planner.dt_s, 1.0 / cfg.sensor.rate_hz),
                   image_shape=(cam.height_px, cam.width_px),
                   intrinsics=tuple(float(v) for v in cam.intrinsics), range_m=cam.range_m,
                   depth_key=topic_key(cfg.episode.vehicle, "depth"))


@dataclass(frozen=True)
class MapperCtx:
    """One episode's: the accepted frames, the map and the stamp it was last fused at."""
    order: Order = field(default_factory=Order)
    map: core.MapState | None = None
    stamp: float | None = None
    published: Out | None = None


@dataclass(frozen=True)
class MapperRun:
    episodes: Episodes[MapperCtx] = field(default_factory=Episodes)


def depth_problem(p: MapperProtocolParams, d: Depth) -> str:
    """Why a frame does not fit the configured camera, or ''."""
    if d.depth.shape != p.image_shape:
        return f"wrong size {d.depth.shape}, the camera's is {p.image_shape}"
    if tuple(float(v) for v in d.intrinsics) != p.intrinsics:
        return "intrinsics are not the configured camera's"
    if d.range_max != p.range_m:
        return f"range {d.range_max} m, the camera's is {p.range_m} m"
    return ""


def map_out(p: MapperProtocolParams, state: core.MapState, stamp: float, inputs: tuple,
            episode: int) -> Out:
    return Out("map", stamp, {"mean": state.mean, "variance": state.variance,
                              "origin": np.asarray(p.core.origin, dtype=np.float64),
                              "resolution": p.core.resolution_m}, inputs, episode)


def on_depth(p: MapperProtocolParams, run: MapperRun, d: Depth, wall: float
             ) -> tuple[MapperRun, str, tuple[Out, ...]]:
    h = d.header
    problem = depth_problem(p, d)
    if problem:
        return run, problem, ()
    ctx = context(run.episodes, h.episode, MapperCtx)
    order, verdict = judge(ctx.order, h, wall, p.ahead_s, not p.lockstep, "sensor")
    if verdict == NEW and ctx.stamp is not None:        # judged against the map, too
        if h.stamp < ctx.stamp - EPS:
            verdict, order = "stale", ctx.order
        elif h.stamp <= ctx.stamp + EPS:
            verdict = REPEAT
    if verdict not in ACCEPTED:
        return after_rejection(run, h.episode, replace(ctx, order=order),
                               order is not ctx.order), verdict, ()
    ctx = replace(ctx, order=order)
    outs: tuple[Out, ...] = ()
    if verdict == REPEAT:
        if p.lockstep and ctx.published is not None and abs(ctx.published.stamp - h.stamp) <= EPS:
            outs = (ctx.published,)
    else:
        bx, by, bz, _ = d.base_pose
        state = ctx.map if ctx.map is not None else core.initial_map(p.core, bx, by, bz)
        state = core.update(p.core, state, d.depth, d.intrinsics, d.cam_position,
                            d.cam_rotation, d.base_pose)
        out = map_out(p, state, h.stamp, (ref(p.depth_key, d),), h.episode)
        ctx = replace(ctx, map=state, stamp=h.stamp, published=out)
        outs = (out,)
    return replace(run, episodes=run.episodes.put(h.episode, ctx)), verdict, outs


def map_problem(p: MapperProtocolParams, m: Map) -> str:
    """Why a map cannot be this mapper's, or ''."""
    n = p.core.size_cells
    if m.mean.shape != (n, n):
        return f"wrong size {m.mean.shape}, the grid is {(n, n)}"
    if m.resolution != p.core.resolution_m or tuple(m.origin) != tuple(p.core.origin):
        return "origin or resolution are not the configured grid's"
    return ""


def restore(p: MapperProtocolParams, run: MapperRun, m: Map) -> MapperRun:
    """Go on from map `m` (the newest on the bus) in its episode."""
    h = m.header
    mean = np.array(m.mean, dtype=np.float32)
    variance = np.array(m.variance, dtype=np.float32)
    state = core.restore(p.core, mean, variance)
    ctx = MapperCtx(map=state, stamp=h.stamp,
                    published=map_out(p, state, h.stamp, h.inputs, h.episode))
    return replace(run, episodes=run.episodes.put(h.episode, ctx))
