"""Faults, for real: the tools `tests/test_faults.py` and `vamppi bench faults` use.

- `Pipeline`: a `vamppi router` process, the services as `vamppi service` processes and
  an observer that records the bus (deploy.recording.record.Recorder) and follows states,
  events and heartbeats live;
- `Up`: `vamppi up` as a process, its stderr read live, its children found by name;
- `Rogue`: another client that sends hostile variants of real messages (`hostile`);
- `Namespace`: a network namespace on a veth pair whose link can be cut (`ip netns`,
  root); `Delay`: a TCP proxy that delays and "loses" in user space.

Nothing here fakes a component: a fault is a signal to a process, a router killed and
started again, a link cut, or messages another client sends.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from common.bus import ZenohTransport, alive_instances, open_session, query_json
from common.config import BusConfig, Config, load_config
from common.messages import DecodeError, Event, Heartbeat, State, decode, on_decoded
from common.topics import SERVICES, heartbeat_key, topic_key
from deploy.launch.certs import make_certs
from deploy.launch.up import free_port, service_command
from deploy.recording.record import Recorder, iter_messages, recording_metadata
from services.plant.protocol import OUTCOMES

PY = sys.executable


def client(endpoint: str) -> BusConfig:
    return BusConfig("client", (endpoint,), (), False)


class Proc:
    """A vamppi process whose stderr is kept in a file (read on failure)."""

    def __init__(self, args: list[str], log: Path, env: dict[str, str] | None = None,
                 prefix: list[str] | None = None):
        self.args, self.log = args, log
        self._f = open(log, "ab")  # noqa: SIM115
        self.p = subprocess.Popen([*(prefix or []), *args], stdout=self._f, stderr=self._f,
                                  stdin=subprocess.DEVNULL, env={**os.environ, **(env or {})})

    @property
    def pid(self) -> int:
        return self.p.pid

    def signal(self, sig: int) -> None:
        if self.p.poll() is None:
            os.kill(self.p.pid, sig)

    def stop(self, timeout: float = 10.0) -> int | None:
        if self.p.poll() is None:
            self.p.terminate()
            try:
                self.p.wait(timeout)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()
        self._f.close()
        return self.p.returncode

    def tail(self, n: int = 3000) -> str:
        return self.log.read_text(errors="replace")[-n:]


class Pipeline:
    """A router process, services as processes and an observer that records everything
    (plain and recovering subscriptions, deploy.recording.record.Recorder) and follows the
    states and events live."""

    def __init__(self, overrides: list[str], tmp: Path, listen: list[str] | None = None,
                 port: int | None = None, endpoint: str | None = None,
                 router_args: list[str] = (), router_prefix: list[str] | None = None,
                 observer: BusConfig | None = None):
        """`listen`: the router's endpoints (default loopback on `port`); `router_args`:
        more of `vamppi router`'s arguments (a site's file, certificates) and
        `router_prefix` its command's (a namespace); `observer`: the observer's session
        (default a plain client of `endpoint`)."""
        self.overrides, self.tmp = list(overrides), tmp
        self.cfg: Config = load_config(overrides=overrides)
        self.port = port or free_port()
        self.endpoint = endpoint or f"tcp/127.0.0.1:{self.port}"
        self.listen = listen or [self.endpoint]
        self.router_args, self.router_prefix = list(router_args), router_prefix
        self.procs: dict[str, Proc] = {}
        self.router = self.start_router()
        self.session = open_session(observer or client(self.endpoint))
        self.bus = ZenohTransport(self.session)
        v = self.cfg.episode.vehicle
        keys = f"vamppi/{v}/**"
        self.path = tmp / "bus.mcap"
        self.recorder = Recorder(self.bus, keys, self.path,
                                 recording_metadata(self.cfg.to_dict(), keys))
        self.events: list[Event] = []
        self.event_at: list[float] = []          # monotonic arrival of each event
        self.last_state: State | None = None
        self.states_seen = 0
        self.beats: list[tuple[float, Heartbeat]] = []
        self._lock = threading.Lock()
        self._subs = [self.bus.subscriber(topic_key(v, "state"), on_decoded(State,
                                                                            self._on_state)),
                      self.bus.subscriber(topic_key(v, "events"), on_decoded(Event,
                                                                             self._on_event)),
                      self.bus.subscriber(heartbeat_key(v), on_decoded(Heartbeat,
                                                                       self._on_beat))]
        self._stats: dict[str, Any] | None = None

    # processes ----------------------------------------------------------------
    def start_router(self) -> Proc:
        args = [PY, "-m", "deploy", "router", *self.router_args]
        for ep in self.listen:
            args += ["--listen", ep]
        log = self.tmp / "router.log"
        before = log.read_text().count("router listening") if log.exists() else 0
        p = Proc(args, log, prefix=self.router_prefix)
        deadline = time.monotonic() + 30
        while log.read_text().count("router listening") <= before:
            assert time.monotonic() < deadline and p.p.poll() is None, p.tail()
            time.sleep(0.05)
        return p

    def restart_router(self, down_s: float = 1.0) -> None:
        """SIGKILL the router, and start another on the same port `down_s` later."""
        self.router.signal(signal.SIGKILL)
        self.router.p.wait()
        time.sleep(down_s)
        self.router = self.start_router()

    def service(self, name: str, extra: list[str] = (), endpoint: str | None = None,
                prefix: list[str] | None = None, env: dict[str, str] | None = None,
                config: str | None = None) -> Proc:
        cmd = service_command(name, endpoint or self.endpoint, [*self.overrides, *extra],
                              config)
        p = Proc(cmd, self.tmp / f"{name}.log", env, prefix)
        self.procs[name] = p
        return p

    def up(self, services: tuple[str, ...] = SERVICES, timeout: float = 240.0,
           **kw: Any) -> None:
        for name in services:
            self.service(name, **kw)
        self.wait(lambda: all(s in {x for x, _ in alive_instances(self.bus,
                                                                   self.cfg.episode.vehicle)}
                              for s in services), timeout, "services ready")

    def kill(self, name: str, sig: int = signal.SIGKILL) -> float:
        p = self.procs[name]
        t = time.monotonic()
        p.signal(sig)
        if sig in (signal.SIGKILL, signal.SIGTERM):
            p.p.wait(20)
        return t

    # observing ------------------------------------------------------------------
    def _on_state(self, s: State) -> None:
        with self._lock:
            self.states_seen += 1
            if self.last_state is None or s.header.stamp >= self.last_state.header.stamp:
                self.last_state = s

    def _on_event(self, e: Event) -> None:
        with self._lock:
            self.events.append(e)
            self.event_at.append(time.monotonic())

    def _on_beat(self, hb: Heartbeat) -> None:
        with self._lock:
            self.beats.append((time.monotonic(), hb))

    @property
    def t(self) -> float:
        with self._lock:
            return -1.0 if self.last_state is None else self.last_state.header.stamp

    @property
    def speed(self) -> float:
        with self._lock:
            s = self.last_state
            return 0.0 if s is None else float(np.hypot(s.x[0], s.x[1]))

    def outcome(self) -> Event | None:
        with self._lock:
            done = [e for e in self.events if e.kind in OUTCOMES]
        return done[0] if done else None

    def first_event(self, kind: str, after: float = 0.0) -> tuple[float, Event] | None:
        """The first event of `kind` that arrived after monotonic time `after`."""
        with self._lock:
            for at, e in zip(self.event_at, self.events, strict=True):
                if e.kind == kind and at >= after:
                    return at, e
        return None

    def kinds(self) -> list[tuple[float, str, str]]:
        with self._lock:
            return [(round(e.header.stamp, 2), e.kind, e.detail) for e in self.events]

    def wait(self, pred: Callable[[], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not pred():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for {what}\n" + self.logs())
            time.sleep(0.02)

    def wait_outcome(self, timeout: float = 300.0) -> Event:
        self.wait(lambda: self.outcome() is not None, timeout, "the outcome")
        return self.outcome()

    def health(self, service: str, instance: str = "0") -> dict[str, Any]:
        from common.topics import admin_key
        got = query_json(self.bus, admin_key(self.cfg.episode.vehicle, service, instance,
                                             "health"))
        return got[0] if got else {}

    def logs(self) -> str:
        return "\n".join(f"--- {n}\n{p.tail(1500)}" for n, p in
                         [("router", self.router), *self.procs.items()])

    # the end ----------------------------------------------------------------------
    def close(self) -> dict[str, Any]:
        if self._stats is None:
            for p in self.procs.values():
                p.stop()
            self._stats = self.recorder.stop(drain_s=0.5)
            for s in self._subs:
                s.undeclare()
            self.session.close()
            self.router.stop()
        return self._stats

    def trajectory(self) -> np.ndarray:
        """The 50 Hz trajectory of the episode, from the recording (`recorded_trajectory`)."""
        self.close()
        return recorded_trajectory(self.path)

    def __enter__(self) -> Pipeline:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def json_lines(text: str, prefix: str) -> list[dict[str, Any]]:
    """The JSON objects logged after `prefix` in a process's stderr."""
    out = []
    for line in text.splitlines():
        if prefix in line:
            try:
                out.append(json.loads(line.split(prefix, 1)[1]))
            except json.JSONDecodeError:
                pass
    return out


