"""Recording to MCAP, recovery after a crash, replay, feed-and-compare, timing, Foxglove."""

import base64
import dataclasses
import io
import json
import signal
import subprocess
import sys
import time

import msgpack
import numpy as np
import pytest
import zenoh
from mcap.reader import make_reader

from common.bus import open_session
from common.config import BusConfig, load_config
from common.messages import (
    MESSAGE_TYPES,
    Header,
    Map,
    State,
    decode,
    encode,
    json_schema,
)
from common.topics import topic_key
from deploy.recording.foxglove import export
from deploy.recording.record import (
    RecordingError,
    RecordingWriter,
    is_complete,
    iter_messages,
    read_metadata,
    recorded_config,
    recording_metadata,
    recover,
)
from deploy.recording.replay import compare_messages, feed, replay
from deploy.recording.timing import analyse, table
from deploy.sim.runner import run_episode

SHORT = ["planner.samples=64", "episode.timeout_s=2.0", 'episode.scenario="open-field"']


def state(seq, source="plant/0", stamp=None):
    return State(Header(seq, seq * 0.02 if stamp is None else stamp, time.time(), source),
                 x=np.arange(6.0) + seq, z=0.1, u_applied=np.zeros(2), tick=seq // 5,
                 authority="planner/0")


def a_map(seq, rng, n=400):
    return Map(Header(seq, seq * 0.1, time.time(), "mapper/0"),
               mean=rng.normal(size=(n, n)).astype("<f4"),
               variance=rng.uniform(0, 3, (n, n)).astype("<f4"),
               origin=np.zeros(2), resolution=0.2)


def wait_for_subscriber(*publishers, timeout_s=30.0):
    """Until the recorder's subscription has reached every publisher (Zenoh matching)."""
    deadline = time.monotonic() + timeout_s
    while not all(p.matching_status.matching for p in publishers):
        assert time.monotonic() < deadline, "no subscriber matched"
        time.sleep(0.05)


def client(endpoint):
    return BusConfig(mode="client", connect=(endpoint,), listen=(), multicast_scouting=False)


# ----------------------------------------------------------------------------- writer, reader
def test_every_message_is_written_exactly_and_gaps_and_garbage_are_counted(tmp_path, rng):
    path = tmp_path / "w.mcap"
    meta = recording_metadata({"episode": {"scenario": "x"}}, "vamppi/v/**")
    meta["services"] = {"planner/0": json.dumps({"episode": {"scenario": "y"}})}
    w = RecordingWriter(path, meta)
    key_s, key_m = topic_key("v", "state"), topic_key("v", "map")
    sent = []
    seqs = [s for s in range(40) if s not in (7, 8, 30)]        # three lost upstream
    for s in seqs:
        p = encode(state(s))
        sent.append((key_s, p))
        w.add(key_s, p, 1_000_000_000 + s)
    for s in range(3):
        p = encode(a_map(s, rng, 50))
        sent.append((key_m, p))
        w.add(key_m, p, 2_000_000_000 + s)
    w.add("vamppi/v/odd/key", b"\x00garbage", 3_000_000_000)
    stats = w.close()
    assert stats["messages"] == len(sent) + 1 and stats["undecodable"] == 1
    assert stats["missing"] == 3
    (pub,) = [p for p in stats["publishers"] if p["key"] == key_s]
    assert pub["gaps"] == [[7, 8], [30, 30]] and pub["late"] == pub["duplicates"] == 0

    with open(path, "rb") as f:                         # the mcap library, CRCs checked
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary.statistics.message_count == len(sent) + 1
        got = [(c.topic, m.data, m.sequence, m.log_time, s.name if s else None,
                c.message_encoding) for s, c, m in reader.iter_messages(log_time_order=False)]
    assert [(k, p) for k, p, *_ in got[:-1]] == sent
    assert all(enc == "msgpack" for *_, enc in got)
    assert [sq for k, _, sq, *_ in got if k == key_s] == seqs
    assert {sch for k, _, _, _, sch, _ in got if k == key_m} == {"vamppi.Map"}
    assert got[-1][0] == "vamppi/v/odd/key" and got[-1][1] == b"\x00garbage"
    assert got[-1][4] is None                           # recorded without a schema
    meta = read_metadata(path)
    assert meta["vamppi"]["scenario"] == "x" and "numpy" in meta["versions"]
    assert json.loads(meta["vamppi.recording"]["missing"]) == 3
    assert recorded_config(path) == {"episode": {"scenario": "x"}}
    assert recorded_config(path, "planner") == {"episode": {"scenario": "y"}}
    assert recorded_config(path, "mapper") == {"episode": {"scenario": "x"}}
    assert meta["vamppi"]["git_commit"]                 # the commit, or "unknown" outside git


