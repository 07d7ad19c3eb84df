"""The scenarios do what their rationale says: the hidden obstacles are hidden.

The ground-truth depth camera is driven along the approach each scenario is
built around (the road for offroad, the alley's centre line for alleyway);
every return is projected back onto the map. The obstacles meant to be hidden
must never be hit from there; the occluders and visible obstacles must be.
"""

import json
import subprocess
import sys

import numpy as np
import pytest

from common.config import ConfigError, load_config
from common.scenarios import LAYOUTS, build_scenario, scenario_of
from deploy.analysis.reveal import returns_on, seen_from
from services.sensor import core as sensor

CFG = load_config()
CAM = sensor.CameraParams.from_config(CFG.sensor)


def seen_points(scn, poses):
    """World x, y of every depth return from the vehicle poses (x, y, yaw)."""
    return np.concatenate([seen_from(CAM, scn, x, y, yaw)[:, :2] for x, y, yaw in poses])


@pytest.mark.parametrize("layout", [1, 2])
def test_offroad_hides_the_obstacles_that_close_the_gap_until_the_vehicle_faces_it(layout):
    scn = build_scenario("offroad", layout=layout)
    road = [(x, 20.0, 0.0) for x in np.arange(8.0, 55.0, 2.0)]
    turn = [(55.0, 20.3, 0.3), (56.5, 21.2, 0.6), (57.5, 22.5, 0.9), (58.0, 23.5, 1.1)]
    cyl = [o for o in scn.obstacles if o.kind == "cylinder"]
    trees = [o for o in cyl if o.height >= 4.0]
    hidden = [o for o in cyl if o.hidden]
    rocks = [o for o in cyl if o.height < 4.0 and not o.hidden]
    assert len(rocks) == 3 and len(hidden) == 2
    pts = seen_points(scn, road)
    assert sum(returns_on(pts, t) for t in trees) > 1000            # the tree line occludes
    assert all(returns_on(pts, o) == 0 for o in rocks + hidden)     # the field is unseen
    pts = seen_points(scn, turn)                                 # turning at the row's end
    assert all(returns_on(pts, r) > 100 for r in rocks)             # the rocks are seen ...
    assert all(returns_on(pts, h) == 0 for h in hidden)             # ... the gap looks open
    pts = seen_points(scn, [(58.3, 24.5, 1.3)])                  # facing the gap, ~8 m off
    assert returns_on(pts, hidden[0]) > 100


def test_alleyway_hides_the_obstacles_behind_the_block_until_it_is_passed():
    scn = build_scenario("alleyway")
    pts = seen_points(scn, [(x, 40.0, 0.0) for x in np.arange(12.0, 31.0, 2.0)])
    hidden = [o for o in scn.obstacles if o.hidden]
    block = [o for o in scn.obstacles if o.kind == "box" and o.half_y < 5.0][0]
    assert len(hidden) == 2
    assert returns_on(pts, block) > 1000
    assert all(returns_on(pts, h) == 0 for h in hidden)


def test_older_layouts_stay_buildable_and_a_bad_one_is_a_config_error():
    assert LAYOUTS["offroad"] == 2 and build_scenario("offroad").layout == 2
    rocks = {lay: sorted({o.y for o in build_scenario("offroad", layout=lay).obstacles
                          if o.radius == 1.3 and not o.hidden}) for lay in (1, 2)}
    assert rocks == {1: [33.0], 2: [35.0]}                   # only the rocks moved
    one, two = build_scenario("offroad", layout=1), build_scenario("offroad", layout=2)
    assert one.terrain.tobytes() == two.terrain.tobytes()
    assert [o for o in one.obstacles if o.y != 33.0] == [o for o in two.obstacles if o.y != 35.0]
    cfg = load_config(overrides=["episode.scenario=offroad", "episode.layout=1"])
    assert scenario_of(cfg).layout == 1
    assert scenario_of(cfg.replace(**{"episode.layout": 0})).layout == 2
    for bad in (["episode.scenario=alleyway", "episode.layout=2"], ["episode.layout=-1"]):
        with pytest.raises(ConfigError, match="episode.layout"):
            load_config(overrides=bad)


def test_scenarios_are_deterministic_and_the_cli_describes_and_draws_them(tmp_path):
    a, b = build_scenario("offroad", 3), build_scenario("offroad", 3)
    assert a.heightmap.tobytes() == b.heightmap.tobytes()
    assert build_scenario("offroad", 4).heightmap.tobytes() != a.heightmap.tobytes()
    png = tmp_path / "offroad.png"
    r = subprocess.run([sys.executable, "-m", "deploy", "scenario", "--scenario", "offroad",
                        "--plot", str(png)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    layout = json.loads(r.stdout)
    assert layout["name"] == "offroad" and len(layout["obstacles"]) == len(a.obstacles)
    assert layout["layout"] == LAYOUTS["offroad"]
    assert layout["goal"] == {"x": 45.0, "y": 46.0, "yaw": a.goal.yaw}
    assert png.stat().st_size > 10_000
