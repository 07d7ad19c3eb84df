"""`vamppi up`: an embedded Zenoh router and every service as its own OS process, supervised.

The launcher opens a router session on a free loopback port, starts plant, sensor,
mapper and planner as `vamppi service NAME --connect tcp/127.0.0.1:PORT` subprocesses,
waits until every service's liveliness token is up, follows the plant's events until
the episode's outcome, then stops every child (SIGTERM, then SIGKILL after a grace
period).

Supervision (`Supervisor`): every child's heartbeat is followed. A child that exits, or
whose beats stop or say `stalled` for longer than the deadline they state (a process
wedged or stopped: its liveliness token stays up while zenoh's threads run), has failed;
a failed child is killed and started again, up to `supervision.restarts` times per
service, and resumes its part of the episode (each service's protocol recovers its
state from the bus). Past that the launcher gives up: the summary names the service and
why, and `vamppi up` exits non-zero. Children die with the launcher (the kernel's
parent-death signal), so `kill -9` of it leaves no process behind.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from common.bus import Health, Inbox, ZenohTransport, alive_instances, open_session
from common.config import BusConfig, Config
from common.messages import DecodeError, Event, Heartbeat, decode
from common.process import PARENT_ENV
from common.security import default_certs
from common.supervision import FAILED, REFUSED_EXIT, RETIRED_EXIT
from common.topics import (
    PREFIX,
    SERVICES,
    alive_key,
    heartbeat_key,
    launcher_key,
    topic_key,
)
from deploy.launch.certs import ensure_certs
from deploy.launch.running import announce
from services.plant.protocol import OUTCOMES

log = logging.getLogger(__name__)

SETTLE_S = 0.5           # after the outcome: the final state's depth, map and command flow


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def router_config(port: int, certs: str = "") -> BusConfig:
    """A router on loopback: plain TCP, or with `certs` mutual TLS and the generated
    access-control rules (common.security)."""
    return BusConfig(mode="router", connect=(),
                     listen=(f"{'tls' if certs else 'tcp'}/127.0.0.1:{port}",),
                     multicast_scouting=False, certs=certs, identity="router" if certs else "")


def router_certs(cfg: Config, endpoint: str) -> str:
    """The certificates a client of `endpoint` uses ('' for plain TCP)."""
    return (cfg.bus.certs or str(default_certs())) if endpoint.startswith("tls/") else ""


def client_endpoint(port: int, certs: str = "") -> str:
    """How a client on this machine reaches `router_config(port, certs)` (TLS checks the
    certificate's name: localhost)."""
    return f"tls/localhost:{port}" if certs else f"tcp/127.0.0.1:{port}"


def service_command(name: str, endpoint: str, overrides: list[str], config_path: str | None,
                    instance: str = "0", with_parent: bool = True) -> list[str]:
    """`vamppi service NAME`, a client of the router at `endpoint`, stopping with its
    parent (unless not `with_parent`)."""
    cmd = [sys.executable, "-m", "deploy", "service", name, "--instance", instance,
           *(["--stop-with-parent"] if with_parent else [])]
    if config_path:
        cmd += ["--config", config_path]
    for o in overrides:
        cmd += ["--set", o]
    return cmd + ["--set", 'bus.mode="client"', "--set", f"bus.connect={json.dumps([endpoint])}",
                  "--set", "bus.listen=[]"]


def spawn_service(name: str, endpoint: str, overrides: list[str], config_path: str | None,
                  instance: str = "0", env: dict[str, str] | None = None,
                  args: list[str] = ()) -> subprocess.Popen:
    """`vamppi service NAME` as a subprocess (`service_command`), `args` added."""
    return subprocess.Popen([*service_command(name, endpoint, overrides, config_path, instance),
                             *args],
                            stdout=sys.stderr, stderr=sys.stderr, stdin=subprocess.DEVNULL,
                            env={**os.environ, PARENT_ENV: str(os.getpid()), **(env or {})})


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


# ----------------------------------------------------------------------------- supervision
@dataclass(frozen=True)
class ChildView:
    """What the supervisor knows of one child process: when it started, its exit code, its
    newest beat (status, deadline, monotonic receive time)."""
    started: float
    exit_code: int | None
    beat_status: str = ""
    beat_deadline_s: float = 0.0
    beat_at: float | None = None


def judge(child: ChildView, now: float, ready_timeout_s: float) -> str:
    """Why the child has failed, or '' while it is well: it exited, it is not ready in
    time, or its beats stopped or say it failed for longer than their deadline."""
    if child.exit_code is not None:
        if child.exit_code == RETIRED_EXIT:
            return ""
        if child.exit_code == REFUSED_EXIT:
            return "refused: the plant runs another scenario"
        return f"exited with code {child.exit_code}"
    if child.beat_at is None or child.beat_status == "starting":
        if now - child.started > ready_timeout_s:
            return f"not ready after {ready_timeout_s:.0f} s"
        return ""
    late = now - child.beat_at
    if child.beat_status == "retired":
        return ""
    if child.beat_status in FAILED:
        return f"heartbeat says {child.beat_status}"
    if late > child.beat_deadline_s:
        return f"no heartbeat for {late:.2f} s (deadline {child.beat_deadline_s:.2f} s)"
    return ""


class Supervisor:
    """The children of `vamppi up`, watched and restarted (module docstring). A child is
    named by its service ("planner") for instance 0, "service/instance" for others (a
    swapped-in planner); one that retires (a replaced planner) is let go."""

    def __init__(self, endpoint: str, overrides: list[str], config_path: str | None,
                 services: tuple[str, ...], restarts: int, ready_timeout_s: float,
                 env: dict[str, str] | None = None, min_deadline_s: float = 1.0):
        self.endpoint, self.overrides, self.config_path = endpoint, overrides, config_path
        self.max_restarts, self.ready_timeout_s, self.env = restarts, ready_timeout_s, env
        self.min_deadline_s = min_deadline_s
        self.procs: dict[str, subprocess.Popen] = {}
        self.restarts: dict[str, int] = {}
        self.failures: list[dict[str, Any]] = []
        self.retired: list[str] = []
        self._how: dict[str, tuple[str, str, list[str], list[str], str | None]] = {}
        self._started: dict[str, tuple[float, int]] = {}      # monotonic, time_ns
        self._beats: dict[str, tuple[str, float, float]] = {}  # status, deadline, at
        self._lock = threading.Lock()
        for name in services:
            self.start(name)

    @staticmethod
    def label(service: str, instance: str) -> str:
        return service if instance == "0" else f"{service}/{instance}"

    def start(self, service: str, instance: str = "0", args: list[str] = (),
              overrides: list[str] | None = None, config_path: str | None = None) -> str:
        """Start (or start again) a child; its label."""
        label = self.label(service, instance)
        if label not in self._how:
            self._how[label] = (service, instance, list(args),
                                [*self.overrides, *(overrides or [])],
                                config_path or self.config_path)
        service, instance, args, overrides, config = self._how[label]
        with self._lock:
            self._started[label] = (time.monotonic(), time.time_ns())
            self._beats.pop(label, None)
        self.procs[label] = spawn_service(service, self.endpoint, overrides, config, instance,
                                          self.env, args)
        return label

    def stop_child(self, label: str) -> None:
        proc = self.procs.pop(label, None)
        if proc is not None:
            stop_all({label: proc})

    def on_beat(self, hb: Heartbeat) -> None:
        """A heartbeat from the bus: kept if it is the newest process of a child's."""
        service, _, instance = hb.header.source.partition("/")
        label = self.label(service, instance)
        with self._lock:
            started = self._started.get(label)
            if started is not None and hb.header.boot >= started[1]:
                self._beats[label] = (hb.status, max(hb.deadline_s, self.min_deadline_s),
                                      time.monotonic())

    def owns(self, header: Any) -> bool:
        """Whether a message's header names a process this supervisor started: its source
        one of its children's, its boot no earlier than that child's (re)start."""
        service, _, instance = header.source.partition("/")
        with self._lock:
            started = self._started.get(self.label(service, instance))
        return started is not None and header.boot >= started[1]

    def view(self, label: str) -> ChildView:
        with self._lock:
            status, deadline, at = self._beats.get(label, ("", 0.0, None))
            started = self._started[label][0]
        return ChildView(started, self.procs[label].poll(), status, deadline, at)

    def check(self, expected_exit: Callable[[str], bool] = lambda name: False
              ) -> dict[str, Any] | None:
        """Restart every failed child (an exit `expected_exit` allows is none; a retired one
        is let go); the failure that exhausted its service's restarts, if one did."""
        now = time.monotonic()
        for label in list(self.procs):
            child = self.view(label)
            if child.exit_code == RETIRED_EXIT:
                self.procs.pop(label)
                self.retired.append(label)
                log.info("vamppi up: %s", json.dumps({"retired": label}))
                continue
            why = judge(child, now, self.ready_timeout_s)
            if not why or (child.exit_code == 0 and expected_exit(label)):
                continue
            beat_age = None if child.beat_at is None else round(now - child.beat_at, 3)
            failure = {"service": label, "why": why, "last_beat_s_ago": beat_age,
                       "restarts": self.restarts.get(label, 0)}
            self.failures.append(failure)
            proc = self.procs[label]
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            # a service refused for another scenario would be refused again
            if self.restarts.get(label, 0) >= self.max_restarts or \
                    child.exit_code == REFUSED_EXIT:
                log.error("vamppi up: %s", json.dumps({"gave_up": failure}))
                return failure
            self.restarts[label] = self.restarts.get(label, 0) + 1
            log.warning("vamppi up: %s", json.dumps({"restarting": failure}))
            self.start(label.split("/")[0], label.partition("/")[2] or "0")
        return None

    def request(self, req: dict[str, Any]) -> None:
        """A launcher request from the bus (`vamppi swap`): spawn or stop an instance."""
        if "spawn" in req:
            r = req["spawn"]
            label = self.start(str(r["name"]), str(r["instance"]), list(r.get("args", [])),
                               list(r.get("overrides", [])), r.get("config"))
            log.info("vamppi up: %s", json.dumps({"started": label, "for": "a swap"}))
        elif "stop" in req:
            service, _, instance = str(req["stop"]).partition("/")
            self.stop_child(self.label(service, instance or "0"))

    def stop(self) -> None:
        stop_all(self.procs)


@contextlib.contextmanager
def services_up(cfg: Config, overrides: list[str], config_path: str | None = None,
                services: tuple[str, ...] = SERVICES, ready_timeout_s: float = 300.0,
                subscriptions: dict[str, Callable[[Any], None]] | None = None,
                on_session: Callable[[Any, str], Callable[[], None]] | None = None,
                restarts: int = 0, env: dict[str, str] | None = None,
                args: dict[str, list[str]] | None = None, secure: bool = True
                ) -> Iterator[tuple[Any, str, Supervisor]]:
    """Router + the named services, ready (every token up). Yields (session, endpoint,
    supervisor); `restarts` per service are allowed before a failure is final; `args`:
    extra command-line arguments per service.

    `secure` (the default): mutual TLS on loopback and the generated access-control rules,
    with bus.certs or the certificates made on first use in `default_certs()`; otherwise
    plain TCP (unless bus.certs is set).

    `subscriptions` (key -> callback) are declared on the router's session before
    any service starts, so nothing the services publish is missed; so is
    `on_session(session, endpoint)` (a recorder, a viewer: `hooks`), whose returned
    finaliser runs after every service has stopped.
    """
    certs = cfg.bus.certs or (str(ensure_certs(default_certs())) if secure else "")
    if certs != cfg.bus.certs:
        overrides = [*overrides, f"bus.certs={json.dumps(certs)}"]
    port = free_port()
    endpoint = client_endpoint(port, certs)
    with open_session(router_config(port, certs)) as session:
        for key, callback in (subscriptions or {}).items():
            session.declare_subscriber(key, callback)
        finish = on_session(session, endpoint) if on_session is not None else None
        sup = Supervisor(endpoint, overrides, config_path, (), restarts, ready_timeout_s,
                         env, cfg.supervision.heartbeat_deadline_s)
        for name in services:
            sup.start(name, args=(args or {}).get(name, []))

        def on_beat(_key: str, payload: bytes) -> None:
            try:
                sup.on_beat(decode(payload, Heartbeat))
            except DecodeError as exc:
                log.warning("an undecodable heartbeat: %s", exc)

        beats = ZenohTransport(session).subscriber(heartbeat_key(cfg.episode.vehicle), on_beat)
        try:
            while True:
                up = {s for s, _ in alive_instances(ZenohTransport(session), cfg.episode.vehicle)}
                if all(s in up for s in services):
                    break
                failure = sup.check()
                if failure is not None:
                    raise RuntimeError(f"{failure['service']} {failure['why']} before it was "
                                       "ready")
                time.sleep(0.1)
            yield session, endpoint, sup
        finally:
            sup.stop()
            beats.undeclare()
            if finish is not None:
                finish()


Hook = Callable[[Any, str], Callable[[], None]]


def hooks(*each: Hook | None) -> Hook | None:
    """One `on_session` of several (None: skipped); finalisers run in reverse order."""
    given = [h for h in each if h is not None]
    if not given:
        return None

    def start(session: Any, endpoint: str) -> Callable[[], None]:
        finishers = [h(session, endpoint) for h in given]

        def finish() -> None:
            for f in reversed(finishers):
                f()
        return finish
    return start


def recording_hook(cfg: Config, path: str, summary: dict[str, Any]) -> Hook:
    """An `on_session` that records every key of the vehicle to `path`; the recorder's
    statistics land in `summary["recording"]`."""
    from deploy.recording.record import Recorder, recording_metadata

    def start(session: Any, _endpoint: str) -> Callable[[], None]:
        keys = f"{PREFIX}/{cfg.episode.vehicle}/**"
        rec = Recorder(ZenohTransport(session), keys, path,
                       recording_metadata(cfg.to_dict(), keys))
        log.info("recording %s to %s", keys, path)

        def finish() -> None:
            stats = rec.stop()
            summary["recording"] = {"path": path, "messages": stats["messages"],
                                    "missing": stats["missing"],
                                    "undecodable": stats["undecodable"],
                                    "max_backlog": stats["max_backlog"]}
        return finish
    return start


def start_viewer(endpoint: str, overrides: list[str], config_path: str | None,
                 args: list[str]) -> subprocess.Popen:
    """`vamppi view` (deploy/recording/view.py) on the router at `endpoint`, stopping with
    this process; its statistics come back on its stdout (`stop_viewer`)."""
    cmd = [sys.executable, "-m", "deploy", "view", "--stop-with-parent", *args,
           *(["--config", config_path] if config_path else [])]
    for o in overrides:
        cmd += ["--set", o]
    cmd += ["--set", 'bus.mode="client"', "--set", f"bus.connect={json.dumps([endpoint])}",
            "--set", "bus.listen=[]"]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=sys.stderr,
                            stdin=subprocess.DEVNULL, text=True,
                            env={**os.environ, PARENT_ENV: str(os.getpid())})


