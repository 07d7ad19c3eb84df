"""Configuration: one TOML file of defaults (`defaults.toml`), frozen dataclasses.

Every parameter has exactly one default, in `defaults.toml`. The dataclasses
here declare types and valid ranges only. `load_config` merges, in order: the
defaults, an optional user TOML file, then `section.key=value` overrides; any
unknown key, wrong type or out-of-range value raises `ConfigError` naming the
key, before anything starts.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any


class ConfigError(ValueError):
    """A bad configuration value; the message names the key."""


def _rng(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
         choices: tuple[str, ...] | None = None) -> Any:
    return field(metadata={"lo": lo, "hi": hi, "lo_open": lo_open, "choices": choices})


@dataclass(frozen=True)
class EpisodeConfig:
    scenario: str = _rng()      # a built-in's name or a scenario file (common.scenarios)
    seed: int = _rng(0)
    scenario_seed: int = _rng(0)
    layout: int = _rng(0)
    clock: str = _rng(choices=("lockstep", "realtime"))
    vehicle: str = _rng()
    timeout_s: float = _rng(0.0, lo_open=True)
    goal_radius_m: float = _rng(0.0, lo_open=True)
    goal_speed_mps: float = _rng(0.0, lo_open=True)


@dataclass(frozen=True)
class VehicleConfig:
    mass_kg: float = _rng(0.0, lo_open=True)
    lf_m: float = _rng(0.0, lo_open=True)
    lr_m: float = _rng(0.0, lo_open=True)
    track_m: float = _rng(0.0, lo_open=True)
    pacejka_b: float = _rng(0.0, lo_open=True)
    pacejka_c: float = _rng(0.0, lo_open=True)
    pacejka_d: float = _rng(0.0, lo_open=True)
    pacejka_e: float = _rng()
    drag_coefficient: float = _rng(0.0)
    frontal_area_m2: float = _rng(0.0)
    air_density: float = _rng(0.0)
    rolling_coefficient: float = _rng(0.0)
    gravity: float = _rng(0.0, lo_open=True)
    cg_height_m: float = _rng(0.0)
    yaw_inertia_kgm2: float = _rng(0.0, lo_open=True)
    steer_max_rad: float = _rng(0.0, 1.5, lo_open=True)
    steer_rate_max_radps: float = _rng(0.0, lo_open=True)
    force_max_n: float = _rng(0.0, lo_open=True)
    force_min_n: float = _rng(None, 0.0)
    force_rate_max_nps: float = _rng(0.0, lo_open=True)
    kinematic_below_mps: float = _rng(0.0)
    dynamic_above_mps: float = _rng(0.0, lo_open=True)
    kinematic_tau_s: float = _rng(0.0, lo_open=True)
    slip_speed_floor_mps: float = _rng(0.0, lo_open=True)
    brake_speed_eps_mps: float = _rng(0.0, lo_open=True)
    footprint_length_m: float = _rng(0.0, lo_open=True)
    footprint_width_m: float = _rng(0.0, lo_open=True)


@dataclass(frozen=True)
class PlantConfig:
    rate_hz: float = _rng(1.0, 1000.0)
    cmd_timeout_s: float = _rng(0.0, lo_open=True)
    perception_timeout_s: float = _rng(0.0, lo_open=True)
    obstacle_height_m: float = _rng(0.0, lo_open=True)
    lockstep_wait_s: float = _rng(0.0, lo_open=True)
    reoffer_s: float = _rng(0.0, lo_open=True)
    authority: str = _rng()


@dataclass(frozen=True)
class SensorConfig:
    width_px: int = _rng(2, 4096)
    height_px: int = _rng(2, 4096)
    hfov_deg: float = _rng(1.0, 170.0)
    range_m: float = _rng(0.0, lo_open=True)
    mount_height_m: float = _rng(0.0, lo_open=True)
    mount_forward_m: float = _rng()
    mount_pitch_deg: float = _rng(-80.0, 80.0)
    rate_hz: float = _rng(0.1, 1000.0)
    march_step_m: float = _rng(0.0, 1.0, lo_open=True)
    render_kernel: str = _rng(choices=("auto", "jax", "native"))


@dataclass(frozen=True)
class MapperConfig:
    size_cells: int = _rng(8, 4096)
    resolution_m: float = _rng(0.0, lo_open=True)
    prior_variance: float = _rng(0.0, lo_open=True)
    known_radius_m: float = _rng(0.0)
    known_variance: float = _rng(0.0, lo_open=True)
    noise_sigma0_m: float = _rng(0.0, lo_open=True)
    noise_k_per_m: float = _rng(0.0)
    min_variance: float = _rng(0.0, lo_open=True)
    inpaint_radius_cells: int = _rng(1, 50)
    occluder_height_m: float = _rng(0.0)
    fill_between_pixels: bool = _rng()


@dataclass(frozen=True)
class PlannerConfig:
    controller: str = _rng(choices=("deterministic", "prescient", "va"))
    samples: int = _rng(2, 1_000_000)
    horizon: int = _rng(40, 1000)
    dt_s: float = _rng(0.0, lo_open=True)
    substeps: int = _rng(1, 100)
    iterations: int = _rng(1, 100)
    temperature: float = _rng(0.0, lo_open=True)
    noise_steer_rad: float = _rng(0.0)
    noise_force_n: float = _rng(0.0)
    noise_correlation: float = _rng(0.0, 0.999)
    brake_samples: int = _rng(0, 64)
    swerve_samples: int = _rng(0, 64)
    advance_samples: int = _rng(0, 64)
    effective_update: bool = _rng()
    rollouts_published: int = _rng(0, 1000)
    footprint_points: int = _rng(2, 64)
    footprint_arrays: int = _rng(2, 16)
    footprint_margin_m: float = _rng(0.0, 2.0)
    crash_variance: float = _rng(0.0)
    surface_distance_m: float = _rng(0.0)
    goal_distance: str = _rng(choices=("turning", "straight", "route"))
    route_cell_m: float = _rng(0.0, lo_open=True)
    route_unseen_factor: float = _rng(1.0)
    route_unseen_turn_factor: float = _rng(1.0)
    route_cap_m: float = _rng(0.0)
    route_sweeps: int = _rng(0, 10_000)
    turn_radius_speed: bool = _rng()
    stop_poses: int = _rng(0, 64)
    time_cost: str = _rng(choices=("instants", "running"))
    w_time: float = _rng(0.0)
    w_dynamic: float = _rng(0.0)
    w_surface: float = _rng(0.0)
    w_dist: float = _rng(0.0)
    w_acc: float = _rng(0.0)
    w_orientation: float = _rng(0.0)
    activation_distance_m: float = _rng(0.0)
    time_speed_floor_mps: float = _rng(0.0, lo_open=True)
    acc_distance_floor_m: float = _rng(0.0, lo_open=True)
    grad_sq_threshold: float = _rng(0.0)
    step_sq_threshold: float = _rng(0.0)
    height_threshold_m: float = _rng(0.0)
    a_roll_mps2: float = _rng(0.0, lo_open=True)
    a_max_mps2: float = _rng(0.0, lo_open=True)
    beta_max_rad: float = _rng(0.0, lo_open=True)
    v_lat_max_mps: float = _rng(0.0, lo_open=True)
    visibility_rays: int = _rng(1, 1000)
    visibility_points: int = _rng(2, 1000)
    visibility_min_m: float = _rng(0.0)
    visibility_max_m: float = _rng(0.0, lo_open=True)
    visibility_height_m: float = _rng(0.0)
    visibility_lag_steps: int = _rng(1, 1000)
    visibility_in_time: bool = _rng()
    visibility_stop_decel_mps2: float = _rng(0.0)
    count_value: float = _rng(0.0)
    splat_size: int = _rng(1, 99)
    splat_sigma_cells: float = _rng(0.0, lo_open=True)
    decay_gamma: float = _rng(0.0)
    va_chunk: int = _rng(0, 1_000_000)
    va_kernel: str = _rng(choices=("auto", "jax", "native"))
    va_threads: int = _rng(0, 1024)
    rollout_kernel: str = _rng(choices=("auto", "jax", "native"))
    surface_estimator: str = _rng(choices=("closed_form", "monte_carlo"))
    surface_samples: int = _rng(1, 1_000_000)


@dataclass(frozen=True)
class BusConfig:
    mode: str = _rng(choices=("peer", "client", "router"))
    connect: tuple[str, ...] = _rng()
    listen: tuple[str, ...] = _rng()
    multicast_scouting: bool = _rng()
    # mutual TLS (common.security): "" is plain TCP; the other two have defaults here too,
    # so that a router's or a test's BusConfig can be built without them
    certs: str = field(default="", metadata={**_rng().metadata, "empty": True})
    identity: str = field(default="", metadata={**_rng().metadata, "empty": True})
    credentials: str = field(default="", metadata={**_rng().metadata, "empty": True})
    zenoh: str = field(default="", metadata={**_rng().metadata, "empty": True})


@dataclass(frozen=True)
class SupervisionConfig:
    heartbeat_period_s: float = _rng(0.0, lo_open=True)
    heartbeat_deadline_s: float = _rng(0.0, lo_open=True)
    planner_deadline_s: float = _rng(0.0, lo_open=True)
    restarts: int = _rng(0, 100)


@dataclass(frozen=True)
class Config:
    episode: EpisodeConfig
    vehicle: VehicleConfig
    plant: PlantConfig
    sensor: SensorConfig
    mapper: MapperConfig
    planner: PlannerConfig
    bus: BusConfig
    supervision: SupervisionConfig

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return {s.name: {k: (list(v) if isinstance(v, tuple) else v)
                         for k, v in dataclasses.asdict(getattr(self, s.name)).items()}
                for s in dataclasses.fields(self)}

    def replace(self, **overrides: Any) -> Config:
        """`cfg.replace(**{"planner.samples": 400})`, validated like the CLI."""
        return config_from_dict(_merge(self.to_dict(), _dotted(overrides)))


_SECTION_TYPES = {
    "episode": EpisodeConfig, "vehicle": VehicleConfig, "plant": PlantConfig,
    "sensor": SensorConfig, "mapper": MapperConfig, "planner": PlannerConfig, "bus": BusConfig,
    "supervision": SupervisionConfig,
}


def default_dict() -> dict[str, dict[str, Any]]:
    text = resources.files("common").joinpath("defaults.toml").read_text()
    return tomllib.loads(text)


def _merge(base: dict, extra: dict) -> dict:
    out = {k: dict(v) for k, v in base.items()}
    for section, values in extra.items():
        if section not in out:
            raise ConfigError(f"unknown config section [{section}]")
        if not isinstance(values, dict):
            raise ConfigError(f"config section [{section}] must be a table")
        for key, value in values.items():
            if key not in out[section]:
                raise ConfigError(f"unknown config key {section}.{key}")
            out[section][key] = value
    return out


def _dotted(pairs: dict[str, Any]) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for dotted, value in pairs.items():
        if dotted.count(".") != 1:
            raise ConfigError(f"override {dotted!r} must look like section.key")
        section, key = dotted.split(".")
        out.setdefault(section, {})[key] = value
    return out


def parse_override(text: str) -> tuple[str, Any]:
    """`planner.samples=400` -> ("planner.samples", 400); the value is read as TOML,
    and a bare word that is not TOML is taken as a string."""
    if "=" not in text:
        raise ConfigError(f"override {text!r} must look like section.key=value")
    key, raw = text.split("=", 1)
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    return key.strip(), value


def _check_value(section: str, f: dataclasses.Field, value: Any) -> Any:
    name = f"{section}.{f.name}"
    meta = f.metadata
    typ = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
    if typ == "bool":
        if not isinstance(value, bool):
            raise ConfigError(f"{name} must be true or false, got {value!r}")
        return value
    if typ == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{name} must be an integer, got {value!r}")
    elif typ == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{name} must be a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f"{name} must be finite, got {value!r}")
    elif typ == "str":
        if not isinstance(value, str) or not (value or meta.get("empty")):
            raise ConfigError(f"{name} must be a non-empty string, got {value!r}")
        if meta["choices"] and value not in meta["choices"]:
            raise ConfigError(f"{name} must be one of {', '.join(meta['choices'])}; got {value!r}")
        return value
    elif typ.startswith("tuple"):
        if isinstance(value, str):
            value = [value] if value else []
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"{name} must be a list of strings, got {value!r}")
        return tuple(value)
    lo, hi = meta["lo"], meta["hi"]
    if lo is not None and (value < lo or (meta["lo_open"] and value == lo)):
        raise ConfigError(f"{name} must be {'>' if meta['lo_open'] else '>='} {lo}, got {value!r}")
    if hi is not None and value > hi:
        raise ConfigError(f"{name} must be <= {hi}, got {value!r}")
    return value


def config_from_dict(data: dict[str, dict[str, Any]]) -> Config:
    sections = {}
    for section, cls in _SECTION_TYPES.items():
        values = data.get(section, {})
        kwargs = {}
        for f in dataclasses.fields(cls):
            if f.name not in values:
                raise ConfigError(f"missing config key {section}.{f.name}")
            kwargs[f.name] = _check_value(section, f, values[f.name])
        sections[section] = cls(**kwargs)
    cfg = Config(**sections)
    _check_cross(cfg)
    return cfg


def _check_cross(cfg: Config) -> None:
    from common.scenarios import LayoutError, resolve_layout
    try:
        resolve_layout(cfg.episode.scenario, cfg.episode.layout)
    except LayoutError as exc:
        raise ConfigError(f"episode.layout: {exc}") from None
    except ValueError as exc:
        raise ConfigError(f"episode.scenario: {exc}") from None
    v, p = cfg.vehicle, cfg.planner
    if v.dynamic_above_mps <= v.kinematic_below_mps:
        raise ConfigError("vehicle.dynamic_above_mps must exceed vehicle.kinematic_below_mps")
    if p.splat_size % 2 != 1:
        raise ConfigError("planner.splat_size must be odd (a kernel centred on its cell)")
    m = cfg.mapper
    if not m.known_variance < m.prior_variance or not m.min_variance < m.prior_variance:
        raise ConfigError("mapper.known_variance and mapper.min_variance must be below "
                          "mapper.prior_variance (an observed cell is one below the prior)")
    sv = cfg.supervision
    if sv.heartbeat_deadline_s <= sv.heartbeat_period_s:
        raise ConfigError("supervision.heartbeat_deadline_s must exceed "
                          "supervision.heartbeat_period_s")
    if p.visibility_max_m <= p.visibility_min_m:
        raise ConfigError("planner.visibility_max_m must exceed planner.visibility_min_m")
    b = cfg.bus
    if b.mode == "peer" and not b.listen and not b.multicast_scouting:
        raise ConfigError("bus.mode=peer needs bus.listen endpoints (or multicast scouting): a "
                          "peer that does not listen cannot reach other peers through a router; "
                          "use bus.mode=client to go through the router")
    ticks = p.dt_s * cfg.plant.rate_hz
    if abs(ticks - round(ticks)) > 1e-9:
        raise ConfigError("planner.dt_s * plant.rate_hz must be a whole number of plant steps")
    if p.horizon * p.dt_s < 4.0 - 1e-9:
        raise ConfigError("planner.horizon * planner.dt_s must cover the 4 s of Eq. time_cost")
    cells = p.route_cell_m / m.resolution_m
    if p.goal_distance == "route" and (abs(cells - round(cells)) > 1e-6
                                       or m.size_cells % round(cells)):
        raise ConfigError("planner.route_cell_m must be a whole number of mapper.resolution_m "
                          "that divides mapper.size_cells (a lattice cell is a block of map cells)")


def load_config(path: str | Path | None = None, overrides: list[str] | dict[str, Any] | None = None,
                base: Config | None = None) -> Config:
    """Defaults (or the configuration `base`), then the TOML file at `path`, then
    `section.key=value` overrides."""
    data = base.to_dict() if base is not None else default_dict()
    if path is not None:
        try:
            user = tomllib.loads(Path(path).read_text())
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise ConfigError(f"cannot read config file {path}: {exc}") from exc
        data = _merge(data, user)
    if overrides:
        pairs = overrides if isinstance(overrides, dict) else dict(
            parse_override(o) for o in overrides)
        data = _merge(data, _dotted(pairs))
    return config_from_dict(data)


PRESETS_DIR = Path(__file__).with_name("presets")


def presets() -> list[str]:
    return sorted(p.stem for p in PRESETS_DIR.glob("*.toml"))


def preset_overrides(name: str) -> list[str]:
    """A preset's parameters (common/presets/NAME.toml) as section.key=value overrides."""
    path = PRESETS_DIR / f"{name}.toml"
    if not path.exists():
        raise ConfigError(f"unknown preset {name!r}; choose one of {', '.join(presets())}")
    data = tomllib.loads(path.read_text())
    defaults = default_dict()
    out = []
    for section, values in data.items():
        for key, value in values.items():
            if key not in defaults.get(section, {}):
                raise ConfigError(f"preset {name}: unknown parameter {section}.{key}")
            out.append(f"{section}.{key}={json.dumps(value)}")
    return out


