"""Message schemas and the msgpack codec: each message defined once.

Every message is a frozen dataclass with a `header` and typed fields. On the
wire it is one msgpack map::

    {"schema": "vamppi.State", "version": 3, "header": {...}, <fields>...}

NumPy arrays travel as ``{"dtype": "<f4", "shape": [..], "pad": <bytes>, "data": <bytes>}``
(``pad``: 0-15 zero bytes that start ``data`` on a 16-byte boundary of the payload,
so that the arrays a receiver gets are aligned views; version 1 had no ``pad`` and is
still read; version 3 added the header's `boot` and `episode` and a few fields, which
older payloads lack and decode to their documented defaults): decoding is exact (the
float32 that leaves is the float32 that arrives) and never casts; arrays are copied once
on the way out and not at all on the way in (common.wire). `decode` validates schema name
and version, every field's type, every array's dtype and shape (named dimensions must
agree across fields) and finiteness where the schema requires it, and raises
`DecodeError` naming the field.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

import msgpack
import numpy as np

from common import wire


class DecodeError(ValueError):
    """A payload that is not a valid message; the text names the field."""


# ----------------------------------------------------------------------------- field kinds
@dataclass(frozen=True)
class ArraySpec:
    dtype: str                       # exact numpy dtype string, e.g. "<f4"
    shape: tuple[int | str, ...]     # ints are fixed, strings are named dims
    finite: bool = True
    nonneg: bool = False


# `since`: the message version that added the field; a payload of an older version has
# none and decodes to `older` (a value, or a callable for arrays), which is also the
# field's default when a message is built without it
def _field(meta: dict[str, Any], since: int, older: Any) -> Any:
    meta = {**meta, "since": since, "older": older}
    if since == 1:
        return field(metadata=meta)
    if callable(older):
        return field(default_factory=older, metadata=meta)
    return field(default=older, metadata=meta)


def array(dtype: str, shape: tuple[int | str, ...], *, finite: bool = True,
          nonneg: bool = False, since: int = 1, older: Any = None) -> Any:
    return _field({"kind": ArraySpec(dtype, shape, finite, nonneg)}, since, older)


def number(*, finite: bool = True, since: int = 1, older: Any = None) -> Any:
    return _field({"kind": "float", "finite": finite}, since, older)


def integer(*, nonneg: bool = True, since: int = 1, older: Any = None) -> Any:
    return _field({"kind": "int", "nonneg": nonneg}, since, older)


def text(*, since: int = 1, older: Any = None) -> Any:
    return _field({"kind": "str"}, since, older)


def flag(*, since: int = 1, older: Any = None) -> Any:
    return _field({"kind": "bool"}, since, older)


def floats_by_name() -> Any:
    return field(metadata={"kind": "dict_float", "since": 1, "older": None})


# ----------------------------------------------------------------------------- header
@dataclass(frozen=True)
class InputRef:
    """One input a message was computed from: its key, seq and sim stamp."""
    key: str
    seq: int
    stamp: float


@dataclass(frozen=True)
class Header:
    seq: int                  # per publisher (source and boot), gap-free, from 0
    stamp: float              # simulation time, s
    wall_time: float          # publish wall time, s since the epoch
    source: str               # publishing instance, "<service>/<instance>"
    inputs: tuple[InputRef, ...] = ()
    boot: int = 0             # the publishing process's start (ns since the epoch): a restarted
                              # instance is a new boot, its seq starts again at 0 (v3; 0 before)
    episode: int = 0          # the episode the message belongs to: the plant names it when it
                              # starts one, every message computed from it carries it on (v3)


# ----------------------------------------------------------------------------- messages
@dataclass(frozen=True)
class Message:
    SCHEMA: ClassVar[str] = ""
    VERSION: ClassVar[int] = 3          # 2: arrays carry `pad`; 3: header boot, episode
    VERSIONS_READ: ClassVar[tuple[int, ...]] = (1, 2, 3)
    header: Header


@dataclass(frozen=True)
class State(Message):
    """Vehicle state x = [V, v, r, X, Y, Psi] (services.plant.dynamics.S)."""
    SCHEMA: ClassVar[str] = "vamppi.State"
    x: np.ndarray = array("<f8", (6,))
    z: float = number()                  # ground elevation under the CG, m
    u_applied: np.ndarray = array("<f8", (2,))   # [delta, f_xt] applied now
    tick: int = integer()                # control tick index
    authority: str = text()              # the planner instance the plant obeys ("" before one)
    epoch: int = integer(since=3, older=0)       # the authority's generation: +1 at each change
    authority_boot: int = integer(since=3, older=0)  # its process (header.boot); 0: not yet
    outcome: str = text(since=3, older="")       # "" while the episode runs, then its outcome
    goal_region: bool = flag(since=3, older=False)   # the vehicle has been within the goal radius


@dataclass(frozen=True)
class Cmd(Message):
    """A timed control sequence: controls[i] applies on [t0 + i dt, t0 + (i+1) dt)."""
    SCHEMA: ClassVar[str] = "vamppi.Cmd"
    t0: float = number()
    dt: float = number()
    controls: np.ndarray = array("<f4", ("N", 2))
    # the planner's sampler state after this solve (a JAX PRNG key's data): with `controls`,
    # which is its nominal, all that its next solve starts from (a restart, a successor)
    rng: np.ndarray = array("<u4", (2,), since=3, older=lambda: np.zeros(2, "<u4"))


@dataclass(frozen=True)
class Depth(Message):
    """Depth image (z along the optical axis, m; 0 = no return) and its camera."""
    SCHEMA: ClassVar[str] = "vamppi.Depth"
    depth: np.ndarray = array("<f4", ("H", "W"), nonneg=True)
    intrinsics: np.ndarray = array("<f8", (4,))      # fx, fy, cx, cy (pixels)
    cam_position: np.ndarray = array("<f8", (3,))    # world frame
    cam_rotation: np.ndarray = array("<f8", (3, 3))  # camera (x right, y down, z fwd) to world
    base_pose: np.ndarray = array("<f8", (4,))       # X, Y, z, Psi of the vehicle
    range_max: float = number()


@dataclass(frozen=True)
class Map(Message):
    """The 2.5D elevation map: per-cell mean and variance, row = y, column = x."""
    SCHEMA: ClassVar[str] = "vamppi.Map"
    mean: np.ndarray = array("<f4", ("H", "W"))
    variance: np.ndarray = array("<f4", ("H", "W"), nonneg=True)
    origin: np.ndarray = array("<f8", (2,))          # world x, y of the corner of cell (0, 0)
    resolution: float = number()


@dataclass(frozen=True)
class Plan(Message):
    SCHEMA: ClassVar[str] = "vamppi.Plan"
    controller: str = text()
    optimal: np.ndarray = array("<f4", ("N1", 6))     # states of the nominal rollout
    nominal: np.ndarray = array("<f4", ("N", 2))      # the nominal control sequence
    rollouts: np.ndarray = array("<f4", ("R", "N1", 2))  # X, Y of some sampled rollouts
    rollout_costs: np.ndarray = array("<f4", ("R",))


@dataclass(frozen=True)
class Stats(Message):
    SCHEMA: ClassVar[str] = "vamppi.Stats"
    controller: str = text()
    samples: int = integer()
    solve_ms: float = number()
    cost_min: float = number()
    cost_mean: float = number()
    terms: dict = floats_by_name()       # cost terms of the nominal rollout


@dataclass(frozen=True)
class Event(Message):
    """Outcomes (success | collision | stopping | timeout | aborted) and what happened on the
    way: start, resume, authority, degraded, recovered (services.plant.protocol)."""
    SCHEMA: ClassVar[str] = "vamppi.Event"
    kind: str = text()
    outcome: str = text()                # "" until the episode ends
    time_to_goal_s: float = number(finite=False)   # nan unless success
    detail: str = text()


@dataclass(frozen=True)
class Clock(Message):
    SCHEMA: ClassVar[str] = "vamppi.Clock"
    tick: int = integer()
    mode: str = text()


@dataclass(frozen=True)
class Handover(Message):
    """A request that planner `to` become the authority (services.plant.protocol): granted
    if `current` and `epoch` are still the plant's authority record and `to` beats, at the
    next tick boundary. Sent by the candidate itself, or by `vamppi swap --to`."""
    SCHEMA: ClassVar[str] = "vamppi.Handover"
    to: str = text()                     # the planner instance to obey
    to_boot: int = integer()             # its process (0: the newest that beats)
    current: str = text()                # the authority it replaces
    epoch: int = integer()               # ... and that authority's epoch
    retire: bool = flag()                # the replaced planner stops (else it stands by)
    reason: str = text()


@dataclass(frozen=True)
class Heartbeat(Message):
    """An instance's beat: its main loop is alive and has made progress (common.supervision).
    The header's stamp is the newest simulation time it has worked on."""
    SCHEMA: ClassVar[str] = "vamppi.Heartbeat"
    VERSION: ClassVar[int] = 5           # 4: world; 5: agree
    VERSIONS_READ: ClassVar[tuple[int, ...]] = (1, 2, 3, 4, 5)
    status: str = text()                 # starting | ready | stalled | stopping
    role: str = text()                   # what the instance does: "" or, for planners, active |
                                         # standby | shadow
    deadline_s: float = number()         # the next beat comes within this, or count it dead
    detail: str = text()
    world: str = text(since=4, older="")     # the digest of the scenario it runs ("" none)
    agree: str = text(since=5, older="")     # common.config.agreement_digest of its config


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.SCHEMA: cls for cls in (State, Cmd, Depth, Map, Plan, Stats, Event, Clock, Handover,
                                Heartbeat)}

