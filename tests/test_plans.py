"""`vamppi plans` (deploy/analysis/plans.py): the plan at one instant priced beside the same
plan carried out sooner."""

import numpy as np
import pytest

from common.config import load_config
from deploy.analysis.plans import plans, steady_plans, table, variants
from services.planner.costs import TERMS


def test_variants_are_the_plan_sooner_its_last_control_held_then_coasting_or_braking(rng):
    nominal = rng.normal(size=(40, 2)).astype(np.float32)
    named = dict(variants(nominal, -6000.0, shifts=(1, 3), tails=(10,)))
    assert list(named) == ["nominal", "1 sooner", "1 sooner, coasting from 10",
                           "1 sooner, braking from 10", "3 sooner", "3 sooner, coasting from 10",
                           "3 sooner, braking from 10"]
    np.testing.assert_array_equal(named["nominal"], nominal)
    three = named["3 sooner"]
    np.testing.assert_array_equal(three[:37], nominal[3:])
    np.testing.assert_array_equal(three[37:], np.repeat(nominal[-1:], 3, axis=0))
    for what, force in (("coasting", 0.0), ("braking", -6000.0)):
        v = named[f"3 sooner, {what} from 10"]
        np.testing.assert_array_equal(v[:, 0], three[:, 0])          # the steering stays
        np.testing.assert_array_equal(v[:10, 1], three[:10, 1])
        assert (v[10:, 1] == force).all()


def test_steady_plans_hold_each_steering_with_each_force_or_brake_first():
    lo, hi = np.array([-0.6, -6000.0]), np.array([0.6, 5000.0])
    named = dict(steady_plans(40, lo, hi, steers=(-1.0, 0.5), forces=("brake", 0.0, 0.5),
                              brake_steps=(10,)))
    assert list(named) == ["steer -1.00, braking", "steer +0.50, braking",
                           "steer -1.00, coasting", "steer +0.50, coasting",
                           "steer -1.00, force 2500 N", "steer +0.50, force 2500 N",
                           "brake 10 steps, then steer -1.00", "brake 10 steps, then steer +0.50"]
    u = named["steer +0.50, force 2500 N"]
    assert u.shape == (40, 2) and (u[:, 0] == np.float32(0.3)).all() and (u[:, 1] == 2500).all()
    assert (named["steer -1.00, braking"][:, 1] == -6000).all()
    b = named["brake 10 steps, then steer -1.00"]
    assert (b[:10] == [0.0, -6000.0]).all() and (b[10:] == [np.float32(-0.6), 0.0]).all()


def test_steady_plans_and_a_second_configuration_price_the_same_state():
    """With `steady` the hand-made plans join the rows; with a second configuration that
    doubles w_time every plan's time term doubles and nothing else moves: the same
    rollouts, priced again on the same map."""
    cfg = load_config(overrides=['episode.scenario="alleyway"', 'planner.controller="va"',
                                 "planner.samples=64"])
    alt = load_config(overrides=[f"planner.w_time={2 * cfg.planner.w_time}"], base=cfg)
    rows = plans(cfg, 1.0, shifts=(2,), tails=(20,), steady=True, alt=alt)
    names = [r["plan"] for r in rows]
    assert "steer +1.00, braking" in names and "brake 15 steps, then steer -0.50" in names
    for r in rows[1:]:
        np.testing.assert_allclose(r["alt"]["time"], 2.0 * r["time"], rtol=1e-6)
        np.testing.assert_allclose([r["alt"][t] for t in TERMS if t != "time"],
                                   [r[t] for t in TERMS if t != "time"], rtol=1e-6, atol=1e-6)
        assert 0.0 <= r["to_goal_nearest_m"] <= r["to_goal_end_m"]
    by = {r["plan"]: r for r in rows}
    assert by["steer +0.00, braking"]["moved_m"] < by["steer +0.00, force 2500 N"]["moved_m"]
    text = table(rows, limit=3)
    assert "total, second config" in text and len(text.splitlines()) == 2 + 2 + 2 + 3


@pytest.mark.parametrize("controller", ["va", "prescient"])
def test_the_plan_is_priced_as_the_solver_priced_it(controller):
    """At 1 s of an alleyway episode (K = 64) the plan the planner sent, priced again, costs
    what the planner reported for it: equal here. (Where a surface cost is paid the two may
    differ by float32 rounding: the solve prices its plan with the JAX form of the expected
    surface cost, `mppi.price` with the kernel form its samples get.) With the route the
    goal distance depends on the map: the prescient controller's plan is priced on the true
    map it planned on (the hidden cylinder in its way), not the mapper's."""
    cfg = load_config(overrides=['episode.scenario="alleyway"',
                                 f'planner.controller="{controller}"', "planner.samples=64",
                                 'planner.goal_distance="route"'])
    rows = plans(cfg, 1.0, shifts=(2,), tails=(20,))
    assert [r["plan"] for r in rows] == ["solver", "nominal", "2 sooner",
                                         "2 sooner, coasting from 20", "2 sooner, braking from 20"]
    solver, nominal = rows[0], rows[1]
    assert solver["t_s"] == pytest.approx(1.0)
    np.testing.assert_allclose([nominal[t] for t in TERMS], [solver[t] for t in TERMS],
                               rtol=1e-6, atol=1e-6)
    assert nominal["moved_m"] > 0 and len(nominal["speed_2_3_4_s"]) == 3
    assert "| nominal |" in table(rows)
