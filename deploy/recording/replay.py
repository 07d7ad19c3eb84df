"""Replaying recordings: onto the bus with the recorded timing, or into fresh services.

`replay` republishes each recorded message on its key, at the recorded spacing of
receive times divided by `rate` (0: as fast as possible), in the manner of `ros2 bag
play` (topic filter, loop, start offset). Each message is stamped anew: its header's
publish wall time becomes the time it is republished (everything else, seq and source
included, is as recorded; an undecodable payload goes out unchanged), and the replay
beats on `vamppi/<vehicle>/replay/heartbeat` as `replay/<pid>` (detail: the file), so
that a recording of a replay says what it is and `vamppi timing` measures the replay's
own transport.

`feed` starts fresh instances of some services (say mapper and planner) in
lockstep with the recording's own configuration, publishes to them the
recorded messages they read that none of them produces (plant state, depth),
and compares what they publish with what was recorded, field by field and bit
for bit: the regression check after a change to a service. It walks the
recording in receive order, publishing inputs as it meets them; at each
recorded output of a fed service it waits for the live output of the same
topic and stamp, so inboxes never overflow and the result does not depend on
machine load.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import tempfile
import threading
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from common.config import Config, config_toml, load_config
from common.messages import DecodeError, Heartbeat, Message, decode, encode
from common.protocol import Out, Stamper
from common.topics import INPUTS, PREFIX, REPLAY_SOURCE, TOPICS, heartbeat_key, topic_of
from deploy.recording.record import Recorded, iter_messages, recorded_config, recording_keys

log = logging.getLogger(__name__)

FEEDABLE = ("sensor", "mapper", "planner")
# outputs compared bit for bit; planner stats carry a wall-clock solve time
COMPARED = ("depth", "map", "cmd", "plan")


def key_matcher(topics: Iterable[str] | None):
    """A predicate on keys: a topic name (`depth`) or a whole key; all if None."""
    wanted = {t.strip() for t in topics or () if t.strip()}
    if not wanted:
        return lambda key: True
    return lambda key: key in wanted or topic_of(key) in wanted


# ----------------------------------------------------------------------------- plain replay

def restamped(payload: bytes, wall_time: float) -> bytes:
    """`payload` with its header's publish wall time set to `wall_time`; an undecodable
    one unchanged."""
    try:
        msg = decode(payload)
    except DecodeError:
        return payload
    return encode(dataclasses.replace(msg, header=dataclasses.replace(msg.header,
                                                                      wall_time=wall_time)))


def replay_vehicle(path: str | Path) -> str:
    """The vehicle whose keys a recording holds (the first key's), '' if none."""
    for key in recording_keys(path):
        parts = key.split("/")
        if len(parts) >= 3 and parts[0] == PREFIX:
            return parts[1]
    return ""


def replay(session: zenoh.Session, path: str | Path, rate: float = 1.0,
           topics: Iterable[str] | None = None, loop: bool = False,
           start_offset_s: float = 0.0, stop: threading.Event | None = None,
           wait_matching_s: float = 1.0) -> dict[str, Any]:
    """Publish the recording onto `session`; returns counts. `rate` scales time (2: twice
    as fast; 0: no waiting); `start_offset_s` skips the first seconds. Every key's
    publisher is declared first; up to `wait_matching_s` is given for subscribers
    already on the bus to be matched, so that the first messages reach them."""
    if rate < 0:
        raise ValueError("rate must be >= 0")
    stop = stop or threading.Event()
    wanted = key_matcher(topics)
    pubs = {key: session.declare_publisher(key, reliability=zenoh.Reliability.RELIABLE,
                                           congestion_control=zenoh.CongestionControl.BLOCK)
            for key in recording_keys(path) if wanted(key)}
    vehicle = replay_vehicle(path)
    beat = Stamper(f"{REPLAY_SOURCE}/{os.getpid()}")
    beat_key = heartbeat_key(vehicle, REPLAY_SOURCE) if vehicle else ""
    beat_pub = session.declare_publisher(beat_key) if beat_key else None
    last_beat = -1e9
    deadline = time.monotonic() + wait_matching_s
    while (time.monotonic() < deadline and not stop.is_set()
           and not all(p.matching_status.matching for p in pubs.values())):
        time.sleep(0.02)
    published, loops = 0, 0
    late_s = 0.0
    while not stop.is_set():
        t_first, wall0 = None, None
        for m in iter_messages(path):
            if stop.is_set():
                break
            if t_first is None:
                t_first = m.log_time_ns + int(start_offset_s * 1e9)
            if m.log_time_ns < t_first or not wanted(m.key):
                continue
            due = (m.log_time_ns - t_first) / 1e9 / rate if rate > 0 else 0.0
            if wall0 is None:
                wall0 = time.monotonic()
            wait = wall0 + due - time.monotonic()
            if wait > 0:
                stop.wait(wait)
            else:
                late_s = max(late_s, -wait)
            if beat_pub is not None and time.monotonic() - last_beat > 0.5:
                last_beat = time.monotonic()
                beat_pub.put(encode(beat.make(Heartbeat, Out(
                    topic="heartbeat", stamp=0.0,
                    fields={"status": "ready", "role": "replay", "deadline_s": 1.0,
                            "detail": f"replay of {Path(path).name}"}))))
            pubs[m.key].put(restamped(m.data, time.time()))
            published += 1
        loops += 1
        if not loop or published == 0:
            break
    for p in [*pubs.values(), *([beat_pub] if beat_pub is not None else [])]:
        p.undeclare()
    return {"published": published, "loops": loops, "keys": sorted(pubs),
            "max_late_ms": round(late_s * 1e3, 3)}


# ----------------------------------------------------------------------------- feed + compare
def compare_messages(recorded: Message, live: Message) -> dict[str, Any] | None:
    """None when every field but the header is bit-identical; else the first field
    that differs, with the largest difference and how many elements differ."""
    for f in dataclasses.fields(recorded):
        if f.name == "header":
            continue
        a, b = getattr(recorded, f.name), getattr(live, f.name)
        if isinstance(a, np.ndarray):
            if a.shape != b.shape:
                return {"field": f.name, "why": f"shape {a.shape} vs {b.shape}"}
            if a.tobytes() != b.tobytes():
                diff = np.abs(a.astype(np.float64) - b.astype(np.float64))
                return {"field": f.name, "max_abs_diff": float(np.nanmax(diff)),
                        "differing": int(np.sum(a != b)), "of": int(a.size)}
        elif isinstance(a, float):
            if not (a == b or (np.isnan(a) and np.isnan(b))):
                return {"field": f.name, "recorded": a, "live": b,
                        "max_abs_diff": abs(a - b)}
        elif a != b:
            return {"field": f.name, "recorded": a, "live": b}
    return None


class LiveOutputs:
    """Outputs of the fed services as they arrive, by (topic, stamp)."""

    def __init__(self) -> None:
        self._got: dict[tuple[str, float], bytes] = {}
        self._cv = threading.Condition()
        self.received = 0

    def on_sample(self, sample: Any) -> None:
        topic = topic_of(str(sample.key_expr))
        payload = sample.payload.to_bytes()
        try:
            msg = decode(payload)
        except DecodeError as exc:
            log.warning("feed: undecodable live output on %s: %s", sample.key_expr, exc)
            return
        with self._cv:
            self._got[(topic, round(msg.header.stamp, 6))] = payload
            self.received += 1
            self._cv.notify_all()

    def wait(self, topic: str, stamp: float, timeout_s: float) -> bytes | None:
        k = (topic, round(stamp, 6))
        with self._cv:
            self._cv.wait_for(lambda: k in self._got, timeout_s)
            return self._got.pop(k, None)


def feed_config(path: str | Path, overrides: list[str], service: str = ""
                ) -> tuple[Config, list[str]]:
    """The recording's configuration (that of its `service` if recorded), in lockstep,
    with `overrides` on top; its `[bus]` (where and as whom the recorded process
    connected) is not taken: the fed services get their own."""
    recorded = recorded_config(path, service)
    if not recorded:
        raise ValueError(f"{path}: no configuration in the recording's metadata")
    base = load_config(overrides={f"{section}.{key}": value
                                  for section, values in recorded.items()
                                  for key, value in values.items()
                                  if section != "bus"})    # that process's links, not ours
    run = [*overrides, 'episode.clock="lockstep"']
    with tempfile.NamedTemporaryFile("w", suffix=".toml", delete=False) as f:
        f.write(config_toml(base))
    return load_config(f.name, run), [f.name, *run]


def feed(path: str | Path, services: list[str], overrides: list[str], keep_going: bool = False,
         output_timeout_s: float = 120.0, progress: Any = None) -> dict[str, Any]:
    """Feed the recording into fresh `services` and compare their outputs (see the
    module docstring). Returns the report; `first_divergence` is None when every
    compared output was bit-identical."""
    from deploy.launch.up import services_up
    bad = sorted(set(services) - set(FEEDABLE))
    if bad or not services:
        raise ValueError(f"can feed {', '.join(FEEDABLE)}; got {', '.join(services) or '-'}")
    cfg, run = feed_config(path, overrides, services[-1])
    config_file, run = run[0], run[1:]
    produced = {t for t, (owner, _) in TOPICS.items() if owner in services}
    inputs = {t for s in services for t in INPUTS[s]} - produced
    outputs = produced & set(COMPARED)
    vehicle = cfg.episode.vehicle
    live = LiveOutputs()
    subs = {f"{PREFIX}/{vehicle}/{TOPICS[t][0]}/{t}": live.on_sample for t in outputs}
    report: dict[str, Any] = {"recording": str(path), "services": services,
                              "inputs": sorted(inputs), "compared_topics": sorted(outputs),
                              "overrides": overrides, "published": 0,
                              "compared": {t: 0 for t in sorted(outputs)}, "identical": 0,
                              "diverged": 0, "missing": [], "first_divergence": None}
    try:
        with services_up(cfg, run, config_file, services=tuple(services),
                         subscriptions=subs, args={"planner": ["--role", "replay"]}
                         ) as (session, _, _):
            pubs = {}
            authority: tuple[str, int] = ("", 0)
            for m in iter_messages(path):
                topic = topic_of(m.key)
                if topic == "state":
                    authority = _authority(m.data, authority)
                if topic in ("cmd", "plan") and not _from(m.data, authority):
                    continue                   # another planner's (a rogue, one replaced)
                if topic in inputs:
                    if m.key not in pubs:
                        pubs[m.key] = session.declare_publisher(
                            m.key, reliability=zenoh.Reliability.RELIABLE,
                            congestion_control=zenoh.CongestionControl.BLOCK)
                    pubs[m.key].put(m.data)
                    report["published"] += 1
                elif topic in outputs:
                    if _check(m, topic, live, report, output_timeout_s) and not keep_going:
                        break
                    if progress is not None:
                        progress(report)
    finally:
        Path(config_file).unlink(missing_ok=True)
    report.pop("_seen", None)
    report["bit_identical"] = (report["first_divergence"] is None and not report["missing"]
                               and sum(report["compared"].values()) > 0)
    return report


def _authority(payload: bytes, current: tuple[str, int]) -> tuple[str, int]:
    """The planner a recorded state names as the plant's authority (source, process)."""
    try:
        s = decode(payload)
    except DecodeError:
        return current
    return (s.authority, s.authority_boot) if s.authority else current


def _from(payload: bytes, authority: tuple[str, int]) -> bool:
    """Whether a recorded planner output is the authority's (any, before a state names
    one): only those are compared, so that the check holds across a swap."""
    try:
        h = decode(payload).header
    except DecodeError:
        return True
    src, boot = authority
    return not src or (h.source == src and boot in (0, h.boot))


def _check(m: Recorded, topic: str, live: LiveOutputs, report: dict[str, Any],
           timeout_s: float) -> bool:
    """Compare one recorded output with its live counterpart; True on divergence."""
    try:
        rec = decode(m.data)
    except DecodeError as exc:
        log.warning("feed: recorded %s undecodable (%s); skipped", m.key, exc)
        return False
    seen = report.setdefault("_seen", set())
    if (topic, round(rec.header.stamp, 6)) in seen:     # a replaced planner's command at a
        return False                                    # swap's tick, or a re-offer's answer
    seen.add((topic, round(rec.header.stamp, 6)))
    got = live.wait(topic, rec.header.stamp, timeout_s)
    report["compared"][topic] += 1
    if got is None:
        report["missing"].append({"topic": topic, "stamp": rec.header.stamp})
        diff: dict[str, Any] | None = {"why": f"no live {topic} within {timeout_s:.0f} s"}
    else:
        diff = compare_messages(rec, decode(got))
    if diff is None:
        report["identical"] += 1
        return False
    report["diverged"] += 1
    if report["first_divergence"] is None:
        report["first_divergence"] = {"topic": topic, "stamp": rec.header.stamp,
                                      "recorded_seq": rec.header.seq, **diff}
    return True