# ----------------------------------------------------------------------------- hostile input
def _with(msg: Any, **header: Any) -> Any:
    from dataclasses import replace
    return replace(msg, header=replace(msg.header, **header))


def hostile(topic: str, msg: Any, first: Any) -> list[tuple[str, bytes]]:
    """Hostile variants of a real message `msg` (and the topic's first, `first`), as another
    client would send them once: (name, payload). Those that claim the real publisher do
    so as a newer process of it (boot + 1), so that it is their stamps and contents that
    must give them away."""
    from dataclasses import replace

    from common.messages import encode
    h = msg.header
    newer = h.boot + 1
    out = [("duplicate", encode(msg)),
           ("stale", encode(_with(first, boot=newer, seq=0))),
           ("future", encode(_with(replace(msg, t0=msg.t0 + 5.0) if topic == "cmd" else msg,
                                   boot=newer, seq=1, stamp=h.stamp + 5.0))),
           ("another client's", encode(_with(msg, source="rogue/0", seq=0, boot=1)))]
    if topic == "state":
        x = msg.x.copy()
        x[3] = np.nan
        out.append(("nan", encode(replace(msg, x=x))[:-1] + b"\x00"))   # and truncated
    elif topic == "depth":
        out += [("wrong size", encode(_with(replace(msg, depth=np.ones((10, 10), np.float32)),
                                            boot=newer, seq=2))),
                ("wrong camera", encode(_with(replace(msg, intrinsics=msg.intrinsics * 2),
                                              boot=newer, seq=3)))]
    elif topic == "map":
        for i, n in enumerate((10, 2600)):
            z = np.zeros((n, n), np.float32)
            out.append((f"{n} x {n}", encode(_with(replace(msg, mean=z, variance=z),
                                                   boot=newer, seq=2 + i))))
    elif topic == "cmd":
        n = len(msg.controls)
        big = np.tile(np.array([[0.0, 1e6]], np.float32), (n, 1))
        out += [("dt 0", encode(_with(replace(msg, dt=0.0), boot=newer, seq=2))),
                ("one control", encode(_with(replace(msg, dt=0.02, controls=msg.controls[:1]),
                                             boot=newer, seq=3))),
                ("beyond limits", encode(_with(replace(msg, controls=big), boot=newer, seq=4))),
                ("another episode", encode(_with(msg, boot=newer, seq=5,
                                                 episode=h.episode + 1)))]
        nan = msg.controls.copy()
        nan[0, 0] = np.nan
        out.append(("nan", encode(replace(msg, controls=nan))))
    return out


