"""The bus wrapper through a real Zenoh router on loopback."""

import time

import numpy as np
import pytest

from common.bus import Node, admin_key, alive_instances, open_session, query_json
from common.config import BusConfig
from common.messages import Header, Map, encode

pytestmark = pytest.mark.integration


def client(endpoint):
    return BusConfig("client", (endpoint,), (), False)


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
        assert got[0].header.source == "mapper/a"

        # a malformed payload and a wrong-type payload: dropped, counted, no crash
        with open_session(client(router)) as raw:
            raw.put(sub_node.key("map"), b"\x00garbage")
            bad = Map(Header(0, 0.0, 0.0, "x"), mean=mean, variance=-np.ones_like(mean),
                      origin=np.zeros(2), resolution=0.2)
            raw.put(sub_node.key("map"), encode(bad))
            time.sleep(0.5)
            health = query_json(raw, admin_key("vt", "planner", "b", "health"))
            assert health and health[0]["dropped"] == 2
            assert "variance" in health[0]["last_error"]
            assert health[0]["messages_in"] == 3
            alive = alive_instances(raw, "vt")
            assert ("mapper", "a") in alive and ("planner", "b") in alive
            cfg = query_json(raw, admin_key("vt", "mapper", "a", "config"))
            assert cfg == [{}]


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


def test_vamppi_health_lists_live_instances(router):
    import json
    import subprocess
    import sys
    with Node(client(router), "vh", "sensor", "s1") as node:
        node.ready()
        time.sleep(0.3)
        r = subprocess.run([sys.executable, "-m", "deploy.cli", "health", "--connect", router,
                            "--vehicle", "vh"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    rows = [json.loads(line) for line in r.stdout.splitlines()]
    assert rows == [{"service": "sensor", "instance": "s1",
                     "health": {"messages_in": 0, "messages_out": 0, "dropped": 0,
                                "superseded": 0, "last_error": ""}}]
