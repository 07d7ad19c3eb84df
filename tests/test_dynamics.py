"""The bicycle model against analytic results (float64 NumPy, the plant's own path)."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from common.config import load_config
from services.plant.dynamics import S, derivatives, integrate

CFG = load_config()
P = CFG.vehicle
DT = 1.0 / CFG.plant.rate_hz


def simulate(x, u, seconds):
    for _ in range(int(round(seconds / DT))):
        x = integrate(P, x, u, DT, 1)
    return x


def test_steady_state_cornering_matches_the_linear_bicycle_model():
    V, delta = 10.0, 0.01
    L = P.lf_m + P.lr_m
    bcd = P.pacejka_b * P.pacejka_c * P.pacejka_d
    m, g = P.mass_kg, P.gravity
    cf = bcd * m * g * P.lr_m / L          # axle cornering stiffness: 2 tires x B C D Fz
    cr = bcd * m * g * P.lf_m / L
    # v_dot = r_dot = 0 of the linear model:
    # alpha_f = delta - (v + lf r) / V, alpha_r = -(v - lr r) / V
    a = np.array([[-(cf + cr) / (m * V), -(P.lf_m * cf - P.lr_m * cr) / (m * V) - V],
                  [-(P.lf_m * cf - P.lr_m * cr) / (P.yaw_inertia_kgm2 * V),
                   -(P.lf_m ** 2 * cf + P.lr_m ** 2 * cr) / (P.yaw_inertia_kgm2 * V)]])
    b = -np.array([cf / m, P.lf_m * cf / P.yaw_inertia_kgm2]) * delta
    v_ss, r_ss = np.linalg.solve(a, b)
    drag = 0.5 * P.air_density * P.drag_coefficient * P.frontal_area_m2 * V * V
    force = drag + m * g * P.rolling_coefficient * math.tanh(V / P.brake_speed_eps_mps)
    x = simulate(np.array([V, 0, 0, 0, 0, 0.0]), np.array([delta, force]), 8.0)
    assert abs(x[S.V] - V) < 0.01
    assert x[S.r] == pytest.approx(r_ss, rel=0.01)
    assert x[S.v] == pytest.approx(v_ss, rel=0.02, abs=1e-4)


def test_straight_coast_down_matches_integrated_drag_and_rolling_resistance():
    v0 = 20.0
    a = P.gravity * P.rolling_coefficient
    b = 0.5 * P.air_density * P.drag_coefficient * P.frontal_area_m2 / P.mass_kg
    x = np.array([v0, 0, 0, 0, 0, 0.0])
    t = 0.0
    while x[S.V] > 3.0:       # above ~15 eps the fade of rolling resistance is 1 to 1e-12
        x = integrate(P, x, np.zeros(2), DT, 1)
        t += DT
        exact = math.sqrt(a / b) * math.tan(math.atan(v0 * math.sqrt(b / a)) - math.sqrt(a * b) * t)
        assert x[S.V] == pytest.approx(exact, rel=1e-7)
    assert x[S.v] == 0 and x[S.r] == 0 and x[S.Y] == 0


@pytest.mark.parametrize("u", [(0.0, 0.0), (0.4, 0.0), (-0.3, -6000.0), (0.5, -100.0)])
def test_standing_still_stays_still(u):
    x0 = np.array([0, 0, 0, 12.0, 34.0, 0.7])
    x = simulate(x0.copy(), np.array(u), 10.0)
    np.testing.assert_array_equal(x, x0)


def test_braking_stops_without_reversing_and_stays_stopped():
    x = np.array([8.0, 0, 0, 0, 0, 0.0])
    speeds = []
    for _ in range(int(10 / DT)):
        x = integrate(P, x, np.array([0.2, -6000.0]), DT, 1)
        speeds.append(x[S.V])
    assert min(speeds) > -1e-9
    assert speeds[-1] < 1e-3 and abs(x[S.r]) < 1e-3 and abs(x[S.v]) < 1e-3


def test_low_speed_turning_is_well_behaved():
    L = P.lf_m + P.lr_m
    x = np.array([0.0, 0, 0, 0, 0, 0.0])
    for _ in range(int(20 / DT)):
        x = integrate(P, x, np.array([0.4, 60.0]), DT, 1)
        assert np.isfinite(x).all()
        assert abs(x[S.v]) < 1.0
    assert 0.0 < x[S.V] < 1.5
    assert x[S.r] == pytest.approx(x[S.V] * math.tan(0.4) / L, rel=0.05)


def test_jax_float32_agrees_with_numpy_float64(rng):
    n = 256
    x = np.stack([rng.uniform(0, 20, n), rng.uniform(-1, 1, n), rng.uniform(-0.5, 0.5, n),
                  rng.uniform(0, 80, n), rng.uniform(0, 80, n), rng.uniform(-3, 3, n)], -1)
    u = np.stack([rng.uniform(-0.6, 0.6, n), rng.uniform(-6000, 5000, n)], -1)
    ref = derivatives(P, x, u)
    got = np.asarray(derivatives(P, jnp.asarray(x, jnp.float32), jnp.asarray(u, jnp.float32),
                                 jnp))
    scale = np.maximum(np.abs(ref), 1.0)
    assert np.isfinite(got).all()
    assert np.max(np.abs(got - ref) / scale) < 2e-3


@pytest.mark.parametrize("v", [4.0, 6.0, 8.0, 10.0])
def test_the_reaction_swerve_is_what_the_plant_model_does_within_a_quarter(v):
    """`Reaction.swerving` (constant peak lateral acceleration after the steering ramp)
    against the plant's own model, steered at the rate limit to that angle after one tick:
    the sideways move over the claimed distance is 2 m within a quarter (the model's slip
    builds up with a lag, so at 10 m/s it moves 1.5 m; at 4 m/s 2.9 m)."""
    import math

    from services.plant.dynamics import ControlLimits, Reaction, clamp_control, integrate
    cfg = load_config()
    veh, react = cfg.vehicle, Reaction.from_config(cfg.vehicle)
    lim = ControlLimits.from_config(veh)
    d = float(react.swerving(v, 2.0, cfg.planner.dt_s))
    steer = min(veh.steer_max_rad, math.atan(react.lateral_accel_mps2 * react.wheelbase_m / v ** 2))
    x, u, t, dt = np.array([v, 0, 0, 0, 0, 0.0]), np.zeros(2), 0.0, 0.02
    while x[S.X] < d:
        u = clamp_control(np.array([0.0 if t < cfg.planner.dt_s else steer, 800.0]), u, lim, dt)
        x, t = integrate(veh, x, u, dt, 2), t + dt
    assert 0.74 * 2.0 <= x[S.Y] <= 1.46 * 2.0
    assert float(react.stopping(v, 0.1)) == pytest.approx(
        float(Reaction.from_config(veh).distance(v, 0.1, 1e9)))     # no swerve that far