class Rogue:
    """Another client on the router: at the `at`-th real message of each of `topics` (of
    states, which come five a tick, the 5 `at`-th) it sends every hostile variant of it
    once (from its own thread)."""

    TOPICS = ("state", "depth", "map", "cmd")

    def __init__(self, endpoint: str, vehicle: str, at: int = 10,
                 bus: BusConfig | None = None, topics: tuple[str, ...] = TOPICS):
        from common.messages import MESSAGE_TYPES
        self.topics = topics
        self.session = open_session(bus or client(endpoint))
        self.sent: list[tuple[str, str]] = []
        self._first: dict[str, Any] = {}
        self._count: dict[str, int] = {}
        self._types = {t: MESSAGE_TYPES[f"vamppi.{t.capitalize()}"] for t in topics}
        self._lock = threading.Lock()
        self._threads: list[threading.Thread] = []
        self.vehicle = vehicle
        self._subs = [self.session.declare_subscriber(
            topic_key(vehicle, t), lambda s, t=t: self._on(t, s.payload.to_bytes()))
            for t in topics]
        self.at = at

    def _on(self, topic: str, payload: bytes) -> None:
        try:
            msg = decode(payload, self._types[topic])
        except DecodeError:
            return
        if msg.header.source.startswith("rogue") or msg.header.boot != self._boot(topic, msg):
            return
        with self._lock:
            self._first.setdefault(topic, msg)
            n = self._count[topic] = self._count.get(topic, 0) + 1
        if n == self.at * (5 if topic == "state" else 1):
            th = threading.Thread(target=self._send, args=(topic, msg))
            with self._lock:
                self._threads.append(th)
            th.start()

    def _boot(self, topic: str, msg: Any) -> int:
        first = self._first.get(topic)
        return msg.header.boot if first is None else first.header.boot

    def _send(self, topic: str, msg: Any) -> None:
        import zenoh
        for name, payload in hostile(topic, msg, self._first[topic]):
            self.session.put(topic_key(self.vehicle, topic), payload,      # every one arrives
                             congestion_control=zenoh.CongestionControl.BLOCK)
            with self._lock:
                self.sent.append((topic, name))

    def close(self) -> None:
        """Finish the hostile sends under way (`sent` is complete after this), then close."""
        with self._lock:
            threads = list(self._threads)
        for th in threads:
            th.join(10)
        self.session.close()