def by_name(cls: type, *sections: Any, **derived: Any) -> Any:
    """An instance of the frozen dataclass `cls` (a core's parameters) whose fields are
    config keys of `sections` under the same names, the first section that has one
    winning; `derived` gives the fields computed from other keys, or a key's value made
    effective (a count clamped to what the others leave); each must be a field."""
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(derived) - set(names))
    if unknown:
        raise TypeError(f"{cls.__name__} has no field {', '.join(unknown)}")
    keys = {f.name: s for s in reversed(sections) for f in dataclasses.fields(s)}
    missing = [n for n in names if n not in derived and n not in keys]
    if missing:
        raise TypeError(f"{cls.__name__}: no config key and no value for {', '.join(missing)}")
    return cls(**{n: derived[n] if n in derived else getattr(keys[n], n) for n in names})


def as_overrides(cfg: Config, skip: tuple[str, ...] = ()) -> list[str]:
    """The `section.key=value` overrides that turn the defaults into `cfg` (sections in
    `skip` left out): a configuration handed to another process on its command line."""
    defaults = config_from_dict(default_dict()).to_dict()
    return [f"{section}.{key}={json.dumps(value)}"
            for section, values in cfg.to_dict().items() if section not in skip
            for key, value in values.items() if value != defaults[section][key]]