@pytest.mark.parametrize("schema", sorted(MESSAGE_TYPES))
def test_json_schema_names_exactly_the_fields_the_codec_writes(schema):
    cls = MESSAGE_TYPES[schema]
    js = json_schema(cls)
    json.dumps(js)
    assert js["title"] == schema
    msg_fields = {f.name for f in dataclasses.fields(cls)} - {"header"}
    assert set(js["properties"]) == {"schema", "version", "header"} | msg_fields
    assert set(js["required"]) == set(js["properties"])


def test_a_truncated_recording_reads_and_recovers_up_to_its_last_complete_chunk(tmp_path, rng):
    """A crash at any byte: what was flushed before it is read and recovered, bit for bit."""
    buf = io.BytesIO()
    w = RecordingWriter(buf, {"vamppi": {"config": "{}"}}, flush_interval_s=1e9)
    key = topic_key("v", "state")
    flushed_at = []                                     # (file size, messages so far)
    payloads = []
    for s in range(60):
        payloads.append(encode(state(s)))
        w.add(key, payloads[-1], 10 + s)
        if s % 10 == 9:
            w.flush()
            flushed_at.append((buf.tell(), s + 1))
    data = buf.getvalue()
    for cut in sorted(rng.integers(flushed_at[0][0], len(data), 12)):
        path = tmp_path / f"cut{cut}.mcap"
        path.write_bytes(data[:cut])
        assert not is_complete(path)
        safe = max(n for size, n in flushed_at if size <= cut)
        got = [m.data for m in iter_messages(path)]
        assert got[:safe] == payloads[:safe] and got == payloads[:len(got)]
        report = recover(path, tmp_path / "rec.mcap")
        assert report["messages"] == len(got)
        with open(tmp_path / "rec.mcap", "rb") as f:
            reader = make_reader(f, validate_crcs=True)
            assert [m.data for _, _, m in reader.iter_messages()] == got
        assert is_complete(tmp_path / "rec.mcap")