def _flood(bus: BusConfig, key: str, stop: Any, sent: Any) -> None:
    """A flood's process: copies of the newest sample on `key`, put until `stop`."""
    os.nice(10)                          # the flood's own work yields to the pipeline's
    latest: list[bytes] = []
    with open_session(bus) as session:
        session.declare_subscriber(key, lambda smp: latest.append(smp.payload.to_bytes()))
        n = 0
        while not stop.is_set():
            if latest:
                session.put(key, latest[-1])
                n += 1
                del latest[:-1]
                if n % 1000 == 0:
                    sent.value = n
            else:
                time.sleep(0.01)
        sent.value = n


class Flood:
    """A client in its own process (niced) that puts copies of the newest real message of
    `topic` as fast as it can until `close()`, which returns how many it put. Its own
    process: a flood in the observer's would cost the observer, not the pipeline."""

    def __init__(self, bus: BusConfig, vehicle: str, topic: str = "cmd"):
        import multiprocessing
        ctx = multiprocessing.get_context("spawn")
        self._stop, self._sent = ctx.Event(), ctx.Value("q", 0)
        self._proc = ctx.Process(target=_flood, args=(bus, topic_key(vehicle, topic),
                                                     self._stop, self._sent), daemon=True)
        self._proc.start()

    def close(self) -> int:
        self._stop.set()
        self._proc.join(10)
        if self._proc.is_alive():
            self._proc.kill()
        return int(self._sent.value)


def rejections(text: str) -> list[tuple[str, str]]:
    """(topic, reason) of every "rejected a <topic> message: <reason>" log line."""
    import re
    return [(m.group(1), m.group(2)) for m in re.finditer(
        r"rejected a (\w+) message: (.+?) from \S+ seq \d+ stamp", text)]



def recorded_trajectory(path: Path) -> np.ndarray:
    """The 50 Hz trajectory (t, x) in a recording, one row per stamp (a re-offered tick is
    the same state again), of the plant processes that ran the episode (those that
    published its events: not another client's states)."""
    boots = set()
    for m in iter_messages(path):
        if m.key.endswith("/plant/events"):
            try:
                boots.add(decode(m.data, Event).header.boot)
            except DecodeError:
                pass
    rows: dict[float, np.ndarray] = {}
    for m in iter_messages(path):
        if m.key.endswith("/plant/state"):
            try:
                s = decode(m.data, State)
            except DecodeError:
                continue
            if s.header.boot in boots:
                rows.setdefault(round(s.header.stamp, 6),
                                np.concatenate([[s.header.stamp], s.x]))
    return np.array([rows[k] for k in sorted(rows)])


class Up:
    """`vamppi up` as a process: its stderr read live (each line with its monotonic time),
    its children found by the vehicle name it was given."""

    def __init__(self, args: list[str], vehicle: str):
        self.vehicle = vehicle
        self.p = subprocess.Popen([PY, "-m", "deploy", "up", "--vehicle", vehicle, *args],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines: list[tuple[float, str]] = []
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self) -> None:
        for line in self.p.stderr:
            self.lines.append((time.monotonic(), line.rstrip()))

    def wait_line(self, text: str, timeout: float, after: float = 0.0) -> float:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for t, line in list(self.lines):
                if t >= after and text in line:
                    return t
            time.sleep(0.02)
        raise AssertionError(f"no line with {text!r} in {timeout} s:\n" + self.stderr()[-4000:])

    def child(self, service: str) -> int:
        (pid,) = [p for p in processes_with(self.vehicle)
                  if f"service {service} " in cmdline(p)]
        return pid

    def finish(self, timeout: float = 600.0) -> dict[str, Any]:
        out, _ = self.p.communicate(timeout=timeout)
        self._t.join(5)
        lines = out.strip().splitlines()
        if not lines:
            raise AssertionError(f"vamppi up exited {self.p.returncode} with no summary:\n"
                                 + self.stderr()[-4000:])
        return json.loads(lines[-1])

    def stderr(self) -> str:
        return "\n".join(line for _, line in self.lines)


def cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def processes_with(marker: str) -> list[int]:
    """The pids of the processes whose command line names `marker`."""
    return [int(p) for p in os.listdir("/proc") if p.isdigit() and marker in cmdline(int(p))]


