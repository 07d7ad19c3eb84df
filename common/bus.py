"""The bus: transports, typed publishers and subscribers, liveliness, health, heartbeats.

Its keys, one builder each, are in common.topics.

A `Transport` is the seam between a node and the wire: `ZenohTransport` (a zenoh
session) or `MemoryTransport` (an in-process `MemoryBus`, for tests of a node's
protocol without a router). Callbacks never block: they decode and put the
message in an `Inbox` (per source: latest-value, a ring of one, or a bounded FIFO
for lockstep) and return. A payload that fails to decode is dropped with one log
line and counted; seq gaps are tracked per publisher (source and boot).
"""

from __future__ import annotations

import collections
import itertools
import json
import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, Protocol, TypeVar

from common.config import BusConfig, agreement_digest, disagreements
from common.memory import keep_large_buffers
from common.messages import DecodeError, Heartbeat, InputRef, Message, decode, encode
from common.protocol import Out, SeqTrack, Stamper
from common.topics import (
    admin_key,
    alive_key,
    heartbeat_key,
    key_matches,
    latest_key,
    topic_key,
    topic_of,
)

log = logging.getLogger(__name__)

class Transport(Protocol):
    """What a node needs of the wire."""

    def publisher(self, key: str, *, express: bool = False, drop: bool = False,
                  cache: int = 0) -> Any: ...                      # .put(bytes)
    def subscriber(self, key: str, callback: Callable[[str, bytes], None], *,
                   recover: bool = False,
                   on_miss: Callable[[str, int], None] | None = None) -> Any: ...
    def queryable(self, key: str, answer: Callable[[str], list[tuple[str, bytes]]]) -> Any: ...
    def query(self, key: str, timeout: float = 2.0) -> list[tuple[str, bytes]]: ...
    def token(self, key: str) -> Any: ...
    def tokens(self, key: str, timeout: float = 2.0) -> list[str]: ...
    def close(self) -> None: ...


def zenoh_config(cfg: BusConfig, wait: bool = False):
    """A zenoh.Config from our BusConfig: bus.zenoh's file if any, then mode, endpoints
    (where set), multicast scouting, mutual TLS (bus.certs) or user/password
    (bus.credentials), and for a secured router the generated access-control rules
    (common.security). `wait`: a client that finds no router waits for one (zenoh retries)
    instead of failing."""
    import zenoh
    zc = zenoh.Config.from_file(cfg.zenoh) if cfg.zenoh else zenoh.Config()
    zc.insert_json5("mode", json.dumps(cfg.mode))
    for name, endpoints in (("connect", cfg.connect), ("listen", cfg.listen)):
        if endpoints or not cfg.zenoh:
            zc.insert_json5(f"{name}/endpoints", json.dumps(list(endpoints)))
    zc.insert_json5("scouting/multicast/enabled", json.dumps(bool(cfg.multicast_scouting)))
    router = cfg.mode == "router"
    name = cfg.identity or ("router" if router else "")
    if (cfg.certs or cfg.credentials) and not name:
        raise ValueError("bus.certs or bus.credentials is set but not bus.identity: who?")
    users: tuple[str, ...] = ()
    if cfg.certs:
        from common.security import tls
        listens, connects = (bool(endpoints_of(zc, k, cfg.mode)) for k in ("listen", "connect"))
        block = tls(cfg.certs, name, listen=listens)
        if connects and listens:             # a router linked to another: both ends
            block |= tls(cfg.certs, name, listen=False)
        zc.insert_json5("transport/link/tls", json.dumps(block))
    if cfg.credentials:
        from common.security import read_credentials
        known = read_credentials(cfg.credentials)
        users = tuple(known)
        auth: dict[str, str] = {}
        if router:
            auth["dictionary_file"] = str(Path(cfg.credentials).expanduser().resolve())
        if name in known:
            auth |= {"user": name, "password": known[name]}
        elif not router:
            raise ValueError(f"{cfg.credentials} has no line for {name!r}")
        zc.insert_json5("transport/auth/usrpwd", json.dumps(auth))
    if router and (cfg.certs or cfg.credentials):
        from common.security import accepted_names, access_control
        # every vehicle's keys (the rules' vehicle chunk a wildcard)
        names = accepted_names(cfg.certs) if cfg.certs else ()
        zc.insert_json5("access_control", json.dumps(access_control("*", users=users,
                                                                    names=names)))
    if wait and cfg.mode == "client":
        zc.insert_json5("connect/timeout_ms", "-1")
        zc.insert_json5("connect/exit_on_failure", "false")
    return zc


