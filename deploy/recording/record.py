"""Bus recordings in MCAP: the writer, the recorder on the bus, reading and recovery.

A recording holds every sample of the recorded keys, as it arrived:

- one MCAP channel per key, message encoding `msgpack` (the payload exactly as it
  travelled), the channel's schema the JSON Schema of its message type
  (`common.messages.json_schema`; a payload no schema matches is still recorded,
  on a channel without schema, and counted);
- `log_time` = receive wall time, `publish_time` = the header's publish wall
  time, `sequence` = the header's seq (per publisher);
- zstd chunks, message and chunk indexes, statistics, CRCs (the `mcap` library's
  defaults);
- metadata `vamppi` (config as JSON, scenario, vehicle, clock, key expression,
  git commit), `versions` (Python packages) and, at a clean stop,
  `vamppi.recording` (counts, seq gaps per publisher, largest backlog);
- metadata `services`: the effective configuration of every service instance the
  recorder met on the bus (its `config` queryable), also of those that appeared after it
  started. A standalone `vamppi record` stores no configuration of its own (`config`
  "{}", `config_source` "services"): what the recording was made with is what the
  services said (`recorded_config`, `recording_label`), or unknown.

Crash safety: the open chunk is closed and handed to the OS at least every
`flush_interval_s` (0.5 s), so a SIGKILLed recorder loses at most that much plus
its backlog; `recover` (or `iter_messages`, which reads a file without summary
record by record) gives every message of the complete chunks.
"""

from __future__ import annotations

import collections
import json
import logging
import os
import platform
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import IO, Any

from mcap.reader import make_reader
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from common.messages import MESSAGE_TYPES, DecodeError, json_schema, peek
from common.protocol import SeqTrack
from common.topics import CACHED

log = logging.getLogger(__name__)
CLOCK_METADATA = "vamppi.clock"      # the publishers' clock offsets (Recorder)

PROFILE = "vamppi"
MESSAGE_ENCODING = "msgpack"
FLUSH_INTERVAL_S = 0.5
CHUNK_SIZE = 8 << 20
PACKAGES = ("vamppi", "eclipse-zenoh", "jax", "jaxlib", "numpy", "mcap", "msgpack",
            "opencv-python-headless", "zstandard")


# ----------------------------------------------------------------------------- provenance
def git_commit(path: Path | None = None) -> str:
    """HEAD of the checkout this code runs from ("+dirty" if it has changes), or "unknown"."""
    where = path or Path(__file__).resolve().parents[2]
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=where, capture_output=True,
                              text=True, timeout=5, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=where, capture_output=True, text=True, timeout=5).stdout
        return head + ("+dirty" if dirty.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def package_versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            out[name] = importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def recording_metadata(cfg_dict: dict[str, Any] | None, keys: str, vehicle: str = ""
                       ) -> dict[str, dict[str, str]]:
    """The metadata records written at the start of a recording: `cfg_dict` is the
    configuration every service was given (`vamppi up --record`), None for a standalone
    recorder, whose own configuration says nothing of the services'."""
    episode = (cfg_dict or {}).get("episode", {})
    return {"vamppi": {"config": json.dumps(cfg_dict or {}), "keys": keys,
                       "config_source": "launcher" if cfg_dict else "services",
                       "scenario": str(episode.get("scenario", "")),
                       "vehicle": str(episode.get("vehicle", vehicle)),
                       "clock": str(episode.get("clock", "")),
                       "git_commit": git_commit(), "host": platform.node(),
                       "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")},
            "versions": package_versions()}


SERVICES_METADATA = "services"       # "<service>/<instance>" -> its configuration (JSON)