# ----------------------------------------------------------------------------- the network
class Namespace:
    """A network namespace joined to this one by a veth pair: `host_ip` on this side,
    `ip` inside. `cut()` / `mend()` take the link down and up. Made by the test, removed
    by it (`ip netns`, root)."""

    def __init__(self, tag: str, subnet: int):
        self.name, self.host_dev, self.dev = f"vns{tag}", f"vh{tag}", f"vn{tag}"
        self.host_ip, self.ip = f"10.{subnet}.0.1", f"10.{subnet}.0.2"
        run = self._run
        run("ip", "netns", "add", self.name)
        try:
            run("ip", "link", "add", self.host_dev, "type", "veth", "peer", "name", self.dev)
            run("ip", "link", "set", self.dev, "netns", self.name)
            run("ip", "addr", "add", f"{self.host_ip}/24", "dev", self.host_dev)
            run("ip", "link", "set", self.host_dev, "up")
            self.exec_("ip", "addr", "add", f"{self.ip}/24", "dev", self.dev)
            self.exec_("ip", "link", "set", self.dev, "up")
            self.exec_("ip", "link", "set", "lo", "up")
        except BaseException:
            self.remove()
            raise

    @staticmethod
    def _run(*args: str) -> None:
        subprocess.run(args, check=True, capture_output=True, timeout=30)

    def exec_(self, *args: str) -> None:
        self._run("ip", "netns", "exec", self.name, *args)

    @property
    def prefix(self) -> list[str]:
        return ["ip", "netns", "exec", self.name]

    def cut(self) -> None:
        self._run("ip", "link", "set", self.host_dev, "down")

    def mend(self) -> None:
        self._run("ip", "link", "set", self.host_dev, "up")

    def wire(self, other: Namespace, subnet: int) -> tuple[str, str]:
        """A veth pair straight from this namespace to `other` (a link between two sites
        that bypasses this one): the addresses (`10.subnet.0.1` here, `.2` there)."""
        ends = (f"vw{self.name[3:]}", f"vx{self.name[3:]}")
        ips = (f"10.{subnet}.0.1", f"10.{subnet}.0.2")
        self._run("ip", "link", "add", ends[0], "netns", self.name, "type", "veth", "peer",
                  "name", ends[1], "netns", other.name)
        for ns, dev, ip in ((self, ends[0], ips[0]), (other, ends[1], ips[1])):
            ns.exec_("ip", "addr", "add", f"{ip}/24", "dev", dev)
            ns.exec_("ip", "link", "set", dev, "up")
        return ips

    def remove(self) -> None:
        subprocess.run(["ip", "link", "del", self.host_dev], capture_output=True, timeout=30)
        subprocess.run(["ip", "netns", "del", self.name], capture_output=True, timeout=30)

    def __enter__(self) -> Namespace:
        return self

    def __exit__(self, *exc: object) -> None:
        self.remove()


SITES = Path(__file__).resolve().parents[1] / "configs"
SITE_ENDPOINT = "tls/127.0.0.1:7447"          # a site's router, to the services of its site


@dataclass
class Sites:
    """Two sites in network namespaces (`two_sites`): the pipeline (site A's router, the
    observer), the namespaces, the certificates, site B's router and its addresses."""
    pipeline: Pipeline
    a: Namespace
    b: Namespace
    certs: Path
    router_b: Proc
    wan_a: str

    def secured(self, role: str, endpoint: str) -> BusConfig:
        """A client session of `endpoint` presenting `role`'s certificate."""
        return BusConfig("client", (endpoint,), (), False, str(self.certs), role)

    def service(self, name: str, **kw: Any) -> Proc:
        """`name` in its site: plant and sensor in A, mapper and planner in B, each a client
        of its own site's router (deploy/configs/site-*.toml)."""
        site = "a" if name in ("plant", "sensor") else "b"
        ns = self.a if site == "a" else self.b
        return self.pipeline.service(name, endpoint=SITE_ENDPOINT, prefix=ns.prefix,
                                     config=str(SITES / f"site-{site}.toml"),
                                     extra=[f"bus.certs={json.dumps(str(self.certs))}"], **kw)

    def up(self, timeout: float = 240.0) -> None:
        p = self.pipeline
        for name in SERVICES:
            self.service(name)
        p.wait(lambda: set(SERVICES) <= {x for x, _ in alive_instances(
            p.bus, p.cfg.episode.vehicle)}, timeout, "services ready")