M = TypeVar("M", bound=Message)


# ----------------------------------------------------------------------------- codec
def _encode_value(kind: Any, value: Any) -> Any:
    if kind == "float":
        return float(value)
    if kind == "int":
        return int(value)
    if kind == "bool":
        return bool(value)
    if kind == "dict_float":
        return {str(k): float(v) for k, v in value.items()}
    return value


@dataclass(frozen=True)
class _Layout:
    """What `encode` writes for one message type besides the values: the map's header
    with the schema and version, and each field's packed key."""
    prefix: bytes
    fields: tuple[tuple[str, Any, bytes], ...]


_LAYOUTS: dict[type, _Layout] = {}
ALIGN = 16                      # array data starts at a multiple of this in the payload
_ARRAY_DTYPE = wire.map_header(4) + msgpack.packb("dtype")
_ARRAY_SHAPE, _ARRAY_PAD = msgpack.packb("shape"), msgpack.packb("pad")
_ARRAY_DATA = msgpack.packb("data")


def _layout(cls: type[Message]) -> _Layout:
    layout = _LAYOUTS.get(cls)
    if layout is None:
        fields = tuple((f.name, f.metadata["kind"], msgpack.packb(f.name))
                       for f in dataclasses.fields(cls) if f.name != "header")
        prefix = (wire.map_header(3 + len(fields)) + msgpack.packb("schema")
                  + msgpack.packb(cls.SCHEMA) + msgpack.packb("version")
                  + msgpack.packb(cls.VERSION) + msgpack.packb("header"))
        layout = _LAYOUTS[cls] = _Layout(prefix, fields)
    return layout


