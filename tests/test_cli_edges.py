"""The command line's sharp edges, each reproduced: a clear line and an exit code instead of
a traceback; the pipeline found without --connect; a standalone recorder that stores the
services' configuration; services that say where their configurations disagree; a
recording of a replay that says so."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from common.bus import MemoryBus, MemoryTransport, Node, ZenohTransport, open_session
from common.config import agreement_digest, disagreements, load_config
from common.messages import State, encode
from common.protocol import Out, Stamper
from common.topics import heartbeat_key, topic_key
from deploy.launch import running
from deploy.launch.up import free_port, router_config
from deploy.recording import timing
from deploy.recording.record import (
    Recorder,
    RecordingWriter,
    recorded_config,
    recording_label,
    recording_metadata,
)
from deploy.recording.replay import feed_config, replay


def vamppi(*argv: str, env: dict[str, str] | None = None, timeout: float = 120
           ) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "deploy", *argv], capture_output=True,
                          text=True, timeout=timeout, env={**os.environ, **(env or {})})


@pytest.fixture
def runtime(tmp_path, monkeypatch):
    """An empty runtime directory: no `vamppi up` announced."""
    d = tmp_path / "run"
    d.mkdir()
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(d))
    return {"XDG_RUNTIME_DIR": str(d)}


@pytest.mark.parametrize("argv", [("health",), ("record", "-o", "x.mcap", "--duration", "1"),
                                  ("view", "--duration", "1"), ("swap", "planner"),
                                  ("health", "--connect", "tcp/127.0.0.1:9")])
def test_bus_commands_without_a_router_say_so_in_one_line(argv, runtime, tmp_path):
    r = vamppi(*argv, env=runtime)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and "ZError" not in r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith(f"vamppi {argv[0]}: ")
    assert ("no router to connect to" in last) == ("--connect" not in argv)


def test_replay_of_a_missing_file_says_so_before_the_bus(runtime, tmp_path):
    r = vamppi("replay", str(tmp_path / "none.mcap"), env=runtime)
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        f"vamppi replay: no such recording: {tmp_path / 'none.mcap'}"]


@pytest.mark.parametrize("argv", [("config", "--markdown"), ("scenario", "--scenario", "offroad"),
                                  ("config",)])
def test_output_piped_into_a_closed_reader_is_no_traceback(argv):
    """`vamppi config | head`: the reader is gone before the first write."""
    p = subprocess.Popen([sys.executable, "-m", "deploy", *argv], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    p.stdout.close()
    err = p.stderr.read()
    assert p.wait(60) == 141 and err == "", err


def test_bench_peer_without_its_extra_is_one_line():
    pytest.importorskip("pytest")
    try:
        import pytorch_mppi  # noqa: F401
        pytest.skip("the peer extra is installed")
    except ImportError:
        pass
    r = vamppi("bench", "peer", "--samples", "8", "--reps", "1")
    assert r.returncode == 2 and r.stderr.strip().splitlines()[-1] == (
        "vamppi bench peer: needs the optional extra: pip install -e '.[peer]' "
        "(torch, pytorch-mppi)")


def test_router_help_offers_no_episode_flags():
    out = vamppi("router", "--help").stdout
    assert "--set" in out and "--scenario" not in out and "--controller" not in out


# ----------------------------------------------------------------------------- finding up
def test_a_running_up_is_found_and_a_dead_one_forgotten(runtime):
    assert running.locate("v0") is None
    with running.announce("tcp/127.0.0.1:5", "v0", ""):
        found = running.locate("v0")
        assert found is not None and found.pid == os.getpid()
        assert found.endpoint == "tcp/127.0.0.1:5" and running.locate("v1") is None
    assert running.locate("v0") is None
    dead = subprocess.Popen(["true"])
    dead.wait()
    stale = running.runtime_dir() / f"up-{dead.pid}.json"
    stale.write_text(json.dumps({"pid": dead.pid, "endpoint": "tcp/127.0.0.1:6", "vehicle": "v0",
                                 "certs": "", "started": time.time()}))
    assert running.locate("v0") is None and not stale.exists()


@pytest.mark.integration
def test_health_finds_the_router_of_a_running_up_by_itself(runtime):
    """A router announced as `vamppi up` announces its own: `vamppi health` with no
    --connect reaches it (no service there: exit 1 and says so, not 'no router')."""
    port = free_port()
    with open_session(router_config(port)), running.announce(f"tcp/127.0.0.1:{port}", "v0", ""):
        r = vamppi("health", env=runtime)
    assert r.returncode == 1, r.stderr
    assert f"connecting to the router of vamppi up (pid {os.getpid()})" in r.stderr
    assert "no live service under vehicle 'v0'" in r.stderr


# ----------------------------------------------------------------------------- recorder
def test_a_standalone_recorder_stores_the_services_configurations(tmp_path):
    """Started before the services (the natural order): it stores what each service
    runs, also one that comes later, not its own defaults; unknown stays unknown."""
    bus = MemoryBus()
    path = tmp_path / "rec.mcap"
    rec = Recorder(MemoryTransport(bus), "vamppi/v0/**", path,
                   recording_metadata(None, "vamppi/v0/**", "v0"), clock_sync_s=None)
    plant_cfg = load_config(overrides=['episode.scenario="offroad"', 'episode.clock="realtime"'])
    planner_cfg = plant_cfg.replace(**{"planner.controller": "va", "planner.samples": 400})
    with Node(MemoryTransport(bus), "v0", "plant", "0", plant_cfg.to_dict()):
        time.sleep(0.5)
        with Node(MemoryTransport(bus), "v0", "planner", "0", planner_cfg.to_dict()):
            time.sleep(0.5)
    rec.stop()
    assert recorded_config(path, "plant") == plant_cfg.to_dict()
    assert recorded_config(path, "planner") == planner_cfg.to_dict()
    assert recording_label(path) == {"scenario": "offroad", "clock": "realtime",
                                     "controller": "va", "samples": "400"}

    empty = tmp_path / "empty.mcap"
    Recorder(MemoryTransport(MemoryBus()), "vamppi/v0/**", empty,
             recording_metadata(None, "vamppi/v0/**", "v0"), clock_sync_s=None).stop()
    assert recorded_config(empty) == {} and set(recording_label(empty).values()) == {"unknown"}
    with pytest.raises(ValueError, match="no configuration"):
        feed_config(empty, [])


# ----------------------------------------------------------------------------- agreement
def test_services_say_where_their_configurations_disagree(caplog):
    base = load_config()
    heavier = base.replace(**{"vehicle.mass_kg": 1800.0})
    assert disagreements(base.to_dict(), heavier.to_dict()) == ["vehicle.mass_kg: 1650.0 vs 1800.0"]
    assert agreement_digest(base.to_dict()) != agreement_digest(heavier.to_dict())
    # a planner setting is the planner's own business: no disagreement
    assert agreement_digest(base.replace(**{"planner.samples": 16}).to_dict()) == \
        agreement_digest(base.to_dict())
    bus = MemoryBus()
    with Node(MemoryTransport(bus), "v0", "plant", "0", base.to_dict()) as plant, \
            Node(MemoryTransport(bus), "v0", "planner", "0", heavier.to_dict()) as planner, \
            Node(MemoryTransport(bus), "v0", "mapper", "0", base.to_dict()) as mapper:
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not (plant.disagreements and mapper.disagreements
                                                    and len(planner.disagreements) == 2):
            time.sleep(0.05)
    assert plant.disagreements == {"planner/0": ["vehicle.mass_kg: 1650.0 vs 1800.0"]}
    assert planner.disagreements == {"plant/0": ["vehicle.mass_kg: 1800.0 vs 1650.0"],
                                     "mapper/0": ["vehicle.mass_kg: 1800.0 vs 1650.0"]}
    assert mapper.disagreements == {"planner/0": ["vehicle.mass_kg: 1650.0 vs 1800.0"]}
    assert plant.health.as_dict()["config_disagreements"] == 1
    assert "vehicle.mass_kg: 1650.0 vs 1800.0" in caplog.text


# ----------------------------------------------------------------------------- replay
@pytest.mark.integration
def test_a_recording_of_a_replay_says_so_and_times_the_replay(tmp_path):
    """Messages published 1000 s ago, replayed and recorded again: timing names the
    replay, and the transport it measures is the replay's (not 1000 s)."""
    old = tmp_path / "old.mcap"
    w = RecordingWriter(old, recording_metadata(load_config().to_dict(), "vamppi/v0/**"))
    st = Stamper("plant/0", wall=lambda: time.time() - 1000.0)
    t0 = time.time_ns() - 1000 * 10**9
    for i in range(30):
        msg = st.make(State, Out(topic="state", stamp=i * 0.1, fields={
            "x": np.zeros(6), "z": 0.0, "u_applied": np.zeros(2), "tick": i,
            "authority": "planner/0"}))
        w.add(topic_key("v0", "state"), encode(msg), t0 + i * 10**8)
    w.close()

    again = tmp_path / "again.mcap"
    port = free_port()
    with open_session(router_config(port)) as session:
        rec = Recorder(ZenohTransport(session), "vamppi/v0/**", again,
                       recording_metadata(None, "vamppi/v0/**", "v0"), clock_sync_s=None)
        report = replay(session, old, rate=0)
        rec.stop()
    assert report["published"] == 30
    t = timing.analyse(again)
    assert t["replayed"] == ["replay of old.mcap"]
    state = next(r for r in t["topics"] if r["key"] == topic_key("v0", "state"))
    assert state["messages"] == 30 and state["transport"]["max_ms"] < 1000.0
    assert any(r["key"] == heartbeat_key("v0", "replay") for r in t["topics"])
    assert "a recording of a replay (replay of old.mcap)" in timing.table(t)
    assert Path(again).stat().st_size > 0