def stop_viewer(proc: subprocess.Popen, grace_s: float = 5.0) -> dict[str, Any]:
    """Stop the viewer; its statistics (Viewer.stats), or why there are none."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        out, _ = proc.communicate(timeout=grace_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    try:
        return json.loads(out.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return {"error": f"the viewer exited with code {proc.returncode} and no statistics"}


def viewer_hook(overrides: list[str], config_path: str | None, args: list[str],
                summary: dict[str, Any]) -> Hook:
    """An `on_session` that starts `vamppi view` with `args` on the router before any
    service (so that it sees the episode from its start); its statistics land in
    `summary["view"]`."""
    def start(_session: Any, endpoint: str) -> Callable[[], None]:
        proc = start_viewer(endpoint, overrides, config_path, args)

        def finish() -> None:
            summary["view"] = stop_viewer(proc)
        return finish
    return start


def summary_template(cfg: Config) -> dict[str, Any]:
    """`vamppi up`'s summary before the episode: every key it prints (`view` and
    `recording` join when asked for)."""
    return {"scenario": cfg.episode.scenario, "controller": cfg.planner.controller,
            "samples": cfg.planner.samples, "seed": cfg.episode.seed, "outcome": "error",
            "time_to_goal_s": None, "sim_time_s": None, "wall_time_s": None, "restarts": {},
            "failure": None, "router": None}


def up(cfg: Config, overrides: list[str], config_path: str | None = None,
       timeout_s: float = 900.0, record: str | None = None, secure: bool = True,
       view: list[str] | None = None) -> dict[str, Any]:
    """Run one episode across processes (recorded to `record` if given, served live to
    Foxglove with `vamppi view`'s arguments `view` if given), supervised, secured unless
    not `secure` (`services_up`); returns the summary record. The outcome is taken only
    from the plant this launcher started (`Supervisor.owns`). While it runs, its router is
    announced on this machine (deploy/launch/running.py)."""
    summary = summary_template(cfg)
    events = Inbox(Event, topic_key(cfg.episode.vehicle, "events"), Health(), maxlen=1024)
    wall0 = time.monotonic()
    try:
        with services_up(cfg, overrides, config_path, subscriptions={
                events.key: lambda s: events.on_payload(s.payload.to_bytes())},
                on_session=hooks(recording_hook(cfg, record, summary) if record else None,
                                 viewer_hook(overrides, config_path, view, summary) if view
                                 else None),
                restarts=cfg.supervision.restarts, secure=secure) as (session, endpoint, sup), \
                announce(endpoint, cfg.episode.vehicle, router_certs(cfg, endpoint)):
            summary["router"] = endpoint
            log.info("all services up after %.1f s, router on %s (vamppi health, record, view "
                     "and swap on this machine find it by themselves)",
                     time.monotonic() - wall0, endpoint)
            bus = ZenohTransport(session)
            requests: queue.SimpleQueue[dict[str, Any]] = queue.SimpleQueue()

            def on_request(_key: str, payload: bytes) -> None:
                try:
                    requests.put(json.loads(payload))
                except ValueError as exc:
                    log.warning("an unreadable launcher request: %s", exc)
            keep = [bus.subscriber(launcher_key(cfg.episode.vehicle), on_request),
                    bus.token(alive_key(cfg.episode.vehicle, "launcher", "0"))]
            start_wall = None
            deadline = time.monotonic() + timeout_s
            ended_at = None
            while time.monotonic() < deadline:
                ev = events.get(timeout=0.1)
                if ev is not None and not sup.owns(ev.header):
                    summary["foreign_events"] = summary.get("foreign_events", 0) + 1
                    log.warning("vamppi up: an event not from its plant ignored: %s from %s",
                                ev.kind, ev.header.source)
                    ev = None
                if ev is not None and ev.kind == "start":
                    start_wall = time.monotonic()
                if ev is not None and ev.kind in OUTCOMES:
                    summary.update(outcome=ev.kind, sim_time_s=round(ev.header.stamp, 6),
                                   time_to_goal_s=None if ev.kind != "success"
                                   else round(ev.time_to_goal_s, 6),
                                   wall_time_s=round(time.monotonic() - (start_wall or wall0), 3))
                    time.sleep(SETTLE_S)    # the answers to the final state reach the recording
                    break
                if sup.procs["plant"].poll() == 0:      # the plant ends with its episode
                    ended_at = ended_at or time.monotonic()
                    if time.monotonic() - ended_at > 5.0:
                        summary["failure"] = {"service": "plant", "why": "the episode ended "
                                              "but its outcome event never arrived"}
                        break
                while not requests.empty():
                    sup.request(requests.get())
                failure = sup.check(expected_exit=lambda name: name == "plant")
                summary["restarts"] = dict(sup.restarts)
                if failure is not None:
                    summary["failure"] = failure
                    break
            else:
                log.error("no outcome after %.0f s wall", timeout_s)
                summary["failure"] = {"service": None, "why": f"no outcome after "
                                                              f"{timeout_s:.0f} s wall"}
            for k in keep:
                k.undeclare()
    except (RuntimeError, TimeoutError) as exc:
        log.error("%s", exc)
        summary["failure"] = {"service": None, "why": str(exc)}
    return summary
