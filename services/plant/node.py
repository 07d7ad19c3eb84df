"""Plant service: steps the vehicle at 50 Hz, publishes state, clock and events.

The shell of `services.plant.protocol`. lockstep: publish the pending tick's state, obey
the authority's command for it, step the tick, repeat; re-offer a tick nobody answers.
realtime: step on the wall clock at 50 Hz with the command in force, braking when it or
the perception behind it is stale. Its publishers keep the last 30 s of what they sent
(common.bus.CACHED: the recorder fetches what a cut link lost) and
never block the realtime loop (congestion control drop). At start it asks the bus for the
newest tick state of a running episode (the sensor and planner hold it) and resumes it;
else it waits for every other service and starts one.
"""

from __future__ import annotations

import logging
import math
import threading
import time

from common.bus import Node, Transport, alive_instances
from common.config import Config
from common.messages import Clock, Cmd, Event, Handover, Heartbeat, State, encode
from common.protocol import NEW, Out
from common.scenarios import scenario_of
from common.supervision import Watch, missing, on_beat
from common.topics import HEARTBEAT, RECOVERY_S, SERVICES, heartbeat_key
from services.plant import core, protocol

log = logging.getLogger(__name__)

def wait_for_peers(node: Node, stop: threading.Event, services: tuple[str, ...]) -> bool:
    """Block until every named service has a liveliness token up (or stop)."""
    assert node.transport is not None
    last_log = 0.0
    while not stop.is_set():
        node.progress()
        up = {s for s, _ in alive_instances(node.transport, node.vehicle)}
        todo = [s for s in services if s not in up]
        if not todo:
            return True
        if time.monotonic() - last_log > 10:
            log.info("plant waiting for %s", ", ".join(todo))
            last_log = time.monotonic()
        stop.wait(0.1)
    return False


def main(cfg: Config, instance: str = "0", stop: threading.Event | None = None,
         bus: Transport | None = None) -> str:
    """Run (or resume) one episode; returns its outcome ("" if stopped first)."""
    stop = stop or threading.Event()
    scenario = scenario_of(cfg)
    p = protocol.PlantProtocolParams.from_config(cfg, core.PlantParams.from_config(cfg, scenario))
    sv = cfg.supervision
    with Node(bus or cfg.bus, cfg.episode.vehicle, "plant", instance, cfg.to_dict(),
              sv.heartbeat_period_s, sv.heartbeat_deadline_s, world=scenario.digest) as node:
        drop = not p.lockstep
        tick_hz = 1.0 / p.sim.tick_s
        pubs = {"state": node.publisher("state", State, drop=drop,
                                        cache=math.ceil(cfg.plant.rate_hz * RECOVERY_S)),
                "clock": node.publisher("clock", Clock, drop=drop,
                                        cache=math.ceil(tick_hz * RECOVERY_S)),
                "events": node.publisher("events", Event, drop=drop, cache=256)}
        cmds = node.subscribe("cmd", Cmd, maxlen=256 if p.lockstep else 2)
        beats = node.subscribe(HEARTBEAT, Heartbeat, maxlen=64,
                               key=heartbeat_key(cfg.episode.vehicle))
        handovers = node.subscribe("handover", Handover, maxlen=16)
        held = {"state": None, "cmd": None}
        node.hold("state", lambda: held["state"])
        node.hold("cmd", lambda: held["cmd"])

        def publish(outs: tuple[Out, ...]) -> None:
            for out in outs:
                msg = pubs[out.topic].publish_out(out)
                if out.topic == "state" and (protocol.resumable(p, msg) or msg.outcome):
                    held["state"] = pubs["state"].latest
                if out.topic == "events":
                    log.info("event %s %s", out.fields["kind"], out.fields["detail"])

        node.ready()
        found = [m for m in node.query_latest("state", State) if protocol.resumable(p, m)]
        if found:
            run, outs = protocol.resume(p, found[-1], time.time())
        else:
            if not wait_for_peers(node, stop, tuple(s for s in SERVICES if s != "plant")):
                return ""
            run, outs = protocol.start(p, node.boot, time.time())
        publish(outs)
        watch = Watch()
        period = 1.0 / cfg.plant.rate_hz
        next_wall = time.monotonic()
        while not run.done and not stop.is_set():
            for hb, wall in beats.drain():
                watch = on_beat(watch, hb, wall)
            obeyed = run.cmd
            if p.lockstep:
                got = cmds.get_received(timeout=0.05)
                got_all = [got] if got is not None else []
            else:
                got_all = cmds.drain()
            for h, wall in handovers.drain():
                run, verdict, outs = protocol.on_handover(p, run, h, wall, watch)
                if verdict != NEW:
                    node.reject("handover", verdict, h)
                publish(outs)
            for cmd, wall in got_all:
                run, verdict, outs = protocol.on_cmd(p, run, cmd, wall, watch)
                if verdict != NEW:
                    node.reject("cmd", verdict, cmd)
                publish(outs)
            if run.cmd is not obeyed and run.cmd is not None:
                held["cmd"] = encode(run.cmd)
            if p.lockstep:
                if not got_all:
                    gone = missing(watch, ("sensor", "mapper", "planner"), time.time())
                    run, outs = protocol.lockstep_idle(
                        p, run, time.time(), f"no heartbeat: {', '.join(gone)}" if gone else "",
                        watch)
                    publish(outs)
            else:
                run, outs = protocol.realtime_step(p, run, time.time(), watch)
                publish(outs)
                next_wall += period
                delay = next_wall - time.monotonic()
                if delay > 0:
                    stop.wait(delay)
                else:
                    node.health.count("overruns")
                    if delay < -1.0:            # hopelessly behind: re-anchor, do not burst
                        next_wall = time.monotonic()
            node.health.extra["stale_steps"] = run.stale_steps
            node.progress(run.sim.t, run.episode)
        if run.done:
            log.info("episode over: %s at t=%.2f", run.sim.outcome, run.sim.t)
            time.sleep(0.3)   # let the last messages leave before the session closes
        return run.sim.outcome
