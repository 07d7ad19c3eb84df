"""`vamppi bench ... --json`: complete, well-formed documents (no timing asserted)."""

import json
import subprocess
import sys

import pytest

from deploy.bench.main import table


def test_planner_bench_json_names_the_device_and_every_case():
    r = subprocess.run([sys.executable, "-m", "deploy", "bench", "planner", "--samples",
                        "16", "--controllers", "va", "--forms", "native,jax", "--reps", "3",
                        "--json"], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads(r.stdout)
    assert doc["benchmark"] == "planner" and doc["backend"] == "cpu" and doc["device"]
    assert doc["settings"]["horizon"] == 40 and doc["settings"]["map_cells"] == [400, 400]
    assert doc["settings"]["forms"] == ["native", "jax"]
    cases = {(c["controller"], c["samples"], c["forms"]): c for c in doc["cases"]}
    assert set(cases) == {("va", 16, "native/native"), ("va", 16, "jax/jax")}
    for c in cases.values():
        assert c["reps"] == 3 and 0 < c["min_ms"] <= c["median_ms"] <= c["p95_ms"]
        assert c["compile_s"] > 0 and c["peak_mem_mb"] > 0
    # the JAX form's count maps (8 x 410 x 410 float32) are in XLA's program; the native
    # kernel's (0.4 MB a thread) are its own, outside XLA's accounting
    assert cases["va", 16, "jax/jax"]["peak_mem_mb"] > cases["va", 16, "native/native"][
        "peak_mem_mb"] + 4
    assert "| va | 16 | jax/jax |" in table(doc)


def bench_json(*args):
    r = subprocess.run([sys.executable, "-m", "deploy", "bench", *args, "--json"],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout)


def test_mapper_bench_times_every_stage_at_both_camera_sizes():
    doc = bench_json("mapper", "--reps", "3")
    assert [(c["width"], c["height"]) for c in doc["cases"]] == [(128, 72), (320, 240)]
    for c in doc["cases"]:
        assert c["map_bytes"] > 2 * 400 * 400 * 4
        for stage in ("fuse", "inpaint", "encode", "total"):
            assert c[stage]["reps"] == 3 and c[stage]["median_ms"] > 0
        assert c["total"]["median_ms"] >= c["fuse"]["median_ms"]


def test_bus_bench_delivers_map_sized_messages_through_a_loopback_router():
    doc = bench_json("bus", "--reps", "10")
    assert [c["payload"] for c in doc["cases"]] == ["codec", "raw", "floor"]
    for c in doc["cases"]:
        assert c["bytes"] > 2 * 400 * 400 * 4 and c["reps"] == 10
        assert 0 < c["median_ms"] <= c["p99_ms"] and c["msgs_per_s"] > 0
    assert doc["cases"][1]["over_raw_p50"] == 0
    for stage in ("encode", "decode"):
        assert doc["codec_alone"][stage]["reps"] == 100
        assert doc["codec_alone"][stage]["median_ms"] > 0


def test_chain_log_follows_depth_map_cmd_to_the_first_state_that_applies_it():
    """Messages are named by (seq, stamp), commands also by source, and a state applies the
    command of the authority it names: another planner's command of the same seq and stamp
    (a standby, a rogue) is not taken for it."""
    import msgpack

    from deploy.recording.timing import ChainLog
    log = ChainLog("v0")

    def put(topic, seq, stamp, wall, inputs=(), source="x/0", **body):
        log.on(topic, msgpack.packb({"header": {
            "seq": seq, "stamp": stamp, "wall_time": wall, "source": source,
            "inputs": [[log.keys[t], s, st] for t, s, st in inputs]}, **body}))

    put("depth", 0, 0.0, 10.00)
    put("depth", 1, 0.1, 10.10)
    put("map", 0, 0.1, 10.15, [("depth", 1, 0.1)])                 # the newer frame's map
    put("cmd", 5, 0.1, 10.25, [("state", 3, 0.1), ("map", 0, 0.1)], "planner/0")
    put("cmd", 5, 0.1, 10.40, [("state", 3, 0.1), ("map", 0, 0.1)], "planner/rogue")
    put("state", 0, 0.1, 10.20, authority="planner/0")              # no command: stale
    put("state", 1, 0.12, 10.26, [("cmd", 5, 0.1)], authority="planner/0")  # the first
    put("state", 2, 0.14, 10.28, [("cmd", 5, 0.1)], authority="planner/0")
    put("state", 3, 0.16, 10.30, [("cmd", 9, 0.1)], authority="planner/0")  # never seen
    log.on("state", b"\xc1 not msgpack")                  # ignored, not raised
    s = log.summary()
    assert s["chains"] == 1 and s["commands"] == 2 and s["states"] == 4 and s["stale_states"] == 1
    assert abs(s["end_to_end"]["median_ms"] - 160.0) < 1e-6     # 10.26 - 10.10
    assert abs(s["depth_to_map"]["median_ms"] - 50.0) < 1e-6
    assert abs(s["map_to_cmd"]["median_ms"] - 100.0) < 1e-6     # planner/0's, not the rogue's
    assert abs(s["cmd_to_applied"]["median_ms"] - 10.0) < 1e-6


def test_pipeline_bench_runs_the_services_in_realtime_and_follows_the_chain():
    doc = bench_json("pipeline", "--samples", "16", "--controllers", "deterministic",
                     "--duration", "4", "--scenario", "open-field")
    assert doc["settings"]["clock"] == "realtime"
    (c,) = doc["cases"]
    assert c["controller"] == "deterministic" and c["samples"] == 16
    assert c["commands"] > 3 and c["chains"] > 3 and c["command_rate_hz"] > 0
    assert 0 < c["end_to_end"]["median_ms"] <= c["end_to_end"]["p95_ms"]


def test_faults_table_renders_the_committed_figures():
    from pathlib import Path

    result = json.loads((Path(__file__).parent.parent / "docs/bench/faults-cpu.json").read_text())
    text = table(result)
    assert text.count("| supervised |") == 8 and "| lost at speed | realtime | router |" in text
    assert all(c["outcome"] in ("success", "timeout") for c in result["cases"])
    assert all(c["bit_identical"] for c in result["cases"] if c["case"] == "supervised")


def test_startup_bench_times_each_services_import_and_names_the_versions():
    doc = bench_json("startup", "--reps", "1")
    assert doc["benchmark"] == "startup" and doc["device"]
    assert set(doc["settings"]["versions"]) == {"jax", "jaxlib", "ml_dtypes", "numpy"}
    cases = {c["case"]: c for c in doc["cases"]}
    assert set(cases) == {"sensor", "mapper", "planner", "plant", "jax", "ml_dtypes"}
    for c in cases.values():
        assert c["reps"] == 1 and 0 < c["min_s"] <= c["median_s"] <= c["max_s"]
    assert cases["ml_dtypes"]["after"] == "import numpy"
    assert "| planner | services.planner.node | 1 |" in table(doc)


def test_startup_bench_says_which_import_failed():
    from deploy.bench.startup import ImportFailed, import_s
    with pytest.raises(ImportFailed, match="importing no_such_module failed: ModuleNotFoundError"):
        import_s("", "no_such_module")
