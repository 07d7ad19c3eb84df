"""Scenarios are data: a TOML file holds a world's terrain, obstacles, start, goal and
description (docs/scenarios.md has the format).

A scenario names either a built-in (`open-field`, `alleyway`, `offroad`: the files in
`common/scenarios/builtin`) or a path to such a file. Building one gives the ground-truth
heightmap on the map's grid (80 m x 80 m at 0.2 m, the paper's, by default): the bare
terrain (a sum of low-frequency waves drawn from a seed, flat, or a heightmap array or
image beside the file) plus the obstacles (cylinders and boxes of a height above the
terrain). The same file, `episode.scenario_seed` and resolution give the same bytes, and
the same `Scenario.digest`: every service builds the world from its own copy of the file
and the plant refuses a service whose digest differs from its own.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

SIZE_M = 80.0
FORMAT = 1                    # the scenario file format this module reads and writes
BUILTIN_DIR = Path(__file__).with_name("builtin")
BENCHMARK_DIR = Path(__file__).with_name("benchmark")
OBSTACLE_KINDS = ("cylinder", "box")
TERRAIN_KINDS = ("waves", "flat", "heightmap")


class ScenarioError(ValueError):
    """A scenario that cannot be found, read or built: says which file and what is wrong."""


class LayoutError(ScenarioError):
    """A layout number the scenario does not have."""


@dataclass(frozen=True)
class Obstacle:
    kind: str                 # "cylinder" | "box"
    x: float
    y: float
    height: float             # above the bare terrain, m
    radius: float = 0.0       # cylinder
    half_x: float = 0.0       # box half extents along its own axes
    half_y: float = 0.0
    yaw: float = 0.0          # box orientation
    hidden: bool = False      # meant to stay unseen from the approach the scenario is built
                              # around (tests/test_scenarios.py, `vamppi reveal`)

    def local(self, x: Any, y: Any) -> tuple[Any, Any]:
        """World points in the obstacle's own frame (u along its yaw, v across); arrays ok."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return (x - self.x) * c + (y - self.y) * s, -(x - self.x) * s + (y - self.y) * c

    def contains(self, x: Any, y: Any) -> Any:
        """Whether world points lie on the obstacle's footprint (its cells are those whose
        centres do); arrays ok."""
        if self.kind == "cylinder":
            return (x - self.x) ** 2 + (y - self.y) ** 2 <= self.radius ** 2
        if self.kind == "box":
            u, v = self.local(x, y)
            return (np.abs(u) <= self.half_x) & (np.abs(v) <= self.half_y)
        raise ValueError(f"unknown obstacle kind {self.kind!r}")

    def distance(self, x: Any, y: Any) -> Any:
        """Distance from world points to the obstacle's footprint, 0 inside; arrays ok."""
        if self.kind == "cylinder":
            return np.maximum(0.0, np.hypot(x - self.x, y - self.y) - self.radius)
        u, v = self.local(x, y)
        return np.hypot(np.maximum(0.0, np.abs(u) - self.half_x),
                        np.maximum(0.0, np.abs(v) - self.half_y))

    def corners(self) -> np.ndarray:
        """A box's four corners (4, 2), world frame, in order round it."""
        u = np.array([1.0, -1.0, -1.0, 1.0]) * self.half_x
        v = np.array([1.0, 1.0, -1.0, -1.0]) * self.half_y
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.stack([self.x + u * c - v * s, self.y + u * s + v * c], axis=-1)

    def clearance(self, other: Obstacle) -> float:
        """The gap between two footprints, 0 where they touch or overlap. Both are convex,
        so apart, the gap is reached at a cylinder's centre or a box's corner against the
        other's outline; two boxes may cross with no corner inside the other (a plus sign),
        which their edges crossing tells."""
        if self.kind == "cylinder" or other.kind == "cylinder":
            a, b = (self, other) if self.kind == "cylinder" else (other, self)
            return float(max(0.0, b.distance(a.x, a.y) - a.radius))
        pa, pb = self.corners(), other.corners()
        if any(_segments_cross(pa[i], pa[(i + 1) % 4], pb[j], pb[(j + 1) % 4])
               for i in range(4) for j in range(4)):
            return 0.0
        return float(min(np.min(other.distance(pa[:, 0], pa[:, 1])),
                         np.min(self.distance(pb[:, 0], pb[:, 1]))))