def parameters_markdown() -> str:
    """docs/parameters.md, generated from defaults.toml: every key, its default, its comment."""
    text = resources.files("common").joinpath("defaults.toml").read_text()
    out = ["# Parameters", "",
           "Generated from `common/defaults.toml` by `vamppi config --markdown`; every",
           "parameter has this one default. (Table I) / (Table II) / (text) mark the paper's",
           "values; the choices behind the others are in dynamics.md, sensor.md, mapper.md,",
           "planner.md and scenarios.md. Override with `--config FILE` or",
           "`--set section.key=value`.", ""]
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("[") and line.endswith("]"):
            out += ["", f"## {line[1:-1]}", "", "| key | default | meaning |", "|---|---|---|"]
        elif line and not line.startswith("#") and "=" in line:
            key, rest = line.split("=", 1)
            value, _, comment = rest.partition("#")
            meaning = comment.strip().replace("|", "\\|")
            out.append(f"| `{key.strip()}` | `{value.strip()}` | {meaning} |")
    return "\n".join(out) + "\n"


def config_toml(cfg: Config) -> str:
    """The whole configuration as a TOML file `load_config` reads back to an equal Config
    (a recording's config, handed to services it feeds)."""
    lines = []
    for section, values in cfg.to_dict().items():
        lines.append(f"[{section}]")
        lines += [f"{key} = {json.dumps(value)}" for key, value in values.items()]
        lines.append("")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- agreement