def endpoints_of(zc: Any, name: str, mode: str) -> list[str]:
    """A zenoh.Config's `listen` or `connect` endpoints for `mode` (zenoh's defaults are
    per mode)."""
    got = json.loads(zc.get_json(f"{name}/endpoints"))
    return list(got.get(mode, [])) if isinstance(got, dict) else list(got)


def open_session(cfg: BusConfig, wait: bool = False):
    """A zenoh session (`wait`: for the router, as a service does; a tool fails at once)."""
    import zenoh
    zenoh.try_init_log_from_env()
    keep_large_buffers()
    return zenoh.open(zenoh_config(cfg, wait))


class ZenohTransport:
    """A zenoh session as a `Transport`. Publishers with `cache` are zenoh-ext advanced
    publishers (the last `cache` samples kept for subscribers that missed them, and a
    heartbeat by which they notice a miss); `recover` subscribers are advanced subscribers
    that fetch what they missed from those caches (delivered late, in order)."""

    def __init__(self, session: Any, owned: bool = False):
        self.session, self._owned = session, owned

    @classmethod
    def open(cls, cfg: BusConfig, wait: bool = False) -> ZenohTransport:
        return cls(open_session(cfg, wait), owned=True)

    def publisher(self, key: str, *, express: bool = False, drop: bool = False,
                  cache: int = 0) -> Any:
        import zenoh
        cc = zenoh.CongestionControl.DROP if drop else zenoh.CongestionControl.BLOCK
        if cache:
            import zenoh.ext as ze
            return ze.declare_advanced_publisher(
                self.session, key, reliability=zenoh.Reliability.RELIABLE, congestion_control=cc,
                express=express, cache=ze.CacheConfig(cache),
                sample_miss_detection=ze.MissDetectionConfig(heartbeat=0.5),
                publisher_detection=True)
        return self.session.declare_publisher(key, reliability=zenoh.Reliability.RELIABLE,
                                              congestion_control=cc, express=express)

    def subscriber(self, key: str, callback: Callable[[str, bytes], None], *,
                   recover: bool = False,
                   on_miss: Callable[[str, int], None] | None = None) -> Any:
        def on_sample(s: Any) -> None:
            callback(str(s.key_expr), s.payload.to_bytes())
        if not recover:
            return self.session.declare_subscriber(key, on_sample)
        import zenoh.ext as ze
        sub = ze.declare_advanced_subscriber(
            self.session, key, on_sample, history=ze.HistoryConfig(detect_late_publishers=True),
            recovery=ze.RecoveryConfig(heartbeat=True))
        if on_miss is not None:
            listener = sub.sample_miss_listener(lambda m: on_miss(str(m.source), int(m.nb)))
            return (sub, listener)
        return sub

    def queryable(self, key: str, answer: Callable[[str], list[tuple[str, bytes]]]) -> Any:
        def on_query(q: Any) -> None:
            for k, payload in answer(str(q.key_expr)):
                q.reply(k, payload)
        return self.session.declare_queryable(key, on_query)

    def query(self, key: str, timeout: float = 2.0) -> list[tuple[str, bytes]]:
        return [(str(r.ok.key_expr), r.ok.payload.to_bytes())
                for r in self.session.get(key, timeout=timeout) if r.ok is not None]

    def token(self, key: str) -> Any:
        return self.session.liveliness().declare_token(key)

    def tokens(self, key: str, timeout: float = 2.0) -> list[str]:
        return [str(r.ok.key_expr) for r in self.session.liveliness().get(key, timeout=timeout)
                if r.ok is not None]

    def close(self) -> None:
        if self._owned:
            self.session.close()


