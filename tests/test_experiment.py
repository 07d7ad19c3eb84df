"""A small lockstep experiment: records complete and valid, resumable, plots written."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import NamedTuple

import pytest

from common.config import load_config
from common.scenarios import spec_of, spec_toml
from deploy.analysis.summary import summarize
from deploy.sim.experiment import (
    KEY_FIELDS,
    RECORD_FORMAT,
    ExperimentError,
    config_digest,
    cpu_shares,
    expand_scenarios,
    experiment,
    read_runs,
    record_format,
    saved_config,
)
from services.plant.core import OUTCOMES

SETTINGS = ["--set", "episode.timeout_s=1.5", "--set", "planner.horizon=40"]


def run(out, runs, extra=()):
    return subprocess.run(
        [sys.executable, "-m", "deploy", "experiment", "--scenario", "alleyway",
         "--controllers", "va,deterministic,prescient", "--samples", "16", "--runs", str(runs),
         "--seed", "3", "--out", str(out), "--quiet", *SETTINGS, *extra],
        capture_output=True, text=True, timeout=900)


class Serial(NamedTuple):
    out: Path                 # the directory: two runs of each controller, resumed
    first: list               # the records after one run of each
    first_summary: str        # summary.md after one run of each


# the tests that read `serial` run on one worker, which makes it once: the other never waits
SERIAL = pytest.mark.xdist_group("serial")


@pytest.fixture(scope="session")
def serial(tmp_path_factory):
    """The in-process runs that the other wirings must give: one run of each controller
    (no plots), a torn last line as after a crash mid-write, then resumed to two runs each
    (with plots). Its tests share an xdist_group, so that one worker makes it once."""
    out = tmp_path_factory.mktemp("serial")
    r = run(out, 1, ["--no-plots"])
    assert r.returncode == 0, r.stderr[-2000:]
    first = read_runs(out / "runs.jsonl")
    first_summary = (out / "summary.md").read_text()
    with (out / "runs.jsonl").open("a") as f:
        f.write('{"scenario": "alleyway", "contr')
    r = run(out, 2)
    assert r.returncode == 0, r.stderr[-2000:]
    return Serial(out, first, first_summary)


@SERIAL
def test_small_experiment_records_are_complete_and_resumable(tmp_path, serial):
    out = tmp_path / "exp"
    shutil.copytree(serial.out, out)
    first = serial.first
    assert len(first) == 3
    assert "±" not in serial.first_summary.split("\n\n")[0]   # one run: no spread
    # the torn last line was skipped, and resuming added run 2
    runs = read_runs(out / "runs.jsonl")
    assert len(runs) == 6
    assert {tuple(x[k] for k in KEY_FIELDS) for x in runs} == {
        ("alleyway", c, 16, s) for c in ("va", "deterministic", "prescient") for s in (3, 4)}
    assert [x for x in runs if x["seed"] == 3] == first            # finished runs kept as they were
    for x in runs:
        assert x["outcome"] in OUTCOMES
        assert x["sim_time_s"] <= 1.5 + 1e-9
        assert len(x["path"]) >= 10 and len(x["path"][0]) == 5       # t, X, Y, V, psi
        assert len(x["solve_ms"]) >= 10 and x["max_speed_mps"] >= 0
        assert ("collision" in x) == (x["outcome"] == "collision")
        assert x["layout"] == 1                                     # the alleyway's only one
        assert x["format"] == RECORD_FORMAT == record_format(x)
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
    rows = [json.loads(line) for line in r.stdout.splitlines()]
    assert {x["controller"] for x in rows} == {"va", "deterministic", "prescient"}
    # resumed for one controller: only its rows are printed (summary.json keeps them all)
    only = subprocess.run(
        [sys.executable, "-m", "deploy", "experiment", "--scenario", "alleyway",
         "--controllers", "va", "--samples", "16", "--runs", "2", "--seed", "3", "--out",
         str(out), "--quiet", "--no-plots", "--config", str(out / "config.toml")],
        capture_output=True, text=True, timeout=900)
    assert only.returncode == 0, only.stderr[-2000:]
    assert [json.loads(line)["controller"] for line in only.stdout.splitlines()] == ["va"]
    assert len(json.loads((out / "summary.json").read_text())) == 3
    saved = load_config(out / "config.toml")
    assert saved.episode.timeout_s == 1.5 and config_digest(saved) == runs[0]["config_digest"]
    assert (saved.episode.scenario, saved.episode.layout) == ("alleyway", 1)   # pinned
    other = run(out, 2, ["--no-plots", "--set", "planner.temperature=2.0"])
    assert other.returncode == 2 and "another configuration" in other.stderr
    assert read_runs(out / "runs.jsonl") == runs                  # nothing touched
    text = (out / "summary.md").read_text()
    table = text.split("\n\n")[0].splitlines()          # then, if any run collided, what on
    assert len(table) == 2 + len(summary)
    assert ("What the collisions were on" in text) == any(x["outcome"] == "collision"
                                                          for x in runs)
    assert all(row.startswith("| alleyway | ") and row.count("|") == 14 for row in table[2:])
    for name in ("failures.png", "time_to_goal.png", "solve_time.png",
                 "trajectories_alleyway.png", "visibility_alleyway.png"):
        assert (out / name).stat().st_size > 10_000, name


def test_runs_on_an_older_scenario_layout_are_not_resumed_with_the_newest(tmp_path):
    cfg = load_config(overrides=["episode.timeout_s=1.5"])
    old = {"scenario": "offroad", "controller": "va", "samples": 16, "seed": 0,
           "outcome": "timeout", "config_digest": config_digest(cfg)}     # no layout: 1
    (tmp_path / "runs.jsonl").write_text(json.dumps(old) + "\n")
    before = (tmp_path / "runs.jsonl").read_text()
    with pytest.raises(ExperimentError, match="layout 1.*episode.layout=1"):
        experiment(cfg, ["offroad"], ["va"], [16], 2, 0, tmp_path, progress=False)
    assert (tmp_path / "runs.jsonl").read_text() == before
    assert not (tmp_path / "config.toml").exists()


@pytest.mark.parametrize("broken", ["truncated", "heightmap", "missing", "unknown"])
def test_a_scenario_that_cannot_be_built_is_refused_before_any_run(tmp_path, broken):
    """A bad world in the list (a truncated file, a heightmap not there, no such file or
    built-in) is one error naming it, before anything runs or is written."""
    good = tmp_path / "worlds" / "good.toml"
    good.parent.mkdir()
    good.write_text(spec_toml(spec_of("open-field")))
    bad = tmp_path / "worlds" / "bad.toml"
    if broken == "truncated":
        bad.write_text(good.read_text()[:200])
    elif broken == "heightmap":
        bad.write_text(good.read_text().replace('kind = "waves"',
                                                'kind = "heightmap"\nheightmap = "gone.npy"'))
    scenario = {"missing": str(tmp_path / "gone.toml"),
                "unknown": "no-such-world"}.get(broken, str(good.parent))
    out = tmp_path / "out"
    cfg = load_config(overrides=["episode.timeout_s=1.5"])
    with pytest.raises(ExperimentError, match={"truncated": "bad.toml: not valid TOML",
                                               "heightmap": "bad.toml: .*gone.npy",
                                               "missing": "gone.toml: no such",
                                               "unknown": "unknown scenario"}[broken]):
        experiment(cfg, expand_scenarios([scenario]), ["va"], [16], 1, 0, out, progress=False)
    assert not out.exists()


def test_the_saved_configuration_pins_one_scenario_and_its_layout_by_number():
    from common.scenarios import LAYOUTS
    cfg = load_config(overrides=["planner.brake_samples=1"])
    newest = saved_config(cfg, ["offroad"])
    assert (newest.episode.scenario, newest.episode.layout) == ("offroad", LAYOUTS["offroad"])
    old = saved_config(cfg.replace(**{"episode.layout": 1}), ["offroad"])
    assert old.episode.layout == 1
    assert config_digest(newest) == config_digest(old) == config_digest(cfg)
    assert newest.planner == cfg.planner and newest.vehicle == cfg.vehicle
    assert saved_config(cfg, ["alleyway", "offroad"]) == cfg        # one number cannot pin two


def records(out):
    """A directory's records by key, all but the solve and wall times."""
    return {tuple(x[k] for k in KEY_FIELDS):
            {k: v for k, v in x.items() if k not in ("solve_ms", "wall_time_s")}
            for x in read_runs(out / "runs.jsonl")}


