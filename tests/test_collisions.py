"""What a collision was on: the run record's `collision` and `vamppi collisions`."""

import json
import subprocess
import sys

import numpy as np
import pytest

from common.config import config_toml, load_config
from deploy.analysis.collisions import (
    NOT_REPRODUCED,
    UNATTRIBUTED,
    attribute,
    hidden_lead,
    load_saved,
    room_to_stop,
    save,
    table,
)
from deploy.analysis.reveal import stopping_distance
from deploy.analysis.summary import collisions_section
from deploy.sim.experiment import config_digest
from deploy.sim.runner import Cores, collision_record, mapped_obstacles
from services.plant.dynamics import S


def test_an_obstacle_is_mapped_once_one_of_its_cells_is_observed_standing():
    terrain = np.zeros((4, 4), np.float32)
    mean = np.zeros((4, 4), np.float32)
    var = np.full((4, 4), 3.0, np.float32)
    cells = (np.array([0, 1]), np.array([10, 11]))
    args = (terrain, 0.3, 1.5)
    assert not mapped_obstacles(cells, mean, var, *args).any()      # unseen
    var.flat[[1, 10]] = 0.01
    assert not mapped_obstacles(cells, mean, var, *args).any()      # seen, but flat
    mean.flat[10] = 0.31
    assert mapped_obstacles(cells, mean, var, *args).tolist() == [False, True]
    mean.flat[0] = 2.0                                               # tall but unseen
    assert mapped_obstacles(cells, mean, var, *args).tolist() == [False, True]


def test_collision_record_names_the_obstacle_and_how_long_it_was_mapped():
    cores = Cores.from_config(load_config(overrides=["episode.scenario=offroad"]))
    obs = cores.scenario.obstacles
    rock = min((i for i, o in enumerate(obs) if o.radius == 1.3 and not o.hidden),
               key=lambda i: obs[i].x)
    x = np.zeros(6)
    x[S.X], x[S.Y], x[S.PSI], x[S.V] = obs[rock].x, obs[rock].y - 2.5, np.pi / 2, 5.0
    hidden = [i for i, o in enumerate(obs) if o.hidden]
    rec = collision_record(cores, x, 9.5, {rock: 8.0, hidden[0]: 9.0})
    assert rec["speed_mps"] == 5.0 and rec["off_map"] is False and rec["t_s"] == 9.5
    assert rec["obstacles"] == [{"index": rock, "kind": "cylinder", "x": obs[rock].x,
                                 "y": obs[rock].y, "hidden": False, "mapped_at_s": 8.0,
                                 "mapped_for_s": 1.5}]
    assert [(h["index"], h["mapped_at_s"]) for h in rec["hidden"]] == [(hidden[0], 9.0),
                                                                       (hidden[1], None)]
    assert collision_record(cores, x, 9.5, {})["obstacles"][0]["mapped_for_s"] is None
    x[S.Y] -= 2.0
    assert collision_record(cores, x, 9.5, {}) is None


# a straight run north at 6 m/s, x = 60, from y = 18.5 at t = 7.0 to the collision at 9.5 s
PATH = [[round(7.0 + 0.1 * i, 1), 60.0, 18.5 + 0.6 * i, 6.0] for i in range(26)]


def test_room_to_stop_measures_along_the_path_from_the_moment_the_map_showed_it():
    cfg = load_config()
    c = {"t_s": 9.45, "x": 60.0, "y": 33.2, "speed_mps": 6.0,
         "obstacles": [{"mapped_at_s": 8.05}, {"mapped_at_s": 7.5}]}
    room = room_to_stop(cfg, PATH, c)            # from 8.05 s (the later), 1.4 s at 6 m/s
    assert room["travelled_m"] == pytest.approx(8.4, abs=0.01)
    assert room["speed_mps"] == 6.0 and room["stopping_m"] == round(stopping_distance(cfg, 6.0), 2)
    assert room["could_stop"] == (8.4 > stopping_distance(cfg, 6.0))
    c["obstacles"][0]["mapped_at_s"] = 9.0
    assert room_to_stop(cfg, PATH, c)["could_stop"] is False           # 2.7 m at 6 m/s
    c["obstacles"][1]["mapped_at_s"] = None
    assert room_to_stop(cfg, PATH, c) is None                           # never shown


def _record(seed, outcome="collision", collision=None, **extra):
    r = {"scenario": "offroad", "controller": "va", "samples": 400, "seed": seed,
         "outcome": outcome, "sim_time_s": 9.5, "path": PATH, **extra}
    if collision is not None:
        r["collision"] = collision
    return r


