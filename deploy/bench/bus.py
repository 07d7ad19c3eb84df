"""`vamppi bench bus`, `pipeline`, `security` and `record`: messages through a real Zenoh
router, the services as processes, and the recorder.

bus       a map-sized message (two 400 x 400 float32 layers) from one client
          session to another through a real Zenoh router on loopback: one-way
          latency (one message in flight) and throughput (back to back), with
          our codec (encode + put ... decode), a raw put of the same bytes, and the
          floor under any checked array codec (one copy out, one checked read in).
pipeline  the four services as processes around an embedded router in realtime
          mode (what `vamppi up --clock realtime` runs): the achieved command
          rate and the end-to-end latency from a depth frame's publication to
          the first plant step that applies a command computed from it,
          followed through the input references in the headers.
security  the pipeline over plain TCP, over mutual TLS with access control, and
          under a denied flood, side by side.
record    synthetic traffic through the recorder at real time and as fast as possible.
"""

from __future__ import annotations

import json
import time
from importlib.metadata import version
from typing import Any

import numpy as np

from common.config import Config
from deploy.bench.device import device_info, heading, markdown_table
from deploy.recording.timing import ChainLog, stats_ms


def bench_bus(cfg: Config, reps: int, burst: int = 200) -> dict[str, Any]:
    """Map-sized messages through a router on a free loopback port (client sessions), three
    ways side by side: our codec; a raw put of bytes made once; and the floor under any codec
    that carries numpy arrays over zenoh-python and checks them on arrival (the arrays joined
    into a new `bytes`, the one copy `put` needs as it takes no buffer views, then their values
    checked as `decode` checks them, nothing else)."""
    import dataclasses
    import threading

    import zenoh

    from common.bus import open_session
    from common.config import BusConfig
    from common.messages import ALIGN, Header, Map, check_values, decode, encode
    from deploy.launch.up import free_port
    n = cfg.mapper.size_cells
    rng = np.random.default_rng(0)
    mean = rng.normal(size=(n, n)).astype(np.float32)
    var = rng.uniform(0, 3, (n, n)).astype(np.float32)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    specs = {f.name: f.metadata["kind"] for f in dataclasses.fields(Map) if f.name != "header"}

    def make(i: int) -> Map:
        return Map(Header(i, 0.0, time.time(), "bench/0"), mean, var, np.zeros(2), 0.2)

    def floor_payload(i: int) -> bytes:
        return b"".join((i.to_bytes(ALIGN, "little"), mean.data, var.data))

    def floor_check(payload: bytes) -> None:
        layers = np.frombuffer(payload, np.float32, offset=ALIGN).reshape(2, n, n)
        check_values(Map.SCHEMA, "mean", specs["mean"], layers[0])
        check_values(Map.SCHEMA, "variance", specs["variance"], layers[1])

    size = len(encode(make(0)))
    # the codec alone, in this thread, before any session exists: what each end costs
    # without the bus (its figure in the bus's latency also holds cache misses)
    codec_t: dict[str, list[float]] = {"encode": [], "decode": []}
    for i in range(max(reps, 100) + 5):
        t0 = time.perf_counter()
        payload = encode(make(i))
        t1 = time.perf_counter()
        decode(payload, Map)
        t2 = time.perf_counter()
        if i >= 5:
            codec_t["encode"].append(t1 - t0)
            codec_t["decode"].append(t2 - t1)
    raw = encode(make(0))
    # payload name: (what the sender puts for message i, what the receiver does with the bytes)
    cases: dict[str, tuple[Any, Any]] = {
        "codec": (lambda i: encode(make(i)), lambda b: decode(b, Map)),
        "raw": (lambda i: raw, lambda b: None),
        "floor": (floor_payload, floor_check)}
    router = open_session(BusConfig("router", (), (endpoint,), False))
    pub_s = open_session(BusConfig("client", (endpoint,), (), False))
    sub_s = open_session(BusConfig("client", (endpoint,), (), False))
    got: list[float] = []
    arrived = threading.Condition()

    def on_sample(sample, receive) -> None:
        receive(sample.payload.to_bytes())
        with arrived:
            got.append(time.perf_counter())
            arrived.notify_all()

    results = []
    try:
        pubs = {}
        for name, (_, receive) in cases.items():
            key = f"bench/bus/{name}"
            sub_s.declare_subscriber(key, lambda s, r=receive: on_sample(s, r))
            pubs[name] = pub_s.declare_publisher(
                key, reliability=zenoh.Reliability.RELIABLE,
                congestion_control=zenoh.CongestionControl.BLOCK)
        time.sleep(0.5)                              # routes established
        lat: dict[str, list[float]] = {name: [] for name in cases}
        for i in range(reps + 5):                    # interleaved: the ratios hold
            for name, (send, _) in cases.items():
                got.clear()
                t0 = time.perf_counter()
                pubs[name].put(send(i))
                with arrived:
                    if not arrived.wait_for(lambda: got, timeout=5.0):
                        raise RuntimeError(f"bus bench: message {i} not delivered in 5 s")
                if i >= 5:                           # warm-up excluded
                    lat[name].append(got[0] - t0)
        rates: dict[str, list[float]] = {name: [] for name in cases}
        for _ in range(3):                           # bursts, alternating
            for name, (send, _) in cases.items():
                got.clear()
                t0 = time.perf_counter()
                for i in range(burst):
                    pubs[name].put(send(i))
                with arrived:
                    if not arrived.wait_for(lambda: len(got) >= burst, timeout=60.0):
                        raise RuntimeError(f"bus bench: {len(got)} of {burst} delivered")
                rates[name].append(burst / (got[-1] - t0))
        raw_p50 = float(np.median(lat["raw"]))
        for name, (send, _) in cases.items():
            rate = float(np.median(rates[name]))
            nbytes = len(send(0))
            over = float(np.median(lat[name])) / raw_p50 - 1
            results.append({"payload": name, "bytes": nbytes, **stats_ms(lat[name]),
                            "over_raw_p50": round(over, 3), "msgs_per_s": round(rate, 1),
                            "mb_per_s": round(rate * nbytes / 1e6, 1)})
    finally:
        for s in (pub_s, sub_s, router):
            s.close()
    return {"benchmark": "bus", **device_info(), "zenoh": version("eclipse-zenoh"),
            "settings": {"endpoint": "tcp loopback, via a router", "reps": reps,
                         "burst": burst, "interleaved": True, "map_bytes": size},
            "codec_alone": {k: stats_ms(v) for k, v in codec_t.items()}, "cases": results}