class MemoryBus:
    """An in-process bus: what `MemoryTransport`s put reaches every matching subscription at
    once, in the putting thread (so a node's protocol runs in a test without a router)."""

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self._subs: dict[int, tuple[str, Callable[[str, bytes], None]]] = {}
        self._queryables: dict[int, tuple[str, Callable[[str], list[tuple[str, bytes]]]]] = {}
        self._tokens: dict[int, str] = {}
        self._ids = itertools.count()
        self.puts: collections.Counter[str] = collections.Counter()

    def put(self, key: str, payload: bytes) -> None:
        with self._lock:
            subs = [cb for pattern, cb in self._subs.values() if key_matches(pattern, key)]
            self.puts[key] += 1
        for cb in subs:
            cb(key, payload)

    def add(self, table: dict, value: Any) -> Callable[[], None]:
        with self._lock:
            i = next(self._ids)
            table[i] = value
        return lambda: self._remove(table, i)

    def _remove(self, table: dict, i: int) -> None:
        with self._lock:
            table.pop(i, None)


class _Handle:
    def __init__(self, undeclare: Callable[[], None], put: Callable[[bytes], None] | None = None):
        self.undeclare = undeclare
        if put is not None:
            self.put = put


class MemoryTransport:
    """A `Transport` on a `MemoryBus`."""

    def __init__(self, bus: MemoryBus):
        self.bus = bus
        self._handles: list[_Handle] = []

    def _keep(self, h: _Handle) -> _Handle:
        self._handles.append(h)
        return h

    def publisher(self, key: str, *, express: bool = False, drop: bool = False,
                  cache: int = 0) -> Any:
        return self._keep(_Handle(lambda: None, lambda payload: self.bus.put(key, payload)))

    def subscriber(self, key: str, callback: Callable[[str, bytes], None], *,
                   recover: bool = False,
                   on_miss: Callable[[str, int], None] | None = None) -> Any:
        return self._keep(_Handle(self.bus.add(self.bus._subs, (key, callback))))

    def queryable(self, key: str, answer: Callable[[str], list[tuple[str, bytes]]]) -> Any:
        return self._keep(_Handle(self.bus.add(self.bus._queryables, (key, answer))))

    def query(self, key: str, timeout: float = 2.0) -> list[tuple[str, bytes]]:
        with self.bus._lock:
            found = [(k, a) for k, a in self.bus._queryables.values() if key_matches(key, k)]
        return [reply for k, a in found for reply in a(k)]

    def token(self, key: str) -> Any:
        return self._keep(_Handle(self.bus.add(self.bus._tokens, key)))

    def tokens(self, key: str, timeout: float = 2.0) -> list[str]:
        with self.bus._lock:
            return [k for k in self.bus._tokens.values() if key_matches(key, k)]

    def close(self) -> None:
        for h in self._handles:
            h.undeclare()
        self._handles.clear()


def as_transport(bus: BusConfig | Transport) -> Transport:
    """A service's transport: a zenoh session that waits for its router, or `bus` itself."""
    return ZenohTransport.open(bus, wait=True) if isinstance(bus, BusConfig) else bus


# ----------------------------------------------------------------------------- health
@dataclass
class Health:
    """Counters a service exposes on its health queryable."""
    messages_in: int = 0
    messages_out: int = 0
    dropped: int = 0              # failed to decode or validate
    superseded: int = 0           # replaced in a latest-value inbox before being read
    last_error: str = ""
    rejected: collections.Counter = field(default_factory=collections.Counter)  # "topic: why"
    last_rejected: str = ""
    missed: collections.Counter = field(default_factory=collections.Counter)   # zenoh's count
    extra: dict[str, Any] = field(default_factory=dict)
    seqs: dict[tuple[str, str, int], SeqTrack] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def count_error(self, text: str) -> None:
        with self._lock:
            self.dropped += 1
            self.last_error = text

    def count_rejected(self, topic: str, reason: str, detail: str = "") -> None:
        with self._lock:
            self.rejected[f"{topic}: {reason}"] += 1
            self.last_rejected = f"{topic}: {reason}" + (f" ({detail})" if detail else "")

    def count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.extra[name] = self.extra.get(name, 0) + n

    def saw(self, topic: str, source: str, boot: int, seq: int) -> None:
        with self._lock:
            self.seqs.setdefault((topic, source, boot), SeqTrack()).see(seq)

    def as_dict(self) -> dict[str, Any]:
        with self._lock:
            gaps = {f"{t} {s} {b}": {"missing": tr.missing, "gaps": tr.gaps[:20],
                                     "late": tr.late, "duplicates": tr.duplicates}
                    for (t, s, b), tr in self.seqs.items() if tr.missing or tr.late}
            out = {"messages_in": self.messages_in, "messages_out": self.messages_out,
                   "dropped": self.dropped, "superseded": self.superseded,
                   "last_error": self.last_error}
            if self.rejected:
                out.update(rejected=dict(self.rejected), last_rejected=self.last_rejected)
            if gaps:
                out["seq_gaps"] = gaps
            if self.missed:
                out["missed"] = dict(self.missed)
            return {**out, **self.extra}