def wait_for_line(proc: Proc, text: str, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while text not in proc.tail(100_000):
        assert time.monotonic() < deadline and proc.p.poll() is None, proc.tail()
        time.sleep(0.05)


@contextlib.contextmanager
def two_sites(overrides: list[str], tmp: Path) -> Iterator[Sites]:
    """Site A (plant, sensor) and site B (mapper, planner), each in its own network
    namespace with its own router started from deploy/configs/site-*.json5; the routers
    linked over a veth pair between the two namespaces. Every link is mutual TLS with
    certificates made here, and both routers enforce the generated rules. The observer
    (a recorder's certificate) is a client of site A's router from this namespace; site B's
    router is reachable from here too (`Sites.b.ip`), for the attacks."""
    tag = f"{os.getpid() % 10000}"
    with Namespace(f"{tag}a", 94) as a, Namespace(f"{tag}b", 95) as b:
        wan_a, _ = a.wire(b, 96)
        certs = tmp / "certs"
        make_certs(certs, hosts=("localhost", "127.0.0.1", wan_a, a.ip, b.ip))
        sec = ["--set", f"bus.certs={json.dumps(str(certs))}"]
        here = f"tls/{a.ip}:7447"
        with Pipeline(overrides, tmp, listen=[SITE_ENDPOINT, here, f"tls/{wan_a}:7447"],
                      endpoint=here, router_prefix=a.prefix,
                      router_args=["--config", str(SITES / "site-a.json5"), *sec],
                      observer=BusConfig("client", (here,), (), False, str(certs),
                                         "recorder")) as p:
            rb = Proc([PY, "-m", "deploy", "router", "--config",
                       str(SITES / "site-b.json5"), *sec, "--listen", SITE_ENDPOINT,
                       "--listen", f"tls/{b.ip}:7447", "--connect", f"tls/{wan_a}:7447"],
                      tmp / "router-b.log", prefix=b.prefix)
            try:
                wait_for_line(rb, "router listening")
                yield Sites(p, a, b, certs, rb, wan_a)
            finally:
                p.close()
                rb.stop()


class Delay:
    """A TCP proxy on loopback that delays what it forwards, in user space (this kernel has
    no netem): every chunk by `delay_s`, and a fraction `loss` of them by `retransmit_s`
    more, as TCP delivers a lost segment once it is sent again. Order is kept."""

    def __init__(self, target: tuple[str, int], delay_s: float = 0.02, loss: float = 0.01,
                 retransmit_s: float = 0.2, seed: int = 0):
        import random
        import socket
        self.target, self.delay_s, self.loss, self.retransmit_s = (target, delay_s, loss,
                                                                    retransmit_s)
        self._rng = random.Random(seed)
        self._rng_lock = threading.Lock()
        self.chunks = self.slowed = 0
        self._srv = socket.socket()
        self._srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._srv.bind(("127.0.0.1", 0))
        self._srv.listen(16)
        self.port = self._srv.getsockname()[1]
        self._stop = threading.Event()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        import socket
        while not self._stop.is_set():
            try:
                a, _ = self._srv.accept()
            except OSError:
                return
            b = socket.create_connection(self.target)
            for s in (a, b):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            for src, dst in ((a, b), (b, a)):
                threading.Thread(target=self._pipe, args=(src, dst), daemon=True).start()

    def _pipe(self, src: Any, dst: Any) -> None:
        import collections
        q: collections.deque[tuple[float, bytes]] = collections.deque()
        cv = threading.Condition()

        def send() -> None:
            while True:
                with cv:
                    cv.wait_for(lambda: q)
                    due, data = q[0]
                wait = due - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                with cv:
                    q.popleft()
                if not data:
                    dst.close()
                    return
                try:
                    dst.sendall(data)
                except OSError:
                    return
        threading.Thread(target=send, daemon=True).start()
        last = 0.0
        while True:
            try:
                data = src.recv(65536)
            except OSError:
                data = b""
            with self._rng_lock:
                slow = bool(data) and self._rng.random() < self.loss
                self.chunks += 1
                self.slowed += slow
            due = max(last, time.monotonic() + self.delay_s + (self.retransmit_s if slow else 0))
            last = due
            with cv:
                q.append((due, data))
                cv.notify()
            if not data:
                return

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.port}"

    def close(self) -> None:
        self._stop.set()
        self._srv.close()


# ----------------------------------------------------------------------------- the figures
LOCKSTEP = ["planner.samples=64", "episode.timeout_s=3.0", 'episode.scenario="open-field"']
REALTIME = ["planner.samples=64", 'episode.scenario="open-field"', 'episode.clock="realtime"',
            "episode.timeout_s=40"]


