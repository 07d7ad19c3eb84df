"""The bus wrapper: through a real Zenoh router on loopback, and on the in-memory bus."""

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from common.bus import (
    MemoryBus,
    MemoryTransport,
    Node,
    ZenohTransport,
    alive_instances,
    open_session,
    query_json,
)
from common.config import BusConfig
from common.messages import Header, Heartbeat, Map, State, decode, encode
from common.protocol import SeqTrack
from common.topics import admin_key, heartbeat_key, key_matches


def client(endpoint):
    return BusConfig("client", (endpoint,), (), False)


def a_state(seq: int, source: str = "plant/0", boot: int = 1) -> State:
    return State(Header(seq, 0.02 * seq, time.time(), source, (), boot, 1), x=np.zeros(6),
                 z=0.0, u_applied=np.zeros(2), tick=seq // 5, authority="planner/0")


@pytest.mark.integration
def test_typed_pub_sub_health_and_liveliness(router):
    with Node(client(router), "vt", "mapper", "a") as pub_node, \
            Node(client(router), "vt", "planner", "b") as sub_node:
        inbox = sub_node.subscribe("map", Map, maxlen=16)
        pub = pub_node.publisher("map", Map)
        pub_node.ready()
        sub_node.ready()
        time.sleep(0.5)
        mean = np.random.default_rng().normal(size=(400, 400)).astype(np.float32)
        for i in range(3):
            pub.publish(0.1 * i, mean=mean + i, variance=np.ones_like(mean),
                        origin=np.zeros(2), resolution=0.2)
        got = [inbox.get(timeout=5.0) for _ in range(3)]
        assert [m.header.seq for m in got] == [0, 1, 2]
        assert got[2].mean.tobytes() == (mean + 2).tobytes()
        assert got[0].header.source == "mapper/a" and got[0].header.boot == pub_node.boot

        # a malformed payload and a wrong-type payload: dropped, counted, no crash
        with open_session(client(router)) as s:
            raw = ZenohTransport(s)
            s.put(sub_node.key("map"), b"\x00garbage")
            bad = Map(Header(0, 0.0, 0.0, "x"), mean=mean, variance=-np.ones_like(mean),
                      origin=np.zeros(2), resolution=0.2)
            s.put(sub_node.key("map"), encode(bad))
            time.sleep(0.5)
            health = query_json(raw, admin_key("vt", "planner", "b", "health"))
            assert health and health[0]["dropped"] == 2
            assert "variance" in health[0]["last_error"]
            assert health[0]["messages_in"] == 3
            alive = alive_instances(raw, "vt")
            assert ("mapper", "a") in alive and ("planner", "b") in alive
            cfg = query_json(raw, admin_key("vt", "mapper", "a", "config"))
            assert cfg == [{}]


@pytest.mark.integration
def test_latest_value_inbox_never_queues(router):
    with Node(client(router), "vt", "mapper", "a") as a, Node(client(router), "vt", "x", "b") as b:
        inbox = b.subscribe("map", Map, maxlen=1)
        pub = a.publisher("map", Map)
        time.sleep(0.5)
        z = np.zeros((4, 4), np.float32)
        for i in range(20):
            pub.publish(float(i), mean=z, variance=z, origin=np.zeros(2), resolution=0.2)
        time.sleep(0.5)
        m = inbox.get(timeout=1.0)
        assert m.header.seq == 19 and inbox.get(timeout=0.1) is None
        assert b.health.superseded == 19


@pytest.mark.integration
def test_vamppi_health_lists_live_instances(router):
    with Node(client(router), "vh", "sensor", "s1") as node:
        node.ready()
        time.sleep(0.3)
        r = subprocess.run([sys.executable, "-m", "deploy", "health", "--connect", router,
                            "--vehicle", "vh"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    rows = [json.loads(line) for line in r.stdout.splitlines()]
    assert rows == [{"service": "sensor", "instance": "s1",
                     "health": {"messages_in": 0, "messages_out": 0, "dropped": 0,
                                "superseded": 0, "last_error": ""}}]


def test_key_expressions_match_as_zenoh_matches_them():
    assert key_matches("vamppi/v/**", "vamppi/v/plant/state")
    assert key_matches("vamppi/v/*/heartbeat", "vamppi/v/plant/heartbeat")
    assert not key_matches("vamppi/v/*/heartbeat", "vamppi/v/alive/plant/heartbeat")
    assert key_matches("vamppi/v/admin/*/*/latest/*", "vamppi/v/admin/planner/0/latest/map")
    assert key_matches("a/**/c", "a/c") and key_matches("a/**/c", "a/b/b/c")
    assert not key_matches("a/*", "a") and not key_matches("a/b", "a/b/c")


def test_a_flood_from_one_source_never_displaces_another_source():
    bus = MemoryBus()
    with Node(MemoryTransport(bus), "v", "plant", "0") as rx:
        inbox = rx.subscribe("state", State, maxlen=1)
        inbox_fifo = rx.subscribe("state", State, maxlen=4)
        key = rx.key("state")
        bus.put(key, encode(a_state(0)))
        for i in range(100):                           # another client, its own id
            bus.put(key, encode(a_state(i, "rogue/9")))
        got = [m for m, _ in inbox.drain()]
        assert [(m.header.source, m.header.seq) for m in got] == [("plant/0", 0),
                                                                  ("rogue/9", 99)]
        got = [m for m, _ in inbox_fifo.drain()]
        assert [m.header.source for m in got] == ["plant/0"] + ["rogue/9"] * 4
        assert rx.health.superseded == 99 + 96


def test_seq_gaps_are_exact_per_publisher_and_late_arrivals_fill_them():
    t = SeqTrack()
    for s in [0, 1, 2, 5, 6, 9, 3, 10, 6]:
        t.see(s)
    assert t.gaps == [[4, 4], [7, 8]] and t.missing == 3
    assert t.late == 1 and t.duplicates == 1 and t.count == 8 and t.last == 10
    bus = MemoryBus()
    with Node(MemoryTransport(bus), "v", "sensor", "0") as rx:
        rx.subscribe("state", State, maxlen=16)
        for s in (0, 1, 4, 5):
            bus.put(rx.key("state"), encode(a_state(s)))
        for s in (0, 1):                               # the plant restarted: a new boot
            bus.put(rx.key("state"), encode(a_state(s, boot=2)))
        gaps = rx.health.as_dict()["seq_gaps"]
        assert gaps == {"state plant/0 1": {"missing": 2, "gaps": [[2, 3]], "late": 0,
                                            "duplicates": 0}}


def test_heartbeats_say_starting_ready_then_stalled_when_the_main_loop_stops():
    bus = MemoryBus()
    beats = []
    watcher = MemoryTransport(bus)
    watcher.subscriber(heartbeat_key("v"), lambda k, p: beats.append(decode(p, Heartbeat)))
    with Node(MemoryTransport(bus), "v", "mapper", "0", heartbeat_s=0.02, deadline_s=0.2) as n:
        time.sleep(0.1)
        n.ready()
        for _ in range(10):
            n.progress(1.5, 7)
            time.sleep(0.02)
        time.sleep(0.4)                                 # the main loop wedged
    status = [b.status for b in beats]
    assert status[0] == "starting" and "ready" in status and status[-1] == "stopping"
    assert "stalled" in status[status.index("ready"):]
    ready = [b for b in beats if b.status == "ready"]
    assert ready[-1].header.stamp == 1.5 and ready[-1].header.episode == 7
    assert all(b.deadline_s == 0.2 and b.header.source == "mapper/0" for b in beats)
    assert watcher.tokens("vamppi/v/alive/**") == []    # the token went with the node


def test_latest_values_are_served_to_whoever_asks():
    bus = MemoryBus()
    with Node(MemoryTransport(bus), "v", "planner", "0") as holder, \
            Node(MemoryTransport(bus), "v", "mapper", "0") as asker:
        holder.hold("state", lambda: encode(a_state(3)))
        holder.hold("map", lambda: None)
        got = asker.query_latest("state", State)
        assert [m.header.seq for m in got] == [3]
        assert asker.query_latest("map", Map) == []
