"""`vamppi view`: the bus, live, in Foxglove.

A Foxglove WebSocket server (the `foxglove-sdk` package) that follows one vehicle's
topics on the bus and publishes what `vamppi export-foxglove` writes, on the same topics,
in the same schemas, by the same `Converter` (deploy/recording/foxglove.py). Open the
Foxglove app, "Open connection", "Foxglove WebSocket", `ws://HOST:8765` (docs/foxglove.md).

Never in the pipeline's way:

- the bus callbacks only keep the newest payload of each topic (`Latest`; events: the
  newest 256) and count what a newer one replaced before it was shown (`dropped`), so a
  slow viewer costs the services nothing and never queues;
- one thread converts and publishes, at most `rate_hz` times a second (maps: `map_hz`),
  and converts nothing for a topic no client subscribes to (`unwatched`); states are
  always taken in, so the path is whole when a client arrives;
- the server drops the oldest message for a client that reads too slowly
  (`message_backlog_size`);
- the process runs at a lower CPU priority (`os.nice`) than the services it watches.
"""

from __future__ import annotations

import asyncio
import collections
import json
import logging
import os
import struct
import threading
import time
from typing import Any

from common.messages import DecodeError, Event, Map, Message, State, decode
from common.topics import topic_key
from deploy.recording.foxglove import SCHEMAS, TOPICS, Converter, violations
from services.sensor.core import CameraParams

log = logging.getLogger(__name__)

# bus topic -> the Foxglove topics its messages become (Converter.convert)
VIEWED: dict[str, tuple[str, ...]] = {
    "state": ("/tf", "/vehicle/pose", "/vehicle/path"),
    "map": ("/map/mean", "/map/variance"),
    "plan": ("/planner/plan",),
    "depth": ("/sensor/depth",),
    "events": ("/events",),
    "stats": ("/planner/stats",),
}
KEEP = {"events": 256}          # how many of a topic wait to be shown (others: the newest)
NICE = 10                       # the viewer's CPU priority below the services'


class Latest:
    """The newest payloads per topic (`keep[topic]` of them, default 1): `put` from the bus
    callbacks never blocks or grows; what it pushes out unseen is counted as dropped."""

    def __init__(self, keep: dict[str, int] | None = None):
        self._keep = keep or {}
        self._slots: dict[str, collections.deque[bytes]] = {}
        self._cv = threading.Condition()
        self.received: collections.Counter[str] = collections.Counter()
        self.dropped: collections.Counter[str] = collections.Counter()

    def put(self, topic: str, payload: bytes) -> None:
        with self._cv:
            slot = self._slots.get(topic)
            if slot is None:
                slot = self._slots[topic] = collections.deque(maxlen=self._keep.get(topic, 1))
            if len(slot) == slot.maxlen:
                self.dropped[topic] += 1
            slot.append(payload)
            self.received[topic] += 1
            self._cv.notify()

    def take(self, topics: set[str] | None = None, timeout: float = 0.0
             ) -> dict[str, list[bytes]]:
        """What waits (of `topics`, default all), oldest first; waits up to `timeout` for
        something if nothing does."""
        with self._cv:
            def ready() -> bool:
                return any(s for t, s in self._slots.items() if topics is None or t in topics)
            if timeout > 0:
                self._cv.wait_for(ready, timeout)
            out = {}
            for t, slot in self._slots.items():
                if slot and (topics is None or t in topics):
                    out[t] = list(slot)
                    slot.clear()
            return out