M = TypeVar("M", bound=Message)


class Inbox(Generic[M]):
    """Decoded messages of one topic, in arrival order, kept per source: `maxlen` per source
    (1: latest value, never a queue), so that one source's flood displaces only its own.
    At most `max_sources` sources are kept; messages of more are counted and dropped."""

    def __init__(self, cls: type[M], key: str, health: Health, maxlen: int = 1,
                 max_sources: int = 32, arrived: threading.Event | None = None):
        self.cls, self.key, self.health = cls, key, health
        self.arrived = arrived              # set on every message (the node's, shared)
        self.topic = topic_of(key) or key.rsplit("/", 1)[-1]
        self.maxlen, self.max_sources = maxlen, max_sources
        self._q: dict[str, collections.deque[tuple[int, M, float]]] = {}
        self._arrivals = itertools.count()
        self._cv = threading.Condition()

    def on_payload(self, payload: bytes) -> None:
        """Decode and store; never raises, never blocks for long."""
        received = time.time()
        try:
            msg = decode(payload, self.cls)
        except DecodeError as exc:
            self.health.count_error(f"{self.key}: {exc}")
            log.warning("dropped a message on %s: %s", self.key, exc)
            return
        h = msg.header
        self.health.saw(self.topic, h.source, h.boot, h.seq)
        with self._cv:
            q = self._q.get(h.source)
            if q is None:
                if len(self._q) >= self.max_sources:
                    self.health.count_rejected(self.topic, "too many sources", h.source)
                    return
                q = self._q[h.source] = collections.deque(maxlen=self.maxlen)
            if len(q) == q.maxlen:
                self.health.superseded += 1
            q.append((next(self._arrivals), msg, received))
            self.health.messages_in += 1
            self._cv.notify_all()
        if self.arrived is not None:
            self.arrived.set()

    def _pop_oldest(self) -> tuple[M, float] | None:
        best = None
        for q in self._q.values():
            if q and (best is None or q[0][0] < best[0][0]):
                best = q
        if best is None:
            return None
        _, msg, received = best.popleft()
        return msg, received

    def get(self, timeout: float | None = None) -> M | None:
        """The oldest waiting message, or None after `timeout`."""
        got = self.get_received(timeout)
        return None if got is None else got[0]

    def get_received(self, timeout: float | None = None) -> tuple[M, float] | None:
        """The oldest waiting message and its receive wall time, or None after `timeout`."""
        with self._cv:
            got = self._pop_oldest()
            if got is None and timeout and self._cv.wait(timeout):
                got = self._pop_oldest()
            return got

    def drain(self) -> list[tuple[M, float]]:
        """Every waiting message with its receive wall time, in arrival order."""
        with self._cv:
            out = []
            while (got := self._pop_oldest()) is not None:
                out.append(got)
            return out

    def wait(self, timeout: float) -> bool:
        """Block until a message is waiting (True) or `timeout` passes."""
        with self._cv:
            return any(self._q.values()) or self._cv.wait(timeout)

    def peek_latest(self) -> M | None:
        """The newest waiting message of any source, left in place."""
        with self._cv:
            items = [q[-1] for q in self._q.values() if q]
            return max(items, key=lambda i: i[0])[1] if items else None


class TypedPublisher(Generic[M]):
    """Publishes one message type on one key; fills the header (gap-free seq, boot)."""

    def __init__(self, transport: Transport, key: str, cls: type[M], stamper: Stamper,
                 health: Health, express: bool = False, drop: bool = False, cache: int = 0):
        self.key, self.cls, self.health = key, cls, health
        self._stamper = stamper
        self._pub = transport.publisher(key, express=express, drop=drop, cache=cache)
        self.latest: bytes | None = None          # what `serve_latest` answers

    @property
    def seq(self) -> int:
        return self._stamper.seq

    def publish(self, stamp: float, inputs: Iterable[InputRef] = (), episode: int = 0,
                **fields: Any) -> M:
        return self.publish_out(Out(self.key, stamp, fields, tuple(inputs), episode))

    def publish_out(self, out: Out) -> M:
        msg = self._stamper.make(self.cls, out)
        payload = encode(msg)
        self._pub.put(payload)
        self.latest = payload
        self.health.messages_out += 1
        return msg  # type: ignore[return-value]


