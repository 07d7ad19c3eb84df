"""The live view (`vamppi view`): a Foxglove WebSocket client connects, subscribes to every
channel and checks what arrives against the schemas; the converter's camera transform;
the latest-value slots that keep a slow viewer out of the pipeline's way."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time

import numpy as np
import pytest

from common.bus import MemoryBus, MemoryTransport
from common.config import load_config
from common.messages import Depth, Event, Map, Plan, State, Stats, encode
from common.protocol import Out, Stamper
from common.topics import topic_key
from deploy.launch.up import free_port
from deploy.recording.foxglove import SCHEMAS, TOPICS, camera_mount, quaternion, violations
from deploy.recording.view import KEEP, VIEWED, Latest, Viewer, watch
from services.sensor.core import CameraParams, camera_pose


def check(got: dict[str, list[dict]]) -> dict[str, list[dict]]:
    """Every channel advertised as ours, every message conforming to its schema; the
    bodies per topic."""
    for topic, msgs in got.items():
        for m in msgs:
            ch = m["channel"]
            assert ch["encoding"] == "json" and ch["schemaEncoding"] == "jsonschema"
            assert TOPICS[topic] == ch["schemaName"]
            assert json.loads(ch["schema"]) == SCHEMAS[ch["schemaName"]]
            assert m["violations"] == [], (topic, m["violations"])
    return {topic: [m["body"] for m in msgs] for topic, msgs in got.items()}


# ----------------------------------------------------------------------------- messages
def _messages(t: float, cam: CameraParams) -> dict[str, bytes]:
    st = Stamper("test/0")

    def make(cls, **fields):
        return encode(st.make(cls, Out(topic="", stamp=t, fields=fields)))
    pos, rot = camera_pose(cam, 3.0, 4.0, 0.1, 0.5)
    rng = np.random.default_rng(int(t * 10))
    return {
        "state": make(State, x=np.array([2.0, 0.0, 0.0, 3.0, 4.0, 0.5]), z=0.1,
                      u_applied=np.zeros(2), tick=int(t * 10), authority="planner/0"),
        "map": make(Map, mean=rng.normal(size=(20, 20)).astype("<f4"),
                    variance=rng.uniform(0, 1, (20, 20)).astype("<f4"),
                    origin=np.array([-5.0, -5.0]), resolution=0.5),
        "plan": make(Plan, controller="va", optimal=rng.normal(size=(11, 6)).astype("<f4"),
                     nominal=np.zeros((10, 2), "<f4"),
                     rollouts=rng.normal(size=(4, 11, 2)).astype("<f4"),
                     rollout_costs=np.ones(4, "<f4")),
        "depth": make(Depth, depth=rng.uniform(0, 9, (6, 8)).astype("<f4"),
                      intrinsics=np.array([4.0, 4.0, 3.5, 2.5]), cam_position=pos,
                      cam_rotation=rot, base_pose=np.array([3.0, 4.0, 0.1, 0.5]),
                      range_max=10.0),
        "events": make(Event, kind="start", outcome="", time_to_goal_s=math.nan, detail=""),
        "stats": make(Stats, controller="va", samples=16, solve_ms=1.5, cost_min=1.0,
                      cost_mean=2.0, terms={"goal": 1.0}),
    }


def test_viewer_serves_every_channel_in_its_schema():
    """Every bus topic the view follows arrives on each of its Foxglove channels, decoded
    against the channel's schema; what nobody watches is not converted."""
    cam = CameraParams.from_config(load_config().sensor)
    bus = MemoryBus()
    viewer = Viewer(MemoryTransport(bus), "v0", cam, port=0, rate_hz=50, map_hz=50)
    try:
        for topic, payload in _messages(0.0, cam).items():
            bus.put(topic_key("v0", topic), payload)
        time.sleep(0.2)
        assert viewer.stats()["unwatched"] == {t: 1 for t in VIEWED if t != "state"}
        stop = False

        def feed() -> None:
            t = 0.1
            while not stop:
                for topic, payload in _messages(t, cam).items():
                    bus.put(topic_key("v0", topic), payload)
                t += 0.1
                time.sleep(0.02)
        import threading
        th = threading.Thread(target=feed, daemon=True)
        th.start()
        got = check(watch(viewer.port, 20.0, set(TOPICS)))
        stop = True
        th.join()
    finally:
        stats = viewer.close()
    assert set(got) == set(TOPICS), stats
    frames = {(m["parent_frame_id"], m["child_frame_id"]) for m in got["/tf"]}
    assert frames == {("world", "base_link"), ("base_link", "camera")}
    assert got["/sensor/depth"][0]["frame_id"] == "camera"
    assert stats["errors"] == stats["undecodable"] == 0


