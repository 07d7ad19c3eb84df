import dataclasses
import re

import msgpack
import numpy as np
import pytest

from common.messages import (
    MESSAGE_TYPES,
    Clock,
    Cmd,
    DecodeError,
    Depth,
    Event,
    Handover,
    Header,
    Heartbeat,
    InputRef,
    Map,
    Plan,
    State,
    Stats,
    decode,
    encode,
)


def header(rng) -> Header:
    return Header(int(rng.integers(0, 1 << 40)), float(rng.normal()), float(rng.uniform(0, 2e9)),
                  "svc/0", (InputRef("vamppi/v0/plant/state", 3, 0.1),),
                  int(rng.integers(0, 1 << 62)), int(rng.integers(0, 1 << 62)))


def sample(cls, rng):
    h = header(rng)
    n, hh, ww = int(rng.integers(1, 50)), int(rng.integers(1, 40)), int(rng.integers(1, 40))
    f4 = lambda *s: rng.normal(size=s).astype("<f4")  # noqa: E731
    f8 = lambda *s: rng.normal(size=s).astype("<f8")  # noqa: E731
    return {
        State: lambda: State(h, x=f8(6), z=1.5, u_applied=f8(2), tick=4, authority="planner/0",
                             epoch=int(rng.integers(0, 9)), outcome="",
                             goal_region=bool(rng.integers(0, 2))),
        Cmd: lambda: Cmd(h, t0=0.3, dt=0.1, controls=f4(n, 2),
                         rng=rng.integers(0, 1 << 32, 2, dtype=np.uint64).astype("<u4")),
        Depth: lambda: Depth(h, depth=np.abs(f4(hh, ww)), intrinsics=f8(4), cam_position=f8(3),
                             cam_rotation=f8(3, 3), base_pose=f8(4), range_max=25.0),
        Map: lambda: Map(h, mean=f4(hh, ww), variance=np.abs(f4(hh, ww)), origin=f8(2),
                         resolution=0.2),
        Plan: lambda: Plan(h, controller="deterministic", optimal=f4(n + 1, 6), nominal=f4(n, 2),
                           rollouts=f4(3, n + 1, 2), rollout_costs=f4(3)),
        Stats: lambda: Stats(h, controller="va", samples=800, solve_ms=12.5, cost_min=1.0,
                             cost_mean=2.0, terms={"time": 1.0, "surface": 0.5}),
        Event: lambda: Event(h, kind="success", outcome="success", time_to_goal_s=float("nan"),
                             detail=""),
        Clock: lambda: Clock(h, tick=12, mode="lockstep"),
        Handover: lambda: Handover(h, to="planner/1", to_boot=5, current="planner/0", epoch=3,
                                   retire=True, reason="swap"),
        Heartbeat: lambda: Heartbeat(h, status="ready", role="active", deadline_s=1.0,
                                     detail=""),
    }[cls]()


def same(a, b) -> bool:
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            if x.dtype != y.dtype or x.shape != y.shape or x.tobytes() != y.tobytes():
                return False
        elif isinstance(x, float) and np.isnan(x):
            if not np.isnan(y):
                return False
        elif x != y:
            return False
    return True


@pytest.mark.parametrize("cls", list(MESSAGE_TYPES.values()))
def test_round_trip_is_bit_exact(cls, rng):
    for _ in range(5):
        msg = sample(cls, rng)
        back = decode(encode(msg), cls)
        assert same(msg, back)


def raw_of(msg) -> dict:
    return msgpack.unpackb(encode(msg), raw=False)


def pack(d) -> bytes:
    return msgpack.packb(d, use_bin_type=True)


