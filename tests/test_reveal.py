"""`vamppi reveal`: first sightings of hidden obstacles and the distance to stop."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from common.config import load_config
from common.scenarios import build_scenario
from deploy.analysis.reveal import first_sightings, poses_of_path, reveal_runs, stopping_distance

CFG = load_config()


def stopping_reference(cfg, v0, dt=1e-5):
    """Euler, float64: one tick coasting, force ramping at the rate limit, then full brake."""
    veh = cfg.vehicle
    t, x, v = 0.0, 0.0, v0
    while v > 0.0:
        f = 0.0 if t < cfg.planner.dt_s else max(veh.force_min_n,
                                                 -veh.force_rate_max_nps * (t - cfg.planner.dt_s))
        v_next = v + f / veh.mass_kg * dt
        x += 0.5 * (v + max(v_next, 0.0)) * dt
        v, t = v_next, t + dt
    return x


@pytest.mark.parametrize("v", [0.5, 1.0, 2.0, 5.0, 9.5])
def test_stopping_distance_matches_the_integrated_reference(v):
    assert stopping_distance(CFG, v) == pytest.approx(stopping_reference(CFG, v), abs=1e-3)


def test_offroad_hidden_obstacle_is_first_seen_facing_the_gap():
    scn = build_scenario("offroad")
    hidden = [i for i, o in enumerate(scn.obstacles) if o.hidden]
    road = [(0.1 * k, x, 20.0, 0.0, 8.0) for k, x in enumerate(np.arange(30.0, 55.0, 5.0))]
    facing = [(5.0, 58.3, 24.5, 1.3, 3.0)]
    s = first_sightings(CFG, scn, road + facing, hidden)
    assert s[0].t_s == 5.0 and 3.0 < s[0].gap_m < 9.0          # the gap's closer, ~8 m off
    assert s[0].stoppable and s[0].stopping_m == pytest.approx(stopping_distance(CFG, 3.0))
    assert s[1].t_s is None and not s[1].stoppable
    fast = first_sightings(CFG, scn, [(0.0, 58.3, 24.5, 1.3, 12.0)], hidden[:1])[0]
    assert fast.t_s == 0.0 and not fast.stoppable             # 12 m/s needs > 20 m


def test_poses_of_a_path_take_the_heading_from_consecutive_samples():
    path = np.array([[0.0, 0.0, 0.0, 0.0], [0.1, 0.0, 0.0, 0.1], [0.2, 1.0, 1.0, 2.0],
                     [0.3, 1.0, 2.0, 2.0]])
    poses = poses_of_path(path)
    assert [p[0] for p in poses] == [0.2, 0.3]                  # standing still: skipped
    assert poses[0][3] == pytest.approx(math.pi / 4) and poses[1][3] == pytest.approx(math.pi / 2)
    # a record with the heading: the camera points where the vehicle does, not where it
    # slides, and standing still it still looks (the same view once)
    with_psi = np.hstack([path, np.array([[0.0], [0.0], [0.3], [1.2]])])
    assert [(p[0], p[3]) for p in poses_of_path(with_psi)] == [(0.0, 0.0), (0.2, 0.3),
                                                               (0.3, 1.2)]


def test_cli_reports_runs_and_skips_a_torn_line(tmp_path):
    path = [[0.1 * k, x, 20.0, 8.0] for k, x in enumerate(np.arange(40.0, 55.0, 1.0))]
    path += [[2.0, 58.22, 24.21, 3.0], [2.1, 58.3, 24.5, 3.0]]      # heading 1.3 rad
    rec = {"scenario": "offroad", "controller": "deterministic", "samples": 400, "seed": 7,
           "outcome": "collision", "time_to_goal_s": None, "path": path, "scenario_seed": 0}
    runs = tmp_path / "runs.jsonl"
    runs.write_text(json.dumps(rec) + "\n" + '{"scenario": "off')
    r = subprocess.run([sys.executable, "-m", "deploy", "reveal", str(tmp_path), "--json"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    rows = json.loads(r.stdout)
    assert len(rows) == 2 and rows[0]["seed"] == 7 and rows[0]["seen_at_s"] == 2.1
    assert rows[0]["stoppable"] is True and rows[1]["seen_at_s"] is None
    assert "skipped 1" in r.stderr
    r = subprocess.run([sys.executable, "-m", "deploy", "reveal", str(tmp_path / "no")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "no such file" in r.stderr and "Traceback" not in r.stderr


def test_each_record_is_revealed_on_the_layout_it_ran_on():
    path = [[0.1 * k, 56.0 + 0.25 * k, 27.0 + 0.5 * k, 3.0, 1.1] for k in range(12)]
    old = {"scenario": "offroad", "controller": "va", "samples": 400, "seed": 1,
           "outcome": "success", "path": path, "scenario_seed": 0}      # no layout: 1
    rows = reveal_runs(load_config(), [old, {**old, "seed": 2, "layout": 2}], obstacles="all")
    rocks = {(r["seed"], r["obstacle"][1]) for r in rows if r["obstacle"][0] == 59.5}
    assert rocks == {(1, 33.0), (2, 35.0)}
