"""`vamppi plans` (deploy/analysis/plans.py): the plan at one instant priced beside the same
plan carried out sooner."""

import numpy as np
import pytest

from common.config import load_config
from deploy.analysis.plans import plans, table, variants
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
