"""`vamppi bench planner` and `vamppi bench mapper`: the planner's and the mapper's kernels
in one process.

planner   one full MPPI iteration (sampling, rollouts, the visibility-aware
          variance update for `va`, costs, weights, update) per controller and
          sample count, all cases in one process and interleaved repetition by
          repetition, so their ratios hold even when the machine is busy.
mapper    one depth frame fused, the occluded field of view inpainted, the map
          message encoded; at the default camera resolution and at 320 x 240.

Timing: compilation is timed apart (lower + compile) and excluded; every
repetition is blocked on (`jax.block_until_ready`); medians and p95 over many
repetitions. Memory: what XLA's compiled program needs on the device
(arguments + outputs + temporaries, `Compiled.memory_analysis`), the same
measure on a CPU and a GPU.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from common.config import Config
from common.scenarios import scenario_of
from deploy.bench.device import device_info, heading, markdown_table
from deploy.recording.timing import stats_ms
from services.planner import mppi, native
from services.planner.params import PlannerParams


@dataclass
class Case:
    controller: str
    samples: int
    fn: Any
    args: tuple
    compile_s: float
    mem_mb: float
    times: list[float]
    forms: str                  # the kernels' forms that ran: visibility/rollouts

    def row(self) -> dict[str, Any]:
        t = np.asarray(self.times) * 1e3
        return {"controller": self.controller, "samples": self.samples, "forms": self.forms,
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


def planner_case(cfg: Config, controller: str, samples: int, inputs: tuple,
                 form: str | None = None) -> Case:
    """One iteration of `controller` at K = `samples`, compiled; with `form` (jax, native,
    auto) both kernel settings (planner.va_kernel, planner.rollout_kernel) set to it."""
    run_cfg = cfg.replace(**{"planner.controller": controller, "planner.samples": samples,
                             "planner.iterations": 1,
                             **({"planner.va_kernel": form, "planner.rollout_kernel": form}
                                if form else {})})
    params = PlannerParams.from_config(run_cfg)
    x0, u0, goal, mean, var, origin, res = inputs
    state = mppi.initial_state(params, 0)
    args = (state, *(jnp.asarray(a) for a in (x0, u0, goal, mean, var, origin)))
    t0 = time.perf_counter()
    compiled = mppi.jitted(params).lower(*args, resolution=res).compile()
    compile_s = time.perf_counter() - t0
    mem = compiled.memory_analysis()
    mem_mb = ((mem.argument_size_in_bytes + mem.output_size_in_bytes + mem.temp_size_in_bytes)
              / 2 ** 20) if mem is not None else float("nan")
    jax.block_until_ready(compiled(*args))          # first run (allocation) excluded too
    return Case(controller, samples, compiled, args, compile_s, mem_mb, [],
                f"{params.visibility.va_kernel}/{params.rollout_kernel}")


def bench_planner(cfg: Config, samples: list[int], controllers: list[str], reps: int,
                  forms: list[str] | None = None) -> dict[str, Any]:
    """Every controller x sample count (x kernel form of `forms`, default the configured
    ones), interleaved."""
    inputs = planner_inputs(cfg)
    cases = [planner_case(cfg, c, k, inputs, f) for k in samples for c in controllers
             for f in (forms or [None])]
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
                         "va_kernel": native.resolve(p.va_kernel),
                         "rollout_kernel": native.resolve(p.rollout_kernel),
                         "forms": forms or "configured"},
            "cases": [c.row() for c in cases]}


def planner_table(result: dict[str, Any]) -> str:
    """`vamppi bench planner`'s result as a markdown table."""
    rows = result["cases"]
    det = {(r["samples"], r.get("forms")): r["median_ms"] for r in rows
           if r["controller"] == "deterministic"}
    native = {(r["controller"], r["samples"]): r["median_ms"] for r in rows
              if r.get("forms") == "native/native"}

    def ratio(r: dict[str, Any]) -> str:
        d = det.get((r["samples"], r.get("forms")))
        return f"{r['median_ms'] / d:.2f}" if r["controller"] == "va" and d else ""

    def to_native(r: dict[str, Any]) -> str:
        n = native.get((r["controller"], r["samples"]))
        return f"{r['median_ms'] / n:.2f}" if n and r.get("forms") != "native/native" else ""
    return markdown_table(
        f"planner, one iteration: {result['device']} ({result['backend']}, jax {result['jax']})",
        ["controller", "K", "forms", "median ms", "p95 ms", "min ms", "va / det",
         "/ native", "compile s", "memory MB"],
        [[r["controller"], r["samples"], r.get("forms", ""), f"{r['median_ms']:.1f}",
          f"{r['p95_ms']:.1f}", f"{r['min_ms']:.1f}", ratio(r), to_native(r),
          f"{r['compile_s']:.1f}", f"{r['peak_mem_mb']:.0f}"] for r in rows])


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
                                 params.resolution_m))
            t3 = time.perf_counter()
            for k, dt in (("fuse", t1 - t0), ("inpaint", t2 - t1), ("encode", t3 - t2),
                          ("total", t3 - t0)):
                stages[k].append(dt)
        cases.append({"width": cam.width_px, "height": cam.height_px,
                      "compile_s": round(compile_s, 2),
                      "map_bytes": len(payload),
                      **{k: stats_ms(v) for k, v in stages.items()}})
    return {"benchmark": "mapper", **device_info(),
            "settings": {"map_cells": [params.size_cells, params.size_cells], "reps": reps},
            "cases": cases}


def mapper_table(result: dict[str, Any]) -> str:
    """`vamppi bench mapper`'s result as a markdown table."""
    return markdown_table(
        heading(result), ["camera", "fuse ms", "inpaint ms", "encode ms", "total median ms",
                          "total p95 ms", "compile s"],
        [[f"{c['width']} x {c['height']}", f"{c['fuse']['median_ms']:.1f}",
          f"{c['inpaint']['median_ms']:.1f}", f"{c['encode']['median_ms']:.1f}",
          f"{c['total']['median_ms']:.1f}", f"{c['total']['p95_ms']:.1f}",
          f"{c['compile_s']:.1f}"] for c in result["cases"]])