# What every service of one vehicle must run with alike: the episode's rules and clock,
# the vehicle the planner predicts and the plant simulates, the supervision's timings.
# (The world itself, scenario and layout, is compared by its digest: common.bus.Node.)
AGREE: dict[str, tuple[str, ...] | None] = {
    "episode": ("scenario", "scenario_seed", "layout", "clock", "timeout_s", "goal_radius_m",
                "goal_speed_mps"),
    "vehicle": None,                     # None: every key of the section
    "supervision": None,
}


def agreement(cfg_dict: dict[str, Any]) -> dict[str, Any]:
    """The `AGREE` part of a configuration (as `Config.to_dict` gives it), by dotted key."""
    out = {}
    for section, keys in AGREE.items():
        values = cfg_dict.get(section, {})
        for key in sorted(values) if keys is None else keys:
            if key in values:
                out[f"{section}.{key}"] = values[key]
    return out


def agreement_digest(cfg_dict: dict[str, Any]) -> str:
    """A short digest of `agreement(cfg_dict)`: equal digests, equal agreement."""
    import hashlib
    text = json.dumps(agreement(cfg_dict), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def disagreements(mine: dict[str, Any], theirs: dict[str, Any]) -> list[str]:
    """`key: mine vs theirs` for each `AGREE` key two configurations differ on."""
    a, b = agreement(mine), agreement(theirs)
    return [f"{k}: {a.get(k)!r} vs {b.get(k)!r}" for k in sorted(set(a) | set(b))
            if a.get(k) != b.get(k)]
