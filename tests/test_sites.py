"""Two sites in network namespaces (deploy.bench.faults.two_sites): plant and sensor in one,
mapper and planner in the other, a router each from deploy/configs, every link mutual TLS
and both routers enforcing the generated access-control rules; and the attacks on it."""

import collections
import json
import os
import shutil
import time

import pytest
import zenoh

from common.config import load_config
from common.messages import DecodeError, State, decode, peek
from common.topics import alive_key, topic_key
from deploy.bench.faults import Flood, Rogue, rejections, two_sites
from deploy.recording.record import iter_messages, read_metadata
from deploy.recording.timing import analyse
from deploy.sim.runner import run_episode

pytestmark = [
    pytest.mark.integration,
    pytest.mark.xdist_group("netns"),       # fixed subnets (conftest)
    pytest.mark.skipif(os.geteuid() != 0 or shutil.which("ip") is None
                       or shutil.which("openssl") is None,
                       reason="network namespaces need root, ip and openssl"),
]

SHORT = ["planner.samples=64", "episode.timeout_s=3.0", 'episode.scenario="open-field"']
RT = ["planner.samples=64", 'episode.scenario="open-field"', 'episode.clock="realtime"',
      "episode.timeout_s=40"]


def test_lockstep_across_two_secured_sites_is_bit_identical_under_attack(tmp_path):
    """Lockstep across the two sites is the in-process episode bit for bit, while: a client
    without a certificate is refused at connect; a client with a viewer's certificate (the
    wrong role) at site B replays every topic's hostile messages (deploy.bench.faults.hostile)
    and raises a planner's liveliness token, all denied by its router; and a client with a
    planner's certificate sends the same forged commands (its role's one topic), the real
    planner's source id among them, which its router lets through and the plant rejects,
    each counted."""
    ref = run_episode(load_config(overrides=SHORT)).trajectory
    with two_sites(SHORT, tmp_path) as s:
        p, v = s.pipeline, s.pipeline.cfg.episode.vehicle
        b_here = f"tls/{s.b.ip}:7447"
        bare = zenoh.Config()
        bare.insert_json5("mode", '"client"')
        bare.insert_json5("connect/endpoints", f'["{b_here}"]')
        bare.insert_json5("transport/link/tls", '{"root_ca_certificate": "%s"}'
                          % (s.certs / "ca.pem"))
        with pytest.raises(zenoh.ZError):
            zenoh.open(bare)
        viewer = Rogue(b_here, v, at=10, bus=s.secured("viewer", b_here))
        token = viewer.session.liveliness().declare_token(alive_key(v, "planner", "9"))
        for topic in ("events", "clock"):                   # the plant's other topics
            viewer.session.put(topic_key(v, topic), b"forged")
        forger = Rogue(b_here, v, at=5, bus=s.secured("planner", b_here), topics=("cmd",))
        s.up()
        assert p.bus.tokens(alive_key(v, "planner", "9")) == []        # denied at B
        assert p.wait_outcome().kind == "timeout"
        time.sleep(0.5)
        sent = {"viewer": list(viewer.sent), "planner": list(forger.sent)}
        token.undeclare()
        for r in (viewer, forger):
            r.close()
        got = p.trajectory()
        clocks = {k: json.loads(x) for k, x in read_metadata(p.path)["vamppi.clock"].items()}
        plant_log = p.procs["plant"].tail(500_000)
        logs = {n: q.tail(200_000) for n, q in p.procs.items()}
    assert got.tobytes() == ref.tobytes()
    # the recorder measured every service's clock across the sites: one host's clock, so
    # each offset is within its measurement's uncertainty
    assert set(clocks) == {"plant/0", "sensor/0", "mapper/0", "planner/0"}
    assert all(abs(c["offset_s"]) <= c["rtt_s"] / 2 + 1e-6 for c in clocks.values()), clocks
    # every hostile message was sent; the viewer's reached nobody, the planner's cmd did
    assert {t for t, _ in sent["viewer"]} == {"state", "depth", "map", "cmd"}
    assert {t for t, _ in sent["planner"]} == {"cmd"}
    publishers = collections.defaultdict(set)          # what the observer received
    for m in iter_messages(p.path):
        try:
            _, h = peek(m.data)
        except DecodeError:
            publishers[m.key.rsplit("/", 1)[1]].add("undecodable")
            continue
        publishers[m.key.rsplit("/", 1)[1]].add((h.source, h.boot))
    for topic in ("state", "depth", "map", "events", "clock"):
        assert len(publishers[topic]) == 1, publishers[topic]     # the real one alone
    assert len(publishers["cmd"]) > 2                  # the forger's newer boot, rogue/0
    rej = collections.Counter(r for text in logs.values() for r in rejections(text))
    assert {t for t, _ in rej} == {"cmd"}, rej         # only the planner's cmd got through
    cmd_why = {w for t, w in rejections(plant_log) if t == "cmd"}
    assert {"duplicate", "stale", "future", "not the authority"} <= cmd_why, cmd_why


@pytest.mark.realtime
def test_realtime_across_two_secured_sites_loses_no_command_under_a_denied_flood(tmp_path):
    """Realtime across the two sites: every command the planner sends reaches site A (its
    sequence numbers have no gap) and the vehicle reaches the goal, while a client with a
    viewer's certificate floods `cmd` with copies of the real commands from site B; its
    router denies every one, so none reaches the observer. The command rate and any state
    braked for want of a command are printed (`vamppi bench bus` measures them)."""
    with two_sites(RT, tmp_path) as s:
        p, v = s.pipeline, s.pipeline.cfg.episode.vehicle
        s.up()
        flood = Flood(s.secured("viewer", f"tls/{s.b.ip}:7447"), v)
        ev = p.wait_outcome(180)
        sent = flood.close()
        p.close()
    assert ev.kind == "success", p.kinds()
    result = analyse(p.path)
    chain = result["chain"]
    cmd = next(t for t in result["topics"] if t["key"] == topic_key(v, "cmd"))
    print(f"two sites, realtime: flood puts {sent}, commands {cmd['messages']}, "
          f"chain {chain}, to goal {ev.time_to_goal_s:.2f} s")
    assert sent > 10 * cmd["messages"]               # a flood: tens of times the rate
    assert cmd["publishers"] == 1                       # none of it reached the observer
    seqs = sorted(peek(m.data)[1].seq for m in iter_messages(p.path)
                  if m.key == topic_key(v, "cmd"))
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), seqs
    states = sorted((decode(m.data, State) for m in iter_messages(p.path)
                     if m.key == topic_key(v, "state")), key=lambda x: x.header.stamp)
    first = next(x.header.stamp for x in states if x.header.inputs)
    braked = [x.header.stamp for x in states if x.header.stamp > first and not x.header.inputs]
    print(f"stale states after the first command (braking for want of one): {braked}")