def test_a_file_that_is_not_a_recording_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.mcap"
    for content in (b"", b"garbage\n", b"\x89MCAP0\r"):
        bad.write_bytes(content)
        with pytest.raises(RecordingError, match="not an MCAP recording"):
            list(iter_messages(bad))
        with pytest.raises(RecordingError):
            recover(bad, tmp_path / "out.mcap")
    r = subprocess.run([sys.executable, "-m", "deploy", "timing", str(bad)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "not an MCAP recording" in r.stderr
    assert "Traceback" not in r.stderr


def test_compare_reports_the_first_differing_field():
    a = state(3)
    assert compare_messages(a, state(3)) is None        # headers (wall time) are not compared
    x = a.x.copy()
    x[2] += 1e-9
    d = compare_messages(a, State(a.header, x=x, z=a.z, u_applied=a.u_applied, tick=a.tick,
                                  authority=a.authority))
    assert d["field"] == "x" and d["differing"] == 1 and 0 < d["max_abs_diff"] < 1e-8


# ----------------------------------------------------------------------------- on the bus
@pytest.mark.integration
def test_recorder_killed_mid_stream_loses_at_most_the_last_second(router, tmp_path, rng):
    """`vamppi record` as a process, 50 Hz states and 1.3 MB maps at 10 Hz, SIGKILL."""
    out = tmp_path / "killed.mcap"
    proc = subprocess.Popen([sys.executable, "-m", "deploy", "record", "-o", str(out),
                             "--connect", router, "--set", 'episode.vehicle="v"'],
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while "recording" not in proc.stderr.readline():
            assert time.monotonic() < deadline and proc.poll() is None
        maps = [encode(a_map(i, rng)) for i in range(2)]
        with open_session(client(router)) as s:
            # published as the nodes publish (common.bus.TypedPublisher): reliable, blocking;
            # the default (drop) loses states queued behind a 1.3 MB map on a loaded machine
            ps, pm = (s.declare_publisher(topic_key("v", k), reliability=zenoh.Reliability.RELIABLE,
                                          congestion_control=zenoh.CongestionControl.BLOCK)
                      for k in ("state", "map"))
            wait_for_subscriber(ps, pm)
            sent_at = []
            t0 = time.monotonic()
            for i in range(200):                        # 4 s
                ps.put(encode(state(i)))
                sent_at.append(time.monotonic())
                if i % 5 == 0:
                    pm.put(maps[(i // 5) % 2])
                time.sleep(max(0.0, t0 + (i + 1) * 0.02 - time.monotonic()))
            proc.send_signal(signal.SIGKILL)
            killed = time.monotonic()
            proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not is_complete(out)
    report = recover(out, tmp_path / "recovered.mcap")
    seqs = [decode(m.data).header.seq for m in iter_messages(tmp_path / "recovered.mcap")
            if m.key.endswith("/state")]
    must = sum(t <= killed - 1.0 for t in sent_at)
    assert seqs == list(range(len(seqs))), "a gap inside the recovered part"
    assert len(seqs) >= must, (len(seqs), must)
    assert report["per_key"][topic_key("v", "map")] >= must // 5


@pytest.mark.integration
def test_replay_publishes_every_message_with_the_recorded_spacing(router, tmp_path):
    path = tmp_path / "r.mcap"
    w = RecordingWriter(path, {"vamppi": {"config": "{}"}})
    key = topic_key("v", "state")
    for s in range(20):
        w.add(key, encode(state(s)), 1_000_000_000 + s * 20_000_000)    # 50 Hz
    w.add(topic_key("v", "events"), b"not msgpack", 1_500_000_000)
    w.close()
    got = []
    with open_session(client(router)) as s:
        s.declare_subscriber(key, lambda smp: got.append((time.monotonic(),
                                                          smp.payload.to_bytes())))
        time.sleep(0.3)
        t0 = time.monotonic()
        r = replay(s, path, rate=1.0, topics=["state"])
        took = time.monotonic() - t0
        time.sleep(0.3)
        assert r["published"] == 20
        assert 0.35 <= took < 1.5                       # 19 gaps of 20 ms
        r = replay(s, path, rate=0, start_offset_s=0.2)  # the first 10 skipped, garbage kept
        assert r["published"] == 11
        time.sleep(0.3)
    assert [decode(p).header.seq for _, p in got] == list(range(20)) + list(range(10, 20))


@pytest.mark.integration
def test_lockstep_episode_recorded_whole_replays_bit_for_bit_and_a_change_diverges(tmp_path):
    path = tmp_path / "episode.mcap"
    r = subprocess.run([sys.executable, "-m", "deploy", "up", "--record", str(path),
                        *sum((["--set", o] for o in SHORT), [])],
                       capture_output=True, text=True, timeout=600)
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert summary["recording"]["missing"] == 0
    with open(path, "rb") as f:                         # the reference reader, CRCs checked
        reader = make_reader(f, validate_crcs=True)
        msgs = [(c.topic, m) for _, c, m in reader.iter_messages()]
    per: dict = {}
    for key, m in msgs:
        h = msgpack.unpackb(m.data)["header"]
        per.setdefault((key, h["source"]), []).append(h["seq"])
    for (key, _), seqs in per.items():                  # every publisher: 0, 1, 2, ... no gap
        assert sorted(seqs) == list(range(len(seqs))), key
    ref = run_episode(load_config(overrides=SHORT))
    states = [m for k, m in msgs if k.endswith("/state")]
    assert len(states) == ref.trajectory.shape[0]       # every state the plant published

    same = feed(path, ["mapper", "planner"], [])
    assert same["bit_identical"], same
    assert same["compared"]["cmd"] == same["compared"]["map"] > 5
    changed = feed(path, ["planner"], ["planner.temperature=0.37"])
    first = changed["first_divergence"]
    assert first is not None and first["topic"] in ("cmd", "plan") and first["stamp"] == 0.0

    fox = tmp_path / "fox.mcap"
    rep = export(path, fox)
    assert rep["messages"]["/map/mean"] == same["compared"]["map"]
    with open(fox, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        for schema, channel, m in reader.iter_messages():
            assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
            body = json.loads(m.data)
            if schema.name == "foxglove.Grid":
                cells = len(base64.b64decode(body["data"])) // body["cell_stride"]
                assert cells == body["column_count"] ** 2 == 400 * 400


@pytest.mark.realtime
@pytest.mark.integration
def test_timing_of_a_realtime_recording_agrees_with_the_live_pipeline_bench(tmp_path):
    """The bench's live chain follower and `vamppi timing` on its recording: same run,
    same numbers; a realtime episode recorded at full rate has no seq gap."""
    path = tmp_path / "rt.mcap"
    r = subprocess.run([sys.executable, "-m", "deploy", "bench", "pipeline", "--json",
                        "--samples", "16", "--controllers", "deterministic", "--duration", "4",
                        "--scenario", "open-field", "--record", str(path)],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    (case,) = json.loads(r.stdout)["cases"]
    assert case["recording"]["missing"] == 0 and case["recording"]["undecodable"] == 0
    res = analyse(path)
    assert res["clock"] == "realtime"
    assert all(t["seq_missing"] == 0 for t in res["topics"])
    rates = {t["key"].split("/")[-1]: t["rate_hz"] for t in res["topics"]}
    assert rates["state"] > 40                          # the plant's 50 Hz, recorded whole
    for k in ("commands", "chains", "states", "stale_states"):
        assert res["chain"][k] == case[k], k
    assert res["chain"]["end_to_end"] == case["end_to_end"]
    text = table(res)
    assert "end_to_end" in text and "plant/state" in text
    assert res["solve_ms"]["count"] == case["commands"]


# ----------------------------------------------------------------------------- clocks
def test_a_clock_offset_is_true_within_half_the_round_trip(rng):
    """NTP's estimate against the float64 truth: another clock `d` ahead, one-way delays
    `a` out and `b` back; the estimate is off by exactly (a - b) / 2, never more than half
    the round trip."""
    from common.bus import ClockOffset
    for _ in range(200):
        t, d = rng.uniform(1e9, 2e9), rng.normal(0, 30)
        a, b = rng.exponential(0.01, 2)
        m = ClockOffset.from_round_trip(t, t + a + d, t + a + b)
        assert abs(m.offset_s - (d + (a - b) / 2)) < 1e-6          # 2e9 s in float64
        assert abs(m.offset_s - d) <= m.rtt_s / 2 + 1e-6
        assert m.best(ClockOffset(0.0, m.rtt_s * 2)) is m


def test_recorder_measures_clocks_and_timing_corrects_for_them(tmp_path):
    """A publisher whose clock runs 5 s ahead: once it beats, the recorder measures its
    offset over the bus (a clock queryable on a MemoryBus) and notes it; `vamppi timing`
    puts its wall times on the recorder's clock, so the transport latency is its true few
    milliseconds, not -5 s."""
    from common.bus import MemoryBus, MemoryTransport
    from common.messages import Heartbeat
    from common.topics import admin_key, alive_key, heartbeat_key
    from deploy.recording.record import Recorder, recorded_clocks
    bus, ahead = MemoryBus(), 5.0
    svc = MemoryTransport(bus)
    svc.token(alive_key("v0", "plant", "0"))
    svc.queryable(admin_key("v0", "plant", "0", "clock"), lambda k: [
        (k, json.dumps({"wall_time": time.time() + ahead}).encode())])
    path = tmp_path / "clocks.mcap"
    rec = Recorder(MemoryTransport(bus), "vamppi/v0/**", path,
                   recording_metadata(load_config(overrides=SHORT).to_dict(), "vamppi/v0/**"),
                   clock_sync_s=0.2)
    pub = MemoryTransport(bus).publisher(topic_key("v0", "state"))
    beat = MemoryTransport(bus).publisher(heartbeat_key("v0", "plant"))
    for i in range(50):
        beat.put(encode(Heartbeat(Header(i, 0.0, time.time() + ahead, "plant/0"),
                                  status="ready", role="", deadline_s=1.0, detail="")))
        s = state(i)
        s = dataclasses.replace(s, header=dataclasses.replace(
            s.header, wall_time=time.time() + ahead - 0.003))         # sent 3 ms before
        pub.put(encode(s))
        time.sleep(0.01)
    rec.stop()
    clocks = recorded_clocks(path)
    assert list(clocks) == ["plant/0"] and abs(clocks["plant/0"] - ahead) < 1e-3
    row = next(t for t in analyse(path)["topics"] if t["key"] == topic_key("v0", "state"))
    assert 2.0 < row["transport"]["p50_ms"] < 5.0, row["transport"]
    assert "plant/0 +4999.99" in table(analyse(path)) or "plant/0 +5000.00" in table(analyse(path))
