"""common.wire against msgpack itself: the reader gives msgpack.unpackb's values (bins as
views), fails only with WireError, and the writer's headers are msgpack's."""

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common import wire

ints = st.integers(-(1 << 63), (1 << 64) - 1)
scalars = (st.none() | st.booleans() | ints | st.floats(width=32, allow_nan=False)
           | st.text(max_size=300) | st.binary(max_size=300))
values = st.recursive(
    scalars, lambda inner: st.lists(inner, max_size=20)
    | st.dictionaries(st.text(max_size=40), inner, max_size=20), max_leaves=60)


def plain(v):
    """memoryviews as bytes, for comparison with msgpack's values."""
    if isinstance(v, memoryview):
        return v.tobytes()
    if isinstance(v, list):
        return [plain(x) for x in v]
    if isinstance(v, dict):
        return {k: plain(x) for k, x in v.items()}
    return v


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(values, st.booleans())
def test_read_gives_msgpacks_values(v, single_float):
    payload = msgpack.packb(v, use_bin_type=True, use_single_float=single_float)
    assert plain(wire.read(payload)) == msgpack.unpackb(payload, raw=False, strict_map_key=False)


def test_large_containers_strings_and_bins():
    v = {"a" * 70000: [1] * 70000, "m": {str(i): i for i in range(300)}, "b": b"x" * 70000,
         "s": "é" * 40000, "e": [], "n": -(1 << 63), "u": (1 << 64) - 1}
    payload = msgpack.packb(v)
    got = wire.read(payload)
    assert plain(got) == v
    assert isinstance(got["b"], memoryview) and got["b"].obj is payload     # a view, no copy


@settings(max_examples=100, deadline=None)
@given(values)
def test_every_truncation_fails_with_wire_error(v):
    payload = msgpack.packb(v, use_bin_type=True)
    for n in range(len(payload)):
        with pytest.raises(wire.WireError):
            wire.read(payload[:n])
    with pytest.raises(wire.WireError, match="left over"):
        wire.read(payload + b"\x00")


def unusual(v, depth=0) -> bool:
    """What msgpack reads and no message holds: ext types, non-string keys, deep nests."""
    if isinstance(v, msgpack.ExtType):
        return True
    if depth >= wire.MAX_DEPTH and isinstance(v, (list, tuple, dict)):
        return True                                  # a container this deep, even empty
    if isinstance(v, (list, tuple)):
        return any(unusual(x, depth + 1) for x in v)
    if isinstance(v, dict):
        return any(not isinstance(k, str) or unusual(k, depth + 1) or unusual(x, depth + 1)
                   for k, x in v.items())
    return False


@settings(max_examples=1000, deadline=None)
@given(st.binary(max_size=64))
def test_garbage_fails_with_wire_error_or_reads_as_msgpack_does(data):
    try:
        want = msgpack.unpackb(data, raw=False, strict_map_key=False)
    except Exception:
        with pytest.raises(wire.WireError):
            wire.read(data)
        return
    try:
        got = plain(wire.read(data))
    except wire.WireError:
        assert unusual(want)
        return
    assert got == want


@pytest.mark.parametrize("payload,why", [
    (b"\x91" * 40 + b"\x90", "nested deeper"),
    (b"\x91" * 32 + b"\x90", "nested deeper"),         # an empty container at the limit
    (b"\x81\x01\x02", "map key is a int"),
    (b"\xd4\x01\x00", "ext type"),
    (b"\xc1", "0xc1"),
    (b"\xa2\xff\xfe", "not UTF-8"),
    (b"\xdd\xff\xff\xff\xff", "truncated"),
])
def test_what_is_refused_and_why(payload, why):
    with pytest.raises(wire.WireError, match=why):
        wire.read(payload)


@pytest.mark.parametrize("n", [0, 1, 255, 256, 65535, 65536, 1 << 20])
def test_headers_are_msgpacks(n):
    assert wire.bin_header(n) == msgpack.packb(b"\x00" * n)[:-n or None]
    assert wire.map_header(n % 70000) == msgpack.packb({str(i): 0 for i in range(n % 70000)})[
        :len(wire.map_header(n % 70000))]
