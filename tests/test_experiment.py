"""A small lockstep experiment: records complete and valid, resumable, plots written."""

import json
import subprocess
import sys

from common.config import load_config
from deploy.experiment import KEY_FIELDS, config_digest, read_runs, summarize
from services.plant.core import OUTCOMES

SETTINGS = ["--set", "episode.timeout_s=1.5", "--set", "planner.horizon=40"]


def run(out, runs, extra=()):
    return subprocess.run(
        [sys.executable, "-m", "deploy.cli", "experiment", "--scenario", "alleyway",
         "--controllers", "va,deterministic,prescient", "--samples", "16", "--runs", str(runs),
         "--seed", "3", "--out", str(out), "--quiet", *SETTINGS, *extra],
        capture_output=True, text=True, timeout=900)


def test_small_experiment_records_are_complete_and_resumable(tmp_path):
    out = tmp_path / "exp"
    r = run(out, 1, ["--no-plots"])
    assert r.returncode == 0, r.stderr[-2000:]
    first = read_runs(out / "runs.jsonl")
    assert len(first) == 3
    # a torn last line (as after a crash mid-write) is skipped, and resuming adds run 2
    with (out / "runs.jsonl").open("a") as f:
        f.write('{"scenario": "alleyway", "contr')
    r = run(out, 2)
    assert r.returncode == 0, r.stderr[-2000:]
    runs = read_runs(out / "runs.jsonl")
    assert len(runs) == 6
    assert {tuple(x[k] for k in KEY_FIELDS) for x in runs} == {
        ("alleyway", c, 16, s) for c in ("va", "deterministic", "prescient") for s in (3, 4)}
    assert [x for x in runs if x["seed"] == 3] == first            # finished runs kept as they were
    for x in runs:
        assert x["outcome"] in OUTCOMES
        assert x["sim_time_s"] <= 1.5 + 1e-9
        assert len(x["path"]) >= 10 and len(x["path"][0]) == 4
        assert len(x["solve_ms"]) >= 10 and x["max_speed_mps"] >= 0
        assert ("collision" in x) == (x["outcome"] == "collision")
    summary = json.loads((out / "summary.json").read_text())
    assert summary == summarize(runs)
    assert {s["controller"] for s in summary} == {"va", "deterministic", "prescient"}
    for s in summary:
        assert s["runs"] == 2 and sum(s[o] for o in OUTCOMES) == 2
    assert len({x["config_digest"] for x in runs}) == 1
    # the configuration beside the runs resumes them (nothing left to do, nothing added)
    r = run(out, 2, ["--no-plots", "--config", str(out / "config.toml")])
    assert r.returncode == 0, r.stderr[-2000:]
    assert read_runs(out / "runs.jsonl") == runs
    saved = load_config(out / "config.toml")
    assert saved.episode.timeout_s == 1.5 and config_digest(saved) == runs[0]["config_digest"]
    other = run(out, 2, ["--no-plots", "--set", "planner.temperature=2.0"])
    assert other.returncode == 2 and "another configuration" in other.stderr
    assert read_runs(out / "runs.jsonl") == runs                  # nothing touched
    text = (out / "summary.md").read_text()
    table = text.split("\n\n")[0].splitlines()          # then, if any run collided, what on
    assert len(table) == 2 + len(summary)
    assert ("What the collisions were on" in text) == any(x["outcome"] == "collision"
                                                          for x in runs)
    assert all(row.startswith("| alleyway | ") and row.count("|") == 12 for row in table[2:])
    for name in ("failures.png", "time_to_goal.png", "solve_time.png",
                 "trajectories_alleyway.png", "visibility_alleyway.png"):
        assert (out / name).stat().st_size > 10_000, name