def _segments_cross(p: np.ndarray, q: np.ndarray, r: np.ndarray, s: np.ndarray) -> bool:
    """Whether the segments p-q and r-s meet (touching counts)."""
    def side(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
        return float((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))
    d1, d2, d3, d4 = side(r, s, p), side(r, s, q), side(p, q, r), side(p, q, s)
    return d1 * d2 <= 0.0 and d3 * d4 <= 0.0 and not (d1 == d2 == 0.0)


@dataclass(frozen=True)
class Pose2:
    x: float
    y: float
    yaw: float


@dataclass(frozen=True)
class Terrain:
    """The bare ground under the obstacles."""
    kind: str = "waves"       # waves | flat | heightmap
    amplitude_m: float = 0.25     # waves: about +- this
    seed: int = 0             # waves: drawn from [episode.scenario_seed, seed]
    heightmap: str = ""       # heightmap: a .npy (metres) or .png file beside the scenario file
    resolution_m: float = 0.2     # heightmap: its cell size (resampled to the map's)
    height_min_m: float = 0.0     # heightmap .png: the elevation of pixel value 0 ...
    height_max_m: float = 1.0     # ... and of the largest value (255 or 65535)
    ridge_height_m: float = 0.0   # a ridge added to any kind: its crest's height; 0 = none
    ridge_width_m: float = 12.0   # ... its width across, a raised cosine from foot to foot
    ridge_x: float = 0.0          # ... a point of its crest line
    ridge_y: float = 0.0
    ridge_yaw: float = 0.0        # ... the crest line's direction


@dataclass(frozen=True)
class ScenarioSpec:
    """A scenario file, as read: what the world is, before it is built on a grid."""
    name: str
    description: str
    start: Pose2
    goal: Pose2
    obstacles: tuple[Obstacle, ...]
    terrain: Terrain = Terrain()
    size_m: float = SIZE_M
    kind: str = "built-in"    # the family it belongs to (`vamppi scenario generate --kind`)
    layout: int = 1           # a built-in's layout number (LAYOUTS); 1 for every other file
    generator: dict[str, Any] = field(default_factory=dict)   # how it was drawn, if it was
    base: str = ""            # the directory a heightmap file is relative to (not saved)


@dataclass(frozen=True)
class Scenario:
    name: str
    seed: int
    resolution: float
    origin: tuple[float, float]
    terrain: np.ndarray       # (H, W) float32 bare ground
    heightmap: np.ndarray     # (H, W) float32 ground truth: terrain + obstacles
    start: Pose2
    goal: Pose2
    obstacles: tuple[Obstacle, ...]
    description: str
    layout: int = 1           # which of the scenario's layouts (LAYOUTS) it was built to
    kind: str = "built-in"

    @functools.cached_property
    def digest(self) -> str:
        """What two services must agree on to drive the same world: the grid, the ground
        truth, start, goal and obstacles (16 hex digits)."""
        h = hashlib.sha256()
        h.update(json.dumps([self.resolution, list(self.origin), list(self.heightmap.shape),
                             [self.start.x, self.start.y, self.start.yaw],
                             [self.goal.x, self.goal.y, self.goal.yaw],
                             [list(_obstacle_dict(o).values()) for o in self.obstacles]]
                            ).encode())
        h.update(np.ascontiguousarray(self.heightmap, "<f4").tobytes())
        h.update(np.ascontiguousarray(self.terrain, "<f4").tobytes())
        return h.hexdigest()[:16]

    def obstacle_mask(self, min_height: float) -> np.ndarray:
        """Cells whose ground truth stands `min_height` or more above the bare terrain."""
        return (self.heightmap - self.terrain) >= min_height

    def cell_centres(self, rows: Any, cols: Any) -> tuple[Any, Any]:
        """World (x, y) of the centres of cells (row, col)."""
        return (self.origin[0] + (np.asarray(cols) + 0.5) * self.resolution,
                self.origin[1] + (np.asarray(rows) + 0.5) * self.resolution)

    def obstacle_cells(self, min_height: float) -> tuple[np.ndarray, ...]:
        """For each obstacle, the flat indices of its cells that stand `min_height` or more
        above the bare terrain (an obstacle's cell another one overlaps counts for both)."""
        mask = self.obstacle_mask(min_height)
        rows, cols = np.nonzero(mask)
        x, y = self.cell_centres(rows, cols)
        flat = rows * mask.shape[1] + cols
        return tuple(flat[ob.contains(x, y)] for ob in self.obstacles)

    def obstacles_at(self, rows: Any, cols: Any) -> tuple[int, ...]:
        """Indices of the obstacles on which any of the cells (row, col) lies."""
        x, y = self.cell_centres(rows, cols)
        return tuple(i for i, ob in enumerate(self.obstacles) if np.any(ob.contains(x, y)))


# ----------------------------------------------------------------------------- files
def _obstacle_dict(o: Obstacle) -> dict[str, Any]:
    d: dict[str, Any] = {"kind": o.kind, "x": o.x, "y": o.y, "height": o.height}
    if o.kind == "cylinder":
        d["radius"] = o.radius
    else:
        d.update(half_x=o.half_x, half_y=o.half_y, yaw=o.yaw)
    d["hidden"] = o.hidden
    return d


def _toml_value(v: Any) -> str:
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + "}"
    return json.dumps(v)


def spec_toml(spec: ScenarioSpec) -> str:
    """The scenario file's text; `parse_spec` reads it back to an equal spec."""
    def table(d: dict[str, Any]) -> list[str]:
        return [f"{k} = {_toml_value(v)}" for k, v in d.items()]

    head = {"format": FORMAT, "name": spec.name, "kind": spec.kind,
            "description": spec.description, "size_m": float(spec.size_m)}
    if spec.layout != 1:
        head["layout"] = spec.layout
    lines = ["# a vamppi scenario (docs/scenarios.md)"] + table(head)
    if spec.generator:
        lines += ["", "[generator]"] + table(spec.generator)
    terrain = {f.name: getattr(spec.terrain, f.name) for f in fields(Terrain)
               if getattr(spec.terrain, f.name) != f.default or f.name == "kind"}
    lines += ["", "[terrain]"] + table(terrain)
    for name in ("start", "goal"):
        p = getattr(spec, name)
        lines += ["", f"[{name}]"] + table({"x": float(p.x), "y": float(p.y),
                                            "yaw": float(p.yaw)})
    for o in spec.obstacles:
        lines += ["", "[[obstacle]]"] + table(_obstacle_dict(o))
    return "\n".join(lines) + "\n"


def _number(where: str, d: dict[str, Any], key: str, default: float | None = None,
            positive: bool = False) -> float:
    if key not in d:
        if default is None:
            raise ScenarioError(f"{where}: missing {key!r}")
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ScenarioError(f"{where}.{key}: expected a finite number, got {v!r}")
    if positive and v <= 0:
        raise ScenarioError(f"{where}.{key}: must be > 0, got {v!r}")
    return float(v)


def _known(where: str, d: Any, keys: set[str]) -> dict[str, Any]:
    if not isinstance(d, dict):
        raise ScenarioError(f"{where}: expected a table, got {d!r}")
    extra = sorted(set(d) - keys)
    if extra:
        raise ScenarioError(f"{where}: unknown key(s) {', '.join(extra)} (known: "
                            f"{', '.join(sorted(keys))})")
    return d


def _pose(where: str, d: Any, size: float) -> Pose2:
    d = _known(where, d, {"x", "y", "yaw"})
    p = Pose2(_number(where, d, "x"), _number(where, d, "y"), _number(where, d, "yaw", 0.0))
    if not (0 < p.x < size and 0 < p.y < size):
        raise ScenarioError(f"{where}: ({p.x}, {p.y}) is off the {size} m map")
    return p


def _obstacle(where: str, d: Any) -> Obstacle:
    d = _known(where, d, {"kind", "x", "y", "height", "radius", "half_x", "half_y", "yaw",
                          "hidden"})
    kind = d.get("kind")
    if kind not in OBSTACLE_KINDS:
        raise ScenarioError(f"{where}.kind: one of {', '.join(OBSTACLE_KINDS)}, got {kind!r}")
    hidden = d.get("hidden", False)
    if not isinstance(hidden, bool):
        raise ScenarioError(f"{where}.hidden: expected true or false, got {hidden!r}")
    common = dict(x=_number(where, d, "x"), y=_number(where, d, "y"),
                  height=_number(where, d, "height", positive=True), hidden=hidden)
    if kind == "cylinder":
        if {"half_x", "half_y", "yaw"} & set(d):
            raise ScenarioError(f"{where}: a cylinder has a radius, not half_x/half_y/yaw")
        return Obstacle("cylinder", radius=_number(where, d, "radius", positive=True), **common)
    if "radius" in d:
        raise ScenarioError(f"{where}: a box has half_x, half_y and yaw, not a radius")
    return Obstacle("box", half_x=_number(where, d, "half_x", positive=True),
                    half_y=_number(where, d, "half_y", positive=True),
                    yaw=_number(where, d, "yaw", 0.0), **common)


def parse_spec(data: dict[str, Any], where: str = "scenario", base: str = "") -> ScenarioSpec:
    """A scenario file's tables as a spec, every key checked (ScenarioError says which)."""
    d = _known(where, data, {"format", "name", "kind", "description", "size_m", "layout",
                             "generator", "terrain", "start", "goal", "obstacle"})
    fmt = d.get("format")
    if fmt != FORMAT:
        raise ScenarioError(f"{where}: format {fmt!r}; this vamppi reads format {FORMAT}")
    for key in ("name", "description"):
        if not isinstance(d.get(key), str) or not d[key]:
            raise ScenarioError(f"{where}: {key!r} must be a non-empty string")
    size = _number(where, d, "size_m", SIZE_M, positive=True)
    layout = d.get("layout", 1)
    if isinstance(layout, bool) or not isinstance(layout, int) or layout < 1:
        raise ScenarioError(f"{where}.layout: a positive integer, got {layout!r}")
    tf = {f.name: f for f in fields(Terrain)}
    t = _known(f"{where}.terrain", d.get("terrain", {}), set(tf))
    tkind = t.get("kind", "waves")
    if tkind not in TERRAIN_KINDS:
        raise ScenarioError(f"{where}.terrain.kind: one of {', '.join(TERRAIN_KINDS)}, "
                            f"got {tkind!r}")
    seed = t.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ScenarioError(f"{where}.terrain.seed: a non-negative integer, got {seed!r}")
    hm = t.get("heightmap", "")
    if tkind == "heightmap" and (not isinstance(hm, str) or not hm):
        raise ScenarioError(f"{where}.terrain: kind heightmap needs heightmap = \"FILE\"")
    terrain = Terrain(tkind, _number(f"{where}.terrain", t, "amplitude_m", 0.25), seed, hm,
                      _number(f"{where}.terrain", t, "resolution_m", 0.2, positive=True),
                      _number(f"{where}.terrain", t, "height_min_m", 0.0),
                      _number(f"{where}.terrain", t, "height_max_m", 1.0),
                      _number(f"{where}.terrain", t, "ridge_height_m", 0.0),
                      _number(f"{where}.terrain", t, "ridge_width_m", 12.0, positive=True),
                      *(_number(f"{where}.terrain", t, k, 0.0)
                        for k in ("ridge_x", "ridge_y", "ridge_yaw")))
    obstacles = d.get("obstacle", [])
    if not isinstance(obstacles, list):
        raise ScenarioError(f"{where}.obstacle: expected [[obstacle]] tables")
    gen = d.get("generator", {})
    if not isinstance(gen, dict):
        raise ScenarioError(f"{where}.generator: expected a table")
    kind = d.get("kind", "built-in")
    if not isinstance(kind, str) or not kind:
        raise ScenarioError(f"{where}.kind: a non-empty string, got {kind!r}")
    return ScenarioSpec(
        d["name"], d["description"], _pose(f"{where}.start", d.get("start"), size),
        _pose(f"{where}.goal", d.get("goal"), size),
        tuple(_obstacle(f"{where}.obstacle[{i}]", o) for i, o in enumerate(obstacles)),
        terrain, size, kind, layout, dict(gen), base)


def load_spec(path: str | Path) -> ScenarioSpec:
    """Read a scenario file (ScenarioError: missing, not TOML, or not a valid scenario)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ScenarioError(f"{path}: no such scenario file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{path}: cannot read it: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{path}: not valid TOML: {exc}") from None
    return parse_spec(data, str(path), str(path.parent))


def save_spec(spec: ScenarioSpec, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(spec_toml(spec))
    return path


# ----------------------------------------------------------------------------- built-ins
def _builtin_files() -> dict[str, dict[int, Path]]:
    """Built-in name -> layout -> file: `NAME.toml` is the newest, `NAME-layoutK.toml` older."""
    out: dict[str, dict[int, Path]] = {}
    for p in sorted(BUILTIN_DIR.glob("*.toml")):
        name, _, layout = p.stem.partition("-layout")
        spec = load_spec(p)
        out.setdefault(spec.name, {})[spec.layout] = p
        if layout and int(layout) != spec.layout:
            raise ScenarioError(f"{p}: named layout {layout}, holds layout {spec.layout}")
    return out


BUILTINS = _builtin_files() if BUILTIN_DIR.exists() else {}
SCENARIOS = tuple(BUILTINS)
# the newest layout of each built-in; older ones stay buildable, so the records of runs on
# them (which carry their layout; records without one ran on layout 1) can be replayed,
# attributed and plotted (docs/scenarios.md lists what each changed)
LAYOUTS = {name: max(files) for name, files in BUILTINS.items()}


def is_path(scenario: str) -> bool:
    """Whether `scenario` names a file rather than a built-in."""
    return scenario not in BUILTINS


def label(scenario: str) -> str:
    """A short name for file names and titles: a built-in's name, a file's stem."""
    return Path(scenario).stem if is_path(scenario) else scenario


def resolve_layout(name: str, layout: int = 0) -> int:
    """The layout number `layout` asks of scenario `name`: 0 is the newest (a file has
    one layout, its own)."""
    if is_path(name):
        if not name.endswith(".toml"):
            raise ScenarioError(f"unknown scenario {name!r}: a built-in ("
                                f"{', '.join(SCENARIOS)}) or a .toml file")
        own = load_spec(name).layout
        if layout not in (0, own):
            raise LayoutError(f"scenario {name} is layout {own}, not {layout}")
        return own
    if layout == 0:
        return LAYOUTS[name]
    if layout not in BUILTINS[name]:
        raise LayoutError(f"scenario {name!r} has layouts 1-{LAYOUTS[name]} (0 = the "
                            f"newest), not {layout}")
    return layout


def spec_of(name: str, layout: int = 0) -> ScenarioSpec:
    """The spec a scenario name (a built-in, at `layout`) or path names."""
    layout = resolve_layout(name, layout)
    return load_spec(name if is_path(name) else BUILTINS[name][layout])


# ----------------------------------------------------------------------------- building
def _centres(n: int, res: float) -> tuple[np.ndarray, np.ndarray]:
    """x and y (n, n) of the cells' centres, row 0 the southern edge."""
    c = (np.arange(n) + 0.5) * res
    return np.meshgrid(c, c, indexing="xy")


def _waves(rng: np.random.Generator, n: int, res: float, amplitude: float) -> np.ndarray:
    xx, yy = _centres(n, res)
    z = np.zeros((n, n))
    for _ in range(6):
        wavelength = rng.uniform(15.0, 60.0)
        theta = rng.uniform(0.0, math.pi)
        phase = rng.uniform(0.0, 2 * math.pi)
        k = 2 * math.pi / wavelength
        z += np.cos(k * (xx * math.cos(theta) + yy * math.sin(theta)) + phase)
    return (amplitude * z / 6.0).astype(np.float32)


def _ridge(t: Terrain, n: int, res: float) -> np.ndarray:
    """The terrain's ridge on the grid: ridge_height_m (1 + cos(2 pi d / width)) / 2 at
    distance d < width / 2 from its crest line, 0 beyond."""
    xx, yy = _centres(n, res)
    d = np.abs(-(xx - t.ridge_x) * math.sin(t.ridge_yaw) + (yy - t.ridge_y) * math.cos(t.ridge_yaw))
    z = np.where(d < t.ridge_width_m / 2,
                 0.5 * (1.0 + np.cos(2.0 * math.pi * d / t.ridge_width_m)), 0.0)
    return (t.ridge_height_m * z).astype(np.float32)


def _heightmap_file(spec: ScenarioSpec, n: int) -> np.ndarray:
    t = spec.terrain
    path = Path(spec.base or ".") / t.heightmap
    try:
        if path.suffix == ".npy":
            z = np.load(path, allow_pickle=False).astype(np.float64)
        elif path.suffix == ".png":
            import cv2
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise ScenarioError(f"{path}: not a readable image")
            if img.ndim == 3:
                img = img[..., 0]
            top = 65535.0 if img.dtype == np.uint16 else 255.0
            # image row 0 is the map's north edge (as the picture is seen)
            z = t.height_min_m + (t.height_max_m - t.height_min_m) * img[::-1] / top
        else:
            raise ScenarioError(f"{path}: a heightmap is a .npy or .png file")
    except (OSError, ValueError) as exc:
        if isinstance(exc, ScenarioError):
            raise
        raise ScenarioError(f"{path}: cannot read the heightmap: {exc}") from None
    if z.ndim != 2 or not np.all(np.isfinite(z)):
        raise ScenarioError(f"{path}: a heightmap is a 2-D array of finite heights")
    cover = (z.shape[0] * t.resolution_m, z.shape[1] * t.resolution_m)
    if not all(abs(c - spec.size_m) < 1e-6 * spec.size_m for c in cover):
        raise ScenarioError(f"{path}: {z.shape} cells of {t.resolution_m} m cover "
                            f"{cover[0]} x {cover[1]} m, the scenario is {spec.size_m} m")
    if z.shape != (n, n):
        import cv2
        z = cv2.resize(z, (n, n), interpolation=cv2.INTER_LINEAR)
    return z.astype(np.float32)


def _render(terrain: np.ndarray, res: float, obstacles: tuple[Obstacle, ...]) -> np.ndarray:
    n = terrain.shape[0]
    c = (np.arange(n) + 0.5) * res
    xx, yy = np.meshgrid(c, c, indexing="xy")
    extra = np.zeros_like(terrain)
    for ob in obstacles:
        extra = np.where(ob.contains(xx, yy), np.maximum(extra, ob.height), extra)
    return (terrain + extra).astype(np.float32)


def build(spec: ScenarioSpec, seed: int = 0, resolution: float = 0.2) -> Scenario:
    """The world on a grid of `resolution`; `seed` (episode.scenario_seed) redraws wave
    terrain."""
    n = int(round(spec.size_m / resolution))
    t = spec.terrain
    if t.kind == "waves":
        terrain = _waves(np.random.default_rng([seed, t.seed]), n, resolution, t.amplitude_m)
    elif t.kind == "flat":
        terrain = np.zeros((n, n), np.float32)
    else:
        terrain = _heightmap_file(spec, n)
    if t.ridge_height_m:
        terrain = terrain + _ridge(t, n, resolution)
    heightmap = _render(terrain, resolution, spec.obstacles)
    for a in (terrain, heightmap):
        a.setflags(write=False)           # shared: build_scenario caches the world
    return Scenario(spec.name, seed, resolution, (0.0, 0.0), terrain, heightmap,
                    spec.start, spec.goal,
                    spec.obstacles, spec.description, spec.layout, spec.kind)


@functools.lru_cache(maxsize=8)
def _built(name: str, seed: int, resolution: float, layout: int, stamp: float) -> Scenario:
    return build(spec_of(name, layout), seed, resolution)


def build_scenario(name: str, seed: int = 0, resolution: float = 0.2,
                   layout: int = 0) -> Scenario:
    """Scenario `name` (a built-in or a file's path) built on the grid (cached per file
    and its modification time)."""
    layout = resolve_layout(name, layout)
    path = Path(name) if is_path(name) else BUILTINS[name][layout]
    return _built(name, seed, resolution, layout, path.stat().st_mtime)


def scenario_of(cfg) -> Scenario:
    """The scenario a configuration names (every service builds the same one)."""
    return build_scenario(cfg.episode.scenario, cfg.episode.scenario_seed, cfg.mapper.resolution_m,
                          layout=cfg.episode.layout)
