"""The services' shells (node.py) on the in-memory bus: no router, no processes."""

import threading
import time

import numpy as np

from common.bus import MemoryBus, MemoryTransport, query_json
from common.config import load_config
from common.messages import Cmd, InputRef, State, decode, encode
from common.protocol import Out, Stamper
from common.topics import admin_key, alive_key, topic_key
from deploy.sim.runner import run_episode
from services.mapper import node as mapper_node
from services.planner import node as planner_node
from services.plant import node as plant_node
from services.sensor import node as sensor_node

SHORT = ["planner.samples=16", "episode.timeout_s=1.0", 'episode.scenario="open-field"']


def test_the_four_nodes_on_the_memory_bus_give_the_in_process_trajectory():
    cfg = load_config(overrides=SHORT)
    bus, stop = MemoryBus(), threading.Event()
    rows, lock = {}, threading.Lock()

    def on_state(_key, payload):
        s = decode(payload, State)
        with lock:
            rows.setdefault(round(s.header.stamp, 6), np.concatenate([[s.header.stamp], s.x]))
    watch = MemoryTransport(bus)
    watch.subscriber(topic_key("v0", "state"), on_state)
    outcome = []
    threads = [threading.Thread(target=lambda m=m: m.main(cfg, "0", stop, MemoryTransport(bus)),
                                daemon=True)
               for m in (sensor_node, mapper_node, planner_node)]
    threads.append(threading.Thread(target=lambda: outcome.append(
        plant_node.main(cfg, "0", stop, MemoryTransport(bus))), daemon=True))
    for t in threads:
        t.start()
    threads[-1].join(240)
    stop.set()
    for t in threads:
        t.join(5)
    assert outcome == ["timeout"] and not any(t.is_alive() for t in threads)
    got = np.array([rows[k] for k in sorted(rows)])
    assert got.tobytes() == run_episode(cfg).trajectory.tobytes()


def test_the_plant_node_rejects_and_counts_a_forged_command_and_stops_at_once():
    """The plant alone, its peers' tokens faked: a command with dt 0 is counted by reason
    and does not move the vehicle; the authority's steps the tick; stop ends it at once."""
    cfg = load_config(overrides=SHORT)
    bus, stop = MemoryBus(), threading.Event()
    peers = MemoryTransport(bus)
    for svc in ("sensor", "mapper", "planner"):
        peers.token(alive_key("v0", svc, "0"))
    states = []
    peers.subscriber(topic_key("v0", "state"), lambda k, p: states.append(decode(p, State)))
    t = threading.Thread(target=plant_node.main, args=(cfg, "0", stop, MemoryTransport(bus)),
                         daemon=True)
    t.start()
    deadline = time.monotonic() + 30
    while not states and time.monotonic() < deadline:
        time.sleep(0.01)
    first = states[0]
    pub = peers.publisher(topic_key("v0", "cmd"))
    st = Stamper("planner/0", 7)
    n = cfg.planner.horizon

    def cmd(dt):
        return st.make(Cmd, Out("cmd", 0.0, {"t0": 0.0, "dt": dt,
                                             "controls": np.zeros((n, 2), np.float32)},
                                (InputRef(topic_key("v0", "map"), 0, 0.0),),
                                first.header.episode))
    pub.put(encode(cmd(0.0)))
    time.sleep(0.3)
    assert len(states) == 1                                   # nothing stepped
    pub.put(encode(cmd(cfg.planner.dt_s)))
    deadline = time.monotonic() + 10
    while len(states) < 6 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert [round(s.header.stamp, 2) for s in states[1:6]] == [0.02, 0.04, 0.06, 0.08, 0.1]
    health = query_json(peers, admin_key("v0", "plant", "0", "health"))[0]
    assert health["rejected"] == {"cmd: dt 0.0 is not positive": 1}
    t0 = time.monotonic()
    stop.set()
    t.join(5)
    assert not t.is_alive() and time.monotonic() - t0 < 1.0