@SERIAL
def test_worker_processes_give_the_records_of_one_process(tmp_path, serial):
    """--jobs 2: the runs spread over two pinned worker processes, the parent writing their
    records, are the in-process runs bit for bit (all but the solve and wall times)."""
    parallel = tmp_path / "parallel"
    r = run(parallel, 2, ["--no-plots", "--jobs", "2"])
    assert r.returncode == 0, r.stderr[-2000:]
    a, b = records(serial.out), records(parallel)
    assert len(a) == 6 and a == b
    assert (parallel / "summary.json").read_text() == (serial.out / "summary.json").read_text()
    assert run(tmp_path / "x", 1, ["--jobs", "0"]).returncode == 2


def _ray_tasks():
    """Processes running a Ray task of the experiment (Ray titles a worker by its task)."""
    found = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                if f.read().startswith(b"ray::run_task"):
                    found.append(int(pid))
        except OSError:
            pass
    return found


@SERIAL
def test_a_local_ray_cluster_gives_the_records_of_one_process_though_a_worker_dies(
        tmp_path, serial):
    """--cluster local --jobs 2: the runs as Ray tasks on two workers, one of them killed
    during its run; Ray runs that task again, and the records are the in-process ones bit
    for bit (all but the solve and wall times); resuming a complete directory starts no
    cluster."""
    out = tmp_path / "ray"
    cmd = [sys.executable, "-m", "deploy", "experiment", "--scenario", "alleyway",
           "--controllers", "va,deterministic,prescient", "--samples", "16", "--runs", "2",
           "--seed", "3", "--out", str(out), "--quiet", *SETTINGS, "--no-plots",
           "--cluster", "local", "--jobs", "2"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while not (busy := _ray_tasks()):            # a worker is running a run
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.05)
        os.kill(busy[0], signal.SIGKILL)
        _, err = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.wait(60)
    assert proc.returncode == 0, err[-3000:]
    assert not _alive(busy[0])
    assert records(out) == records(serial.out)
    assert (out / "summary.json").read_text() == (serial.out / "summary.json").read_text()
    again = subprocess.run(cmd[:-4] + ["--cluster", "ray://nowhere:1", "--jobs", "2"],
                           capture_output=True, text=True, timeout=300)
    assert again.returncode == 0 and "0 run(s) to do" in again.stderr, again.stderr[-2000:]
    gone = run(tmp_path / "gone", 1, ["--no-plots", "--cluster", "127.0.0.1:1"])
    assert gone.returncode == 2 and "Traceback" not in gone.stderr
    assert "vamppi experiment: no Ray cluster at 127.0.0.1:1" in gone.stderr, gone.stderr[-2000:]