# ----------------------------------------------------------------------------- node
class WorldMismatch(RuntimeError):
    """The plant runs another scenario (its heartbeat's digest differs from this node's)."""


class Node:
    """One service instance on the bus: transport, token, health, config and latest-value
    queryables, its heartbeat.

    Use as a context manager; declare subscribers and publishers, then call `ready()` to
    raise the liveliness token once the service can work. The heartbeat (`Heartbeat`
    every `heartbeat_s` on `heartbeat_key`, stating `deadline_s` as the time within which
    the next one comes) runs from `__enter__`, status `starting` until `ready()`; its
    thread beats `ready` only while the main loop calls `progress()` within `stall_s`
    (else `stalled`), so that a wedged loop is seen even while the process's transport
    threads still answer the router.
    """

    def __init__(self, bus: BusConfig | Transport, vehicle: str, service: str, instance: str,
                 config_dict: dict[str, Any] | None = None, heartbeat_s: float = 0.1,
                 deadline_s: float = 1.0, stall_s: float | None = None, world: str = ""):
        self._bus, self.vehicle, self.service, self.instance = bus, vehicle, service, instance
        self.source = f"{service}/{instance}"
        self.boot = time.time_ns()
        self.health = Health()
        self.config_dict = config_dict or {}
        self.transport: Transport | None = None
        self.heartbeat_s, self.deadline_s = heartbeat_s, deadline_s
        self.stall_s = deadline_s if stall_s is None else stall_s
        self.role = ""
        self.detail = ""
        self.world = world                 # the digest of the scenario this instance runs
        self.refused = ""                  # why it must stop: the plant runs another world
        self.agree = agreement_digest(self.config_dict) if self.config_dict else ""
        self.disagreements: dict[str, list[str]] = {}   # source -> what it runs otherwise
        self._checked: set[tuple[str, int]] = set()     # (source, boot) compared
        self._keep: list[Any] = []
        self._token = None
        self._status = "starting"
        self._progress_wall = time.monotonic()
        self._stamp = 0.0
        self._episode = 0
        self._stop_beat = threading.Event()
        self._arrived = threading.Event()
        self._beat_thread: threading.Thread | None = None

    def __enter__(self) -> Node:
        self.transport = as_transport(self._bus)
        for what, reply in (("health", self.health.as_dict), ("config", lambda: self.config_dict),
                            ("clock", lambda: {"wall_time": time.time()})):
            key = admin_key(self.vehicle, self.service, self.instance, what)
            self._keep.append(self.transport.queryable(
                key, lambda k, key=key, reply=reply: [(key, json.dumps(reply()).encode())]))
        self._beats = TypedPublisher(self.transport, heartbeat_key(self.vehicle, self.service),
                                     Heartbeat, Stamper(self.source, self.boot), Health(),
                                     drop=True)       # a beat never blocks (nor is queued)
        self._beat_thread = threading.Thread(target=self._beat_loop, daemon=True,
                                             name=f"{self.service}-heartbeat")
        self._beat_thread.start()
        if (self.world and self.service != "plant") or self.agree:
            self._keep.append(self.transport.subscriber(heartbeat_key(self.vehicle),
                                                        self._on_beat))
        return self

    def _on_beat(self, _key: str, payload: bytes) -> None:
        """Another instance's beat: refuse a plant that runs another world; compare the
        configuration of one that states another agreement digest (`_compare`)."""
        try:
            hb = decode(payload, Heartbeat)
        except DecodeError:
            return                        # counted where heartbeats are judged
        h = hb.header
        if (hb.agree and self.agree and hb.agree != self.agree and h.source != self.source
                and (h.source, h.boot) not in self._checked):
            self._checked.add((h.source, h.boot))
            threading.Thread(target=self._compare, args=(h.source,), daemon=True,
                             name=f"{self.service}-compare").start()
        if not h.source.startswith("plant/") or self.service == "plant" or not self.world:
            return
        if hb.world and hb.world != self.world and not self.refused:
            self.refused = (f"this {self.service} runs scenario digest {self.world}, the plant "
                            f"({hb.header.source}) {hb.world}: every service must load the "
                            "same scenario file")
            log.error("%s", self.refused)
            self._arrived.set()

    def _compare(self, source: str) -> None:
        """Ask `source` its configuration and warn of every `common.config.AGREE` key it
        runs otherwise (counted: health `config_disagreements`)."""
        service, _, instance = source.partition("/")
        transport = self.transport
        if transport is None:
            return
        try:
            replies = transport.query(admin_key(self.vehicle, service, instance, "config"),
                                      timeout=2.0)
            theirs = json.loads(replies[0][1]) if replies else None
        except Exception as exc:          # a closing session, a malformed answer
            log.debug("config of %s: %s", source, exc)
            theirs = None
        keys = (disagreements(self.config_dict, theirs) if isinstance(theirs, dict)
                else ["(its configuration did not come)"])
        if not keys:
            return
        self.disagreements[source] = keys
        self.health.count("config_disagreements")
        log.warning("this %s and %s run different configurations where every service of "
                    "vehicle %s must agree: %s", self.source, source, self.vehicle,
                    "; ".join(keys))

    def __exit__(self, *exc: object) -> None:
        self._stop_beat.set()
        if self._beat_thread is not None:
            self._beat_thread.join(timeout=1.0)
        if self.transport is not None:
            try:
                if self._status != "retired":
                    self._status = "stopping"
                self._beat()
            except Exception:             # the session may be closing under us
                pass
            self.transport.close()
            self.transport = None

    # heartbeat --------------------------------------------------------------
    def progress(self, stamp: float | None = None, episode: int | None = None) -> None:
        """The main loop is alive (call it every iteration), working at sim time `stamp`.
        Raises WorldMismatch once the plant has been heard running another scenario."""
        if self.refused:
            raise WorldMismatch(self.refused)
        self._progress_wall = time.monotonic()
        if stamp is not None:
            self._stamp = float(stamp)
        if episode is not None:
            self._episode = int(episode)

    def _beat(self) -> None:
        status = self._status
        if status == "ready" and time.monotonic() - self._progress_wall > self.stall_s:
            status = "stalled"
        self._beats.publish(self._stamp, episode=self._episode, status=status, role=self.role,
                            deadline_s=self.deadline_s, detail=self.detail, world=self.world,
                            agree=self.agree)

    def _beat_loop(self) -> None:
        while not self._stop_beat.wait(self.heartbeat_s):
            try:
                self._beat()
            except Exception as exc:      # never let the beat kill the service
                log.debug("heartbeat not sent: %s", exc)

    def wait_any(self, timeout: float) -> bool:
        """Block until a message arrives in any of this node's inboxes, or `timeout`."""
        got = self._arrived.wait(timeout)
        self._arrived.clear()
        return got

    # topics -----------------------------------------------------------------
    def key(self, topic: str) -> str:
        return topic_key(self.vehicle, topic)

    def subscribe(self, topic: str, cls: type[M], maxlen: int = 1, recover: bool = False,
                  key: str | None = None) -> Inbox[M]:
        """An inbox of `topic` (its key, or `key`: a key expression such as every
        heartbeat's)."""
        assert self.transport is not None
        inbox: Inbox[M] = Inbox(cls, key or self.key(topic), self.health, maxlen,
                                arrived=self._arrived)
        self._keep.append(self.transport.subscriber(
            inbox.key, lambda _k, payload: inbox.on_payload(payload), recover=recover,
            on_miss=lambda src, n: self.health.missed.update({f"{topic} {src}": n})))
        return inbox

    def publisher(self, topic: str, cls: type[M], express: bool = False, drop: bool = False,
                  cache: int = 0) -> TypedPublisher[M]:
        assert self.transport is not None
        return TypedPublisher(self.transport, self.key(topic), cls,
                              Stamper(self.source, self.boot), self.health, express, drop, cache)

    def reject(self, topic: str, reason: str, msg: Message | None = None) -> None:
        """Count a rejected input (its reason in health) with one log line."""
        detail = "" if msg is None else (f"from {msg.header.source} seq {msg.header.seq} "
                                         f"stamp {msg.header.stamp:.3f}")
        self.health.count_rejected(topic, reason, detail)
        log.warning("rejected a %s message: %s %s", topic, reason, detail)

    # latest values ------------------------------------------------------------
    def hold(self, topic: str, latest: Callable[[], bytes | None]) -> None:
        """Answer queries for the newest `topic` message this instance holds (its own
        output, or an input it accepted): what a restarted service asks for."""
        assert self.transport is not None
        key = latest_key(self.vehicle, self.service, self.instance, topic)

        def answer(_key: str) -> list[tuple[str, bytes]]:
            payload = latest()
            return [] if payload is None else [(key, payload)]
        self._keep.append(self.transport.queryable(key, answer))

    def query_latest(self, topic: str, cls: type[M], timeout: float = 1.0) -> list[M]:
        """The newest `topic` message held by each instance on the bus that answers (valid
        ones only), oldest first by (episode, stamp)."""
        assert self.transport is not None
        found = []
        for key, payload in self.transport.query(latest_key(self.vehicle, "*", "*", topic),
                                                 timeout):
            if not key.endswith(f"/latest/{topic}"):
                continue
            try:
                found.append(decode(payload, cls))
            except DecodeError as exc:
                log.warning("a latest %s from %s is not valid: %s", topic, key, exc)
        return sorted(found, key=lambda m: (m.header.episode, m.header.stamp))

    def retire(self) -> None:
        """Beat `retired` (the supervisor and the plant take it as gone by design): three
        times, since a heartbeat may be dropped; the process then exits with RETIRED_EXIT."""
        self._status = "retired"
        for _ in range(3):
            self._beat()
            time.sleep(0.02)

    def ready(self) -> None:
        """Raise this instance's liveliness token: the service is up and warmed."""
        assert self.transport is not None
        self._token = self.transport.token(alive_key(self.vehicle, self.service, self.instance))
        self._status = "ready"
        self.progress()


