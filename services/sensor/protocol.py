"""The sensor's protocol: which states it renders, and what it answers, as pure functions.

    on_state(params, run, state, wall) -> (run, verdict, outputs)

A state is checked (common.protocol.check: duplicates, stale, from the future) and, if it
is on the camera's frame clock (one frame per `1 / sensor.rate_hz` of simulation time),
rendered into a depth frame. In lockstep a repeat of the last rendered state (the plant
re-offering its pending tick) is answered with the frame rendered for it, so that a
service that missed the frame gets it and nothing is rendered twice. The newest state on a
tick boundary is held for a plant that restarts (`held_state`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from common.config import Config
from common.messages import State
from common.protocol import (
    ACCEPTED,
    EPS,
    REPEAT,
    Episodes,
    Order,
    Out,
    after_rejection,
    context,
    judge,
    newer,
    on_tick,
    ref,
)
from common.scenarios import Scenario
from common.topics import topic_key
from services.plant.dynamics import S
from services.sensor import core


@dataclass(frozen=True)
class SensorParams:
    camera: core.CameraParams
    scenario: Scenario
    period_s: float                   # the frame clock
    tick_s: float
    lockstep: bool
    ahead_s: float                    # a state may run ahead of the last accepted one by this
    state_key: str

    @classmethod
    def from_config(cls, cfg: Config, scenario: Scenario) -> SensorParams:
        return cls(camera=core.CameraParams.from_config(cfg.sensor), scenario=scenario,
                   period_s=1.0 / cfg.sensor.rate_hz, tick_s=cfg.planner.dt_s,
                   lockstep=cfg.episode.clock == "lockstep", ahead_s=cfg.planner.dt_s,
                   state_key=topic_key(cfg.episode.vehicle, "state"))


@dataclass(frozen=True)
class SensorCtx:
    """One episode's: the accepted states, the frame clock, the last frame."""
    order: Order = field(default_factory=Order)
    next_frame: float = 0.0
    frame: Out | None = None


@dataclass(frozen=True)
class SensorRun:
    episodes: Episodes[SensorCtx] = field(default_factory=Episodes)
    held_state: State | None = None


def render(p: SensorParams, msg: State) -> Out:
    """The depth frame seen from a state."""
    x, scn = msg.x, p.scenario
    depth, pos, rot = core.render(p.camera, scn.heightmap, scn.origin, scn.resolution,
                                  x[S.X], x[S.Y], msg.z, x[S.PSI])
    return Out("depth", msg.header.stamp,
               {"depth": depth, "intrinsics": p.camera.intrinsics, "cam_position": pos,
                "cam_rotation": rot, "base_pose": np.array([x[S.X], x[S.Y], msg.z, x[S.PSI]]),
                "range_max": p.camera.range_m},
               (ref(p.state_key, msg),), msg.header.episode)


def on_state(p: SensorParams, run: SensorRun, msg: State, wall: float
             ) -> tuple[SensorRun, str, tuple[Out, ...]]:
    h = msg.header
    ctx = context(run.episodes, h.episode, SensorCtx)
    order, verdict = judge(ctx.order, h, wall, p.ahead_s, not p.lockstep, "plant",
                           p.tick_s)
    if verdict not in ACCEPTED:
        return after_rejection(run, h.episode, replace(ctx, order=order),
                               order is not ctx.order), verdict, ()
    ctx = replace(ctx, order=order)
    outs: tuple[Out, ...] = ()
    t = h.stamp
    if verdict == REPEAT:
        if p.lockstep and ctx.frame is not None and abs(ctx.frame.stamp - t) <= EPS:
            outs = (ctx.frame,)
    elif t >= ctx.next_frame - EPS:
        frame = render(p, msg)
        ctx = replace(ctx, frame=frame,
                      next_frame=(math.floor(t / p.period_s + EPS) + 1) * p.period_s)
        outs = (frame,)
    held = run.held_state
    if (on_tick(t, p.tick_s) or msg.outcome) and newer(held, msg):
        held = msg
    return replace(run, episodes=run.episodes.put(h.episode, ctx), held_state=held), verdict, outs
