"""The bus: zenoh-python sessions, typed publishers and subscribers, liveliness, health.

Keys (one builder each, below):

    vamppi/<vehicle>/<service>/<topic>                      data
    vamppi/<vehicle>/alive/<service>/<instance>             liveliness token
    vamppi/<vehicle>/admin/<service>/<instance>/health      queryable (JSON counters)
    vamppi/<vehicle>/admin/<service>/<instance>/config      queryable (JSON config)

Callbacks never block: they decode, validate and put the message in an `Inbox`
(latest-value: a ring of one; or a bounded FIFO for lockstep) and return. A
payload that fails to decode is dropped with one log line and counted.
"""

from __future__ import annotations

import collections
import json
import logging
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import zenoh

from common.config import BusConfig
from common.memory import keep_large_buffers
from common.messages import DecodeError, Header, InputRef, Message, decode, encode

log = logging.getLogger(__name__)

PREFIX = "vamppi"

# topic name -> (owning service, message schema name); the one table of topics
TOPICS: dict[str, tuple[str, str]] = {
    "state": ("plant", "vamppi.State"),
    "events": ("plant", "vamppi.Event"),
    "clock": ("plant", "vamppi.Clock"),
    "depth": ("sensor", "vamppi.Depth"),
    "map": ("mapper", "vamppi.Map"),
    "cmd": ("planner", "vamppi.Cmd"),
    "plan": ("planner", "vamppi.Plan"),
    "stats": ("planner", "vamppi.Stats"),
}
SERVICES = ("plant", "sensor", "mapper", "planner")


def topic_key(vehicle: str, topic: str) -> str:
    service, _ = TOPICS[topic]
    return f"{PREFIX}/{vehicle}/{service}/{topic}"


def alive_key(vehicle: str, service: str = "*", instance: str = "*") -> str:
    return f"{PREFIX}/{vehicle}/alive/{service}/{instance}"


def admin_key(vehicle: str, service: str, instance: str, what: str) -> str:
    return f"{PREFIX}/{vehicle}/admin/{service}/{instance}/{what}"


def zenoh_config(cfg: BusConfig) -> zenoh.Config:
    """A zenoh.Config from our BusConfig: mode, endpoints, multicast scouting."""
    zc = zenoh.Config()
    zc.insert_json5("mode", json.dumps(cfg.mode))
    zc.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
    zc.insert_json5("listen/endpoints", json.dumps(list(cfg.listen)))
    zc.insert_json5("scouting/multicast/enabled", json.dumps(bool(cfg.multicast_scouting)))
    return zc


def open_session(cfg: BusConfig) -> zenoh.Session:
    zenoh.try_init_log_from_env()
    keep_large_buffers()
    return zenoh.open(zenoh_config(cfg))


@dataclass
class Health:
    """Counters a service exposes on its health queryable."""
    messages_in: int = 0
    messages_out: int = 0
    dropped: int = 0              # failed to decode or validate
    superseded: int = 0           # replaced in a latest-value inbox before being read
    last_error: str = ""
    extra: dict[str, Any] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def count_error(self, text: str) -> None:
        with self._lock:
            self.dropped += 1
            self.last_error = text

    def as_dict(self) -> dict[str, Any]:
        with self._lock:
            return {"messages_in": self.messages_in, "messages_out": self.messages_out,
                    "dropped": self.dropped, "superseded": self.superseded,
                    "last_error": self.last_error, **self.extra}


M = TypeVar("M", bound=Message)


