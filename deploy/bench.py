"""`vamppi bench`: speed measured, never asserted (the machines are shared and noisy).

planner   one full MPPI iteration (sampling, rollouts, the visibility-aware
          variance update for `va`, costs, weights, update) per controller and
          sample count, all cases in one process and interleaved repetition by
          repetition, so their ratios hold even when the machine is busy.
mapper    one depth frame fused, the occluded field of view inpainted, the map
          message encoded; at the default camera resolution and at 320 x 240.
bus       a map-sized message (two 400 x 400 float32 layers) from one client
          session to another through a real Zenoh router on loopback: one-way
          latency (one message in flight) and throughput (back to back), with
          our codec (encode + put ... decode), a raw put of the same bytes, and the
          floor under any checked array codec (one copy out, one checked read in).
peer      our plain-MPPI iteration against pytorch_mppi's on one problem
          (deploy/peer.py; the optional extra `.[peer]`).
pipeline  the four services as processes around an embedded router in realtime
          mode (what `vamppi up --clock realtime` runs): the achieved command
          rate and the end-to-end latency from a depth frame's publication to
          the first plant step that applies a command computed from it,
          followed through the input references in the headers.

Timing: compilation is timed apart (lower + compile) and excluded; every
repetition is blocked on (`jax.block_until_ready`); medians and p95 over many
repetitions. Memory: what XLA's compiled program needs on the device
(arguments + outputs + temporaries, `Compiled.memory_analysis`), the same
measure on a CPU and a GPU.
"""

from __future__ import annotations

import json
import platform
import time
from dataclasses import dataclass
from importlib.metadata import version
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from common.config import Config
from common.memory import keep_large_buffers
from common.scenarios import scenario_of
from deploy.timing import ChainLog, stats_ms
from services.planner import mppi, native


