"""The tables of record's manifest (deploy/sim/tables.py, `vamppi tables`): it names every
committed table, each holds its whole grid under the configuration its entry gives today,
and `--run` makes a table, resumes it, and refuses one of another configuration."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from deploy.launch.cli import main
from deploy.sim import tables
from deploy.sim.experiment import read_runs
from deploy.sim.tables import Table, table_state

ROOT = Path(__file__).resolve().parents[1]


def test_every_committed_table_is_in_the_manifest_whole_and_current():
    on_disk = {p.name for p in tables.RESULTS_DIR.iterdir() if (p / "runs.jsonl").exists()}
    assert on_disk == set(tables.BY_NAME)
    results = (ROOT / "docs" / "results.md").read_text()
    for t in tables.TABLES:
        s = table_state(t, read_runs(tables.RESULTS_DIR / t.name / "runs.jsonl"))
        assert (s.state, s.found, s.extra, s.wrong_layout) == ("current", s.want, 0, 0), (
            t.name, s)
        assert f"results/{t.name}/summary.md" in results, t.name


def _rec(scenario, controller, samples, seed, digest, layout=1):
    return {"scenario": scenario, "controller": controller, "samples": samples, "seed": seed,
            "config_digest": digest, "layout": layout, "format": 3, "outcome": "success",
            "wall_time_s": 1800.0}


def test_a_table_s_state_tells_missing_part_stale_mixed_and_the_older_program_apart():
    t = Table("t", ("alleyway",), 400, 2, controllers=("va", "prescient"))
    d = table_state(t, []).digest
    grid = [_rec("alleyway", c, 400, i, d) for c in ("va", "prescient") for i in (0, 1)]
    assert table_state(t, []).state == "missing"
    assert table_state(t, grid[:3]).state == "incomplete"
    whole = table_state(t, grid)
    assert (whole.state, whole.found, whole.want, whole.wall_h) == ("current", 4, 4, 2.0)
    old = [dict(r, config_digest="0123456789abcdef") for r in grid]
    assert table_state(t, old).state == "stale"
    assert table_state(t, grid[:2] + old[2:]).state == "mixed"
    assert table_state(t, grid + [_rec("alleyway", "va", 1000, 0, d)]).state == "mixed"
    assert table_state(t, grid[:3] + [dict(grid[3], layout=2)]).state == "mixed"
    paper = Table("p", ("alleyway",), 400, 1, controllers=("va",), preset="paper",
                  sets=tables.PAPER)
    (older,) = [o for o, now in tables.SAME_ARITHMETIC.items()
                if now == table_state(paper, []).digest]
    assert table_state(paper, [_rec("alleyway", "va", 400, 0, older)]).state == "current"


def test_the_run_option_makes_a_table_resumes_it_and_refuses_another_configuration(
        tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(ROOT)
    tiny = Table("tiny", ("open-field",), 32, 2, controllers=("deterministic",),
                 sets=("episode.timeout_s=0.5",))
    monkeypatch.setattr(tables, "TABLES", (tiny,))
    monkeypatch.setattr(tables, "BY_NAME", {"tiny": tiny})
    monkeypatch.setattr(tables, "RESULTS_DIR", tmp_path / "committed")
    root = tmp_path / "remade"
    assert main(["tables", "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert (row["state"], row["want"]) == ("missing", 2)
    assert row["command"] == ("vamppi experiment --scenario open-field --controllers "
                              "deterministic --samples 32 --runs 2 --set "
                              "'episode.timeout_s=0.5' --jobs 2 --no-plots --out DIR")
    assert main(["tables", "--run", "--stale", "--quiet", "--no-plots",
                 "--root", str(root)]) == 0
    assert "| tiny | 2 of 2 |" in capsys.readouterr().out
    runs = (root / "tiny" / "runs.jsonl").read_text().splitlines()
    assert [json.loads(r)["seed"] for r in runs] == [0, 1]
    (root / "tiny" / "runs.jsonl").write_text(runs[0] + "\n")       # one run lost
    assert main(["tables", "tiny", "--run", "--quiet", "--no-plots", "--root", str(root)]) == 0
    again = (root / "tiny" / "runs.jsonl").read_text().splitlines()
    assert again[0] == runs[0] and len(again) == 2
    assert (root / "tiny" / "summary.md").exists()
    capsys.readouterr()
    # a default changed since: the entry's digest moves, the remade table is stale, and
    # --run into its directory is refused rather than mixed
    changed = Table("tiny", tiny.scenarios, 32, 2, controllers=tiny.controllers,
                    sets=(*tiny.sets, "planner.w_time=3.0"))
    monkeypatch.setattr(tables, "TABLES", (changed,))
    monkeypatch.setattr(tables, "BY_NAME", {"tiny": changed})
    assert main(["tables", "--root", str(root)]) == 0
    assert "| stale |" in capsys.readouterr().out
    assert main(["tables", "--run", "--quiet", "--no-plots", "--root", str(root)]) == 2
    assert "another configuration" in capsys.readouterr().err
    with pytest.raises(ValueError, match="unknown table"):
        tables.select(["nope"])