def alive_instances(transport: Transport, vehicle: str) -> list[tuple[str, str]]:
    """(service, instance) of every liveliness token up under this vehicle."""
    out = []
    for key in transport.tokens(alive_key(vehicle), timeout=2.0):
        parts = key.split("/")
        out.append((parts[3], parts[4]))
    return out


def query_json(transport: Transport, key: str, timeout: float = 2.0) -> list[Any]:
    """Answers of a queryable, parsed as JSON."""
    return [json.loads(payload) for _, payload in transport.query(key, timeout)]


@dataclass(frozen=True)
class ClockOffset:
    """How far a process's wall clock is ahead of ours (`offset_s`), measured as NTP does
    from a round trip: true within `rtt_s / 2`, whatever the hosts' clocks."""
    offset_s: float
    rtt_s: float

    @staticmethod
    def from_round_trip(sent: float, remote: float, received: float) -> ClockOffset:
        """Asked at our `sent`, answered `remote` on its clock, heard at our `received`."""
        return ClockOffset(remote - (sent + received) / 2, received - sent)

    def best(self, other: ClockOffset | None) -> ClockOffset:
        """The tighter of two measurements (the smaller round trip)."""
        return self if other is None or self.rtt_s <= other.rtt_s else other


def measure_clocks(transport: Transport, vehicle: str, rounds: int = 3,
                   known: dict[str, ClockOffset] | None = None,
                   reachable: Callable[[str], bool] = lambda source: True
                   ) -> dict[str, ClockOffset]:
    """Every live instance's clock offset ("service/instance" -> the tightest of `rounds`
    round trips to its clock queryable, and of `known`). Only instances `reachable` says
    are asked: a query to one behind a cut link that is still pending when the link
    returns leaves that instance's subscriptions dead in zenoh 1.10 (reproduced by the
    lockstep cut-link test under load)."""
    out = dict(known or {})
    for service, instance in alive_instances(transport, vehicle):
        source = f"{service}/{instance}"
        if not reachable(source):
            continue
        for _ in range(rounds):
            sent = time.time()
            got = query_json(transport, admin_key(vehicle, service, instance, "clock"), 1.0)
            received = time.time()
            if got and isinstance(got[0], dict) and "wall_time" in got[0]:
                m = ClockOffset.from_round_trip(sent, float(got[0]["wall_time"]), received)
                out[source] = m.best(out.get(source))
    return out