def bench_pipeline(cfg: Config, overrides: list[str], samples: list[int],
                   controllers: list[str], duration_s: float,
                   config_path: str | None = None, record: str | None = None,
                   secure: bool = True, flood: bool = False) -> dict[str, Any]:
    """Per controller and K: the whole pipeline in realtime mode for `duration_s` of
    wall time after the episode starts (or until it ends), on this machine.
    `record`: an MCAP file per case (`-<controller>-<K>` added when several), for
    `vamppi timing` to analyse the very same messages. `secure`: mutual TLS and access
    control (`services_up`'s default), else plain TCP; `flood`: a client with a viewer's
    certificate puts copies of the commands on `cmd` as fast as it can (deploy.bench.faults)."""
    from pathlib import Path

    from common.bus import Health, Inbox
    from common.messages import Event
    from common.topics import topic_key
    from deploy.launch.up import recording_hook, services_up
    from services.plant.protocol import OUTCOMES
    cases = []
    for controller in controllers:
        for k in samples:
            run = [*overrides, "episode.clock=realtime", f"planner.controller={controller}",
                   f"planner.samples={k}"]
            chain = ChainLog(cfg.episode.vehicle)
            events = Inbox(Event, topic_key(cfg.episode.vehicle, "events"), Health(), 1024)
            subs = {**chain.callbacks(),
                    events.key: lambda s, ev=events: ev.on_payload(s.payload.to_bytes())}
            outcome, t_start = "", None
            recorded: dict[str, Any] = {}
            hook = None
            if record:
                path = Path(record)
                if len(controllers) * len(samples) > 1:
                    path = path.with_name(f"{path.stem}-{controller}-{k}{path.suffix}")
                case_cfg = cfg.replace(**{"episode.clock": "realtime",
                                          "planner.controller": controller,
                                          "planner.samples": k})
                hook = recording_hook(case_cfg, str(path), recorded)
            t0 = time.monotonic()
            with services_up(cfg, run, config_path, subscriptions=subs, on_session=hook,
                             secure=secure) as (_, endpoint, _sup):
                ready_s = time.monotonic() - t0
                flooder = None
                if flood:
                    from common.config import BusConfig
                    from common.security import default_certs
                    from deploy.bench.faults import Flood
                    flooder = Flood(BusConfig("client", (endpoint,), (), False,
                                              cfg.bus.certs or str(default_certs()),
                                              "viewer"), cfg.episode.vehicle)
                while True:
                    if t_start is not None and time.monotonic() - t_start > duration_s:
                        break
                    ev = events.get(timeout=1.0)
                    if ev is None:
                        if time.monotonic() - t0 > duration_s + 600:
                            raise RuntimeError("pipeline bench: the episode never started")
                        continue
                    if ev.kind == "start":
                        t_start = time.monotonic()
                    if ev.kind in OUTCOMES:
                        outcome = ev.kind
                        break
                wall = time.monotonic() - (t_start or t0)
                flood_sent = None if flooder is None else flooder.close()
            cases.append({"controller": controller, "samples": k, "scenario":
                          cfg.episode.scenario, "secure": secure, "flood_sent": flood_sent,
                          "wall_s": round(wall, 1),
                          "ready_s": round(ready_s, 1), "outcome": outcome or "running",
                          **chain.summary(), **recorded})
    return {"benchmark": "pipeline", **device_info(),
            "settings": {"clock": "realtime", "duration_s": duration_s,
                         "control_rate_hz": round(1.0 / cfg.planner.dt_s, 2),
                         "overrides": overrides}, "cases": cases}