def test_a_ray_worker_with_another_vamppi_or_world_refuses_the_run():
    from deploy.sim.cluster import ClusterError, run_task, source_digest
    cfg = load_config()
    key = ("alleyway", "va", 16, 0)
    with pytest.raises(ClusterError, match="is not the driver's"):
        run_task(cfg, key, "0123456789abcdef", None)
    with pytest.raises(ClusterError, match="another world there"):
        run_task(cfg, key, source_digest(), "0123456789abcdef")


def test_cpu_shares_are_disjoint_and_cover_the_cpus():
    cpus = sorted(os.sched_getaffinity(0))
    for jobs in range(1, len(cpus) + 1):
        shares = cpu_shares(jobs)
        assert len(shares) == jobs and all(shares)
        assert sorted(c for share in shares for c in share) == cpus
    assert cpu_shares(len(cpus) + 1) is None


def _children(pid):
    out = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True).stdout
    return [int(x) for x in out.split()]


def _alive(pid):
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


# SIGKILL: runs long enough (VA-MPPI at K = 16 stands still until a 20 s timeout, some 14 s
# of wall time here) that a worker left to finish its run would outlive the deadline below:
# the worker that wrote the first record is then at the start of its next run
@pytest.mark.parametrize("sig, controllers, timeout_s", [(signal.SIGTERM, "va,deterministic", 1.5),
                                                         (signal.SIGKILL, "va", 20.0)])