def test_table_groups_collisions_by_obstacle_and_keeps_the_unattributed(tmp_path):
    hit = {"t_s": 9.5, "x": 60.0, "y": 33.5, "heading_rad": 1.5, "speed_mps": 5.0,
           "off_map": False, "obstacles": [{"index": 23, "kind": "cylinder", "x": 59.5,
                                            "y": 33.0, "hidden": False, "mapped_at_s": 8.0,
                                            "mapped_for_s": 1.5}]}
    late = json.loads(json.dumps(hit))
    late["obstacles"][0].update(mapped_at_s=None, mapped_for_s=None)
    late["speed_mps"] = 6.0
    late["hidden"] = [{"index": 26, "x": 55.5, "y": 32.0, "mapped_at_s": 9.1},
                      {"index": 27, "x": 52.0, "y": 37.0, "mapped_at_s": 8.9}]
    runs = [_record(1, collision=hit), _record(2, collision=late), _record(3),
            _record(4, outcome="success")]
    rows = attribute(load_config(), runs)
    assert [r["status"] for r in rows] == ["recorded", "recorded", UNATTRIBUTED]
    lines = table(rows).splitlines()
    need = f"{stopping_distance(load_config(), 6.0):.2f} m"
    assert lines[2] == ("| offroad | va | 400 | cylinder (59.5, 33) | 2 | 1.50 s | 1 | 9.00 m "
                        f"| {need} | 1 | 5.50 m/s (5.00-6.00) | 0.40 s | 1, 2 |")
    assert lines[3].startswith("| offroad | va | 400 | (not attributed) | 1 |")
    assert "seed 3: unattributed" in lines[3]
    assert hidden_lead({"t_s": 9.5, "hidden": [{"mapped_at_s": None}]}) is None
    assert hidden_lead(hit) == ""                                     # an older record
    # a rerun's attribution, kept beside the runs, is used from then on
    kept = [{**{k: v for k, v in runs[2].items() if k in ("scenario", "controller", "samples",
                                                          "seed")},
             "config_digest": None, "status": "rerun", "collision": hit}]
    save(tmp_path, [], kept + rows)
    assert load_saved(tmp_path) == kept
    again = attribute(load_config(), runs, saved=load_saved(tmp_path))
    assert [r["status"] for r in again] == ["recorded", "recorded", "rerun"]
    assert again[2]["collision"] == hit
    section = collisions_section(load_config(), runs, tmp_path)       # summary.md's table
    assert section.splitlines()[3:] == table(again).splitlines()
    assert collisions_section(load_config(), runs[3:], tmp_path) == ""  # nothing collided
    (tmp_path / "collisions.json").write_text('[{"scenario": "offroad"}]')
    with pytest.raises(ValueError, match="remove it and attribute again"):
        load_saved(tmp_path)
    assert collisions_section(load_config(), runs, tmp_path).splitlines()[3:] == lines


def test_cli_reruns_an_older_record_and_refuses_what_it_does_not_reproduce(tmp_path):
    cfg = load_config(overrides=["episode.timeout_s=0.3"])
    (tmp_path / "config.toml").write_text(config_toml(cfg))
    rec = {"scenario": "open-field", "controller": "deterministic", "samples": 16, "seed": 0,
           "outcome": "collision", "sim_time_s": 0.2, "config_digest": config_digest(cfg)}
    other = dict(rec, seed=1, config_digest="0" * 16)
    (tmp_path / "runs.jsonl").write_text(json.dumps(rec) + "\n" + json.dumps(other) + "\n")
    r = subprocess.run([sys.executable, "-m", "deploy", "collisions", str(tmp_path),
                        "--rerun", "--json"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = json.loads(r.stdout)
    assert [x["status"] for x in rows] == [NOT_REPRODUCED, NOT_REPRODUCED]
    assert "rerun: timeout at 0.30 s" in rows[0]["why"]
    assert "config digest" in rows[1]["why"]
    assert json.loads(r.stderr.strip().splitlines()[-1]) == {"collisions": 2,
                                                             NOT_REPRODUCED: 2}
    assert json.loads((tmp_path / "collisions.json").read_text()) == []   # nothing to keep
    # two directories, one table: the older records stay unattributed without --rerun
    second = tmp_path / "second"
    second.mkdir()
    hit = {"t_s": 9.5, "x": 60.0, "y": 33.5, "heading_rad": 1.5, "speed_mps": 5.0,
           "off_map": False, "obstacles": []}
    (second / "runs.jsonl").write_text(json.dumps(_record(5, collision=hit)) + "\n")
    r = subprocess.run([sys.executable, "-m", "deploy", "collisions", str(tmp_path),
                        str(second)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads(r.stderr.strip().splitlines()[-1]) == {"collisions": 3, UNATTRIBUTED: 2,
                                                             "recorded": 1}
    assert "| offroad | va | 400 | an obstacle cell of no listed obstacle | 1 |" in r.stdout
    (tmp_path / "collisions.json").write_text("{torn")
    r = subprocess.run([sys.executable, "-m", "deploy", "collisions", str(tmp_path)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 2 and "collisions.json: unreadable" in r.stderr