def bench_security(cfg: Config, overrides: list[str], duration_s: float, reps: int,
                   config_path: str | None = None) -> dict[str, Any]:
    """The cost of security, side by side in one run: the realtime pipeline (the config's
    controller and K) over plain TCP, over mutual TLS with the generated access control,
    and the latter while a viewer's certificate floods `cmd` (denied at the router); the
    three alternate `reps` times. From each run's recording (`vamppi timing`): the map
    message's transport latency, the command rate, the end-to-end chain, stale states."""
    import tempfile
    from pathlib import Path

    from deploy.recording.timing import analyse
    kinds = (("tcp", False, False), ("tls+acl", True, False), ("tls+acl, flood", True, True))
    runs: dict[str, list[dict[str, Any]]] = {name: [] for name, _, _ in kinds}
    with tempfile.TemporaryDirectory(prefix="vamppi-security-") as tmp:
        for rep in range(reps):
            for name, secure, flood in kinds:
                path = Path(tmp) / f"{rep}-{len(runs[name])}-{secure}-{flood}.mcap"
                case = bench_pipeline(cfg, overrides, [cfg.planner.samples],
                                      [cfg.planner.controller], duration_s, config_path,
                                      str(path), secure, flood)["cases"][0]
                timing = analyse(path)
                mp = next(t for t in timing["topics"] if t["key"].endswith("/mapper/map"))
                runs[name].append({"map_transport": mp["transport"],
                                   "command_rate_hz": case.get("command_rate_hz"),
                                   "end_to_end": case.get("end_to_end"),
                                   "stale_states": case["stale_states"],
                                   "states": case["states"], "flood_sent": case["flood_sent"],
                                   "outcome": case["outcome"]})

    def med(name: str, get: Any) -> float:
        return round(float(np.median([get(r) for r in runs[name]])), 3)
    cases = []
    for name, _, _ in kinds:
        cases.append({"case": name, "runs": runs[name],
                      "map_p50_ms": med(name, lambda r: r["map_transport"]["p50_ms"]),
                      "map_p99_ms": med(name, lambda r: r["map_transport"]["p99_ms"]),
                      "command_rate_hz": med(name, lambda r: r["command_rate_hz"]),
                      "end_to_end_p50_ms": med(name, lambda r: r["end_to_end"]["median_ms"]),
                      "stale_states": med(name, lambda r: r["stale_states"]),
                      "flood_sent": med(name, lambda r: r["flood_sent"] or 0)})
    base = cases[0]
    for c in cases[1:]:
        c["map_p50_over_tcp"] = round(c["map_p50_ms"] / base["map_p50_ms"], 3)
        c["map_p99_over_tcp"] = round(c["map_p99_ms"] / base["map_p99_ms"], 3)
        c["command_rate_over_tcp"] = round(c["command_rate_hz"] / base["command_rate_hz"], 3)
    return {"benchmark": "security", **device_info(),
            "settings": {"clock": "realtime", "duration_s": duration_s, "reps": reps,
                         "controller": cfg.planner.controller, "samples": cfg.planner.samples,
                         "scenario": cfg.episode.scenario, "interleaved": True,
                         "overrides": overrides}, "cases": cases}