def test_a_stopped_experiment_stops_its_workers_and_keeps_its_runs(tmp_path, sig, controllers,
                                                                   timeout_s):
    out = tmp_path / "exp"
    proc = subprocess.Popen(
        [sys.executable, "-m", "deploy", "experiment", "--scenario", "alleyway",
         "--controllers", controllers, "--samples", "16", "--runs", "50", "--seed", "3",
         "--out", str(out), "--quiet", "--no-plots", "--jobs", "2",
         "--set", f"episode.timeout_s={timeout_s}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while not read_runs(out / "runs.jsonl"):                # the workers are at work
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.1)
        workers = _children(proc.pid)
        assert len(workers) >= 2
        proc.send_signal(sig)
        proc.wait(timeout=60)
        deadline = time.monotonic() + 3                # SIGKILL: the workers notice at once
        while any(_alive(w) for w in workers):
            assert time.monotonic() < deadline, [w for w in workers if _alive(w)]
            time.sleep(0.1)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    if sig == signal.SIGTERM:                          # unwinds as Ctrl-C does
        assert proc.returncode == 130 and "interrupted" in err, err[-2000:]
    kept = read_runs(out / "runs.jsonl")
    assert 1 <= len(kept) < 100 and all(x["outcome"] in OUTCOMES for x in kept)


def test_fisher_exact_matches_scipys_on_known_tables():
    from deploy.analysis.summary import fisher_exact
    # scipy.stats.fisher_exact (two-sided) gives these
    assert fisher_exact(0, 20, 12, 8) == pytest.approx(4.5095150768120733e-05, rel=1e-12)
    assert fisher_exact(3, 17, 5, 15) == pytest.approx(0.6947646947646948, rel=1e-12)
    assert fisher_exact(5, 5, 5, 5) == pytest.approx(1.0)


def test_summaries_by_kind_and_overall_pair_each_run_with_the_prescient_one():
    from deploy.analysis.summary import summary_markdown
    runs = []
    for world, kind in (("a.toml", "corner"), ("b.toml", "corner"), ("c.toml", "trees")):
        for seed in (0, 1):
            runs.append({"scenario": world, "kind": kind, "controller": "prescient",
                         "samples": 400, "seed": seed, "outcome": "success",
                         "time_to_goal_s": 10.0})
            runs.append({"scenario": world, "kind": kind, "controller": "va", "samples": 400,
                         "seed": seed, "outcome": "success" if seed == 0 else "collision",
                         "time_to_goal_s": 12.0 if seed == 0 else None})
    rows = {(r["kind"], r["controller"]): r for r in summarize(runs, "kind")}
    assert rows["corner", "va"]["worlds"] == 2 and rows["corner", "va"]["runs"] == 4
    assert rows["corner", "va"]["collision"] == 2
    assert rows["corner", "va"]["ratio_to_prescient_median"] == pytest.approx(1.2)
    assert rows["corner", "prescient"]["ratio_to_prescient_median"] is None
    assert rows["corner", "va"]["collision_p"]["prescient"] == pytest.approx(
        0.42857142857142855)                      # [[2, 2], [0, 4]]
    (overall,) = [r for r in summarize(runs, "all") if r["controller"] == "va"]
    assert overall["runs"] == 6 and overall["time_to_goal_median_s"] == 12.0
    text, per = summary_markdown(runs)
    assert "By kind:" in text and "| trees | va | 400 | 2 | 50 % | 50 % |" in text
    assert set(per) == {"scenario", "kind", "all"}


def test_a_record_without_its_format_is_told_by_its_content():
    row4, row5 = [0.0, 1.0, 2.0, 3.0], [0.0, 1.0, 2.0, 3.0, 0.5]
    assert record_format({"path": [row4]}) == 1
    assert record_format({"path": [row5]}) == 2
    assert record_format({"path": [row5], "layout": 2}) == 3
    assert record_format({"path": [row5], "layout": 2, "format": 7}) == 7


def test_every_committed_table_s_configuration_digests_to_its_records():
    """A parameter added since a table was made leaves its digest alone at the neutral
    value (`DIGEST_NEUTRAL`), so `--config DIR/config.toml` still resumes and reruns it.
    Tables of the paper's method made before options were added keep the older program's
    digest in their records (`tables.SAME_ARITHMETIC`; docs/results.md "Reproducing")."""
    from deploy.sim.tables import SAME_ARITHMETIC
    root = Path(__file__).resolve().parents[1] / "docs" / "results"
    tables = sorted(p for p in root.iterdir() if (p / "runs.jsonl").exists())
    assert len(tables) >= 20
    for t in tables:
        digest = config_digest(load_config(t / "config.toml"))
        records = {json.loads(line)["config_digest"]
                   for line in (t / "runs.jsonl").read_text().splitlines()}
        assert records == {digest} or (len(records) == 1 and set(SAME_ARITHMETIC) >= records), (
            t.name, digest, records)
    assert config_digest(load_config(overrides={"planner.turn_radius_speed": True})) != \
        config_digest(load_config())
