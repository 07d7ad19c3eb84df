"""The whole pipeline: services as real subprocesses on a real Zenoh router, lockstep."""

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


def test_lockstep_is_bit_identical_across_runs_and_scenario_files_and_in_process(tmp_path):
    """Two bus episodes, one on a built-in scenario and one on a copy of its file moved
    elsewhere (every service loads that file): the same trajectory as each other and as
    the in-process runner, bit for bit."""
    from common.scenarios import BUILTINS
    world = tmp_path / "elsewhere.toml"
    world.write_text(BUILTINS["open-field"][1].read_text())
    ref = run_episode(load_config(overrides=SHORT))
    a, ev_a = bus_episode(SHORT)
    b, ev_b = bus_episode([*SHORT[:2], f'episode.scenario="{world}"'])
    assert ev_a.kind == ev_b.kind == ref.outcome
    assert a.shape == ref.trajectory.shape == b.shape
    assert a.tobytes() == b.tobytes()
    assert a.tobytes() == ref.trajectory.tobytes()
    assert a[-1, 4] > ref.trajectory[0, 4] + 1.0      # it moved


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
