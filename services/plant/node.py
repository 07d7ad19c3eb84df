"""Plant service: steps the vehicle at 50 Hz, publishes state, clock and events.

lockstep: publish the tick's state, wait for the authority's command stamped
with that tick, step one tick (publishing every 50 Hz state), repeat.
realtime: step on the wall clock at 50 Hz with the newest command; a command
older than `cmd_timeout_s` (or run past its end) is stale: full brake.
"""

from __future__ import annotations

import logging
import math
import threading
import time

import numpy as np

from common.bus import SERVICES, Node, alive_instances, ref_of
from common.config import Config
from common.messages import Clock, Cmd, Event, State
from common.scenarios import scenario_of
from services.plant import core
from services.plant.dynamics import S

log = logging.getLogger(__name__)


def wait_for_peers(node: Node, stop: threading.Event, services: tuple[str, ...]) -> bool:
    """Block until every named service has a liveliness token up (or stop)."""
    assert node.session is not None
    last_log = 0.0
    while not stop.is_set():
        up = {s for s, _ in alive_instances(node.session, node.vehicle)}
        missing = [s for s in services if s not in up]
        if not missing:
            return True
        if time.monotonic() - last_log > 10:
            log.info("plant waiting for %s", ", ".join(missing))
            last_log = time.monotonic()
        stop.wait(0.1)
    return False


def main(cfg: Config, instance: str = "0", stop: threading.Event | None = None) -> str:
    """Run one episode; returns its outcome ("" if stopped first)."""
    stop = stop or threading.Event()
    scenario = scenario_of(cfg)
    params = core.PlantParams.from_config(cfg, scenario)
    lockstep = cfg.episode.clock == "lockstep"
    with Node(cfg.bus, cfg.episode.vehicle, "plant", instance, cfg.to_dict()) as node:
        state_pub = node.publisher("state", State)
        clock_pub = node.publisher("clock", Clock)
        events_pub = node.publisher("events", Event)
        cmds = node.subscribe("cmd", Cmd, maxlen=256 if lockstep else 1)
        cmd_key = node.key("cmd")
        node.ready()
        if not wait_for_peers(node, stop, tuple(s for s in SERVICES if s != "plant")):
            return ""
        state = core.initial_state(params)
        authority = ""

        def publish(st: core.PlantState, inputs=()) -> None:
            x = st.x
            z = core.ground_z(params, x[S.X], x[S.Y])
            state_pub.publish(st.t, inputs, x=np.array(st.x, dtype=np.float64), z=z,
                              u_applied=np.array(st.u_applied, dtype=np.float64),
                              tick=core.tick_of(params, st), authority=authority)
            if st.step % params.steps_per_tick == 0:
                clock_pub.publish(st.t, tick=core.tick_of(params, st), mode=cfg.episode.clock)

        def event(kind: str, st: core.PlantState, detail: str = "") -> None:
            events_pub.publish(st.t, kind=kind, outcome=st.outcome,
                               time_to_goal_s=st.time_to_goal_s, detail=detail)

        event("start", state, f"scenario={scenario.name} clock={cfg.episode.clock}")
        publish(state)
        wall_period = 1.0 / cfg.plant.rate_hz
        next_wall = time.monotonic()
        while not state.done and not stop.is_set():
            if lockstep:
                t_tick = state.t
                cmd = None
                while cmd is None and not stop.is_set():
                    cmd = cmds.get_where(
                        lambda c, t=t_tick, a=authority: abs(c.t0 - t) < 1e-6
                        and (not a or c.header.source == a), timeout=cfg.plant.lockstep_wait_s)
                    if cmd is None and not stop.is_set():
                        log.warning("lockstep: no command for t=%.2f after %.0f s", t_tick,
                                    cfg.plant.lockstep_wait_s)
                if cmd is None:
                    break
                if not authority:
                    authority = cmd.header.source
                    event("authority", state, authority)
                ref = ref_of(cmd_key, cmd)
                for _ in range(params.steps_per_tick):
                    u = core.control_at(state.t, cmd.t0, cmd.dt, cmd.controls)
                    state = core.plant_step(params, state, u)
                    publish(state, [ref])
                    if state.done:
                        break
            else:
                cmd = cmds.peek_latest()
                u = None
                if cmd is not None and state.t - cmd.t0 <= cfg.plant.cmd_timeout_s:
                    if not authority:
                        authority = cmd.header.source
                        event("authority", state, authority)
                    if cmd.header.source == authority:
                        u = core.control_at(state.t, cmd.t0, cmd.dt, cmd.controls)
                stale = u is None
                if stale:
                    u = core.brake_control(params, state)
                state = core.plant_step(params, state, u)
                publish(state, [] if stale else [ref_of(cmd_key, cmd)])
                node.health.extra["stale_steps"] = node.health.extra.get("stale_steps", 0) + stale
                next_wall += wall_period
                delay = next_wall - time.monotonic()
                if delay > 0:
                    stop.wait(delay)
                else:
                    node.health.extra["overruns"] = node.health.extra.get("overruns", 0) + 1
                    if delay < -1.0:            # hopelessly behind: re-anchor, do not burst
                        next_wall = time.monotonic()
        if state.done:
            detail = (f"t={state.t:.2f} x={state.x[S.X]:.2f} y={state.x[S.Y]:.2f} "
                      f"speed={math.hypot(state.x[S.V], state.x[S.v]):.2f}")
            if state.outcome == "collision":
                detail += " on=" + core.collision_text(params, state.x)
            event(state.outcome, state, detail)
            log.info("episode over: %s at t=%.2f", state.outcome, state.t)
            time.sleep(0.2)   # let the event leave before the session closes
        return state.outcome

