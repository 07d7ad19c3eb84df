import math
from dataclasses import replace

import numpy as np

from common.config import load_config
from common.scenarios import build_scenario
from services.plant import core
from services.plant.dynamics import S


def params(**over):
    cfg = load_config(overrides=[f"{k}={v}" for k, v in over.items()])
    return core.PlantParams.from_config(cfg, build_scenario("open-field", 0))


def at(p, x, y, yaw=0.0, V=0.0, t=0.0):
    s = core.initial_state(p)
    xx = s.x.copy()
    xx[S.X], xx[S.Y], xx[S.PSI], xx[S.V] = x, y, yaw, V
    return replace(s, x=xx, t=t)


def test_scenarios_are_deterministic_and_sized():
    a, b = build_scenario("alleyway", 3), build_scenario("alleyway", 3)
    assert a.heightmap.shape == (400, 400) and a.heightmap.dtype == np.float32
    assert a.heightmap.tobytes() == b.heightmap.tobytes()
    assert build_scenario("alleyway", 4).heightmap.tobytes() != a.heightmap.tobytes()
    for name in ("open-field", "alleyway", "offroad"):
        s = build_scenario(name, 0)
        p = core.PlantParams.from_config(load_config(), s)
        assert not core.collides(p, at(p, s.start.x, s.start.y, s.start.yaw).x)
        assert not core.collides(p, at(p, s.goal.x, s.goal.y, s.goal.yaw).x)


def test_collision_with_an_obstacle_and_the_map_edge():
    p = params()
    rock = p.scenario.obstacles[0]
    # the footprint's front edge 0.1 m inside the rock
    x = rock.x - rock.radius - p.vehicle.footprint_length_m / 2 + 0.1
    assert core.judge(p, at(p, x, rock.y)).outcome == "collision"
    assert core.judge(p, at(p, x - 0.4, rock.y)).outcome == ""
    assert core.judge(p, at(p, 0.5, 40.0)).outcome == "collision"


def test_collision_names_what_the_footprint_is_on():
    p = params()
    rock = p.scenario.obstacles[0]
    x = rock.x - rock.radius - p.vehicle.footprint_length_m / 2 + 0.1
    assert core.collision_of(p, at(p, x, rock.y).x) == core.Collision((0,), False)
    assert core.collision_of(p, at(p, x - 0.4, rock.y).x) is None
    assert core.collision_of(p, at(p, 0.5, 40.0).x) == core.Collision((), True)
    # offroad layout 1: across the 1.8 m between the first hidden obstacle and the first rock
    off = core.PlantParams.from_config(load_config(), build_scenario("offroad", 0, layout=1))
    obs = off.scenario.obstacles
    hidden = next(i for i, o in enumerate(obs) if o.hidden)
    first_rock = min((i for i, o in enumerate(obs) if o.y == 33.0), key=lambda i: obs[i].x)
    a, b = obs[hidden], obs[first_rock]
    pose = at(off, (a.x + b.x) / 2, (a.y + b.y) / 2, yaw=math.atan2(b.y - a.y, b.x - a.x))
    both = core.Collision(tuple(sorted((hidden, first_rock))), False)
    assert core.collision_of(off, pose.x) == both
    assert core.collision_text(off, pose.x) == (f"{first_rock}:cylinder(59.5,33),"
                                                f"{hidden}:cylinder(55.5,32)+hidden")
    assert core.collision_text(p, at(p, 0.5, 40.0).x) == "off-map"
    assert core.collision_text(p, at(p, x - 0.4, rock.y).x) == ""


def test_obstacle_cells_partition_the_obstacle_mask():
    for name in ("open-field", "alleyway", "offroad"):
        s = build_scenario(name, 0)
        mask = s.obstacle_mask(0.3)
        cells = s.obstacle_cells(0.3)
        assert len(cells) == len(s.obstacles) and all(len(c) for c in cells)
        union = np.zeros(mask.size, bool)
        for i, c in enumerate(cells):
            union[c] = True
            rows, cols = np.divmod(c, mask.shape[1])
            x, y = s.cell_centres(rows, cols)
            assert np.all(s.obstacles[i].distance(x, y) == 0.0)
            assert i in s.obstacles_at(rows[:1], cols[:1])
        assert np.array_equal(union, mask.ravel())


def test_success_stopping_and_timeout():
    p = params(**{"episode.timeout_s": 5.0})
    g = p.scenario.goal
    s = core.judge(p, at(p, g.x + 1.5, g.y, V=0.5, t=3.0))
    assert s.outcome == "success" and s.time_to_goal_s == 3.0
    fast = core.judge(p, at(p, g.x + 1.5, g.y, V=3.0, t=3.0))
    assert fast.outcome == "" and fast.reached_goal_region
    assert core.judge(p, replace(fast, t=5.0)).outcome == "stopping"
    assert core.judge(p, at(p, 20.0, 40.0, t=5.0)).outcome == "timeout"


def test_actuator_limits_and_rates():
    p = params()
    s = core.plant_step(p, core.initial_state(p), np.array([1.0, 99999.0]))
    assert s.u_applied[0] == math.copysign(p.vehicle.steer_rate_max_radps * p.dt, 1)
    assert s.u_applied[1] == p.vehicle.force_rate_max_nps * p.dt
    for _ in range(200):
        s = core.plant_step(p, s, np.array([1.0, 99999.0]))
    assert s.u_applied[0] == p.vehicle.steer_max_rad and s.u_applied[1] == p.vehicle.force_max_n


def test_control_at_picks_the_entry_for_the_time():
    c = np.arange(8, dtype=np.float32).reshape(4, 2)
    assert core.control_at(1.0, 1.0, 0.1, c)[0] == 0
    assert core.control_at(1.25, 1.0, 0.1, c)[0] == 4
    assert core.control_at(1.4, 1.0, 0.1, c) is None
    assert core.control_at(0.9, 1.0, 0.1, c) is None
