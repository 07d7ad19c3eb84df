"""Roles, generated access control and mutual TLS (common.security, deploy.launch.certs): the
manifests against the topic table, and a real router enforcing the generated rules."""

import json
import shutil
import time

import pytest
import zenoh

from common.security import ROLES, accepted_names, access_control, manifest, tls
from common.topics import INPUTS, TOPICS, alive_key, key_matches, latest_key, topic_key
from deploy.launch.certs import make_certs
from deploy.launch.up import free_port

V = "v0"


def test_manifests_are_the_topic_table():
    """Each service puts exactly the topics it owns (and its heartbeat) and subscribes to its
    inputs; only the plant puts state, events and clock, only planners cmd; the read-only
    tools put nothing."""
    for topic, (owner, _) in TOPICS.items():
        key = topic_key(V, topic)
        putters = [r for r in ROLES if r != "router"
                   and any(key_matches(k, key) for k in manifest(r, V).put)]
        assert putters == [owner] + (["operator"] if topic == "handover" else []), topic
    for service, inputs in INPUTS.items():
        m = manifest(service, V)
        assert all(any(key_matches(k, topic_key(V, t)) for k in m.subscribe) for t in inputs)
    for tool in ("recorder", "viewer"):
        assert manifest(tool, V).put == () and manifest(tool, V).token == ()
    with pytest.raises(ValueError, match="unknown role"):
        manifest("rogue", V)


def test_generated_rules_deny_by_default_and_name_each_role():
    names = tuple(r for r in ROLES if r != "sensor") + ("planner-7",)
    acl = access_control(V, users=("planner", "planner-2", "viewer"), names=names)
    assert acl["enabled"] and acl["default_permission"] == "deny"
    subjects = {s["id"]: s for s in acl["subjects"]}
    assert set(subjects) == {f"{r}-certs" for r in ROLES if r != "sensor"} | {
        "planner-users", "viewer-users"}
    assert subjects["planner-users"] == {"id": "planner-users",
                                         "usernames": ["planner", "planner-2"]}
    assert subjects["planner-certs"]["cert_common_names"] == ["planner", "planner-7"]
    assert all(list(s) == ["id", "cert_common_names"] for r, s in subjects.items()
               if r.endswith("-certs"))     # zenoh: a subject matches only if all of it does
    ids = {r["id"] for r in acl["rules"]}
    policies = {p["id"]: p for p in acl["policies"]}
    assert all(set(p["rules"]) <= ids for p in policies.values())
    assert policies["planner"]["subjects"] == ["planner-certs", "planner-users"]
    assert policies["plant"]["subjects"] == ["plant-certs"]
    assert "sensor" not in policies          # no name of it: no subject, denied everything
    assert not any(r["id"].startswith("sensor-") for r in acl["rules"])
    viewer = [r for r in acl["rules"] if r["id"].startswith("viewer-")]
    assert viewer and not any("put" in r["messages"] and r["flows"] == ["ingress"]
                              for r in viewer)


needs_openssl = pytest.mark.skipif(shutil.which("openssl") is None, reason="no openssl")


def _session(mode, certs, name, port, listen=False, acl=None):
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints" if listen else "connect/endpoints",
                   json.dumps([f"tls/{'127.0.0.1' if listen else 'localhost'}:{port}"]))
    if name is not None:
        c.insert_json5("transport/link/tls", json.dumps(tls(certs, name, listen)))
    else:
        c.insert_json5("transport/link/tls",
                       json.dumps({"root_ca_certificate": str(certs / "ca.pem")}))
    if acl is not None:
        c.insert_json5("access_control", json.dumps(acl))
    return zenoh.open(c)


@needs_openssl
def test_a_router_with_the_generated_rules_refuses_what_a_role_may_not_do(tmp_path):
    """mTLS and the generated rules on a real router: a client without a certificate, or
    with one of another CA, cannot connect; the planner's command reaches the recorder; the
    viewer's cmd, state, events, clock and a liveliness token of a planner do not."""
    certs, other = tmp_path / "certs", tmp_path / "other"
    make_certs(certs, ("router", "planner", "viewer", "recorder", "plant"))
    make_certs(other, ("planner",))
    assert (certs / "planner.key").stat().st_mode & 0o077 == 0
    port = free_port()
    router = _session("router", certs, "router", port, listen=True, acl=access_control(V))
    got, tokens = [], []
    rec = _session("client", certs, "recorder", port)
    rec.declare_subscriber(f"vamppi/{V}/**", lambda s: got.append(
        (str(s.key_expr), s.payload.to_bytes())))
    rec.liveliness().declare_subscriber(alive_key(V), lambda s: tokens.append(
        str(s.key_expr)))
    planner = _session("client", certs, "planner", port)
    viewer = _session("client", certs, "viewer", port)
    time.sleep(0.5)
    planner.put(topic_key(V, "cmd"), b"planner")
    planner.put(topic_key(V, "state"), b"planner")              # not the planner's topic
    for topic in ("cmd", "state", "events", "clock"):
        viewer.put(topic_key(V, topic), b"viewer")
    viewer_token = viewer.liveliness().declare_token(alive_key(V, "planner", "0"))
    planner_token = planner.liveliness().declare_token(alive_key(V, "planner", "0"))
    time.sleep(0.8)
    assert got == [(topic_key(V, "cmd"), b"planner")]
    assert tokens == [alive_key(V, "planner", "0")]                 # the planner's alone
    # a restarted planner asks any instance for the newest command with wildcards: the
    # plant's queryable hears it and its reply comes back
    plant = _session("client", certs, "plant", port)
    held = latest_key(V, "plant", "0", "cmd")
    plant.declare_queryable(held, lambda q: q.reply(held, b"held"))
    time.sleep(0.3)
    replies = [r.ok.payload.to_bytes() for r in
               planner.get(latest_key(V, "*", "*", "cmd"), timeout=2.0) if r.ok is not None]
    assert replies == [b"held"]
    plant.close()
    planner_token.undeclare()
    time.sleep(0.3)
    for name, d in ((None, certs), ("planner", other)):
        with pytest.raises(zenoh.ZError):
            _session("client", d, name, port)
    viewer_token.undeclare()
    for s in (viewer, planner, rec, router):
        s.close()


