"""The whole pipeline: services as real subprocesses on a real Zenoh router, lockstep."""

import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from common.config import load_config
from common.messages import Event, State, decode
from common.topics import topic_key
from deploy.launch.up import services_up
from deploy.sim.runner import run_episode
from services.plant.protocol import OUTCOMES

pytestmark = pytest.mark.integration

SHORT = ["planner.samples=64", "episode.timeout_s=2.0", 'episode.scenario="open-field"']


def bus_episode(overrides, timeout_s=300.0):
    """Run one lockstep episode across processes; the 50 Hz trajectory (t, x) and outcome."""
    cfg = load_config(overrides=overrides)
    rows, outcome, lock = [], [], threading.Lock()
    done = threading.Event()

    def on_state(sample):
        m = decode(sample.payload.to_bytes(), State)
        with lock:
            rows.append(np.concatenate([[m.header.stamp], m.x]))

    def on_event(sample):
        e = decode(sample.payload.to_bytes(), Event)
        if e.kind in OUTCOMES:
            outcome.append(e)
            done.set()

    subs = {topic_key(cfg.episode.vehicle, "state"): on_state,
            topic_key(cfg.episode.vehicle, "events"): on_event}
    with services_up(cfg, overrides, subscriptions=subs):
        assert done.wait(timeout_s), "no outcome"
        time.sleep(0.3)
    # a tick nobody answered in plant.reoffer_s (a busy machine) is offered again: the
    # same state, once in the trajectory
    ticks: dict[float, np.ndarray] = {}
    for r in rows:
        assert r.tobytes() == ticks.setdefault(r[0], r).tobytes(), "a re-offer differs"
    return np.array(list(ticks.values())), outcome[0]


def test_lockstep_is_bit_identical_across_runs_and_equals_the_in_process_runner():
    ref = run_episode(load_config(overrides=SHORT))
    a, ev_a = bus_episode(SHORT)
    b, ev_b = bus_episode(SHORT)
    assert ev_a.kind == ev_b.kind == ref.outcome
    assert a.shape == ref.trajectory.shape == b.shape
    assert a.tobytes() == b.tobytes()
    assert a.tobytes() == ref.trajectory.tobytes()
    assert a[-1, 4] > ref.trajectory[0, 4] + 1.0      # it moved


def test_the_bus_pipeline_runs_a_scenario_file_as_the_in_process_runner_does(tmp_path):
    """Every service loads the same file (here a copy of a built-in's, moved): the same
    trajectory as in-process, bit for bit."""
    from common.scenarios import BUILTINS
    world = tmp_path / "elsewhere.toml"
    world.write_text(BUILTINS["open-field"][1].read_text())
    over = [*SHORT[:2], f'episode.scenario="{world}"']
    ref = run_episode(load_config(overrides=over))
    got, ev = bus_episode(over)
    assert ev.kind == ref.outcome
    assert got.tobytes() == ref.trajectory.tobytes()
    assert got[-1, 4] > got[0, 4] + 1.0               # it moved


def test_vamppi_up_reaches_the_goal_and_prints_the_summary():
    r = subprocess.run([sys.executable, "-m", "deploy", "up", "--scenario", "open-field",
                        "--samples", "256", "--clock", "lockstep", "--seed", "1"],
                       capture_output=True, text=True, timeout=600)
    last = json.loads(r.stdout.strip().splitlines()[-1])
    assert set(last) == {"scenario", "controller", "samples", "seed", "outcome",
                         "time_to_goal_s", "sim_time_s", "wall_time_s", "restarts", "failure",
                         "router"}
    assert last["router"].startswith("tls/localhost:") and f"router on {last['router']}" in \
        r.stderr
    assert last["outcome"] == "success", r.stderr[-3000:]
    assert last["restarts"] == {} and last["failure"] is None
    assert r.returncode == 0
    assert last["samples"] == 256 and last["seed"] == 1 and last["time_to_goal_s"] < 15


def _processes_with(marker: str) -> list[int]:
    out = []
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            try:
                with open(f"/proc/{pid}/cmdline", "rb") as f:
                    if marker.encode() in f.read():
                        out.append(int(pid))
            except OSError:
                pass
    return out


def test_ctrl_c_stops_every_process():
    marker = f"ctrlc{os.getpid()}"
    p = subprocess.Popen([sys.executable, "-m", "deploy", "up", "--samples", "64",
                          "--vehicle", marker], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:
        line = p.stderr.readline()
        if "all services up" in line or not line:
            break
    assert len(_processes_with(marker)) >= 5         # launcher + four services
    time.sleep(2.0)                                   # mid-episode
    os.killpg(p.pid, signal.SIGINT)                   # what a terminal's Ctrl-C does
    p.communicate(timeout=60)
    assert p.returncode in (130, 0, 1)
    time.sleep(0.5)
    assert _processes_with(marker) == []