def supervised(service: str, sig: int, tmp: Path, reference: np.ndarray) -> dict[str, Any]:
    """`vamppi up` in lockstep, `service` stopped or killed mid-episode: from the signal to
    the supervisor's verdict, and whether the episode was the undisturbed one."""
    marker = f"bench{service}{sig}{os.getpid()}"
    rec = tmp / f"up-{service}-{sig}.mcap"
    args = [a for o in LOCKSTEP for a in ("--set", o)] + ["--record", str(rec)]
    up = Up(args, marker)
    up.wait_line("all services up", 300)
    time.sleep(0.5)
    pid = up.child(service)
    t = time.monotonic()
    os.kill(pid, sig)
    detected = up.wait_line('"restarting"', 60, after=t) - t
    summary = up.finish()
    got = recorded_trajectory(rec)
    return {"case": "supervised", "clock": "lockstep", "service": service,
            "signal": signal.Signals(sig).name, "detected_s": round(detected, 3),
            "restarts": summary["restarts"], "outcome": summary["outcome"],
            "bit_identical": got.shape == reference.shape
            and got.tobytes() == reference.tobytes()}


def plant_record(path: Path) -> tuple[list[State], list[Event]]:
    """The plant's states (one per stamp, in stamp order) and events of a recording,
    those that arrived late included."""
    states: dict[float, State] = {}
    events = []
    for m in iter_messages(path):
        if m.key.endswith("/plant/state"):
            s = decode(m.data, State)
            states.setdefault(round(s.header.stamp, 6), s)
        elif m.key.endswith("/plant/events"):
            events.append(decode(m.data, Event))
    return [states[k] for k in sorted(states)], sorted(events, key=lambda e: e.header.stamp)


def _speed(s: State) -> float:
    return float(np.hypot(s.x[0], s.x[1]))


def _after(path: Path, t0: float, t_back: float) -> dict[str, Any]:
    """From a recording: after sim time t0, the first degraded event, the standstill (time
    and distance), and the first state moving again after both t_back (when what was lost
    came back) and the standstill, counted from t_back."""
    states, events = plant_record(path)
    s0 = max((s for s in states if s.header.stamp <= t0), key=lambda s: s.header.stamp)
    deg = next((e for e in events if e.kind == "degraded" and e.header.stamp >= t0), None)
    stop = next((s for s in states if s.header.stamp > t0 and _speed(s) < 0.05), None)
    after = max(t_back, t0 if stop is None else stop.header.stamp)
    back = next((s for s in states if s.header.stamp > after and _speed(s) > 0.5), None)
    return {"speed_mps": round(_speed(s0), 2),
            "degraded": None if deg is None else deg.detail,
            "degraded_after_sim_s": None if deg is None else round(deg.header.stamp - t0, 3),
            "standstill_after_sim_s": None if stop is None
            else round(stop.header.stamp - t0, 3),
            "standstill_distance_m": None if stop is None
            else round(float(np.hypot(*(stop.x[3:5] - s0.x[3:5]))), 2),
            "moving_after_sim_s": None if back is None else round(back.header.stamp - t_back, 3)}


def lost_at_speed(name: str, tmp: Path, at_s: float = 4.0) -> dict[str, Any]:
    """Realtime, no supervisor: `name` killed at speed (the router: started again after
    2 s), the others started again once the vehicle has stopped. From the recording: what
    the plant said and when, the way to a standstill, and back to moving once it was
    started again (simulation seconds, which run with the wall clock in realtime: the
    restart's own warm-up included)."""
    with Pipeline(REALTIME, tmp) as p:
        p.up()
        p.wait(lambda: p.t >= at_s, 120, f"t >= {at_s}")
        t0, w0 = p.t, time.monotonic()
        if name == "router":
            p.restart_router(2.0)
        else:
            p.kill(name)
            p.wait(lambda: p.speed < 0.05, 60, "a standstill")
            time.sleep(0.5)
            p.service(name)
        t_back = t0 + time.monotonic() - w0   # realtime: the plant's clock runs with ours
        ev = p.wait_outcome(180)
        p.close()
    return {"case": "lost at speed", "clock": "realtime", "service": name,
            **_after(p.path, t0, t_back), "outcome": ev.kind}


def run_with_cut(overrides: list[str], cut_s: float, tmp: Path, at_s: float
                 ) -> tuple[Pipeline, dict[str, Any], Event, float]:
    """An episode with the plant in its own network namespace, its link to the router's
    taken down for `cut_s` once the episode reaches `at_s`: the pipeline (closed), the
    recorder's statistics, the outcome, the sim time of the cut."""
    from deploy.launch.up import free_port
    port = free_port()
    with Namespace(f"{os.getpid() % 10000}{int(cut_s)}", 70 + int(cut_s)) as ns, \
            Pipeline(overrides, tmp, listen=[f"tcp/127.0.0.1:{port}",
                                             f"tcp/{ns.host_ip}:{port}"], port=port) as p:
        p.service("plant", endpoint=f"tcp/{ns.host_ip}:{port}", prefix=ns.prefix)
        p.up(("sensor", "mapper", "planner"))
        p.wait(lambda: p.t >= at_s, 120, f"t >= {at_s} s")
        t_cut = p.t
        ns.cut()
        time.sleep(cut_s)
        ns.mend()
        ev = p.wait_outcome(180)
        stats = p.close()
    return p, stats, ev, t_cut