def synthetic_session(cfg: Config, path: str, seconds: float, map_hz: float) -> dict[str, Any]:
    """A recording shaped like the pipeline's traffic: states at the plant rate, depth
    frames, maps (two 400 x 400 float32 layers) and commands at `map_hz`."""
    from common.messages import Cmd, Depth, Header, Map, State, encode
    from common.topics import topic_key
    from deploy.recording.record import RecordingWriter, recording_metadata
    v, n = cfg.episode.vehicle, cfg.mapper.size_cells
    rng = np.random.default_rng(0)
    mean = rng.normal(size=(n, n)).astype(np.float32)
    var = rng.uniform(0, 3, (n, n)).astype(np.float32)
    depth = rng.uniform(0, 25, (cfg.sensor.height_px, cfg.sensor.width_px)).astype(np.float32)
    w = RecordingWriter(path, recording_metadata(cfg.to_dict(), f"vamppi/{v}/**"))
    t0 = 1_700_000_000.0
    rate = float(cfg.plant.rate_hz)
    every = max(1, int(round(rate / map_hz)))
    for i in range(int(seconds * rate)):
        t = t0 + i / rate
        h = Header(i, i / rate, t, "plant/0")
        w.add(topic_key(v, "state"), encode(State(h, np.zeros(6), 0.0, np.zeros(2), i, "")),
              int(t * 1e9))
        if i % every == 0:
            j = i // every
            hj = Header(j, i / rate, t, "x/0")
            w.add(topic_key(v, "depth"), encode(Depth(
                hj, depth, np.ones(4), np.zeros(3), np.eye(3), np.zeros(4), 25.0)),
                int(t * 1e9) + 1000)
            w.add(topic_key(v, "map"), encode(Map(hj, mean, var, np.zeros(2), 0.2)),
                  int(t * 1e9) + 2000)
            w.add(topic_key(v, "cmd"), encode(Cmd(hj, i / rate, 0.1,
                                                  np.zeros((cfg.planner.horizon, 2), np.float32))),
                  int(t * 1e9) + 3000)
    return w.close()


def bench_record(cfg: Config, duration_s: float, rates: list[float],
                 map_hz: float = 10.0) -> dict[str, Any]:
    """The recorder on a router (as `vamppi up --record` runs it) while another process
    (`vamppi replay`) publishes pipeline-shaped traffic at each time scale in `rates`
    (1 = real time; 0 = as fast as the bus goes): delivered vs published, seq gaps,
    the recorder's largest backlog, throughput."""
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    from common.bus import ZenohTransport, open_session
    from deploy.launch.up import free_port, router_config
    from deploy.recording.record import Recorder, iter_messages, recording_metadata
    cases = []
    with tempfile.TemporaryDirectory() as tmp:
        src = str(Path(tmp) / "synthetic.mcap")
        made = synthetic_session(cfg, src, duration_s, map_hz)
        for rate in rates:
            port = free_port()
            out = str(Path(tmp) / f"recorded-{rate}.mcap")
            keys = f"vamppi/{cfg.episode.vehicle}/**"
            with open_session(router_config(port)) as session:
                rec = Recorder(ZenohTransport(session), keys, out,
                               recording_metadata(cfg.to_dict(), keys))
                t0 = time.monotonic()
                r = subprocess.run([sys.executable, "-m", "deploy", "replay", src,
                                    "--rate", str(rate), "--connect", f"tcp/127.0.0.1:{port}",
                                    "--set", "bus.mode=\"client\""],
                                   capture_output=True, text=True, timeout=duration_s * 10 + 120)
                if r.returncode != 0:
                    raise RuntimeError(f"replay failed: {r.stderr[-1000:]}")
                wall = time.monotonic() - t0
                stats = rec.stop(drain_s=1.0)
            got = sum(1 for _ in iter_messages(out))
            published = json.loads(r.stdout.strip().splitlines()[-1])["published"]
            cases.append({"rate": rate, "published": published, "recorded": got,
                          "seq_missing": stats["missing"], "max_backlog": stats["max_backlog"],
                          "wall_s": round(wall, 2),
                          "mb_per_s": round(made["bytes"] / 2 ** 20 / wall, 1),
                          "file_mb": round(Path(out).stat().st_size / 2 ** 20, 1),
                          "payload_mb": round(made["bytes"] / 2 ** 20, 1)})
    return {"benchmark": "record", **device_info(),
            "settings": {"seconds": duration_s, "map_hz": map_hz,
                         "state_hz": cfg.plant.rate_hz, "messages": made["messages"]},
            "cases": cases}