def encode(msg: Message) -> bytes:
    """One message to msgpack bytes. Arrays keep their exact dtype and bytes and are
    copied once, straight from their own buffers into the payload (common.wire)."""
    h = msg.header
    layout = _layout(type(msg))
    chunks: list[Any] = [layout.prefix, msgpack.packb(
        {"seq": int(h.seq), "stamp": float(h.stamp), "wall_time": float(h.wall_time),
         "source": h.source, "inputs": [[i.key, int(i.seq), float(i.stamp)] for i in h.inputs],
         "boot": int(h.boot), "episode": int(h.episode)})]
    pos = len(chunks[0]) + len(chunks[1])             # bytes written so far
    for name, kind, key in layout.fields:
        value = getattr(msg, name)
        if isinstance(kind, ArraySpec):
            a = np.ascontiguousarray(value)
            data = memoryview(a.reshape(-1).view(np.uint8))
            head = (key, _ARRAY_DTYPE, msgpack.packb(a.dtype.str), _ARRAY_SHAPE,
                    msgpack.packb(list(a.shape)), _ARRAY_PAD)
            tail = _ARRAY_DATA + wire.bin_header(data.nbytes)
            pos += sum(map(len, head)) + 2            # + the pad's bin 8 header
            pad = -(pos + len(tail)) % ALIGN
            chunks += (*head, wire.bin_header(pad), bytes(pad), tail, data)
            pos += pad + len(tail) + data.nbytes
        else:
            chunks += (key, msgpack.packb(_encode_value(kind, value), use_bin_type=True))
            pos += len(chunks[-2]) + len(chunks[-1])
    return b"".join(chunks)