# ----------------------------------------------------------------------------- pictures
def test_scenario_picture_explains_its_numbers_and_goal_and_plots_say_what_they_show(
        tmp_path, monkeypatch):
    from deploy.analysis import plots
    seen = {}
    real = plots.save_figure

    def keep(fig, path, *a, **kw):
        seen[Path(path).name] = (fig, kw.get("title", ""))
        legend = fig.axes[0].get_legend()
        seen[Path(path).name + ":legend"] = [t.get_text() for t in legend.get_texts()] \
            if legend else []
        return real(fig, path, *a, **kw)
    monkeypatch.setattr(plots, "save_figure", keep)
    plots.plot_scenario(load_config(), "alleyway", tmp_path / "alley.png")
    legend = seen["alley.png:legend"]
    assert any(t.startswith("goal region: within 2 m of the goal, below 1 m/s") for t in legend)
    assert any("hidden" in t for t in legend) and any(t.startswith("n: obstacle") for t in legend)

    runs = [{"scenario": "alleyway", "controller": c, "samples": k, "seed": 0,
             "outcome": "success", "time_to_goal_s": 10.0, "max_speed_mps": 5.0,
             "path": [[0, 10, 40, 1, 0], [1, 20, 40, 5, 0]], "solve_ms": [9, 8, 7]}
            for c in ("va", "deterministic") for k in (16, 32)]
    from deploy.analysis.summary import summarize
    out = tmp_path / "exp-name"
    out.mkdir()
    plots.plot_failures(summarize(runs), out, "experiment exp-name")
    plots.plot_trajectories(load_config(), runs, "alleyway", out, "experiment exp-name")
    fig, title = seen["trajectories_alleyway.png"]
    assert title == "experiment exp-name" and fig.get_suptitle() == "experiment exp-name"
    assert [ax.get_title() for ax in fig.axes[:2]] == [
        "alleyway, deterministic, K = 16, 32: 2 runs, 0 collisions (x)",
        "alleyway, va, K = 16, 32: 2 runs, 0 collisions (x)"]