def test_latest_keeps_the_newest_and_counts_what_it_drops():
    slots = Latest({"events": 3})
    for i in range(5):
        slots.put("map", bytes([i]))
        slots.put("events", bytes([i]))
    got = slots.take()
    assert got == {"map": [b"\x04"], "events": [b"\x02", b"\x03", b"\x04"]}
    assert slots.dropped == {"map": 4, "events": 2} and slots.received == {"map": 5,
                                                                          "events": 5}
    assert slots.take(timeout=0.01) == {}
    slots.put("map", b"x")
    assert slots.take({"events"}) == {} and slots.take({"map"}) == {"map": [b"x"]}
    assert KEEP["events"] > 1


def _rotation_of(q: dict[str, float]) -> np.ndarray:
    """The rotation matrix of a unit quaternion (the textbook formula, float64)."""
    x, y, z, w = q["x"], q["y"], q["z"], q["w"]
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def test_quaternion_of_random_rotations_against_the_matrix():
    rng = np.random.default_rng()
    worst = 0.0
    for _ in range(2000):
        r, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        r *= np.sign(np.linalg.det(r))                  # a proper rotation
        q = quaternion(r)
        assert abs(math.hypot(*q.values()) - 1.0) < 1e-12
        worst = max(worst, float(np.abs(_rotation_of(q) - r).max()))
    assert worst < 3e-15, worst                          # observed: 1.9e-15 over 20000


def test_camera_mount_places_the_camera_where_the_sensor_renders_from():
    """world -> base_link -> camera, composed, is the sensor's camera pose."""
    cam = CameraParams.from_config(load_config().sensor)
    m = camera_mount(cam)
    x, y, z, yaw = 3.0, -2.0, 0.7, 1.1
    base = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0],
                     [0, 0, 1]])
    t = np.array([m["translation"][k] for k in "xyz"])
    pos, rot = camera_pose(cam, x, y, z, yaw)
    np.testing.assert_allclose(np.array([x, y, z]) + base @ t, pos, atol=1e-12)
    np.testing.assert_allclose(base @ _rotation_of(m["rotation"]), rot, atol=1e-12)


def test_violations_finds_what_breaks_a_schema():
    grid = SCHEMAS["foxglove.Grid"]
    ok = {"column_count": 3, "data": "AAAA", "cell_size": {"x": 0.5, "y": 0.5}}
    assert violations(grid, ok) == []
    assert violations(grid, {**ok, "column_count": -1}) == ["$.column_count: -1 < 0"]
    assert violations(grid, {**ok, "data": "no base64!"}) == ["$.data: not base64"]
    assert violations(grid, {**ok, "cell_size": {"x": "1"}}) == [
        "$.cell_size.x: str is not number"]
    assert violations(SCHEMAS["foxglove.PosesInFrame"], {"poses": [{"position": []}]}) == [
        "$.poses[0].position: list is not object"]


@pytest.mark.integration
def test_up_view_serves_the_episode_live(tmp_path):
    """`vamppi up --view`: a client connected while the episode runs gets every channel,
    in its schema, and the episode ends as without a viewer."""
    port = free_port()
    up = subprocess.Popen(
        [sys.executable, "-m", "deploy", "up", "--scenario", "open-field", "--controller",
         "deterministic", "--samples", "64", "--clock", "lockstep", "--seed", "0",
         "--view", "--view-port", str(port)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        got = check(watch(port, 120.0, set(TOPICS) - {"/events"}))
        out, err = up.communicate(timeout=120)
    finally:
        if up.poll() is None:
            up.kill()
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["outcome"] == "success", err[-3000:]
    assert set(TOPICS) - {"/events"} <= set(got), (sorted(got), summary.get("view"))
    view = summary["view"]
    assert view["errors"] == view["undecodable"] == 0
    assert view["received"]["state"] > 10 and view["published"]["/tf"] > 10
    assert f"router on {summary['router']}" in err
