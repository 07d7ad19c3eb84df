"""`vamppi near-goal` (deploy/analysis/neargoal.py): the distance from the goal to the
nearest hidden obstacle, against a direct float64 construction from the scenario file,
and the split of runs by it."""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import pytest

from common.config import load_config
from common.scenarios import build_scenario
from deploy.analysis.neargoal import hidden_to_goal_m, split, table
from deploy.analysis.summary import fisher_exact
from deploy.launch.cli import main

ROOT = Path(__file__).resolve().parents[1]
NEAR = "common/scenarios/benchmark/heldout/hedge-0014.toml"
FAR = "common/scenarios/benchmark/tune/corner-0001.toml"


def _direct(path: str) -> float:
    """From the file's numbers: a cylinder's centre distance less its radius; a box's
    distance in its own frame past its half extents."""
    d = tomllib.loads((ROOT / path).read_text())
    gx, gy = d["goal"]["x"], d["goal"]["y"]
    out = []
    for o in d["obstacle"]:
        if not o["hidden"]:
            continue
        if o["kind"] == "cylinder":
            out.append(max(0.0, math.hypot(gx - o["x"], gy - o["y"]) - o["radius"]))
        else:
            c, s = math.cos(o["yaw"]), math.sin(o["yaw"])
            u = (gx - o["x"]) * c + (gy - o["y"]) * s
            v = -(gx - o["x"]) * s + (gy - o["y"]) * c
            out.append(math.hypot(max(0.0, abs(u) - o["half_x"]), max(0.0, abs(v) - o["half_y"])))
    return min(out)


@pytest.mark.parametrize("path", [NEAR, FAR])
def test_the_hidden_obstacle_s_distance_from_the_goal_is_the_file_s(path):
    scn = build_scenario(str(ROOT / path), 0, 0.2)
    assert hidden_to_goal_m(scn) == pytest.approx(_direct(path), rel=1e-12)


def _runs(scenario, outcomes):
    return [{"scenario": scenario, "controller": "va", "samples": 400, "seed": i,
             "outcome": o, "layout": 1} for i, o in enumerate(outcomes)]


def test_runs_split_by_a_hidden_obstacle_near_the_goal(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(ROOT)
    assert _direct(NEAR) < 12.0 < _direct(FAR)
    runs = (_runs(NEAR, ["success", "timeout", "timeout"])
            + _runs(FAR, ["success", "success", "collision", "success"]))
    (row,) = split(load_config(), runs, 12.0)
    assert {k: row[k] for k in ("near_runs", "near_success", "near_collision", "near_worlds",
                                "far_runs", "far_success", "far_collision", "far_worlds")} == {
        "near_runs": 3, "near_success": 1, "near_collision": 0, "near_worlds": 1,
        "far_runs": 4, "far_success": 3, "far_collision": 1, "far_worlds": 1}
    assert row["p"] == fisher_exact(1, 2, 3, 1)
    assert "| va | 1, 1 of 3 (33 %), 0 | 1, 3 of 4 (75 %), 1 |" in table([row], 12.0)
    # nearer than the near world's obstacle: everything is far, and no p
    (none,) = split(load_config(), runs, _direct(NEAR) - 0.1)
    assert none["near_runs"] == 0 and none["far_runs"] == 7 and none["p"] is None
    (tmp_path / "runs.jsonl").write_text("".join(json.dumps(r) + "\n" for r in runs))
    assert main(["near-goal", str(tmp_path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)[0]["near_success"] == 1
