"""When did the camera first see each obstacle, and could the vehicle still stop?

`vamppi reveal DIR/runs.jsonl` drives the ground-truth depth camera
(services/sensor/core.py, the sensor service's own renderer) along every
recorded path and reports, per run and obstacle, the first pose from which
`min_returns` or more depth returns land on the obstacle: the time, the gap
from the vehicle's front edge to the obstacle's surface, the speed, and the
distance the vehicle needs to stop from that speed. A hidden obstacle first
seen with a gap larger than the stopping distance could have been avoided by
braking; a collision after such a sighting is the planner's, not the
occlusion's (docs/results.md).

The camera, the vehicle and the control period are the experiment's own
(`DIR/config.toml`, which the experiment writes; `--config` or an older
directory without it: the given configuration).

The path of a run record is 10 Hz (t, X, Y, V, psi), the vehicle's (and the
camera's) heading psi recorded from record format 2 on (deploy/sim/experiment.py);
every sample is a pose, a repeat of the one before only once. A format-1 record has no
psi: its heading at sample i is then the direction from sample i-1 to i, the course, not
where the camera points (a vehicle sliding in a turn moves 11-16 degrees off its heading),
and samples below 0.2 m/s are skipped (standing still, the course is undefined).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.config import Config
from common.geometry import bilinear
from common.scenarios import Obstacle, Scenario
from services.plant.dynamics import Reaction
from services.sensor import core as sensor

MIN_RETURNS = 20       # returns on an obstacle that count as seeing it (a 128 x 72 image)
MIN_SPEED_MPS = 0.2


@dataclass(frozen=True)
class Sighting:
    obstacle: int            # index into scenario.obstacles
    t_s: float | None        # None: never seen along the path
    gap_m: float             # front edge to the obstacle's surface, straight line
    speed_mps: float
    stopping_m: float        # from that speed: one control tick, the brake ramp, full braking

    @property
    def stoppable(self) -> bool:
        return self.t_s is not None and self.gap_m > self.stopping_m


def stopping_distance(cfg: Config, v: float) -> float:
    """Travel from the sighting to standing still on flat ground, drag and rolling
    resistance left out: one control tick at v before the command changes, the force
    ramping 0 -> brake limit at the rate limit, then the brake limit
    (`services.plant.dynamics.Reaction`, which the planner's in-time rule uses too)."""
    return float(Reaction.from_config(cfg.vehicle).stopping(v, cfg.planner.dt_s))


def in_view(ob: Obstacle, x: float, y: float, yaw: float, reach: float, half_fov: float
            ) -> bool:
    """False only where the obstacle cannot be in the image: out of range or wholly outside
    the horizontal field of view (a conservative test; the camera decides the rest)."""
    d = math.hypot(ob.x - x, ob.y - y)
    extent = ob.radius if ob.kind == "cylinder" else math.hypot(ob.half_x, ob.half_y)
    if d - extent > reach:
        return False
    if d <= extent + 1.0:
        return True
    bearing = math.atan2(ob.y - y, ob.x - x) - yaw
    bearing = math.atan2(math.sin(bearing), math.cos(bearing))
    return abs(bearing) <= half_fov + math.asin(min(1.0, (extent + 1.0) / d))


def returns_on(points: np.ndarray, ob: Obstacle, margin: float = 0.15) -> int:
    """How many return points (M, >=2) land on the obstacle's footprint grown by margin."""
    if ob.kind == "cylinder":
        d = np.hypot(points[:, 0] - ob.x, points[:, 1] - ob.y) - ob.radius
    else:
        u, w = ob.local(points[:, 0], points[:, 1])
        d = np.maximum(np.abs(u) - ob.half_x, np.abs(w) - ob.half_y)
    return int((d <= margin).sum())


def seen_from(cam: sensor.CameraParams, scn: Scenario, x: float, y: float, yaw: float
              ) -> np.ndarray:
    """World points (M, 3) of the ground-truth camera's returns from a vehicle pose (on the
    bare terrain, as the plant places it)."""
    z = float(bilinear(scn.terrain, np.float64(x), np.float64(y), scn.origin, scn.resolution))
    depth, pos, rot = sensor.render(cam, scn.heightmap, scn.origin, scn.resolution, x, y, z, yaw)
    return sensor.return_points(cam, depth, pos, rot)


def poses_of_path(path: np.ndarray) -> list[tuple[float, float, float, float, float]]:
    """(t, x, y, yaw, v) of a (T, 5) path (t, X, Y, V, psi), a pose repeated only once;
    of an older (T, 4) one without psi, the yaw is the course from the previous sample
    and standing samples are skipped."""
    out: list[tuple[float, float, float, float, float]] = []
    for i in range(len(path)):
        t, x, y, v = (float(a) for a in path[i][:4])
        if len(path[i]) > 4:                                   # the recorded heading
            yaw = float(path[i][4])
            if out and math.hypot(x - out[-1][1], y - out[-1][2]) <= 1e-6 \
                    and abs(yaw - out[-1][3]) <= 1e-6:
                continue                                       # the same view again
        else:                                                  # older records: the course
            if i == 0:
                continue
            dx, dy = x - path[i - 1][1], y - path[i - 1][2]
            if v < MIN_SPEED_MPS or math.hypot(dx, dy) <= 1e-6:
                continue
            yaw = math.atan2(dy, dx)
        out.append((t, x, y, yaw, v))
    return out


def first_sightings(cfg: Config, scn: Scenario, poses, which: list[int],
                    min_returns: int = MIN_RETURNS) -> list[Sighting]:
    """For each obstacle index in `which`, its first sighting along the poses (t, x, y, yaw, v)."""
    cam = sensor.CameraParams.from_config(cfg.sensor)
    half = cfg.vehicle.footprint_length_m / 2.0
    reach = cam.range_m + cam.mount_forward_m + 1.0         # farther than this: no return
    half_fov = math.atan2(cam.width_px / 2.0, cam.fx)
    found: dict[int, Sighting] = {}
    for t, x, y, yaw, v in poses:
        if len(found) == len(which):
            break
        near = [k for k in which if k not in found
                and in_view(scn.obstacles[k], x, y, yaw, reach, half_fov)]
        if not near:                   # none left to find is in range and in the field of view
            continue
        pts = seen_from(cam, scn, x, y, yaw)
        for k in near:
            if returns_on(pts, scn.obstacles[k]) >= min_returns:
                fx, fy = x + half * math.cos(yaw), y + half * math.sin(yaw)
                found[k] = Sighting(k, t, float(scn.obstacles[k].distance(fx, fy)), v,
                                    stopping_distance(cfg, v))
    return [found.get(k, Sighting(k, None, math.nan, math.nan, math.nan)) for k in which]


def reveal_runs(cfg: Config, runs: list[dict], obstacles: str = "hidden",
                min_returns: int = MIN_RETURNS) -> list[dict]:
    """One row per run and obstacle; `obstacles` is "hidden" or "all"."""
    from deploy.sim.experiment import run_scenario
    cache: dict[tuple[str, int, int], Scenario] = {}
    rows = []
    for r in runs:
        scn = run_scenario(cfg, r, cache)
        which = [i for i, o in enumerate(scn.obstacles) if obstacles == "all" or o.hidden]
        for s in first_sightings(cfg, scn, poses_of_path(np.asarray(r["path"], float)), which,
                                 min_returns):
            ob = scn.obstacles[s.obstacle]
            rows.append({"scenario": r["scenario"], "controller": r["controller"],
                         "samples": r["samples"], "seed": r["seed"], "outcome": r["outcome"],
                         "obstacle": [ob.x, ob.y], "seen_at_s": s.t_s,
                         "gap_m": None if s.t_s is None else round(s.gap_m, 2),
                         "speed_mps": None if s.t_s is None else round(s.speed_mps, 2),
                         "stopping_m": None if s.t_s is None else round(s.stopping_m, 2),
                         "stoppable": s.stoppable})
    return rows


def table(rows: list[dict]) -> str:
    lines = ["| scenario | controller | K | seed | outcome | obstacle | seen at | gap | speed "
             "| stopping distance | could stop |", "|" + "---|" * 11]
    for r in rows:
        ob = f"({r['obstacle'][0]:g}, {r['obstacle'][1]:g})"
        if r["seen_at_s"] is None:
            seen = "never | | | |"
        else:
            seen = (f"{r['seen_at_s']:.1f} s | {r['gap_m']:.1f} m | {r['speed_mps']:.1f} m/s | "
                    f"{r['stopping_m']:.1f} m | {'yes' if r['stoppable'] else 'no'}")
        lines.append(f"| {r['scenario']} | {r['controller']} | {r['samples']} | {r['seed']} | "
                     f"{r['outcome']} | {ob} | {seen} |")
    return "\n".join(lines)