# ----------------------------------------------------------------------------- writer
class RecordingWriter:
    """Writes bus samples into an MCAP file (no bus here: `Recorder` feeds it).

    Not thread-safe: one thread calls `add`, `tick` and `close`.
    """

    def __init__(self, output: str | Path | IO[bytes], meta: dict[str, dict[str, str]],
                 flush_interval_s: float = FLUSH_INTERVAL_S, chunk_size: int = CHUNK_SIZE):
        self._file = open(output, "wb") if isinstance(output, (str, Path)) else None  # noqa: SIM115
        stream = self._file if self._file is not None else output
        self._w = Writer(stream, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self._w.start(profile=PROFILE, library=f"vamppi {package_versions()['vamppi']}")
        for name, data in meta.items():
            self._w.add_metadata(name, data)
        self._w.flush()
        self.flush_interval_s = flush_interval_s
        self._last_flush = time.monotonic()
        self._dirty = False
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.publishers: dict[tuple[str, str, int], SeqTrack] = collections.defaultdict(
            SeqTrack)
        self.messages = 0
        self.undecodable = 0
        self.bytes = 0
        self.closed = False

    def _channel(self, key: str, schema: str | None) -> int:
        if key not in self._channels:
            schema_id = 0
            cls = MESSAGE_TYPES.get(schema or "")
            if cls is not None:
                if cls.SCHEMA not in self._schemas:
                    self._schemas[cls.SCHEMA] = self._w.register_schema(
                        cls.SCHEMA, "jsonschema", json.dumps(json_schema(cls)).encode())
                schema_id = self._schemas[cls.SCHEMA]
            self._channels[key] = self._w.register_channel(
                key, MESSAGE_ENCODING, schema_id,
                {"schema": schema or "", "version": str(cls.VERSION) if cls else ""})
        return self._channels[key]

    def add(self, key: str, payload: bytes, log_time_ns: int) -> None:
        """One sample as received on `key` at `log_time_ns` (wall clock, ns)."""
        try:
            schema, header = peek(payload)
            publish_ns, seq = int(header.wall_time * 1e9), header.seq
            self.publishers[(key, header.source, header.boot)].see(seq)
        except DecodeError as exc:
            schema, publish_ns, seq = None, log_time_ns, 0
            self.undecodable += 1
            log.warning("recording an undecodable payload on %s: %s", key, exc)
        self._w.add_message(self._channel(key, schema), log_time=log_time_ns, data=payload,
                            publish_time=publish_ns, sequence=seq & 0xFFFFFFFF)
        self.messages += 1
        self.bytes += len(payload)
        self._dirty = True
        self.tick()

    def tick(self) -> None:
        """Close the open chunk and hand it to the OS if it is older than the interval."""
        if self._dirty and time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()

    def flush(self) -> None:
        self._w.flush()
        self._last_flush = time.monotonic()
        self._dirty = False

    def summary(self) -> dict[str, Any]:
        pubs = [{"key": k, "source": s, "boot": b, **p.summary()}
                for (k, s, b), p in sorted(self.publishers.items())]
        return {"messages": self.messages, "bytes": self.bytes,
                "undecodable": self.undecodable,
                "missing": sum(p.missing for p in self.publishers.values()),
                "late": sum(p.late for p in self.publishers.values()),
                "duplicates": sum(p.duplicates for p in self.publishers.values()),
                "publishers": pubs}

    def note(self, name: str, values: dict[str, Any], texts: bool = False) -> None:
        """A metadata record now, among the messages (a crash keeps it); values as JSON
        (as they are if `texts`). Of several with one name, readers keep the last."""
        self._w.add_metadata(name, values if texts else {
            k: json.dumps(v) for k, v in values.items()})

    def close(self, extra: dict[str, Any] | None = None) -> dict[str, Any]:
        """Write the statistics metadata, the summary section and close the file."""
        if self.closed:
            return self.summary()
        out = {**self.summary(), **(extra or {})}
        self._w.add_metadata("vamppi.recording", {k: json.dumps(v) for k, v in out.items()})
        self._w.finish()
        if self._file is not None:
            self._file.close()
        self.closed = True
        return out


# ----------------------------------------------------------------------------- on the bus
class Recorder:
    """Subscribes to `keys` on a transport (common.bus) and records every sample to `path`.

    A plain subscription records every sample as it arrives. A second one, on the topics
    whose publisher keeps a cache (common.bus.CACHED: the plant's), recovers what the
    first missed (a cut link): such a sample is recorded only if the first never delivered
    it, late, and what never arrives shows as seq gaps per publisher in the summary. (A
    zenoh-ext advanced subscriber alone would not do: it drops samples of plain
    publishers that interleave on one key.) The callbacks only stamp and queue the sample
    (never block, never drop); a writer thread drains the queue into a `RecordingWriter`
    and flushes on the interval even when the bus is quiet.
    """

    RECOVERY_WAIT_S = 2.0          # a recovered sample the live stream may still bring
    CONFIG_RETRY_S = 1.0           # between asks of a service that has not told its config
    CLOCK_SYNC_S = 10.0            # between measurements of the publishers' clocks
    BEAT_FRESH_S = 0.3             # a publisher is asked its clock only if it beat since

    def __init__(self, bus: Any, keys: str, path: str | Path,
                 meta: dict[str, dict[str, str]], flush_interval_s: float = FLUSH_INTERVAL_S,
                 clock_sync_s: float | None = CLOCK_SYNC_S):
        """`clock_sync_s`: how often the live services' clock offsets are measured
        (`common.bus.measure_clocks`) and noted in the recording (metadata
        `vamppi.clock`, the tightest so far), for `vamppi timing` across hosts; None: never
        (and for keys that are not one vehicle's). Only a service whose heartbeat arrived
        within `BEAT_FRESH_S` is asked, and a new one as soon as it beats.

        The configuration of every service instance whose heartbeat arrives is asked of it
        once (its `config` queryable) and noted (metadata `services`), for keys that are
        one vehicle's."""
        self.keys, self.path = keys, Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._writer = RecordingWriter(self.path, meta, flush_interval_s)
        self._queue: collections.deque[tuple[str, bytes, int, bool]] = collections.deque()
        self._cv = threading.Condition()
        self._stop = False
        self.max_backlog = 0
        self.received = 0
        self.recovered = 0
        self._pending: list[tuple[str, bytes, int, float]] = []
        self.missed: collections.Counter[str] = collections.Counter()
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()
        self.clocks: dict[str, Any] = {}
        self._clocks_changed = False
        self._beats: dict[str, float] = {}        # source -> monotonic time of its beat
        self.configs: dict[str, str] = {}          # source -> its configuration (JSON)
        self._configs_changed = False
        parts = keys.split("/")
        one_vehicle = len(parts) == 3 and parts[2] == "**" and "*" not in parts[1]
        if clock_sync_s is not None and one_vehicle:
            threading.Thread(target=self._sync_clocks, args=(bus, parts[1], clock_sync_s),
                             name="recorder-clocks", daemon=True).start()
        if one_vehicle:
            threading.Thread(target=self._follow_configs, args=(bus, parts[1]),
                             name="recorder-configs", daemon=True).start()
        self._subs = [bus.subscriber(keys, lambda k, p: self._on_sample(k, p, False))]
        prefix = keys[:-3] if keys.endswith("/**") else None
        for topic, owner in CACHED.items():
            key = f"{prefix}/{owner}/{topic}" if prefix else None
            if key is not None and key.count("/") == 3:
                self._subs.append(bus.subscriber(
                    key, lambda k, p: self._on_sample(k, p, True), recover=True,
                    on_miss=lambda src, n: self.missed.update({src: n})))

    def _on_sample(self, key: str, payload: bytes, recovery: bool) -> None:
        item = (key, payload, time.time_ns(), recovery)
        if key.endswith("/heartbeat") and not recovery:
            try:
                self._beats[peek(payload)[1].source] = time.monotonic()
            except DecodeError:
                pass
        with self._cv:
            self._queue.append(item)
            self.received += not recovery
            self.max_backlog = max(self.max_backlog, len(self._queue))
            self._cv.notify()

    def _sync_clocks(self, bus: Any, vehicle: str, every_s: float) -> None:
        from common.bus import measure_clocks

        def beating(source: str) -> bool:
            return time.monotonic() - self._beats.get(source, -1e9) < self.BEAT_FRESH_S
        last = -1e9
        while not self._stop:
            since = time.monotonic() - last
            new = [s for s in list(self._beats) if s not in self.clocks and beating(s)]
            if since >= every_s or (new and since >= 1.0):    # a new one: within a second
                last = time.monotonic()
                try:
                    clocks = measure_clocks(bus, vehicle, known=self.clocks,
                                            reachable=beating)
                except Exception as exc:      # a closing session: the next round, or none
                    log.debug("clock sync: %s", exc)
                    clocks = self.clocks
                with self._cv:
                    if clocks != self.clocks:
                        self.clocks, self._clocks_changed = clocks, True
            time.sleep(0.1)

    def _follow_configs(self, bus: Any, vehicle: str) -> None:
        from common.topics import admin_key
        asked: dict[str, float] = {}
        while not self._stop:
            for source in [s for s in list(self._beats) if s not in self.configs]:
                if time.monotonic() - asked.get(source, -1e9) < self.CONFIG_RETRY_S:
                    continue
                asked[source] = time.monotonic()
                service, _, instance = source.partition("/")
                try:
                    replies = bus.query(admin_key(vehicle, service, instance, "config"),
                                        timeout=1.0)
                except Exception as exc:      # a closing session
                    log.debug("config of %s: %s", source, exc)
                    continue
                if replies:
                    with self._cv:
                        self.configs[source] = replies[0][1].decode()
                        self._configs_changed = True
                        self._cv.notify()
            time.sleep(0.1)

    def _recovered(self, key: str, payload: bytes, t: int, since: float, final: bool) -> bool:
        """Write a sample of the recovering subscription if the live one missed it; False
        while it may still come live."""
        try:
            _, h = peek(payload)
        except DecodeError:
            return True                              # the live subscription records it
        track = self._writer.publishers.get((key, h.source, h.boot))
        if track is not None and track.has(h.seq):
            return True
        if track is None or h.seq > track.last:
            if not final and time.monotonic() - since < self.RECOVERY_WAIT_S:
                return False
        self._writer.add(key, payload, t)
        self.recovered += 1
        return True

    def _run(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._queue or self._stop,
                                  timeout=self._writer.flush_interval_s / 5)
                batch = list(self._queue)
                self._queue.clear()
                stop = self._stop
                clocks = self.clocks if self._clocks_changed else None
                self._clocks_changed = False
                configs = dict(self.configs) if self._configs_changed else None
                self._configs_changed = False
            if configs is not None:
                self._writer.note(SERVICES_METADATA, configs, texts=True)
            if clocks is not None:
                self._writer.note(CLOCK_METADATA, {s: {"offset_s": round(c.offset_s, 6),
                                                       "rtt_s": round(c.rtt_s, 6)}
                                                   for s, c in clocks.items()})
            now = time.monotonic()
            for key, payload, t, recovery in batch:
                if recovery:
                    self._pending.append((key, payload, t, now))
                else:
                    self._writer.add(key, payload, t)
            self._pending = [p for p in self._pending
                             if not self._recovered(*p, final=stop and not batch)]
            self._writer.tick()
            if stop and not batch:
                return

    @property
    def messages(self) -> int:
        return self._writer.messages

    def stop(self, drain_s: float = 0.2) -> dict[str, Any]:
        """Wait `drain_s` for samples in flight, undeclare, drain the queue, write the
        summary and close; returns the statistics."""
        time.sleep(drain_s)
        for sub in self._subs:
            for s in sub if isinstance(sub, tuple) else (sub,):
                try:
                    s.undeclare()
                except Exception:     # the session may already be closed
                    pass
        with self._cv:
            self._stop = True
            self._cv.notify()
        self._thread.join()
        return self._writer.close({"max_backlog": self.max_backlog, "keys": self.keys,
                                   "recovered": self.recovered,
                                   "zenoh_missed": dict(self.missed)})


# ----------------------------------------------------------------------------- reading


def recorded_clocks(path: str | Path) -> dict[str, float]:
    """The publishers' clock offsets a recorder noted ("service/instance" -> seconds its
    clock was ahead of the recorder's), those larger than their measurement's uncertainty
    (half its round trip; a smaller one is indistinguishable from none, the same host's
    clock); {} if it noted none."""
    out = {}
    for source, v in read_metadata(path).get(CLOCK_METADATA, {}).items():
        m = json.loads(v)
        if abs(float(m["offset_s"])) > float(m["rtt_s"]) / 2:
            out[source] = float(m["offset_s"])
    return out


class RecordingError(ValueError):
    """A file that is not a readable MCAP recording at all."""


@dataclass(frozen=True)
class Recorded:
    key: str
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    data: bytes


def _stream_records(f: IO[bytes]) -> Iterator[Any]:
    """Every complete record, CRC-checked; stops quietly at a truncated tail."""
    reader = StreamReader(f, skip_magic=False, emit_chunks=False, validate_crcs=True)
    it = reader.records
    first = True
    while True:
        try:
            rec = next(it)
        except StopIteration:
            return
        except Exception as exc:       # truncated record or chunk: the file ends here
            if first:
                name = getattr(f, "name", "the file")
                raise RecordingError(f"{name}: not an MCAP recording ({type(exc).__name__}: "
                                     f"{exc})") from None
            log.warning("recording ends in an incomplete record (%s: %s); read up to there",
                        type(exc).__name__, exc)
            return
        first = False
        yield rec


def is_complete(path: str | Path) -> bool:
    """Whether the file has its summary (a clean stop); False for a crashed recording."""
    with open(path, "rb") as f:
        try:
            summary = make_reader(f).get_summary()
        except Exception:
            return False
        return summary is not None


def iter_messages(path: str | Path, keys: set[str] | None = None,
                  log_time_order: bool = True) -> Iterator[Recorded]:
    """The messages of a recording (of `keys` only, if given). A complete file is read
    through its index in log-time order, CRCs checked; a crashed one record by record
    up to its last complete chunk."""
    with open(path, "rb") as f:
        if is_complete(path):
            reader = make_reader(f, validate_crcs=True)
            for _, channel, msg in reader.iter_messages(topics=sorted(keys) if keys else None,
                                                        log_time_order=log_time_order):
                yield Recorded(channel.topic, msg.log_time, msg.publish_time, msg.sequence,
                               msg.data)
            return
        channels: dict[int, str] = {}
        for rec in _stream_records(f):
            if isinstance(rec, Channel):
                channels[rec.id] = rec.topic
            elif isinstance(rec, Message):
                key = channels.get(rec.channel_id, "")
                if keys is None or key in keys:
                    yield Recorded(key, rec.log_time, rec.publish_time, rec.sequence, rec.data)


def recording_keys(path: str | Path) -> list[str]:
    """The keys (channel topics) of a recording."""
    with open(path, "rb") as f:
        if is_complete(path):
            summary = make_reader(f).get_summary()
            return sorted({c.topic for c in summary.channels.values()})
        return sorted({r.topic for r in _stream_records(f) if isinstance(r, Channel)})


def read_metadata(path: str | Path) -> dict[str, dict[str, str]]:
    """Every metadata record by name (a crashed file: those before its truncated tail)."""
    with open(path, "rb") as f:
        if is_complete(path):
            return {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
        return {r.name: dict(r.metadata) for r in _stream_records(f) if isinstance(r, Metadata)}


def recorded_config(path: str | Path, service: str = "") -> dict[str, Any]:
    """The configuration a recording was made with: that of a live `service`
    instance if the recorder found one on the bus (metadata `services`), else the
    launcher's (`vamppi up --record`: the one every service was given), else that of
    any service the recorder met; {} when unknown (a standalone recorder that met none)."""
    meta = read_metadata(path)
    live = meta.get(SERVICES_METADATA, {})
    texts = [v for k, v in sorted(live.items()) if k.split("/")[0] == service] + [
        meta.get("vamppi", {}).get("config", "{}")] + [v for _, v in sorted(live.items())]
    for text in texts:
        try:
            cfg = json.loads(text)
        except json.JSONDecodeError:
            continue
        if cfg:
            return cfg
    return {}


def recording_label(path: str | Path) -> dict[str, str]:
    """What a recording shows, from the configuration it was made with (the plant's for
    the episode, the planner's for the controller): scenario, clock, controller, samples;
    "unknown" for what no recorded configuration says."""
    plant, planner = recorded_config(path, "plant"), recorded_config(path, "planner")
    ep, pl = plant.get("episode", {}), planner.get("planner", {})
    known = {"scenario": ep.get("scenario"), "clock": ep.get("clock"),
             "controller": pl.get("controller"), "samples": pl.get("samples")}
    return {k: "unknown" if v is None else str(v) for k, v in known.items()}


def recover(path: str | Path, out: str | Path) -> dict[str, Any]:
    """Rewrite a (crashed) recording into a complete file: every schema, channel,
    metadata and message of its complete chunks, then a fresh summary."""
    path, out = Path(path), Path(out)
    if path.resolve() == out.resolve():
        raise ValueError("recover writes a new file; give an output path")
    ids: dict[int, int] = {}
    topics: dict[int, str] = {}
    counts: collections.Counter[str] = collections.Counter()
    first = last = None
    part = out.with_name(out.name + ".part")
    try:
        with open(path, "rb") as f, open(part, "wb") as g:
            w = Writer(g, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD)
            w.start(profile=PROFILE, library=f"vamppi {package_versions()['vamppi']} (recovered)")
            new_schema: dict[int, int] = {}
            for rec in _stream_records(f):
                if isinstance(rec, Schema):
                    new_schema[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
                elif isinstance(rec, Channel):
                    ids[rec.id] = w.register_channel(rec.topic, rec.message_encoding,
                                                     new_schema.get(rec.schema_id, 0),
                                                     dict(rec.metadata))
                    topics[rec.id] = rec.topic
                elif isinstance(rec, Metadata):
                    w.add_metadata(rec.name, dict(rec.metadata))
                elif isinstance(rec, Message) and rec.channel_id in ids:
                    w.add_message(ids[rec.channel_id], rec.log_time, rec.data, rec.publish_time,
                                  rec.sequence)
                    counts[topics[rec.channel_id]] += 1
                    first = rec.log_time if first is None else min(first, rec.log_time)
                    last = rec.log_time if last is None else max(last, rec.log_time)
            w.finish()
    except BaseException:
        part.unlink(missing_ok=True)
        raise
    part.replace(out)
    return {"input": str(path), "output": str(out), "input_bytes": os.path.getsize(path),
            "messages": sum(counts.values()), "per_key": dict(counts),
            "first_log_time_ns": first, "last_log_time_ns": last}