def test_malformed_payloads_raise_the_clear_error(rng):
    m = sample(Map, rng)
    good = raw_of(m)
    cases = {
        "not a msgpack": b"\xc1\xc1\xc1",
        "not a msgpack message": encode(m)[:-7],                 # truncated
        "not a message": pack([1, 2, 3]),
        "unknown schema": pack({**good, "schema": "vamppi.Nope"}),
        "field 'version'": pack({**good, "version": 99}),
        "field 'mean' is missing": pack({k: v for k, v in good.items() if k != "mean"}),
        "field 'mean' has dtype": pack({**good, "mean": {**good["mean"], "dtype": "<f8"}}),
        "field 'mean' has": pack({**good, "mean": {**good["mean"], "shape": [1, 2, 3]}}),
        "dimension": pack({**good, "variance": {
            "dtype": "<f4", "shape": [1, 1], "data": np.zeros(1, "<f4").tobytes()}}),
        "bytes, shape": pack({**good, "mean": {**good["mean"], "data": b"\x00" * 3}}),
        "field 'origin' has 1 non-finite": pack({**good, "origin": {
            "dtype": "<f8", "shape": [2], "data": np.array([0.0, np.nan]).tobytes()}}),
        "field 'variance' has negative": pack({**good, "variance": {
            **good["variance"], "data": (-np.abs(m.variance)).astype("<f4").tobytes()}}),
        "pad must be bytes": pack({**good, "mean": {**good["mean"], "pad": 3}}),
        "field 'resolution' must be a number": pack({**good, "resolution": "0.2"}),
        "field 'resolution' must be finite": pack({**good, "resolution": float("inf")}),
        "field 'extra' is not in the schema": pack({**good, "extra": 1}),
        "field 'header.seq'": pack({**good, "header": {**good["header"], "seq": -1}}),
        "field 'header.inputs[0]'": pack({**good, "header": {**good["header"], "inputs": [[1]]}}),
        "field 'header.boot' is missing": pack({**good, "header": {
            k: v for k, v in good["header"].items() if k != "boot"}}),
        "field 'header.episode' has a bad value": pack({**good, "header": {
            **good["header"], "episode": -3}}),
        "field 'header.extra' is not in the schema": pack({**good, "header": {
            **good["header"], "extra": 1}}),
    }
    for needle, payload in cases.items():
        with pytest.raises(DecodeError, match=re.escape(needle)):
            decode(payload)
    with pytest.raises(DecodeError, match="expected a vamppi.State"):
        decode(encode(m), State)


@pytest.mark.parametrize("cls", list(MESSAGE_TYPES.values()))
def test_encode_writes_msgpacks_bytes_with_aligned_arrays(cls, rng):
    for _ in range(5):
        msg = sample(cls, rng)
        payload = encode(msg)
        raw = msgpack.unpackb(payload, raw=False)
        assert msgpack.packb(raw, use_bin_type=True) == payload   # msgpack's own encoding
        assert raw["version"] == cls.VERSION == (5 if cls is Heartbeat else 3)
        back = decode(payload, cls)
        start = np.frombuffer(payload, np.uint8).ctypes.data
        for f in dataclasses.fields(cls):
            value = getattr(back, f.name)
            if isinstance(value, np.ndarray):
                assert raw[f.name]["pad"] == bytes(len(raw[f.name]["pad"]))
                assert len(raw[f.name]["pad"]) < 16
                assert (value.ctypes.data - start) % 16 == 0          # aligned ...
                assert np.shares_memory(value, np.frombuffer(payload, np.uint8))  # ... views
                assert not value.flags.writeable


def _older_header(raw: dict) -> dict:
    return {k: v for k, v in raw["header"].items() if k not in ("boot", "episode")}


def test_version_1_payloads_without_pad_still_decode(rng):
    m = sample(Map, rng)
    raw = raw_of(m)
    v1 = {**raw, "version": 1, "header": _older_header(raw),
          **{k: {a: b for a, b in raw[k].items() if a != "pad"}
             for k in ("mean", "variance", "origin")}}
    back = decode(pack(v1), Map)
    assert back.header.boot == back.header.episode == 0
    assert same(back, dataclasses.replace(m, header=back.header))


def test_version_2_payloads_decode_with_the_newer_fields_defaults(rng):
    s, c = sample(State, rng), sample(Cmd, rng)
    for msg, newer in ((s, ("epoch", "authority_boot", "outcome", "goal_region")),
                       (c, ("rng",))):
        raw = raw_of(msg)
        v2 = {k: v for k, v in raw.items() if k not in newer}
        back = decode(pack({**v2, "version": 2, "header": _older_header(raw)}))
        for f in dataclasses.fields(back):
            if f.name in newer:
                older = f.metadata["older"]
                want = older() if callable(older) else older
                assert np.array_equal(getattr(back, f.name), want)
            elif f.name != "header":
                assert np.array_equal(getattr(back, f.name), getattr(msg, f.name))
        with pytest.raises(DecodeError, match="is missing"):    # v3 must carry them
            decode(pack({**v2, "header": raw["header"]}))


def test_a_mutable_payload_is_copied_first(rng):
    m = sample(Map, rng)
    buf = bytearray(encode(m))
    back = decode(buf, Map)
    buf[:] = bytes(len(buf))
    assert same(back, m)


def test_nonnegative_fields_take_minus_zero_and_refuse_nan(rng):
    m = sample(Map, rng)
    var = np.abs(m.variance)
    var.flat[0] = -0.0
    assert decode(encode(dataclasses.replace(m, variance=var)), Map).variance.flat[0] == 0.0
    for bad, why in ((np.nan, "1 non-finite"), (np.inf, "1 non-finite"), (-1e-30, "negative")):
        var = np.abs(m.variance)
        var.flat[-1] = bad
        with pytest.raises(DecodeError, match=why):
            decode(encode(dataclasses.replace(m, variance=var)), Map)