@needs_openssl
def test_a_revoked_certificate_connects_but_is_denied_everything(tmp_path):
    """`vamppi certs --revoke planner-2`: a router started after it (rules from the
    directory's accepted names) lets a stolen copy of planner-2's certificate complete TLS,
    but denies its command and token; planner-3's, issued beside it, still pass."""
    import subprocess
    import sys
    certs, stolen = tmp_path / "certs", tmp_path / "stolen"
    make_certs(certs, ("router", "recorder", "planner-2", "planner-3"))
    stolen.mkdir()
    for f in ("planner-2.pem", "planner-2.key", "ca.pem"):
        shutil.copy(certs / f, stolen / f)
    r = subprocess.run([sys.executable, "-m", "deploy", "certs", str(certs),
                        "--revoke", "planner-2"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["accepted"] == ["planner-3", "recorder", "router"]
    assert not (certs / "planner-2.key").exists()
    with pytest.raises(Exception, match="revoked"):
        make_certs(certs, ("planner-2",))
    port = free_port()
    router = _session("router", certs, "router", port, listen=True,
                      acl=access_control(V, names=accepted_names(certs)))
    got = []
    rec = _session("client", certs, "recorder", port)
    rec.declare_subscriber(f"vamppi/{V}/**", lambda s: got.append(s.payload.to_bytes()))
    thief = _session("client", stolen, "planner-2", port)       # TLS still succeeds
    ok = _session("client", certs, "planner-3", port)
    time.sleep(0.5)
    thief.put(topic_key(V, "cmd"), b"revoked")
    ok.put(topic_key(V, "cmd"), b"accepted")
    time.sleep(0.5)
    assert got == [b"accepted"]
    for s in (ok, thief, rec, router):
        s.close()


@needs_openssl
def test_vamppi_certs_names_the_role_and_instance(tmp_path):
    import subprocess
    import sys
    r = subprocess.run([sys.executable, "-m", "deploy", "certs", str(tmp_path),
                        "--name", "planner-7", "--name", "viewer"], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert len(json.loads(r.stdout)["certificates"]) == 2
    subject = subprocess.run(["openssl", "x509", "-in", str(tmp_path / "planner-7.pem"),
                              "-noout", "-subject"], capture_output=True, text=True).stdout
    assert "CN = planner-7" in subject and "OU = 7" in subject
    bad = subprocess.run([sys.executable, "-m", "deploy", "certs", str(tmp_path),
                          "--name", "rogue"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 1 and "a role" in bad.stderr


@needs_openssl
@pytest.mark.integration
def test_vamppi_up_over_mutual_tls_is_bit_identical_and_denies_a_wrong_role(tmp_path):
    """`vamppi up` with bus.certs: every service on mutual TLS through a router enforcing the
    generated rules; the lockstep episode is the in-process one, bit for bit, while a client
    with a viewer's certificate puts on cmd, state, events and clock and raises a planner's
    liveliness token: the router denies all of it, so the recording (the router's own
    session) holds none of it and the plant never sees it."""
    import os

    from common.config import load_config
    from common.messages import Event, Header, encode
    from deploy.bench.faults import Up, recorded_trajectory
    from deploy.sim.runner import run_episode
    certs = tmp_path / "certs"
    make_certs(certs)
    lock = ["planner.samples=64", "episode.timeout_s=8.0", 'episode.scenario="open-field"']
    undisturbed = run_episode(load_config(overrides=lock))
    marker = f"tls{os.getpid()}"
    path = tmp_path / "bus.mcap"
    up = Up(["--record", str(path), "--set", f"bus.certs={json.dumps(str(certs))}",
             *sum((["--set", o] for o in lock), [])], marker)
    t = up.wait_line("all services up", 240)
    line = next(text for at, text in up.lines if at >= t and "router on" in text)
    port = int(line.split("router on ")[1].split()[0].rsplit(":", 1)[1])
    rogue = _session("client", certs, "viewer", port)
    token = rogue.liveliness().declare_token(alive_key(marker, "planner", "9"))
    # a stolen plant certificate: an outcome event under the plant's name, another process
    thief = _session("client", certs, "plant", port)
    fakes = [encode(Event(Header(i, 0.5 + 0.02 * i, time.time(), "plant/0", boot=1),
                          kind="success", outcome="success", time_to_goal_s=0.5,
                          detail="at the goal"))
             for i in range(50)]
    for fake in fakes:
        for topic in ("cmd", "state", "events", "clock"):
            rogue.put(topic_key(marker, topic), b"forged")
        thief.put(topic_key(marker, "events"), fake)
        time.sleep(0.02)
    summary = up.finish()
    token.undeclare()
    rogue.close()
    thief.close()
    assert summary["outcome"] == undisturbed.outcome and summary["failure"] is None, \
        up.stderr()[-3000:]
    assert summary["foreign_events"] == 50              # not the plant vamppi up started
    from deploy.recording.record import iter_messages
    assert not [m.key for m in iter_messages(path) if m.data == b"forged"]
    assert sum(m.data in fakes for m in iter_messages(path)) == 50   # the role may put them
    assert recorded_trajectory(path).tobytes() == undisturbed.trajectory.tobytes()


def test_user_password_instead_of_tls(tmp_path):
    """bus.credentials: a router with the users' dictionary and the generated rules; the
    planner's command reaches the recorder, the viewer's command and state do not; a wrong
    password and an unknown user are refused at connect."""
    from common.bus import open_session
    from common.config import BusConfig
    users = tmp_path / "users"
    users.write_text("# role[-instance]:password\nrouter:r0\nplanner:p0\nviewer:v0\n"
                     "recorder:c0\n")
    wrong, unknown = tmp_path / "wrong", tmp_path / "unknown"
    wrong.write_text("planner:nope\n")
    unknown.write_text("planner-3:p0\n")
    ep = f"tcp/127.0.0.1:{free_port()}"

    def client(name, cred=users):
        return open_session(BusConfig("client", (ep,), (), False, credentials=str(cred),
                                      identity=name))
    router = open_session(BusConfig("router", (), (ep,), False, credentials=str(users),
                                    identity="router"))
    got = []
    rec = client("recorder")
    rec.declare_subscriber(f"vamppi/{V}/**", lambda s: got.append(
        (str(s.key_expr), s.payload.to_bytes())))
    planner, viewer = client("planner"), client("viewer")
    time.sleep(0.5)
    planner.put(topic_key(V, "cmd"), b"planner")
    viewer.put(topic_key(V, "cmd"), b"viewer")
    viewer.put(topic_key(V, "state"), b"viewer")
    time.sleep(0.5)
    assert got == [(topic_key(V, "cmd"), b"planner")]
    for name, cred in (("planner", wrong), ("planner-3", unknown)):
        with pytest.raises(zenoh.ZError):
            client(name, cred)
    with pytest.raises(ValueError, match="no line for 'operator'"):
        client("operator")
    bad = tmp_path / "bad"
    bad.write_text("rogue:x\n")
    with pytest.raises(ValueError, match="not `role"):
        client("rogue", bad)
    for s in (viewer, planner, rec, router):
        s.close()


def test_site_files_are_routers_that_never_scout_and_a_bad_one_is_a_clear_error(tmp_path):
    """deploy/configs: each router file parses (zenoh's own format), listens where it says
    and never scouts; each service file is a client of its site's router. A missing or
    malformed router file ends `vamppi router` with exit 2 and the reason."""
    import subprocess
    import sys

    from common.bus import endpoints_of
    from common.config import load_config
    from deploy.bench.faults import SITES
    for f in sorted(SITES.glob("*.json5")):
        zc = zenoh.Config.from_file(str(f))
        assert endpoints_of(zc, "listen", "router"), f
        assert json.loads(zc.get_json("scouting/multicast/enabled")) is False
        assert json.loads(zc.get_json("scouting/gossip/enabled")) is False
    assert endpoints_of(zenoh.Config.from_file(str(SITES / "site-b.json5")), "connect",
                        "router") == ["tls/10.0.0.1:7447"]
    for f in sorted(SITES.glob("*.toml")):
        bus = load_config(f).bus
        assert bus.mode == "client" and bus.connect == ("tls/127.0.0.1:7447",)
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: 'router', listen: { endpoints: [1, 2")
    for path in (bad, tmp_path / "missing.json5"):
        r = subprocess.run([sys.executable, "-m", "deploy", "router", "--config",
                            str(path)], capture_output=True, text=True, timeout=60)
        assert r.returncode == 2 and "vamppi router:" in r.stderr, r.stderr[-500:]
