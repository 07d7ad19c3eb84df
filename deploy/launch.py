"""`vamppi up`: an embedded Zenoh router and every service as its own OS process.

The launcher opens a router session on a free loopback port, starts plant,
sensor, mapper and planner as `vamppi service NAME --connect tcp/127.0.0.1:PORT`
subprocesses (each stops when its parent dies: `vamppi service` watches its
parent), waits until every
service's liveliness token is up, follows the plant's events until the episode's
outcome, then stops every child (SIGTERM, then SIGKILL after a grace period).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

from common.bus import PREFIX, SERVICES, Health, Inbox, alive_instances, open_session, topic_key
from common.config import BusConfig, Config
from common.messages import Event
from services.plant.core import OUTCOMES

log = logging.getLogger(__name__)


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def router_config(port: int) -> BusConfig:
    return BusConfig(mode="router", connect=(), listen=(f"tcp/127.0.0.1:{port}",),
                     multicast_scouting=False)


def spawn_service(name: str, endpoint: str, overrides: list[str], config_path: str | None,
                  instance: str = "0", env: dict[str, str] | None = None) -> subprocess.Popen:
    """`vamppi service NAME` as a subprocess, a client of the router at `endpoint`."""
    cmd = [sys.executable, "-m", "deploy.cli", "service", name, "--instance", instance,
           "--stop-with-parent"]
    if config_path:
        cmd += ["--config", config_path]
    for o in overrides:
        cmd += ["--set", o]
    cmd += ["--set", 'bus.mode="client"', "--set", f"bus.connect={json.dumps([endpoint])}",
            "--set", "bus.listen=[]"]
    return subprocess.Popen(cmd, stdout=sys.stderr, stderr=sys.stderr, stdin=subprocess.DEVNULL,
                            env={**os.environ, **(env or {})})


def stop_all(procs: dict[str, subprocess.Popen], grace_s: float = 5.0) -> None:
    for p in procs.values():
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for p in procs.values():
        try:
            p.wait(max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


@contextlib.contextmanager
def services_up(cfg: Config, overrides: list[str], config_path: str | None = None,
                services: tuple[str, ...] = SERVICES, ready_timeout_s: float = 300.0,
                subscriptions: dict[str, Callable[[Any], None]] | None = None,
                on_session: Callable[[Any], Callable[[], None]] | None = None
                ) -> Iterator[tuple[Any, str, dict[str, subprocess.Popen]]]:
    """Router + the named services, ready (every token up). Yields (session, endpoint, procs).

    `subscriptions` (key -> callback) are declared on the router's session before
    any service starts, so nothing the services publish is missed; so is
    `on_session(session)` (a recorder), whose returned finaliser runs after every
    service has stopped.
    """
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with open_session(router_config(port)) as session:
        for key, callback in (subscriptions or {}).items():
            session.declare_subscriber(key, callback)
        finish = on_session(session) if on_session is not None else None
        procs = {name: spawn_service(name, endpoint, overrides, config_path) for name in services}
        try:
            deadline = time.monotonic() + ready_timeout_s
            while True:
                up = {s for s, _ in alive_instances(session, cfg.episode.vehicle)}
                if all(s in up for s in services):
                    break
                dead = [n for n, p in procs.items() if p.poll() is not None]
                if dead:
                    raise RuntimeError(f"service(s) exited before ready: {', '.join(dead)}")
                if time.monotonic() > deadline:
                    missing = sorted(set(services) - up)
                    raise TimeoutError(f"services not ready after {ready_timeout_s:.0f} s: "
                                       f"{', '.join(missing)}")
                time.sleep(0.1)
            yield session, endpoint, procs
        finally:
            stop_all(procs)
            if finish is not None:
                finish()


def recording_hook(cfg: Config, path: str, summary: dict[str, Any]
                   ) -> Callable[[Any], Callable[[], None]]:
    """An `on_session` that records every key of the vehicle to `path`; the recorder's
    statistics land in `summary["recording"]`."""
    from deploy.recording import Recorder, recording_metadata

    def start(session: Any) -> Callable[[], None]:
        keys = f"{PREFIX}/{cfg.episode.vehicle}/**"
        rec = Recorder(session, keys, path, recording_metadata(cfg.to_dict(), keys))
        log.info("recording %s to %s", keys, path)

        def finish() -> None:
            stats = rec.stop()
            summary["recording"] = {"path": path, "messages": stats["messages"],
                                    "missing": stats["missing"],
                                    "undecodable": stats["undecodable"],
                                    "max_backlog": stats["max_backlog"]}
        return finish
    return start


def up(cfg: Config, overrides: list[str], config_path: str | None = None,
       timeout_s: float = 900.0, record: str | None = None) -> dict[str, Any]:
    """Run one episode across processes (recorded to `record` if given); returns the
    summary record."""
    summary: dict[str, Any] = {
        "scenario": cfg.episode.scenario, "controller": cfg.planner.controller,
        "samples": cfg.planner.samples, "seed": cfg.episode.seed, "outcome": "error",
        "time_to_goal_s": None, "sim_time_s": None, "wall_time_s": None}
    events = Inbox(Event, topic_key(cfg.episode.vehicle, "events"), Health(), maxlen=1024)
    wall0 = time.monotonic()
    try:
        with services_up(cfg, overrides, config_path, subscriptions={
                events.key: lambda s: events.on_payload(s.payload.to_bytes())},
                on_session=recording_hook(cfg, record, summary) if record else None
                ) as (_, _, procs):
            log.info("all services up after %.1f s", time.monotonic() - wall0)
            start_wall = None
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline:
                ev = events.get(timeout=0.5)
                if ev is None:
                    dead = [n for n, p in procs.items() if p.poll() is not None]
                    if dead:
                        log.error("service(s) exited during the episode: %s", ", ".join(dead))
                        break
                    continue
                if ev.kind == "start":
                    start_wall = time.monotonic()
                if ev.kind in OUTCOMES:
                    summary.update(outcome=ev.kind, sim_time_s=round(ev.header.stamp, 6),
                                   time_to_goal_s=None if ev.kind != "success"
                                   else round(ev.time_to_goal_s, 6),
                                   wall_time_s=round(time.monotonic() - (start_wall or wall0), 3))
                    break
            else:
                log.error("no outcome after %.0f s wall", timeout_s)
    except (RuntimeError, TimeoutError) as exc:
        log.error("%s", exc)
    return summary