def device_info() -> dict[str, Any]:
    """What ran the benchmark: CPU model or GPU name, JAX backend and version, and
    whether the allocator keeps large freed buffers (common.memory; set here too)."""
    dev = jax.devices()[0]
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            names = [ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")]
        cpu = f"{names[0]} ({len(names)} logical cores)" if names else cpu
    except OSError:
        pass
    return {"backend": jax.default_backend(), "device": dev.device_kind if dev.platform != "cpu"
            else cpu, "cpu": cpu, "jax": jax.__version__, "malloc_tuned": keep_large_buffers()}


@dataclass
class Case:
    controller: str
    samples: int
    fn: Any
    args: tuple
    compile_s: float
    mem_mb: float
    times: list[float]

    def row(self) -> dict[str, Any]:
        t = np.asarray(self.times) * 1e3
        return {"controller": self.controller, "samples": self.samples,
                "median_ms": round(float(np.median(t)), 3),
                "p95_ms": round(float(np.percentile(t, 95)), 3),
                "min_ms": round(float(t.min()), 3), "reps": len(t),
                "compile_s": round(self.compile_s, 2), "peak_mem_mb": round(self.mem_mb, 1)}


def planner_inputs(cfg: Config) -> tuple:
    """A mid-episode planning problem on the offroad map: the vehicle on the road
    at 6 m/s, the map known (variance 1e-4) within 25 m ahead, prior variance 3
    elsewhere, the goal in the field."""
    scn = scenario_of(cfg.replace(**{"episode.scenario": "offroad"}))
    res = scn.resolution
    h, w = scn.heightmap.shape
    x0 = np.array([6.0, 0.0, 0.0, 30.0, 20.0, 0.0], np.float32)
    xs = (np.arange(w) + 0.5) * res
    ys = (np.arange(h) + 0.5) * res
    dx, dy = np.meshgrid(xs - x0[3], ys - x0[4], indexing="xy")
    seen = (dx > -5.0) & (np.hypot(dx, dy) < 25.0) & (np.abs(np.arctan2(dy, dx)) < 0.63)
    variance = np.where(seen, 1e-4, cfg.mapper.prior_variance).astype(np.float32)
    mean = np.where(seen, scn.heightmap, scn.terrain).astype(np.float32)
    goal = np.array([scn.goal.x, scn.goal.y, scn.goal.yaw], np.float32)
    return (x0, np.zeros(2, np.float32), goal, mean, variance,
            np.asarray(scn.origin, np.float32), res)


def planner_case(cfg: Config, controller: str, samples: int, inputs: tuple) -> Case:
    run_cfg = cfg.replace(**{"planner.controller": controller, "planner.samples": samples,
                             "planner.iterations": 1})
    params = mppi.PlannerParams.from_config(run_cfg)
    x0, u0, goal, mean, var, origin, res = inputs
    state = mppi.initial_state(params, 0)
    args = (state, *(jnp.asarray(a) for a in (x0, u0, goal, mean, var, origin)))
    t0 = time.perf_counter()
    compiled = mppi.solver(params).lower(*args, resolution=res).compile()
    compile_s = time.perf_counter() - t0
    mem = compiled.memory_analysis()
    mem_mb = ((mem.argument_size_in_bytes + mem.output_size_in_bytes + mem.temp_size_in_bytes)
              / 2 ** 20) if mem is not None else float("nan")
    jax.block_until_ready(compiled(*args))          # first run (allocation) excluded too
    return Case(controller, samples, compiled, args, compile_s, mem_mb, [])


def bench_planner(cfg: Config, samples: list[int], controllers: list[str], reps: int
                  ) -> dict[str, Any]:
    inputs = planner_inputs(cfg)
    cases = [planner_case(cfg, c, k, inputs) for k in samples for c in controllers]
    for _ in range(reps):
        for case in cases:                          # interleaved: ratios measured side by side
            t0 = time.perf_counter()
            jax.block_until_ready(case.fn(*case.args))
            case.times.append(time.perf_counter() - t0)
    p = cfg.planner
    return {"benchmark": "planner", **device_info(),
            "settings": {"horizon": p.horizon, "iterations": 1, "map_cells": list(inputs[3].shape),
                         "rays": p.visibility_rays, "points": p.visibility_points,
                         "surface_estimator": p.surface_estimator, "reps": reps,
                         "va_kernel": "native" if native.use_native(p.va_kernel) else "jax",
                         "rollout_kernel": "native" if native.use_native(p.rollout_kernel)
                         else "jax"},
            "cases": [c.row() for c in cases]}


def planner_table(result: dict[str, Any]) -> str:
    rows = result["cases"]
    det = {r["samples"]: r["median_ms"] for r in rows if r["controller"] == "deterministic"}
    lines = [f"planner, one iteration: {result['device']} ({result['backend']}, "
             f"jax {result['jax']})", "",
             "| controller | K | median ms | p95 ms | min ms | va / det | compile s | memory MB |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ratio = (f"{r['median_ms'] / det[r['samples']]:.2f}"
                 if r["controller"] == "va" and r["samples"] in det else "")
        lines.append(f"| {r['controller']} | {r['samples']} | {r['median_ms']:.1f} "
                     f"| {r['p95_ms']:.1f} | {r['min_ms']:.1f} | {ratio} | {r['compile_s']:.1f} "
                     f"| {r['peak_mem_mb']:.0f} |")
    return "\n".join(lines)


def bench_mapper(cfg: Config, reps: int, sizes: tuple[tuple[int, int], ...] = ((0, 0), (320, 240))
                 ) -> dict[str, Any]:
    """Per camera size: fuse, inpaint, encode, and the whole, medians over `reps` frames
    (the same frame each time, from the offroad start, fused into a fresh map)."""
    from common.messages import Header, Map, encode
    from services.mapper import core as mapper
    from services.sensor import core as sensor
    scn = scenario_of(cfg.replace(**{"episode.scenario": "offroad"}))
    params = mapper.MapperParams.from_config(cfg, scn.origin)
    x, y, yaw = scn.start.x, scn.start.y, scn.start.yaw
    z = float(scn.heightmap[int(y / scn.resolution), int(x / scn.resolution)])
    cases = []
    for w, h in sizes:
        scfg = cfg.sensor if not w else cfg.replace(**{"sensor.width_px": w,
                                                       "sensor.height_px": h}).sensor
        cam = sensor.CameraParams.from_config(scfg)
        depth, pos, rot = sensor.render(cam, scn.heightmap, scn.origin, scn.resolution, x, y, z,
                                        yaw)
        pose = np.array([x, y, z, yaw])
        fresh = mapper.initial_map(params, x, y, z)
        t0 = time.perf_counter()
        mapper.update(params, fresh, depth, cam.intrinsics, pos, rot, pose)   # compile
        compile_s = time.perf_counter() - t0
        stages: dict[str, list[float]] = {"fuse": [], "inpaint": [], "encode": [], "total": []}
        for i in range(reps):
            t0 = time.perf_counter()
            fused = mapper.fuse_depth(params, fresh, depth, cam.intrinsics, pos, rot)
            jax.block_until_ready((fused.mean, fused.variance))
            t1 = time.perf_counter()
            done = mapper.inpaint_occluded(params, fused, x, y, z, yaw)
            t2 = time.perf_counter()
            payload = encode(Map(Header(i, 0.0, time.time(), "bench/0"), np.asarray(done.mean),
                                 np.asarray(done.variance), np.asarray(params.origin, float),
                                 params.resolution))
            t3 = time.perf_counter()
            for k, dt in (("fuse", t1 - t0), ("inpaint", t2 - t1), ("encode", t3 - t2),
                          ("total", t3 - t0)):
                stages[k].append(dt)
        cases.append({"width": cam.width, "height": cam.height, "compile_s": round(compile_s, 2),
                      "map_bytes": len(payload),
                      **{k: stats_ms(v) for k, v in stages.items()}})
    return {"benchmark": "mapper", **device_info(),
            "settings": {"map_cells": [params.size, params.size], "reps": reps}, "cases": cases}


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
    from deploy.launch import free_port
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
    certificate puts copies of the commands on `cmd` as fast as it can (deploy.faults)."""
    from pathlib import Path

    from common.bus import Health, Inbox, topic_key
    from common.messages import Event
    from deploy.launch import recording_hook, services_up
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
                    from deploy.faults import Flood
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

    from deploy.timing import analyse
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
    from common.bus import topic_key
    from common.messages import Cmd, Depth, Header, Map, State, encode
    from deploy.recording import RecordingWriter, recording_metadata
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
    from deploy.launch import free_port, router_config
    from deploy.recording import Recorder, iter_messages, recording_metadata
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
                r = subprocess.run([sys.executable, "-m", "deploy.cli", "replay", src,
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


def table(result: dict[str, Any]) -> str:
    """A markdown table of any benchmark's result."""
    kind = result["benchmark"]
    if kind == "planner":
        return planner_table(result)
    if kind == "faults":
        from deploy.faults import faults_table
        return faults_table(result)
    if kind == "swaps":
        from deploy.swap import swaps_table
        return swaps_table(result)
    head = f"{kind}: {result['device']} ({result['backend']}, jax {result['jax']})"
    if kind == "record":
        st = result["settings"]
        lines = [f"{head}; {st['seconds']} s of traffic: states {st['state_hz']} Hz, depth, "
                 f"maps and commands {st['map_hz']} Hz ({st['messages']} messages)", "",
                 "| time scale | published | recorded | seq gaps | max backlog | wall s "
                 "| MB/s | file MB (of payload MB) |", "|---|---|---|---|---|---|---|---|"]
        for c in result["cases"]:
            lines.append(f"| {c['rate'] or 'as fast as possible'} | {c['published']} | "
                         f"{c['recorded']} | {c['seq_missing']} | {c['max_backlog']} | "
                         f"{c['wall_s']} | {c['mb_per_s']} | {c['file_mb']} "
                         f"({c['payload_mb']}) |")
        return "\n".join(lines)
    if kind == "security":
        st = result["settings"]
        lines = [f"{head}; realtime, {st['controller']} K = {st['samples']}, "
                 f"{st['scenario']}, {st['reps']} interleaved runs each (medians)", "",
                 "| bus | map p50 ms | map p99 ms | commands/s | end-to-end p50 ms "
                 "| stale states | flood puts | map p50 / tcp | map p99 / tcp |",
                 "|---|---|---|---|---|---|---|---|---|"]
        for c in result["cases"]:
            lines.append(f"| {c['case']} | {c['map_p50_ms']} | {c['map_p99_ms']} "
                         f"| {c['command_rate_hz']} | {c['end_to_end_p50_ms']} "
                         f"| {c['stale_states']:g} | {c['flood_sent']:g} "
                         f"| {c.get('map_p50_over_tcp', 1.0)} | {c.get('map_p99_over_tcp', 1.0)} |")
        return "\n".join(lines)
    if kind == "peer":
        ours = {c["samples"]: c["median_ms"] for c in result["cases"]
                if c["implementation"] == "vamppi"}
        lines = [f"{head}; torch {result['torch']} on {result['torch_device']} "
                 f"({result['torch_threads']} threads), pytorch_mppi {result['pytorch_mppi']}",
                 "", "| implementation | K | median ms | p95 ms | time / ours |",
                 "|---|---|---|---|---|"]
        for c in result["cases"]:
            lines.append(f"| {c['implementation']} | {c['samples']} | {c['median_ms']:.1f} "
                         f"| {c['p95_ms']:.1f} | {c['median_ms'] / ours[c['samples']]:.2f} |")
        return "\n".join(lines)
    if kind == "pipeline":
        lines = [head, "", "| controller | K | commands/s | interval p95 ms | end-to-end p50 ms "
                 "| p95 ms | depth->map p50 | map->cmd p50 | cmd->applied p50 | stale steps "
                 "| outcome |", "|---|---|---|---|---|---|---|---|---|---|---|"]
        for c in result["cases"]:
            e = c.get("end_to_end", {})
            stage = [c.get(s, {}).get("median_ms", float("nan"))
                     for s in ("depth_to_map", "map_to_cmd", "cmd_to_applied")]
            lines.append(f"| {c['controller']} | {c['samples']} "
                         f"| {c.get('command_rate_hz', 0):.1f} "
                         f"| {c.get('command_interval', {}).get('p95_ms', float('nan')):.0f} "
                         f"| {e.get('median_ms', float('nan')):.0f} "
                         f"| {e.get('p95_ms', float('nan')):.0f} "
                         + "".join(f"| {x:.0f} " for x in stage)
                         + f"| {c['stale_states']} / {c['states']} | {c['outcome']} |")
        return "\n".join(lines)
    if kind == "mapper":
        lines = [head, "", "| camera | fuse ms | inpaint ms | encode ms | total median ms "
                 "| total p95 ms | compile s |", "|---|---|---|---|---|---|---|"]
        for c in result["cases"]:
            lines.append(f"| {c['width']} x {c['height']} | {c['fuse']['median_ms']:.1f} "
                         f"| {c['inpaint']['median_ms']:.1f} | {c['encode']['median_ms']:.1f} "
                         f"| {c['total']['median_ms']:.1f} | {c['total']['p95_ms']:.1f} "
                         f"| {c['compile_s']:.1f} |")
        return "\n".join(lines)
    lines = [head, "", "| payload | bytes | latency p50 ms | p99 ms | p50 over raw | msgs/s "
             "| MB/s |", "|---|---|---|---|---|---|---|"]
    for c in result["cases"]:
        lines.append(f"| {c['payload']} | {c['bytes']} | {c['median_ms']:.2f} | {c['p99_ms']:.2f} "
                     f"| {100 * c['over_raw_p50']:+.0f} % | {c['msgs_per_s']:.0f} "
                     f"| {c['mb_per_s']:.0f} |")
    alone = result["codec_alone"]
    lines += ["", "codec alone, one thread, no bus: encode "
              f"{1e3 * alone['encode']['median_ms']:.0f} us, decode "
              f"{1e3 * alone['decode']['median_ms']:.0f} us (medians)"]
    return "\n".join(lines)


def main(cfg: Config, what: str, samples: list[int], controllers: list[str], reps: int,
         as_json: bool, overrides: list[str] = (), duration_s: float = 30.0,
         config_path: str | None = None, record: str | None = None) -> int:
    if what == "pipeline":
        result = bench_pipeline(cfg, list(overrides), samples, controllers, duration_s,
                                config_path, record)
    elif what == "security":
        result = bench_security(cfg, list(overrides), duration_s, reps, config_path)
    elif what == "record":
        result = bench_record(cfg, duration_s, [1.0, 0.0])
    elif what == "peer":
        from deploy.peer import bench_peer
        result = bench_peer(cfg, samples, reps)
    elif what == "planner":
        result = bench_planner(cfg, samples, controllers, reps)
    elif what == "mapper":
        result = bench_mapper(cfg, reps)
    elif what == "bus":
        result = bench_bus(cfg, reps)
    elif what == "faults":
        import tempfile
        from pathlib import Path

        from deploy.faults import bench_faults
        with tempfile.TemporaryDirectory(prefix="vamppi-faults-") as tmp:
            result = bench_faults(cfg, Path(tmp))
    elif what == "swaps":
        import tempfile
        from pathlib import Path

        from deploy.swap import bench_swaps
        with tempfile.TemporaryDirectory(prefix="vamppi-swaps-") as tmp:
            result = bench_swaps(cfg, Path(tmp))
    else:
        raise ValueError(f"unknown benchmark {what!r}")
    print(json.dumps(result) if as_json else table(result), flush=True)
    return 0
