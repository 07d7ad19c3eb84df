"""`vamppi scenario generate`: procedural occluded worlds, drawn from a kind and a seed.

The paper's problem, in six geometries: an occluder stands beside or across the way to
the goal, and one or two obstacles stand behind it on the fast line, where the camera of a
vehicle that drives that line sees them too late to stop. A free way round them stays, so
a controller that knows the map (the prescient one) can take it at speed.

The kinds (docs/scenarios.md has the table): `corner`, a building beside the road and
open ground round it, turned round at a square corner; `street`, buildings on both
sides and a street turning left into one 8-11 m wide, whose far side keeps the turn
tight; `trees`, a tree line along the road (trunks every 2.2 m), and a field behind it
reached round the row's end and back; `hedge`, a solid hedge beside the road at up to
15 degrees to it, and the goal behind it. Two more kinds are not in the benchmark set.
`crest` hides behind terrain: a ridge 1.0-1.4 m high across the way (a raised cosine, no
steeper than Eq. occupied's gradient threshold) and rocks 0.6-1.0 m high behind its crest.
`sprint` hides behind the camera's range: a run of some 94 m along the map's diagonal,
fast enough that the distance to stop outgrows the range, and one wall across it whose
gap lies to one side.

How a world is drawn (`generate`): the kind draws start, goal and occluders from
`[kind, seed, attempt]`; the prescient controller drives that world once (`probe_config`:
with nothing hidden it drives as the deterministic one would), and its path is the fast
line; hidden obstacles go on it where the ground-truth camera, driven along it, first
sees them closer than the distance to stop from the speed there (`place_hidden`,
`deploy.analysis.reveal.stopping_distance`: the vehicle's brake limit and force rate). The world
is kept if a free way round stays (the footprint's half width and a margin,
`reachable`) and the prescient controller, now with the hidden obstacles, reaches the
goal; else the next attempt is drawn. The world is reproducible from kind and seed with
the same code and defaults; the benchmark set's files are the record.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from common.config import Config
from common.scenarios import Obstacle, Pose2, ScenarioSpec, Terrain, build
from services.plant.dynamics import S

KINDS = ("corner", "street", "trees", "hedge")     # the benchmark set's (`write_set`)
ALL_KINDS = KINDS + ("crest", "sprint")            # what `generate` draws
CLEARANCE_M = 1.4       # the free way round: the footprint's half width and a margin
ATTEMPTS = 60
FROM_START_M = 15.0     # hidden obstacles stand at least this far from the start
CANDIDATES = 40         # places on the fast line tried for the hidden obstacles
PROBE_SAMPLES = 400


class GenerateError(ValueError):
    """A kind that does not exist, or no feasible world in ATTEMPTS draws."""


@dataclass(frozen=True)
class Draft:
    """A drawn world before its hidden obstacles: start, goal and the occluders (or the
    terrain's ridge), and what the hidden obstacles are."""
    start: Pose2
    goal: Pose2
    occluders: tuple[Obstacle, ...]
    description: str
    ridge: tuple[tuple[str, float], ...] = ()          # Terrain's ridge_* fields, if any
    behind: str = "the occluder"
    hidden_height_m: tuple[float, float] = (1.8, 2.5)
    hidden_shape: str = "cylinder"     # or "wall": one wall across the fast line, a gap beside


def _street(rng: np.random.Generator) -> Draft:
    y0 = float(rng.uniform(14, 22))
    xc = float(rng.uniform(38, 50))                  # the inside corner
    yc = y0 + float(rng.uniform(3.5, 5.0))
    width = float(rng.uniform(8.0, 11.0))            # of the street round the corner
    height = float(rng.uniform(3.0, 6.0))
    south = y0 - float(rng.uniform(4.0, 5.5))        # the road's far kerb
    east = xc + width
    top = 76.0
    inside = Obstacle("box", (4.0 + xc) / 2, (yc + top) / 2, height, half_x=(xc - 4.0) / 2,
                      half_y=(top - yc) / 2)
    kerb = Obstacle("box", (4.0 + east) / 2, south - 0.5, height, half_x=(east - 4.0) / 2,
                    half_y=0.5)
    far = Obstacle("box", east + 0.5, (south - 1.0 + top) / 2, height, half_x=0.5,
                   half_y=(top - south + 1.0) / 2)
    gx = xc + width / 2 + float(rng.uniform(-1.5, 1.5))
    gy = yc + float(rng.uniform(20, 34))
    return Draft(Pose2(8.0, y0, 0.0), Pose2(gx, gy, math.pi / 2), (inside, kerb, far),
                 f"A street between buildings turning left at a square corner into one "
                 f"{width:.0f} m wide; the goal lies up it.")


def _hedge(rng: np.random.Generator) -> Draft:
    y0 = float(rng.uniform(14, 24))
    x_end = float(rng.uniform(42, 56))
    yaw = float(rng.uniform(-0.25, 0.25))                    # not quite along the road
    length = x_end - 4.0
    yh = y0 + float(rng.uniform(4.5, 6.5))
    cx = x_end - length / 2 * math.cos(yaw)
    cy = yh - length / 2 * math.sin(yaw)
    hedge = Obstacle("box", cx, cy, float(rng.uniform(2.0, 3.0)), half_x=length / 2,
                     half_y=float(rng.uniform(0.4, 1.0)), yaw=yaw)
    gx = x_end - float(rng.uniform(2, 12))
    gy = yh + float(rng.uniform(12, 22))
    return Draft(Pose2(8.0, y0, 0.0), Pose2(gx, gy, math.pi / 2), (hedge,),
                 f"A solid hedge {length:.0f} m long beside the road, at {math.degrees(yaw):.0f} "
                 "degrees to it; the goal lies behind it, round its end and back.")


def _trees(rng: np.random.Generator) -> Draft:
    y0 = float(rng.uniform(14, 24))
    yr = y0 + float(rng.uniform(4.5, 6.0))
    x_end = float(rng.uniform(44, 58))
    trees = tuple(Obstacle("cylinder", float(x), yr, 5.0, radius=0.9)
                  for x in np.arange(6.0, x_end + 1e-9, 2.2))
    gx = trees[-1].x - float(rng.uniform(0, 14))
    gy = yr + float(rng.uniform(14, 24))
    return Draft(Pose2(8.0, y0, 0.0), Pose2(gx, gy, math.pi / 2), trees,
                 "A road beside a tree line; the goal lies in the field behind the row, "
                 "round the row's end and back.")


def _corner(rng: np.random.Generator) -> Draft:
    y0 = float(rng.uniform(12, 22))
    xc = float(rng.uniform(36, 50))                  # the building's corner
    yc = y0 + float(rng.uniform(3.5, 6.0))
    w, d = float(rng.uniform(14, 24)), float(rng.uniform(14, 26))
    building = Obstacle("box", xc - w / 2, yc + d / 2, float(rng.uniform(3.0, 6.0)),
                        half_x=w / 2, half_y=d / 2)
    gx = xc + float(rng.uniform(2, 10))
    gy = min(70.0, yc + float(rng.uniform(20, 34)))
    return Draft(Pose2(10.0, y0, 0.0), Pose2(gx, gy, math.pi / 2), (building,),
                 f"A road along a building {w:.0f} m x {d:.0f} m; the goal lies up its far "
                 "side, round a square corner.")


def _crest(rng: np.random.Generator) -> Draft:
    y0 = float(rng.uniform(25, 55))
    xr = float(rng.uniform(28, 40))                  # where the crest line crosses the road
    yaw = math.pi / 2 + float(rng.uniform(-0.35, 0.35))
    # below Eq. occupied's height threshold (1.5 m against the ground under the vehicle),
    # as wide as keeps its steepest slope, pi h / w, under 0.35 (its gradient threshold 0.5)
    h = float(rng.uniform(1.0, 1.4))
    w = float(rng.uniform(9.0 * h, 18.0))
    gx = xr + float(rng.uniform(18, 30))
    gy = y0 + float(rng.uniform(-10, 10))
    return Draft(Pose2(8.0, y0, 0.0), Pose2(gx, gy, 0.0), (),
                 f"Open ground and a ridge {h:.1f} m high and {w:.0f} m wide across the way, "
                 f"at {math.degrees(yaw - math.pi / 2):.0f} degrees to it; the goal lies beyond.",
                 ridge=(("ridge_height_m", h), ("ridge_width_m", w), ("ridge_x", xr),
                        ("ridge_y", y0), ("ridge_yaw", yaw)),
                 behind="the crest", hidden_height_m=(0.6, 1.0))


def _sprint(rng: np.random.Generator) -> Draft:
    sx, sy = float(rng.uniform(5, 9)), float(rng.uniform(5, 9))
    gx, gy = float(rng.uniform(71, 75)), float(rng.uniform(71, 75))
    yaw = math.atan2(gy - sy, gx - sx)
    return Draft(Pose2(sx, sy, yaw), Pose2(gx, gy, yaw), (),
                 f"A run of {math.hypot(gx - sx, gy - sy):.0f} m over open ground along the "
                 "map's diagonal; the camera's 25 m range is all that hides what lies ahead.",
                 behind="the edge of the camera's range", hidden_height_m=(0.8, 1.2),
                 hidden_shape="wall")


_DRAW = {"street": _street, "hedge": _hedge, "trees": _trees, "corner": _corner,
         "crest": _crest, "sprint": _sprint}


# ----------------------------------------------------------------------------- checks
def _free_space(scn, clearance: float) -> np.ndarray:
    """Cells where the footprint's centre may be: obstacles grown by `clearance`, and the
    map's border."""
    occ = (scn.heightmap - scn.terrain >= 0.3).astype(np.uint8)
    r = int(math.ceil(clearance / scn.resolution))
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    free = cv2.dilate(occ, disk) == 0
    b = r + 1
    free[:b], free[-b:], free[:, :b], free[:, -b:] = False, False, False, False
    return free


def _cell(scn, x: float, y: float) -> tuple[int, int]:
    return int(y / scn.resolution), int(x / scn.resolution)


def reachable(scn, clearance: float = CLEARANCE_M) -> float:
    """The free way's length from start to goal (m, 8-connected cells), inf if there is none."""
    free = _free_space(scn, clearance)
    s, g = _cell(scn, scn.start.x, scn.start.y), _cell(scn, scn.goal.x, scn.goal.y)
    if not (free[s] and free[g]):
        return math.inf
    dist = np.full(free.shape, np.inf)
    dist[s] = 0.0
    front = np.zeros(free.shape, np.uint8)
    front[s] = 1
    reached = front.copy()
    k = np.ones((3, 3), np.uint8)
    steps = 0
    while not reached[g]:
        grown = cv2.dilate(reached, k) & free.astype(np.uint8)
        if np.array_equal(grown, reached):
            return math.inf
        steps += 1
        reached = grown
    return steps * scn.resolution


def probe_config(cfg: Config, scenario: str) -> Config:
    """The run that finds the fast line, and the one that checks a world: the prescient
    controller, seed 0, with the paper's plain sampler (no braking, swerve or advanced
    samples), straight-line goal distance and instants' time cost, three footprint arrays
    and the pixels' own hits, so that a world stays what it was when those additions'
    defaults change."""
    return cfg.replace(**{"episode.scenario": scenario, "planner.controller": "prescient",
                          "planner.samples": PROBE_SAMPLES, "episode.seed": 0,
                          "episode.layout": 0, "episode.scenario_seed": 0,
                          "planner.brake_samples": 0, "planner.swerve_samples": 0,
                          "planner.advance_samples": 0, "planner.effective_update": False,
                          "planner.goal_distance": "straight",
                          "planner.time_cost": "instants", "planner.footprint_arrays": 3,
                          "mapper.fill_between_pixels": False,
                          "planner.stop_poses": 0})


def _drive(cfg: Config, spec: ScenarioSpec):
    import tempfile

    from common.scenarios import save_spec
    from deploy.sim.runner import run_episode
    with tempfile.TemporaryDirectory() as tmp:
        path = save_spec(spec, Path(tmp) / "world.toml")
        return run_episode(probe_config(cfg, str(path)))


def _hidden_at(rng: np.random.Generator, x: float, y: float, psi: float,
               heights: tuple[float, float], shape: str) -> Obstacle:
    """A hidden obstacle on the fast line at (x, y), heading psi: a cylinder up to 1 m to
    either side of it, or a wall across it 20-26 m long that reaches 6-9 m past the line on
    one side (the gap lies beyond) and the rest of its length on the other."""
    if shape == "wall":
        half = float(rng.uniform(10.0, 13.0))
        lateral = float(rng.choice((-1.0, 1.0))) * (half - float(rng.uniform(6.0, 9.0)))
        return Obstacle("box", float(x - math.sin(psi) * lateral),
                        float(y + math.cos(psi) * lateral), float(rng.uniform(*heights)),
                        half_x=0.6, half_y=half, yaw=float(psi), hidden=True)
    lateral = float(rng.uniform(-1.0, 1.0))
    return Obstacle("cylinder", float(x - math.sin(psi) * lateral),
                    float(y + math.cos(psi) * lateral), float(rng.uniform(*heights)),
                    radius=float(rng.uniform(0.8, 1.3)), hidden=True)


def place_hidden(cfg: Config, rng: np.random.Generator, base: ScenarioSpec, path: np.ndarray,
                 occluders: tuple[Obstacle, ...], heights: tuple[float, float] = (1.8, 2.5),
                 shape: str = "cylinder") -> tuple[Obstacle, ...]:
    """One or two obstacles (`_hidden_at`; one wall) on the fast line `path` (the probe's
    10 Hz (t, X, Y, V, psi)), each where the camera driven along that line first sees it
    too late to stop from the speed it has there, or never before reaching it; 1 m clear
    of the occluders' footprints (`Obstacle.clearance`). () if no candidate qualifies."""
    from deploy.analysis.reveal import first_sightings, poses_of_path
    want = 1 if shape == "wall" else 1 + int(rng.uniform() < 0.5)
    found: list[Obstacle] = []
    idx = [i for i in range(len(path)) if path[i, 3] >= 3.0
           and math.hypot(path[i, 1] - base.start.x, path[i, 2] - base.start.y) > FROM_START_M
           and math.hypot(path[i, 1] - base.goal.x, path[i, 2] - base.goal.y) > 6.0]
    for i in rng.permutation(idx)[:CANDIDATES]:
        t, x, y, v, psi = path[i]
        ob = _hidden_at(rng, x, y, psi, heights, shape)
        if any(o.clearance(ob) < 1.0 for o in occluders):
            continue
        if any(math.hypot(ob.x - f.x, ob.y - f.y) < 6.0 for f in found):
            continue
        trial = ScenarioSpec(base.name, base.description, base.start, base.goal,
                             base.obstacles + tuple(found) + (ob,), base.terrain)
        scn = build(trial, 0, cfg.mapper.resolution_m)
        before = [p for p in poses_of_path(path) if p[0] < t]
        sight, = first_sightings(cfg, scn, before, [len(trial.obstacles) - 1])
        if sight.t_s is not None and sight.stoppable:
            continue
        found.append(ob)
        if len(found) == want:
            break
    return tuple(found)


def generate(cfg: Config, kind: str, seed: int, drive: bool = True) -> ScenarioSpec:
    """The world of `kind` and `seed`: the first of its draws whose occluders leave a free
    way, whose fast line (`probe_config`) meets the occluders' shadow, with hidden
    obstacles placed there (`place_hidden`) that still leave a free way, which (with
    `drive`) the prescient controller drives to the goal."""
    if kind not in _DRAW:
        raise GenerateError(f"unknown kind {kind!r}; choose one of {', '.join(ALL_KINDS)}")
    why: list[str] = []
    for attempt in range(ATTEMPTS):
        rng = np.random.default_rng([ALL_KINDS.index(kind), seed, attempt])
        d = _DRAW[kind](rng)
        base = ScenarioSpec(f"{kind}-{seed:04d}", d.description, d.start, d.goal, d.occluders,
                            Terrain("waves", 0.25, int(rng.integers(0, 2 ** 31)),
                                    **dict(d.ridge)), kind=kind)
        if not math.isfinite(reachable(build(base, 0, cfg.mapper.resolution_m))):
            why.append("the occluders close the way")
            continue
        probe = _drive(cfg, base)
        if probe.outcome != "success":
            why.append(f"the probe's {probe.outcome} without hidden obstacles")
            continue
        every = max(1, int(round(cfg.plant.rate_hz * cfg.planner.dt_s)))
        path = probe.trajectory[::every][:, [0, 1 + S.X, 1 + S.Y, 1 + S.V, 1 + S.PSI]]
        hidden = place_hidden(cfg, rng, base, path, d.occluders, d.hidden_height_m,
                              d.hidden_shape)
        if not hidden:
            why.append("no place on the fast line is seen too late")
            continue
        n = len(hidden)
        spec = ScenarioSpec(
            base.name, f"{d.description} {n} obstacle{'s' if n > 1 else ''} behind "
            f"{d.behind} stand{'' if n > 1 else 's'} on the fast line, seen too late to stop for "
            "a vehicle that takes the unseen ground for free.", d.start, d.goal,
            d.occluders + hidden, base.terrain,
            kind=kind, generator={"kind": kind, "seed": seed, "attempt": attempt,
                                  "probe_time_s": round(probe.time_to_goal_s, 2)})
        free = reachable(build(spec, 0, cfg.mapper.resolution_m))
        straight = math.hypot(d.goal.x - d.start.x, d.goal.y - d.start.y)
        if free > 2.2 * straight:
            why.append("no free way round the hidden obstacles")
            continue
        if drive:
            r = _drive(cfg, spec)
            if r.outcome != "success":
                why.append(f"the prescient controller's {r.outcome}")
                continue
            spec = replace(spec, generator={**spec.generator,
                                            "prescient_time_s": round(r.time_to_goal_s, 2)})
        return spec
    raise GenerateError(f"{kind} seed {seed}: no feasible world in {ATTEMPTS} draws "
                        f"({'; '.join(f'{n} x {w}' for w, n in Counter(why).most_common())})")


def set_path(out: Path, kind: str, seed: int) -> Path:
    """Where world (kind, seed) of a benchmark set lives: odd seeds tune, even are held out."""
    return out / ("tune" if seed % 2 else "heldout") / f"{kind}-{seed:04d}.toml"


def _draw_one(job: tuple[Config, str, int, str]) -> str:
    """The world's file, or the reason none could be drawn (a GenerateError's text)."""
    from common.scenarios import save_spec
    cfg, kind, seed, path = job
    try:
        return str(save_spec(generate(cfg, kind, seed), path))
    except GenerateError as exc:
        return f"! {exc}"


def write_set(cfg: Config, out: Path, per_kind: int, kinds: str | None = None,
              jobs: int = 1) -> list[Path]:
    """The benchmark set: seeds 1 .. per_kind of its kinds (KINDS; or `kinds`, comma-separated)
    into out/tune (odd seeds) and out/heldout (even seeds); worlds already there are kept.
    A seed without a feasible world does not stop the others (GenerateError at the end)."""
    import multiprocessing
    chosen = KINDS if not kinds else tuple(k.strip() for k in kinds.split(","))
    for k in chosen:
        if k not in _DRAW:
            raise GenerateError(f"unknown kind {k!r}; choose one of {', '.join(ALL_KINDS)}")
    # seed by seed, every kind in turn: a set stopped early still has every kind
    todo = [(cfg, k, s, str(set_path(out, k, s))) for s in range(1, per_kind + 1)
            for k in chosen if not set_path(out, k, s).exists()]
    if jobs <= 1:
        done = [_draw_one(j) for j in todo]
    else:
        with multiprocessing.get_context("spawn").Pool(jobs) as pool:
            done = pool.map(_draw_one, todo, chunksize=1)
    failed = [d[2:] for d in done if d.startswith("! ")]
    if failed:                      # the others are written: a rerun tries only these again
        raise GenerateError("; ".join(failed))
    return [Path(p) for p in done]
