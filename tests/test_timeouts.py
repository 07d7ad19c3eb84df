"""How a run that timed out ended: deploy/analysis/timeouts.py and `vamppi timeouts`."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from common.config import load_config
from deploy.analysis.timeouts import STAND_MPS, counts, ending, endings, table

GOAL = (55.0, 40.0)                # open-field's goal


def _path(speeds, x0=15.0, y=40.0, dt=0.1):
    """A straight path along +x at these speeds (one row per 0.1 s): (t, X, Y, V, psi)."""
    x = x0 + np.concatenate([[0.0], np.cumsum(np.asarray(speeds[:-1]) * dt)])
    return [[round(i * dt, 3), float(xi), y, float(v), 0.0] for i, (xi, v) in
            enumerate(zip(x, speeds, strict=True))]


def test_a_run_that_stops_short_stands_from_its_last_move_on():
    speeds = [5.0] * 60 + [0.2] * 50          # 6 s at 5 m/s, then 5 s creeping
    e = ending(_path(speeds), GOAL)
    assert e["how"] == "standing" and e["standing_since_s"] == pytest.approx(6.0)
    driven = 5.0 * 0.1 * 60 + 0.2 * 0.1 * 49
    assert e["driven_m"] == pytest.approx(driven, abs=0.05)
    assert e["end_from_goal_m"] == pytest.approx(GOAL[0] - 15.0 - driven, abs=1e-6)
    assert e["nearest_m"] == e["end_from_goal_m"] and e["nearest_at_s"] == pytest.approx(10.9)


def test_a_run_still_moving_at_the_end_is_driving():
    e = ending(_path([4.0] * 50), GOAL)
    assert e["how"] == "driving" and e["standing_since_s"] is None
    assert e["end_speed_mps"] == 4.0
    assert ending(_path([4.0] * 50 + [0.0] * 9 + [STAND_MPS]), GOAL)["how"] == "driving"
    e = ending(_path([4.0] * 50 + [0.5 * STAND_MPS] * 5), GOAL)      # a creep at the end
    assert e["how"] == "standing" and e["standing_since_s"] == pytest.approx(5.0)
    assert ending(_path([0.0] * 40), GOAL) == {
        "how": "standing", "standing_since_s": 0.0, "end_speed_mps": 0.0,
        "end_from_goal_m": 40.0, "nearest_m": 40.0, "nearest_at_s": 0.0, "driven_m": 0.0}
    # a reversing vehicle moves too
    assert ending(_path([-1.0] * 40), GOAL)["how"] == "driving"


def test_the_nearest_approach_is_kept_when_the_run_drives_past_the_goal():
    # past the goal at 10 m/s, then back at an angle: nearest at the crossing
    path = [[i * 0.1, 40.0 + i * 1.0, 40.5, 10.0, 0.0] for i in range(31)]
    e = ending(path, GOAL)
    assert e["nearest_m"] == pytest.approx(0.5) and e["nearest_at_s"] == pytest.approx(1.5)
    assert e["end_from_goal_m"] == pytest.approx(math.hypot(70.0 - 55.0, 0.5), abs=1e-2)


@pytest.mark.parametrize("bad", [[[0.0, 1.0, 2.0, 3.0]], [[0.0, 1.0, 2.0]] * 3,
                                 [[0.0, 1.0, 2.0, float("nan")]] * 3])
def test_a_torn_path_is_an_error(bad):
    with pytest.raises(ValueError, match="finite rows"):
        ending(bad, GOAL)


def _rec(seed, outcome, path=None, controller="va"):
    r = {"scenario": "open-field", "controller": controller, "samples": 16, "seed": seed,
         "outcome": outcome, "world": "open-field"}
    return r | ({"path": path} if path is not None else {})


def test_endings_take_the_goal_from_the_scenario_and_skip_what_succeeded_or_collided():
    cfg = load_config()
    runs = [_rec(0, "success", _path([5.0] * 10)), _rec(1, "collision", _path([5.0] * 10)),
            _rec(2, "timeout", _path([5.0] * 20 + [0.0] * 40)), _rec(3, "stopping"),
            _rec(4, "timeout", _path([3.0] * 30), controller="deterministic")]
    rows = endings(cfg, runs)
    assert [(r["seed"], r["how"]) for r in rows] == [(2, "standing"), (3, "no path"),
                                                     (4, "driving")]
    assert rows[0]["end_from_goal_m"] == pytest.approx(40.0 - 5.0 * 0.1 * 20, abs=1e-6)
    assert counts(rows) == {"va": {"standing": 1, "no path": 1},
                            "deterministic": {"driving": 1}}
    text = table(rows)
    assert "| open-field | va | 16 | 2 | timeout | standing from 2.0 s | 30.0 m |" in text
    assert "| open-field | va | 16 | 3 | stopping | no path recorded |" in text


def test_cli_reads_several_experiments_into_one_table(tmp_path):
    one, two = tmp_path / "one", tmp_path / "two"
    for d, recs in ((one, [_rec(0, "timeout", _path([0.0] * 40))]),
                    (two, [_rec(1, "timeout", _path([2.0] * 40), controller="prescient")])):
        d.mkdir()
        (d / "runs.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    r = subprocess.run([sys.executable, "-m", "deploy", "timeouts", str(one), str(two)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads(r.stderr.strip().splitlines()[-1]) == {
        "va": {"standing": 1}, "prescient": {"driving": 1}}
    assert "standing from 0.0 s" in r.stdout and "driving, 2.0 m/s" in r.stdout
    r = subprocess.run([sys.executable, "-m", "deploy", "timeouts", str(two), "--json",
                        "--controller", "va"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and json.loads(r.stdout) == []
    (two / "runs.jsonl").write_text(json.dumps(_rec(5, "timeout", [[0.0, 1.0, 2.0,
                                                                    float("nan")]] * 3)) + "\n")
    r = subprocess.run([sys.executable, "-m", "deploy", "timeouts", str(two)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "finite rows" in r.stderr