class Inbox(Generic[M]):
    """Decoded messages of one topic. `maxlen=1`: latest value, never a queue."""

    def __init__(self, cls: type[M], key: str, health: Health, maxlen: int = 1):
        self.cls, self.key, self.health = cls, key, health
        self._q: collections.deque[tuple[M, float]] = collections.deque(maxlen=maxlen)
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
        with self._cv:
            if len(self._q) == self._q.maxlen:
                self.health.superseded += 1
            self._q.append((msg, received))
            self.health.messages_in += 1
            self._cv.notify_all()

    def get(self, timeout: float | None = None) -> M | None:
        """The oldest waiting message (the only one, for latest-value), or None."""
        with self._cv:
            if not self._q and not self._cv.wait_for(lambda: bool(self._q), timeout):
                return None
            return self._q.popleft()[0]

    def get_where(self, pred, timeout: float | None = None) -> M | None:
        """Wait for a message satisfying `pred`; messages before it are discarded."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cv:
            while True:
                while self._q:
                    msg = self._q.popleft()[0]
                    if pred(msg):
                        return msg
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return None
                self._cv.wait(left)

    def peek_latest(self) -> M | None:
        with self._cv:
            return self._q[-1][0] if self._q else None


class TypedPublisher(Generic[M]):
    """Publishes one message type on one key; fills the header (gap-free seq)."""

    def __init__(self, session: zenoh.Session, key: str, cls: type[M], source: str,
                 health: Health, express: bool = False):
        self.key, self.cls, self.source, self.health = key, cls, source, health
        self.seq = 0
        self._pub = session.declare_publisher(
            key, reliability=zenoh.Reliability.RELIABLE,
            congestion_control=zenoh.CongestionControl.BLOCK, express=express)

    def publish(self, stamp: float, inputs: Iterable[InputRef] = (), **fields: Any) -> M:
        msg = self.cls(header=Header(self.seq, float(stamp), time.time(), self.source,
                                     tuple(inputs)), **fields)
        self._pub.put(encode(msg))
        self.seq += 1
        self.health.messages_out += 1
        return msg


def ref_of(key: str, msg: Message) -> InputRef:
    """The InputRef naming `msg` as received on `key`."""
    return InputRef(key, msg.header.seq, msg.header.stamp)


class Node:
    """One service instance on the bus: session, token, health and config queryables.

    Use as a context manager; declare subscribers and publishers, then call
    `ready()` to raise the liveliness token once the service can work.
    """

    def __init__(self, cfg: BusConfig, vehicle: str, service: str, instance: str,
                 config_dict: dict[str, Any] | None = None):
        self.cfg, self.vehicle, self.service, self.instance = cfg, vehicle, service, instance
        self.source = f"{service}/{instance}"
        self.health = Health()
        self.config_dict = config_dict or {}
        self.session: zenoh.Session | None = None
        self._keep: list[Any] = []
        self._token = None

    def __enter__(self) -> Node:
        self.session = open_session(self.cfg)
        for what, reply in (("health", self.health.as_dict), ("config", lambda: self.config_dict)):
            key = admin_key(self.vehicle, self.service, self.instance, what)
            self._keep.append(self.session.declare_queryable(
                key, lambda q, key=key, reply=reply: q.reply(key, json.dumps(reply()))))
        return self

    def __exit__(self, *exc: object) -> None:
        if self.session is not None:
            self.session.close()
            self.session = None

    def key(self, topic: str) -> str:
        return topic_key(self.vehicle, topic)

    def subscribe(self, topic: str, cls: type[M], maxlen: int = 1) -> Inbox[M]:
        assert self.session is not None
        inbox: Inbox[M] = Inbox(cls, self.key(topic), self.health, maxlen)
        self._keep.append(self.session.declare_subscriber(
            inbox.key, lambda s: inbox.on_payload(s.payload.to_bytes())))
        return inbox

    def publisher(self, topic: str, cls: type[M], express: bool = False) -> TypedPublisher[M]:
        assert self.session is not None
        return TypedPublisher(self.session, self.key(topic), cls, self.source, self.health,
                              express)

    def ready(self) -> None:
        """Raise this instance's liveliness token: the service is up and warmed."""
        assert self.session is not None
        self._token = self.session.liveliness().declare_token(
            alive_key(self.vehicle, self.service, self.instance))


def alive_instances(session: zenoh.Session, vehicle: str) -> list[tuple[str, str]]:
    """(service, instance) of every liveliness token up under this vehicle."""
    out = []
    for reply in session.liveliness().get(alive_key(vehicle), timeout=2.0):
        if reply.ok is not None:
            parts = str(reply.ok.key_expr).split("/")
            out.append((parts[3], parts[4]))
    return out


def query_json(session: zenoh.Session, key: str, timeout: float = 2.0) -> list[Any]:
    """Answers of a queryable, parsed as JSON."""
    out = []
    for reply in session.get(key, timeout=timeout):
        if reply.ok is not None:
            out.append(json.loads(reply.ok.payload.to_bytes()))
    return out