class Viewer:
    """Follows `vehicle`'s topics on `transport` (common.bus) and serves them to Foxglove
    on `host:port` (0: a free port; `self.port` says which)."""

    def __init__(self, transport: Any, vehicle: str, camera: CameraParams,
                 host: str = "127.0.0.1", port: int = 8765, rate_hz: float = 20.0,
                 map_hz: float = 2.0, rollouts: int = 30, backlog: int = 64):
        import foxglove
        self.context = foxglove.Context()
        self.server = foxglove.start_server(
            name=f"vamppi {vehicle}", host=host, port=port, context=self.context,
            message_backlog_size=backlog)
        self.port = self.server.port
        self.channels = {topic: foxglove.Channel(
            topic, schema=foxglove.Schema(name=schema, encoding="jsonschema",
                                          data=json.dumps(SCHEMAS[schema]).encode()),
            message_encoding="json", context=self.context) for topic, schema in TOPICS.items()}
        self.converter = Converter(1, rollouts, camera)
        self.latest = Latest(KEEP)
        self.rate_hz, self.map_hz = rate_hz, map_hz
        self.published: collections.Counter[str] = collections.Counter()
        self.unwatched: collections.Counter[str] = collections.Counter()
        self.undecodable = 0
        self.errors = 0
        self._stop = threading.Event()
        self._subs = [transport.subscriber(topic_key(vehicle, t),
                                           lambda _k, p, t=t: self.latest.put(t, p))
                      for t in VIEWED]
        self._thread = threading.Thread(target=self._run, name="viewer", daemon=True)
        self._thread.start()

    def _watched(self, topic: str) -> bool:
        return any(self.channels[t].has_sinks() for t in VIEWED[topic])

    def _show(self, topic: str, payload: bytes) -> None:
        if topic != "state" and not self._watched(topic):
            self.unwatched[topic] += 1
            return
        try:
            msg: Message = decode(payload)
        except DecodeError as exc:
            self.undecodable += 1
            log.debug("view: an undecodable %s: %s", topic, exc)
            return
        if not isinstance(msg, State | Map | Event) and not self._watched(topic):
            return
        now = time.time_ns()
        for fox_topic, body in self.converter.convert(msg):
            self.channels[fox_topic].log(json.dumps(body, allow_nan=False).encode(),
                                         log_time=now)
            self.published[fox_topic] += 1

    def _run(self) -> None:
        next_map = 0.0
        others = set(VIEWED) - {"map"}
        while not self._stop.is_set():
            t0 = time.monotonic()
            topics = set(VIEWED) if t0 >= next_map else others
            batch = self.latest.take(topics, timeout=1.0 / self.rate_hz)
            if "map" in batch:
                next_map = t0 + 1.0 / self.map_hz
            for topic, payloads in batch.items():
                for payload in payloads:
                    try:
                        self._show(topic, payload)
                    except Exception as exc:     # a message the converter cannot take
                        self.errors += 1
                        log.warning("view: %s not shown: %s", topic, exc)
            self._stop.wait(max(0.0, 1.0 / self.rate_hz - (time.monotonic() - t0)))

    def stats(self) -> dict[str, Any]:
        return {"port": self.port, "received": dict(self.latest.received),
                "dropped": dict(self.latest.dropped), "unwatched": dict(self.unwatched),
                "published": dict(self.published), "undecodable": self.undecodable,
                "errors": self.errors}

    def close(self) -> dict[str, Any]:
        self._stop.set()
        self._thread.join(timeout=2.0)
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:             # the session may already be closed
                pass
        self.server.stop()
        return self.stats()


# ----------------------------------------------------------------------------- a client
SUBPROTOCOL = "foxglove.sdk.v1"      # what the Foxglove app and foxglove-sdk speak


async def _watch(port: int, until: float, want: set[str], host: str, check: bool
                 ) -> dict[str, list[Any]]:
    import websockets
    while True:
        try:
            ws = await websockets.connect(f"ws://{host}:{port}", subprotocols=[SUBPROTOCOL],
                                          max_size=None)
            break
        except OSError:
            if time.monotonic() > until:
                raise
            await asyncio.sleep(0.2)
    subs: dict[int, dict[str, Any]] = {}
    got: dict[str, list[Any]] = {}
    async with ws:
        while time.monotonic() < until and not (want and want <= set(got)):
            try:
                frame = await asyncio.wait_for(ws.recv(), 0.5)
            except TimeoutError:
                continue
            except websockets.ConnectionClosed:
                break
            if isinstance(frame, str):
                op = json.loads(frame)
                if op.get("op") == "advertise":
                    new = []
                    for ch in op["channels"]:
                        sid = len(subs) + 1
                        subs[sid] = ch
                        new.append({"id": sid, "channelId": ch["id"]})
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                continue
            if frame[0] != 1:                           # not MessageData
                continue
            sid, _log_time = struct.unpack("<IQ", frame[1:13])
            ch = subs[sid]
            if not check:
                got.setdefault(ch["topic"], []).append({"channel": ch, "bytes": len(frame)})
                continue
            body = json.loads(frame[13:])
            problems = violations(SCHEMAS[ch["schemaName"]], body) if (
                ch["schemaName"] in SCHEMAS and ch["schemaEncoding"] == "jsonschema") else []
            got.setdefault(ch["topic"], []).append(
                {"channel": ch, "body": body, "violations": problems})
    return got


def watch(port: int, timeout_s: float, want: set[str] = frozenset(), host: str = "127.0.0.1",
          check: bool = True) -> dict[str, list[dict[str, Any]]]:
    """A Foxglove WebSocket client: connect to `host:port` (retrying until it serves),
    subscribe to every channel it advertises, and collect what arrives, per topic, until
    each topic of `want` has a message or `timeout_s` passes (`want` empty: the whole
    time, or until the server closes). Each message: its channel's advertisement, its
    JSON body and where it breaks its schema (`violations`); without `check`, only its
    size in bytes (what a client that draws elsewhere costs this machine: receiving). The
    tests' client, and without `check` the benchmark's."""
    return asyncio.run(_watch(port, time.monotonic() + timeout_s, set(want), host, check))


def lower_priority() -> None:
    """The viewer yields the CPU to the services it watches."""
    try:
        os.nice(NICE)
    except OSError:
        pass