def bus_table(result: dict[str, Any]) -> str:
    """`vamppi bench bus`'s result as a markdown table."""
    alone = result["codec_alone"]
    return markdown_table(
        heading(result), ["payload", "bytes", "latency p50 ms", "p99 ms", "p50 over raw",
                          "msgs/s", "MB/s"],
        [[c["payload"], c["bytes"], f"{c['median_ms']:.2f}", f"{c['p99_ms']:.2f}",
          f"{100 * c['over_raw_p50']:+.0f} %", f"{c['msgs_per_s']:.0f}", f"{c['mb_per_s']:.0f}"]
         for c in result["cases"]]) + (
        "\n\ncodec alone, one thread, no bus: encode "
        f"{1e3 * alone['encode']['median_ms']:.0f} us, decode "
        f"{1e3 * alone['decode']['median_ms']:.0f} us (medians)")


def pipeline_table(result: dict[str, Any]) -> str:
    """`vamppi bench pipeline`'s result as a markdown table."""
    nan = float("nan")

    def row(c: dict[str, Any]) -> list[Any]:
        e = c.get("end_to_end", {})
        stage = [c.get(s, {}).get("median_ms", nan)
                 for s in ("depth_to_map", "map_to_cmd", "cmd_to_applied")]
        return [c["controller"], c["samples"], f"{c.get('command_rate_hz', 0):.1f}",
                f"{c.get('command_interval', {}).get('p95_ms', nan):.0f}",
                f"{e.get('median_ms', nan):.0f}", f"{e.get('p95_ms', nan):.0f}",
                *(f"{x:.0f}" for x in stage), f"{c['stale_states']} / {c['states']}",
                c["outcome"]]
    return markdown_table(
        heading(result), ["controller", "K", "commands/s", "interval p95 ms",
                          "end-to-end p50 ms", "p95 ms", "depth->map p50", "map->cmd p50",
                          "cmd->applied p50", "stale steps", "outcome"],
        [row(c) for c in result["cases"]])


def security_table(result: dict[str, Any]) -> str:
    """`vamppi bench security`'s result as a markdown table."""
    st = result["settings"]
    return markdown_table(
        f"{heading(result)}; realtime, {st['controller']} K = {st['samples']}, "
        f"{st['scenario']}, {st['reps']} interleaved runs each (medians)",
        ["bus", "map p50 ms", "map p99 ms", "commands/s", "end-to-end p50 ms", "stale states",
         "flood puts", "map p50 / tcp", "map p99 / tcp"],
        [[c["case"], c["map_p50_ms"], c["map_p99_ms"], c["command_rate_hz"],
          c["end_to_end_p50_ms"], f"{c['stale_states']:g}", f"{c['flood_sent']:g}",
          c.get("map_p50_over_tcp", 1.0), c.get("map_p99_over_tcp", 1.0)]
         for c in result["cases"]])


def record_table(result: dict[str, Any]) -> str:
    """`vamppi bench record`'s result as a markdown table."""
    st = result["settings"]
    return markdown_table(
        f"{heading(result)}; {st['seconds']} s of traffic: states {st['state_hz']} Hz, "
        f"depth, maps and commands {st['map_hz']} Hz ({st['messages']} messages)",
        ["time scale", "published", "recorded", "seq gaps", "max backlog", "wall s", "MB/s",
         "file MB (of payload MB)"],
        [[c["rate"] or "as fast as possible", c["published"], c["recorded"], c["seq_missing"],
          c["max_backlog"], c["wall_s"], c["mb_per_s"], f"{c['file_mb']} ({c['payload_mb']})"]
         for c in result["cases"]])
