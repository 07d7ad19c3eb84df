"""The plant's pure core: the vehicle in the scenario's world, stepped at 50 Hz.

`plant_step(params, state, u_cmd) -> state` applies a commanded control
(rate- and bound-limited like a real actuator), integrates the bicycle model
over one plant period, and judges the episode: collision of the footprint with
a ground-truth obstacle, success (within `goal_radius_m` of the goal and
slower than `goal_speed_mps`), timeout (`stopping` when the vehicle had reached
the goal region but never met the speed criterion, else `timeout`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from common.config import Config, VehicleConfig, by_name
from common.geometry import bilinear, body_to_world, cell_of, footprint_grid
from common.scenarios import Scenario
from services.plant.dynamics import ControlLimits, S, clamp_control, integrate

OUTCOMES = ("success", "collision", "stopping", "timeout")


@dataclass(frozen=True)
class PlantParams:
    vehicle: VehicleConfig
    limits: ControlLimits
    dt: float                          # plant period, s (1 / rate_hz)
    steps_per_tick: int                # plant steps per control tick
    tick_s: float                      # control tick, s (planner.dt_s)
    timeout_s: float
    goal_radius_m: float
    goal_speed_mps: float
    scenario: Scenario
    obstacle_mask: np.ndarray          # (H, W) bool
    footprint: np.ndarray              # (P, 2) body-frame points filling the footprint

    @classmethod
    def from_config(cls, cfg: Config, scenario: Scenario) -> PlantParams:
        v = cfg.vehicle
        return by_name(cls, cfg.episode, vehicle=v, limits=ControlLimits.from_config(v),
                       dt=1.0 / cfg.plant.rate_hz,
                       steps_per_tick=int(round(cfg.planner.dt_s * cfg.plant.rate_hz)),
                       tick_s=cfg.planner.dt_s, scenario=scenario,
                       obstacle_mask=scenario.obstacle_mask(cfg.plant.obstacle_height_m),
                       footprint=footprint_grid(v.footprint_length_m, v.footprint_width_m, 0.1))


@dataclass(frozen=True)
class PlantState:
    t: float                           # simulation time, s
    step: int                          # plant steps since the start
    x: np.ndarray                      # (6,) float64, services.plant.dynamics.S
    u_applied: np.ndarray              # (2,) float64
    reached_goal_region: bool = False
    outcome: str = ""                  # "" while running, else one of OUTCOMES
    time_to_goal_s: float = math.nan

    @property
    def done(self) -> bool:
        return bool(self.outcome)


def tick_of(params: PlantParams, state: PlantState) -> int:
    """Control ticks elapsed (a state on a tick boundary has step % steps_per_tick == 0)."""
    return state.step // params.steps_per_tick


def initial_state(params: PlantParams) -> PlantState:
    s = params.scenario.start
    x = np.zeros(6)
    x[S.X], x[S.Y], x[S.PSI] = s.x, s.y, s.yaw
    return PlantState(0.0, 0, x, np.zeros(2))


def ground_z(params: PlantParams, x: float, y: float) -> float:
    sc = params.scenario
    return float(bilinear(sc.terrain, np.float64(x), np.float64(y), sc.origin, sc.resolution))


def _footprint_cells(params: PlantParams, x: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cells (row, col) of the footprint points at state x, and which are on the map."""
    wx, wy = body_to_world(params.footprint, x[S.X], x[S.Y], x[S.PSI])
    sc = params.scenario
    row, col = cell_of(wx, wy, sc.origin, sc.resolution)
    h, w = params.obstacle_mask.shape
    return row, col, (row >= 0) & (row < h) & (col >= 0) & (col < w)


def collides(params: PlantParams, x: np.ndarray) -> bool:
    """Any footprint point on an obstacle cell, or off the map."""
    row, col, inside = _footprint_cells(params, x)
    if not inside.all():
        return True
    return bool(params.obstacle_mask[row, col].any())


@dataclass(frozen=True)
class Collision:
    """What the footprint of a colliding pose is on: the scenario's obstacles (indices into
    `scenario.obstacles`) under it, and whether part of it is off the map."""
    obstacles: tuple[int, ...]
    off_map: bool


def collision_of(params: PlantParams, x: np.ndarray) -> Collision | None:
    """What the footprint at state x is on; None where it is on neither an obstacle cell nor
    off the map (`collides` false)."""
    row, col, inside = _footprint_cells(params, x)
    row, col = row[inside], col[inside]
    hit = params.obstacle_mask[row, col]
    if inside.all() and not hit.any():
        return None
    return Collision(params.scenario.obstacles_at(row[hit], col[hit]), not bool(inside.all()))


def collision_text(params: PlantParams, x: np.ndarray) -> str:
    """What the footprint at x is on, for a log line or an event: `index:kind(x,y)` for each
    obstacle (`+hidden` where it is one) and `off-map`, comma-separated; "" if nothing."""
    hit = collision_of(params, x)
    if hit is None:
        return ""
    obs = params.scenario.obstacles
    return ",".join([f"{i}:{obs[i].kind}({obs[i].x:g},{obs[i].y:g})"
                     + ("+hidden" if obs[i].hidden else "") for i in hit.obstacles]
                    + (["off-map"] if hit.off_map else []))


def goal_distance(params: PlantParams, x: np.ndarray) -> float:
    g = params.scenario.goal
    return math.hypot(x[S.X] - g.x, x[S.Y] - g.y)


def judge(params: PlantParams, state: PlantState) -> PlantState:
    """The episode's outcome after a step, if it ended."""
    x = state.x
    if collides(params, x):
        return replace(state, outcome="collision")
    in_region = goal_distance(params, x) <= params.goal_radius_m
    reached = state.reached_goal_region or in_region
    if in_region and math.hypot(x[S.V], x[S.v]) < params.goal_speed_mps:
        return replace(state, reached_goal_region=True, outcome="success",
                       time_to_goal_s=state.t)
    if state.t >= params.timeout_s - 1e-9:
        return replace(state, reached_goal_region=reached,
                       outcome="stopping" if reached else "timeout")
    return replace(state, reached_goal_region=reached)


def plant_step(params: PlantParams, state: PlantState, u_cmd: np.ndarray) -> PlantState:
    """One plant period with the commanded control; judged afterwards."""
    if state.done:
        return state
    u = clamp_control(np.asarray(u_cmd, dtype=np.float64), state.u_applied, params.limits,
                      params.dt)
    x = integrate(params.vehicle, state.x, u, params.dt, 1)
    step = state.step + 1
    nxt = replace(state, t=step * params.dt, step=step, x=x, u_applied=u)
    return judge(params, nxt)


def brake_control(params: PlantParams, state: PlantState) -> np.ndarray:
    """What the plant applies without a fresh command: hold steering, full brake."""
    return np.array([state.u_applied[0], params.limits.lo[1]])


def control_at(t: float, t0: float, dt: float, controls: np.ndarray) -> np.ndarray | None:
    """The entry of a timed control sequence that applies at time t, or None if outside it."""
    i = int(math.floor((t - t0) / dt + 1e-9))
    if i < 0 or i >= len(controls):
        return None
    return np.asarray(controls[i], dtype=np.float64)