def cut_link(cut_s: float, tmp: Path) -> dict[str, Any]:
    """Realtime, the plant's link cut for `cut_s` at t = 3 s: its way to a standstill, how
    soon it moved after the link returned, what reached the recorder."""
    p, stats, ev, t0 = run_with_cut(REALTIME, cut_s, tmp, 3.0)
    plant = {q["key"].rsplit("/", 1)[1]: q for q in stats["publishers"]
             if q["source"] == "plant/0"}
    return {"case": "link cut", "clock": "realtime", "cut_s": cut_s,
            **_after(p.path, t0, t0 + cut_s), "outcome": ev.kind,
            "plant_states": {k: plant["state"][k] for k in ("count", "missing", "late")},
            "plant_events_missing": plant["events"]["missing"],
            "heartbeats_missing": plant["heartbeat"]["missing"],
            "heartbeat_gaps": plant["heartbeat"]["gaps"]}


def slow_link(tmp: Path, reference_time: float) -> dict[str, Any]:
    """Realtime with every service behind `Delay` (20 ms, 1 % of chunks 200 ms more)."""
    with Pipeline(REALTIME, tmp) as p:
        link = Delay(("127.0.0.1", p.port))
        p.up(endpoint=link.endpoint)
        ev = p.wait_outcome(180)
        kinds = p.kinds()
        link.close()
    degraded = [k for k in kinds if k[1] == "degraded"]
    return {"case": "slow lossy link", "clock": "realtime", "outcome": ev.kind,
            "time_to_goal_s": ev.time_to_goal_s, "undisturbed_time_to_goal_s": reference_time,
            "chunks": link.chunks, "chunks_retransmitted": link.slowed,
            "degraded_events": len(degraded), "degraded": [d for _, _, d in degraded]}


def bench_faults(cfg: Config, tmp: Path) -> dict[str, Any]:
    """Every figure of docs/reliability.md, measured: detection under `vamppi up`, the
    vehicle's stop and restart when a service is lost at speed, link cuts, a slow link."""
    from deploy.bench.device import device_info
    from deploy.sim.runner import run_episode
    reference = run_episode(load_config(overrides=LOCKSTEP)).trajectory
    cases = []
    for service in SERVICES:
        for sig in (signal.SIGSTOP, signal.SIGKILL):
            (tmp / f"{service}{sig}").mkdir()
            cases.append(supervised(service, sig, tmp / f"{service}{sig}", reference))
    for name in ("mapper", "sensor", "planner", "router"):
        (tmp / f"lost-{name}").mkdir()
        cases.append(lost_at_speed(name, tmp / f"lost-{name}"))
    if os.geteuid() == 0:
        for cut in (2.0, 12.0):
            (tmp / f"cut{cut}").mkdir()
            cases.append(cut_link(cut, tmp / f"cut{cut}"))
    rt = run_episode(load_config(overrides=REALTIME), planner_link=lambda t: True)
    (tmp / "slow").mkdir()
    cases.append(slow_link(tmp / "slow", rt.time_to_goal_s))
    return {"benchmark": "faults", **device_info(),
            "settings": {"lockstep": LOCKSTEP, "realtime": REALTIME,
                         "heartbeat_deadline_s": cfg.supervision.heartbeat_deadline_s,
                         "perception_timeout_s": cfg.plant.perception_timeout_s,
                         "cmd_timeout_s": cfg.plant.cmd_timeout_s}, "cases": cases}


def faults_table(result: dict[str, Any]) -> str:
    lines = [f"faults: {result['device']}", "",
             "| case | clock | service | signal or cut | detected s | standstill s (m) "
             "| moving again s | outcome | bit-identical |",
             "|---|---|---|---|---|---|---|---|---|"]
    for c in result["cases"]:
        what = c.get("signal") or (f"{c['cut_s']:g} s" if "cut_s" in c else "")
        det = c.get("detected_s", c.get("degraded_after_sim_s"))
        stop = (f"{c['standstill_after_sim_s']} ({c['standstill_distance_m']})"
                if c.get("standstill_after_sim_s") is not None else "")
        back = c.get("moving_after_sim_s")
        lines.append(f"| {c['case']} | {c['clock']} | {c.get('service', 'plant')} | {what} "
                     f"| {'' if det is None else det} | {stop} | {'' if back is None else back} "
                     f"| {c['outcome']} | {c.get('bit_identical', '')} |")
    return "\n".join(lines)