def _fail(schema: str, name: str, why: str) -> DecodeError:
    return DecodeError(f"{schema}: field '{name}' {why}")


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _count(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


_HEADER_CHECKS = (("seq", _count), ("stamp", lambda v: _is_num(v) and math.isfinite(v)),
                  ("wall_time", lambda v: _is_num(v) and math.isfinite(v)),
                  ("source", lambda v: isinstance(v, str)),
                  ("inputs", lambda v: isinstance(v, list)))
_HEADER_CHECKS_V3 = (*_HEADER_CHECKS, ("boot", _count), ("episode", _count))


def _decode_header(schema: str, raw: Any, version: int = Message.VERSION) -> Header:
    if not isinstance(raw, dict):
        raise _fail(schema, "header", "must be a map")
    checks = _HEADER_CHECKS_V3 if version >= 3 else _HEADER_CHECKS
    for key, ok in checks:
        if key not in raw:
            raise _fail(schema, f"header.{key}", "is missing")
        if not ok(raw[key]):
            raise _fail(schema, f"header.{key}", f"has a bad value {raw[key]!r:.60}")
    extra = set(raw) - {k for k, _ in checks}
    if extra:
        raise _fail(schema, f"header.{sorted(extra)[0]}", "is not in the schema")
    inputs = []
    for i, ref in enumerate(raw["inputs"]):
        if not (isinstance(ref, list) and len(ref) == 3 and isinstance(ref[0], str)
                and isinstance(ref[1], int) and _is_num(ref[2])):
            raise _fail(schema, f"header.inputs[{i}]", "must be [key, seq, stamp]")
        inputs.append(InputRef(ref[0], ref[1], float(ref[2])))
    return Header(raw["seq"], float(raw["stamp"]), float(raw["wall_time"]), raw["source"],
                  tuple(inputs), raw.get("boot", 0), raw.get("episode", 0))


def _decode_array(schema: str, name: str, spec: ArraySpec, raw: Any,
                  dims: dict[str, int]) -> np.ndarray:
    if not isinstance(raw, dict) or set(raw) - {"pad"} != {"dtype", "shape", "data"}:
        raise _fail(schema, name, "must be an array map {dtype, shape, [pad], data}")
    if "pad" in raw and not isinstance(raw["pad"], memoryview):
        raise _fail(schema, name, "pad must be bytes")
    if raw["dtype"] != spec.dtype:
        raise _fail(schema, name, f"has dtype {raw['dtype']!r}, expected {spec.dtype!r}")
    shape = raw["shape"]
    if not (isinstance(shape, list) and all(isinstance(s, int) and s >= 0 for s in shape)):
        raise _fail(schema, name, f"has a bad shape {shape!r:.60}")
    if len(shape) != len(spec.shape):
        raise _fail(schema, name, f"has shape {tuple(shape)}, expected {len(spec.shape)} dims")
    for got, want in zip(shape, spec.shape, strict=True):
        if isinstance(want, int) and got != want:
            raise _fail(schema, name, f"has shape {tuple(shape)}, expected {spec.shape}")
        if isinstance(want, str):
            if dims.setdefault(want, got) != got:
                raise _fail(schema, name, f"has shape {tuple(shape)}: dimension {want} is "
                            f"{got} here but {dims[want]} in another field")
    data = raw["data"]
    if not isinstance(data, memoryview):          # a msgpack bin (common.wire: a view)
        raise _fail(schema, name, "data must be bytes")
    dt = np.dtype(spec.dtype)
    if len(data) != dt.itemsize * math.prod(shape):
        raise _fail(schema, name, f"has {len(data)} bytes, shape {tuple(shape)} needs "
                    f"{dt.itemsize * math.prod(shape)}")
    a = np.frombuffer(data, dtype=dt).reshape(shape)     # a view of the payload
    check_values(schema, name, spec, a)
    return a


def check_values(schema: str, name: str, spec: ArraySpec, a: np.ndarray) -> None:
    """Raise `DecodeError` unless every value of `a` is what field `name` requires (finite,
    not negative): the one read of each received array value that `decode` makes."""
    finite = spec.finite and a.dtype.kind == "f"
    if finite and spec.nonneg and _below_max_bits(a):
        return                                       # one pass (see _below_max_bits)
    if finite and not np.isfinite(a).all():
        raise _fail(schema, name, f"has {int((~np.isfinite(a)).sum())} non-finite values")
    if spec.nonneg and (a < 0).any():
        raise _fail(schema, name, "has negative values")


def _below_max_bits(a: np.ndarray) -> bool:
    """Whether every value of float array `a` is finite and not negative, in one pass: as
    unsigned integers of its width these are exactly the bit patterns 0 .. that of the
    largest finite value (negatives, infinities and NaNs lie above). False also for -0.0,
    which the caller's exact checks then accept."""
    if not a.size:
        return True
    bits = np.dtype(f"{a.dtype.byteorder}u{a.dtype.itemsize}")
    return bool(a.view(bits).max() <= np.array(np.finfo(a.dtype).max, a.dtype).view(bits))


def _read(payload: bytes) -> Any:
    try:
        return wire.read(payload)
    except wire.WireError as exc:
        raise DecodeError(f"not a msgpack message: {exc}") from None


def decode(payload: bytes, expected: type[M] | None = None) -> M:
    """msgpack bytes to a validated message; `expected` pins the type. Its arrays are
    read-only views of `payload` (copied once first if it is not `bytes`, so that
    nothing can change them)."""
    if not isinstance(payload, bytes):
        payload = bytes(payload)
    raw = _read(payload)
    if not isinstance(raw, dict):
        raise DecodeError("not a message: the payload is not a msgpack map")
    schema = raw.get("schema")
    cls = MESSAGE_TYPES.get(schema) if isinstance(schema, str) else None
    if cls is None:
        raise DecodeError(f"unknown schema {schema!r:.60}")
    if expected is not None and cls is not expected:
        raise DecodeError(f"{schema}: expected a {expected.SCHEMA} message")
    version = raw.get("version")
    if version not in cls.VERSIONS_READ:
        raise _fail(schema, "version", f"is {version!r}, expected one of "
                    f"{cls.VERSIONS_READ}")
    kwargs: dict[str, Any] = {"header": _decode_header(schema, raw.get("header"), version)}
    dims: dict[str, int] = {}
    known = {"schema", "version", "header"}
    for f in dataclasses.fields(cls):
        if f.name == "header":
            continue
        if f.metadata["since"] > version:           # an older message: the documented default
            older = f.metadata["older"]
            kwargs[f.name] = older() if callable(older) else older
            continue
        known.add(f.name)
        if f.name not in raw:
            raise _fail(schema, f.name, "is missing")
        v, kind = raw[f.name], f.metadata["kind"]
        if isinstance(kind, ArraySpec):
            v = _decode_array(schema, f.name, kind, v, dims)
        elif kind == "float":
            if not _is_num(v):
                raise _fail(schema, f.name, f"must be a number, got {type(v).__name__}")
            v = float(v)
            if f.metadata["finite"] and not math.isfinite(v):
                raise _fail(schema, f.name, f"must be finite, got {v}")
        elif kind == "int":
            if not isinstance(v, int) or isinstance(v, bool) or (f.metadata["nonneg"] and v < 0):
                raise _fail(schema, f.name, f"must be a non-negative integer, got {v!r:.60}")
        elif kind == "str":
            if not isinstance(v, str):
                raise _fail(schema, f.name, f"must be a string, got {type(v).__name__}")
        elif kind == "bool":
            if not isinstance(v, bool):
                raise _fail(schema, f.name, f"must be true or false, got {v!r:.60}")
        elif kind == "dict_float":
            if not (isinstance(v, dict) and all(isinstance(k, str) and _is_num(x)
                                                for k, x in v.items())):
                raise _fail(schema, f.name, "must be a map of names to numbers")
            v = {k: float(x) for k, x in v.items()}
        kwargs[f.name] = v
    extra = set(raw) - known
    if extra:
        raise _fail(schema, sorted(extra)[0], "is not in the schema")
    return cls(**kwargs)  # type: ignore[return-value]



# ----------------------------------------------------------------------------- describe
def peek(payload: bytes) -> tuple[str, Header]:
    """Schema name and header of a payload without validating its fields (what a
    recorder or a timing tool needs); raises `DecodeError` like `decode`."""
    raw = _read(payload)
    if not isinstance(raw, dict) or not isinstance(raw.get("schema"), str):
        raise DecodeError("not a message: no schema name")
    version = raw.get("version")
    return raw["schema"], _decode_header(raw["schema"], raw.get("header"),
                                         version if isinstance(version, int) else 0)


def on_decoded(expected: type[M], handle: Callable[[M], None]) -> Callable[[str, bytes], None]:
    """A subscriber callback `(key, payload)` that hands `handle` each payload decoded as
    `expected` and drops what does not decode (an observer's, not a service's: services
    count what they drop)."""
    def callback(_key: str, payload: bytes) -> None:
        try:
            msg = decode(payload, expected)
        except DecodeError:
            return
        handle(msg)
    return callback


def json_schema(cls: type[Message]) -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of the msgpack map `encode` writes for `cls`:
    what a recording's channels declare. Binary fields (array data) are msgpack bin,
    shown as base64 strings by JSON tools."""
    def of(kind: Any) -> dict[str, Any]:
        if isinstance(kind, ArraySpec):
            return {"type": "object", "required": ["dtype", "shape", "data"],
                    "additionalProperties": False,
                    "description": f"array {kind.dtype} of shape "
                                   f"({', '.join(map(str, kind.shape))}), raw little-endian bytes",
                    "properties": {"dtype": {"const": kind.dtype},
                                   "shape": {"type": "array", "items": {"type": "integer"}},
                                   "pad": {"type": "string", "contentEncoding": "base64",
                                           "description": "0-15 zero bytes: data starts on a "
                                                          "16-byte boundary of the payload"},
                                   "data": {"type": "string", "contentEncoding": "base64"}}}
        return {"float": {"type": "number"}, "int": {"type": "integer", "minimum": 0},
                "str": {"type": "string"}, "bool": {"type": "boolean"},
                "dict_float": {"type": "object", "additionalProperties": {"type": "number"}},
                }[kind]

    header = {"type": "object",
              "required": ["seq", "stamp", "wall_time", "source", "inputs", "boot", "episode"],
              "additionalProperties": False,
              "properties": {"seq": {"type": "integer", "minimum": 0},
                             "stamp": {"type": "number", "description": "simulation time, s"},
                             "wall_time": {"type": "number",
                                           "description": "publish wall time, s since epoch"},
                             "source": {"type": "string"},
                             "inputs": {"type": "array", "items": {
                                 "type": "array", "prefixItems": [
                                     {"type": "string"}, {"type": "integer"},
                                     {"type": "number"}]}},
                             "boot": {"type": "integer", "minimum": 0,
                                      "description": "publisher process start, ns"},
                             "episode": {"type": "integer", "minimum": 0}}}
    props: dict[str, Any] = {"schema": {"const": cls.SCHEMA},
                             "version": {"const": cls.VERSION}, "header": header}
    for f in dataclasses.fields(cls):
        if f.name != "header":
            props[f.name] = of(f.metadata["kind"])
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": cls.SCHEMA,
            "description": (cls.__doc__ or "").strip(), "type": "object",
            "required": list(props), "additionalProperties": False, "properties": props}
