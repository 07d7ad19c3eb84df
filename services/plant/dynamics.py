"""The paper's 3-DOF nonlinear bicycle model (Eq. dynamics), written once.

State x = [V, v, r, X, Y, Psi] (longitudinal and lateral body velocity, yaw
rate, world position, heading); control u = [delta, f_xt] (road-wheel steering
angle, longitudinal force at the CG). Aerodynamic drag, rolling resistance,
longitudinal and lateral load transfer, Ackermann steering and Pacejka lateral
tire forces (Table I). The same functions run on NumPy float64 (the plant and
the test references) and on jax.numpy float32 (the planner's prediction
model): pass `xp`.

What the paper leaves open, and how we close it (docs/dynamics.md):
- f_xt >= 0 drives; f_xt < 0 brakes, opposing motion and fading to zero at
  standstill (no reverse gear), so a braked vehicle stops and stays stopped.
- Rolling resistance fades the same way (tanh(V / eps)), drag is V|V|.
- Below `kinematic_below_mps` the lateral dynamics are those of the kinematic
  bicycle (v, r relax to their kinematic values), above `dynamic_above_mps`
  pure Pacejka, blended linearly between: the slip-angle model is singular and
  stiff as V -> 0, which the paper names as the cause of its remaining failures.
- Load transfer uses the quasi-static accelerations (no algebraic loop).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np

from common.config import VehicleConfig


class S(IntEnum):
    """State indices."""
    V = 0
    v = 1
    r = 2
    X = 3
    Y = 4
    PSI = 5


class U(IntEnum):
    """Control indices."""
    DELTA = 0
    FXT = 1


@dataclass(frozen=True)
class ControlLimits:
    lo: tuple[float, float]       # delta, f_xt
    hi: tuple[float, float]
    rate: tuple[float, float]     # per second

    @classmethod
    def from_config(cls, v: VehicleConfig) -> ControlLimits:
        return cls(lo=(-v.steer_max_rad, v.force_min_n), hi=(v.steer_max_rad, v.force_max_n),
                   rate=(v.steer_rate_max_radps, v.force_rate_max_nps))


@dataclass(frozen=True)
class Reaction:
    """How the model gets out of the way of something ahead, from its own limits: full
    braking (the brake limit over the mass; drag and rolling resistance, which only help,
    left out) after the force's ramp at its rate limit; or a swerve at the tyres' peak
    lateral acceleration (D g) after the steering's ramp, at its rate limit, to the angle
    that asks for it (the kinematic bicycle's)."""
    decel_mps2: float
    ramp_s: float
    lateral_accel_mps2: float
    wheelbase_m: float
    steer_max_rad: float
    steer_rate_radps: float

    @classmethod
    def braking_only(cls, decel_mps2: float) -> Reaction:
        """Stopping at a given deceleration, at once (no ramp), no swerve."""
        return cls(decel_mps2=decel_mps2, ramp_s=0.0, lateral_accel_mps2=0.0, wheelbase_m=1.0,
                   steer_max_rad=0.0, steer_rate_radps=1.0)

    @classmethod
    def from_config(cls, v: VehicleConfig) -> Reaction:
        return cls(decel_mps2=-v.force_min_n / v.mass_kg,
                   ramp_s=-v.force_min_n / v.force_rate_max_nps,
                   lateral_accel_mps2=v.pacejka_d * v.gravity, wheelbase_m=v.lf_m + v.lr_m,
                   steer_max_rad=v.steer_max_rad, steer_rate_radps=v.steer_rate_max_radps)

    def stopping(self, v: Any, react_s: float, xp: Any = np) -> Any:
        """Travel from speed `v` (arrays ok) to standing still on flat ground: `react_s` at
        v before the command changes, the force ramping to the brake limit, then the limit."""
        a, ramp = self.decel_mps2, max(self.ramp_s, 1e-9)      # no ramp: a vanishing one
        v = xp.maximum(v, 0.0)
        # stops during the ramp (v <= a ramp / 2): v = a t^2 / 2 ramp
        t = xp.sqrt(2.0 * v * ramp / a)
        in_ramp = v * t - a * t ** 3 / (6.0 * ramp)
        v1 = v - a * ramp / 2.0
        after = v * ramp - a * ramp ** 2 / 6.0 + v1 * v1 / (2.0 * a)
        return v * react_s + xp.where(v <= a * ramp / 2.0, in_ramp, after)

    def swerving(self, v: Any, lateral_m: float, react_s: float, xp: Any = np) -> Any:
        """Travel from speed `v` (arrays ok) while the vehicle moves `lateral_m` sideways."""
        a = self.lateral_accel_mps2
        v = xp.maximum(v, 0.0)
        steer = xp.minimum(self.steer_max_rad,
                           xp.arctan(a * self.wheelbase_m / xp.maximum(v * v, 1e-6)))
        lead = react_s + steer / self.steer_rate_radps
        return v * (lead + float(np.sqrt(2.0 * max(lateral_m, 0.0) / a)))

    def distance(self, v: Any, react_s: float, lateral_m: float, xp: Any = np) -> Any:
        """The nearer of stopping and swerving `lateral_m` aside: what still leaves room to
        react to something seen this far ahead (stopping alone without a lateral limit)."""
        if self.lateral_accel_mps2 <= 0.0:
            return self.stopping(v, react_s, xp)
        return xp.minimum(self.stopping(v, react_s, xp), self.swerving(v, lateral_m, react_s, xp))


def clamp_control(u: Any, u_prev: Any, limits: ControlLimits, dt: float, xp: Any = np) -> Any:
    """The control actually applied: within bounds and within rate * dt of `u_prev`."""
    lo, hi = xp.asarray(limits.lo), xp.asarray(limits.hi)
    step = xp.asarray(limits.rate) * dt
    return xp.clip(xp.clip(u, u_prev - step, u_prev + step), lo, hi)


def tire_lateral_force(alpha: Any, fz: Any, p: VehicleConfig, xp: Any = np) -> Any:
    """Pacejka magic formula, F_y = D Fz sin(C atan(B a - E (B a - atan(B a))))."""
    ba = p.pacejka_b * alpha
    shape = ba - p.pacejka_e * (ba - xp.arctan(ba))
    return p.pacejka_d * fz * xp.sin(p.pacejka_c * xp.arctan(shape))


def brake_fade(p: VehicleConfig, V: Any, xp: Any = np) -> Any:
    """How much of the brake (and of the rolling resistance) acts at speed V: tanh(V / eps),
    none at standstill."""
    return xp.tanh(V / p.brake_speed_eps_mps)


def effective_force(p: VehicleConfig, V: Any, f: Any, xp: Any = np) -> Any:
    """The longitudinal force f_xt has on the vehicle at speed V: drive in full, a brake as
    much as `brake_fade` lets it (a brake on a stopped vehicle is none)."""
    return xp.maximum(f, 0.0) + xp.minimum(f, 0.0) * brake_fade(p, V, xp)


def derivatives(p: VehicleConfig, x: Any, u: Any, xp: Any = np) -> Any:
    """dx/dt for states (..., 6) and controls (..., 2)."""
    V, v, r, psi = x[..., S.V], x[..., S.v], x[..., S.r], x[..., S.PSI]
    delta, f = u[..., U.DELTA], u[..., U.FXT]
    m, g, L, h, tr = p.mass_kg, p.gravity, p.lf_m + p.lr_m, p.cg_height_m, p.track_m

    # longitudinal: drive, brake (opposes motion, fades at standstill), drag, rolling
    fade = brake_fade(p, V, xp)
    f_long = effective_force(p, V, f, xp)
    drag = 0.5 * p.air_density * p.drag_coefficient * p.frontal_area_m2 * V * xp.abs(V)
    rolling = m * g * p.rolling_coefficient * fade
    ax = (f_long - drag - rolling) / m

    # quasi-static load transfer (ax without the v r term; ay ~ V r)
    ay = V * r
    fz_front = m * g * p.lr_m / L - m * ax * h / L
    fz_rear = m * g * p.lf_m / L + m * ax * h / L
    dfz_front = m * ay * h / tr * (p.lr_m / L)
    dfz_rear = m * ay * h / tr * (p.lf_m / L)
    # the four wheels, front left, front right, rear left, rear right, as one array (and the
    # two front wheels' angles as another): each element is computed as it would be alone,
    # and the tyre model is traced once instead of four times (the JAX form of the
    # rollouts 30 % faster on a CPU, docs/planner.md "Kernel forms, whole")
    fz = xp.maximum(xp.stack([fz_front / 2 - dfz_front, fz_front / 2 + dfz_front,
                              fz_rear / 2 - dfz_rear, fz_rear / 2 + dfz_rear]), 0.0)

    # Ackermann: the inner front wheel turns more
    tan_d = xp.tan(delta)
    d_front = xp.arctan2(xp.stack([L * tan_d, L * tan_d]),
                         xp.stack([L - 0.5 * tr * tan_d, L + 0.5 * tr * tan_d]))

    # slip angles at each wheel (wheel-speed floor keeps them defined at V -> 0)
    floor = p.slip_speed_floor_mps
    u_left = xp.maximum(V - 0.5 * tr * r, floor)
    u_right = xp.maximum(V + 0.5 * tr * r, floor)
    v_front, v_rear = v + p.lf_m * r, v - p.lr_m * r
    slip = xp.arctan2(xp.stack([v_front, v_front, v_rear, v_rear]),
                      xp.stack([u_left, u_right, u_left, u_right]))
    alpha = xp.stack([d_front[0] - slip[0], d_front[1] - slip[1], -slip[2], -slip[3]])
    f_lat = tire_lateral_force(alpha, fz, p, xp)
    cos_front = xp.cos(d_front)
    f_fl, f_fr = f_lat[0] * cos_front[0], f_lat[1] * cos_front[1]
    f_rl, f_rr = f_lat[2], f_lat[3]

    v_dot_dyn = (f_fl + f_fr + f_rl + f_rr) / m - V * r
    r_dot_dyn = (p.lf_m * (f_fl + f_fr) - p.lr_m * (f_rl + f_rr)) / p.yaw_inertia_kgm2

    # kinematic bicycle at low speed: v, r relax toward V lr tan(delta)/L, V tan(delta)/L
    r_kin = V * tan_d / L
    v_kin = r_kin * p.lr_m
    v_dot_kin = (v_kin - v) / p.kinematic_tau_s
    r_dot_kin = (r_kin - r) / p.kinematic_tau_s
    w = xp.clip((V - p.kinematic_below_mps) / (p.dynamic_above_mps - p.kinematic_below_mps),
                0.0, 1.0)

    V_dot = ax + v * r
    v_dot = w * v_dot_dyn + (1 - w) * v_dot_kin
    r_dot = w * r_dot_dyn + (1 - w) * r_dot_kin
    X_dot = V * xp.cos(psi) - v * xp.sin(psi)
    Y_dot = V * xp.sin(psi) + v * xp.cos(psi)
    return xp.stack([V_dot, v_dot, r_dot, X_dot, Y_dot, r], axis=-1)


def rk4_step(p: VehicleConfig, x: Any, u: Any, dt: float, xp: Any = np) -> Any:
    """One classical Runge-Kutta step with the control held."""
    k1 = derivatives(p, x, u, xp)
    k2 = derivatives(p, x + 0.5 * dt * k1, u, xp)
    k3 = derivatives(p, x + 0.5 * dt * k2, u, xp)
    k4 = derivatives(p, x + dt * k3, u, xp)
    return x + (dt / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)


def integrate(p: VehicleConfig, x: Any, u: Any, dt: float, substeps: int, xp: Any = np) -> Any:
    """Advance by `dt` in `substeps` RK4 steps, control held (heading left unwrapped)."""
    h = dt / substeps
    for _ in range(substeps):
        x = rk4_step(p, x, u, h, xp)
    return x


def accelerations(x: Any, xdot: Any, xp: Any = np) -> tuple[Any, Any, Any]:
    """(longitudinal, lateral, total) acceleration in the body frame from x and dx/dt."""
    V, v, r = x[..., S.V], x[..., S.v], x[..., S.r]
    a_x = xdot[..., S.V] - v * r
    a_y = xdot[..., S.v] + V * r
    return a_x, a_y, xp.sqrt(a_x * a_x + a_y * a_y)
