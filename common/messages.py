"""Message schemas and the msgpack codec: each message defined once.

Every message is a frozen dataclass with a `header` and typed fields. On the
wire it is one msgpack map::

    {"schema": "vamppi.State", "version": 1, "header": {...}, <fields>...}

NumPy arrays travel as ``{"dtype": "<f4", "shape": [..], "data": <bytes>}``:
decoding is exact (the float32 that leaves is the float32 that arrives) and
never casts. `decode` validates schema name and version, every field's type,
every array's dtype and shape (named dimensions must agree across fields) and
finiteness where the schema requires it, and raises `DecodeError` naming the
field.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

import msgpack
import numpy as np


class DecodeError(ValueError):
    """A payload that is not a valid message; the text names the field."""


# ----------------------------------------------------------------------------- field kinds
@dataclass(frozen=True)
class ArraySpec:
    dtype: str                       # exact numpy dtype string, e.g. "<f4"
    shape: tuple[int | str, ...]     # ints are fixed, strings are named dims
    finite: bool = True
    nonneg: bool = False


def array(dtype: str, shape: tuple[int | str, ...], *, finite: bool = True,
          nonneg: bool = False) -> Any:
    return field(metadata={"kind": ArraySpec(dtype, shape, finite, nonneg)})


def number(*, finite: bool = True) -> Any:
    return field(metadata={"kind": "float", "finite": finite})


def integer(*, nonneg: bool = True) -> Any:
    return field(metadata={"kind": "int", "nonneg": nonneg})


def text() -> Any:
    return field(metadata={"kind": "str"})


def floats_by_name() -> Any:
    return field(metadata={"kind": "dict_float"})


# ----------------------------------------------------------------------------- header
@dataclass(frozen=True)
class InputRef:
    """One input a message was computed from: its key, seq and sim stamp."""
    key: str
    seq: int
    stamp: float


@dataclass(frozen=True)
class Header:
    seq: int                  # per publisher, gap-free, from 0
    stamp: float              # simulation time, s
    wall_time: float          # publish wall time, s since the epoch
    source: str               # publishing instance, "<service>/<instance>"
    inputs: tuple[InputRef, ...] = ()


# ----------------------------------------------------------------------------- messages
@dataclass(frozen=True)
class Message:
    SCHEMA: ClassVar[str] = ""
    VERSION: ClassVar[int] = 1
    header: Header


@dataclass(frozen=True)
class State(Message):
    """Vehicle state x = [V, v, r, X, Y, Psi] (services.plant.dynamics.S)."""
    SCHEMA: ClassVar[str] = "vamppi.State"
    x: np.ndarray = array("<f8", (6,))
    z: float = number()                  # ground elevation under the CG, m
    u_applied: np.ndarray = array("<f8", (2,))   # [delta, f_xt] applied now
    tick: int = integer()                # control tick index
    authority: str = text()              # planner instance whose commands the plant takes


@dataclass(frozen=True)
class Cmd(Message):
    """A timed control sequence: controls[i] applies on [t0 + i dt, t0 + (i+1) dt)."""
    SCHEMA: ClassVar[str] = "vamppi.Cmd"
    t0: float = number()
    dt: float = number()
    controls: np.ndarray = array("<f4", ("N", 2))


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
    """collision | goal | timeout | stopping (outcomes), start, stale, authority, error."""
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


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.SCHEMA: cls for cls in (State, Cmd, Depth, Map, Plan, Stats, Event, Clock)}

M = TypeVar("M", bound=Message)


# ----------------------------------------------------------------------------- codec
def _encode_value(kind: Any, value: Any) -> Any:
    if isinstance(kind, ArraySpec):
        a = np.ascontiguousarray(value)
        data = memoryview(a.reshape(-1).view(np.uint8))   # packed from the array's own buffer
        return {"dtype": a.dtype.str, "shape": list(a.shape), "data": data}
    if kind == "float":
        return float(value)
    if kind == "int":
        return int(value)
    if kind == "dict_float":
        return {str(k): float(v) for k, v in value.items()}
    return value


def encode(msg: Message) -> bytes:
    """One message to msgpack bytes. Arrays keep their exact dtype and bytes."""
    h = msg.header
    out: dict[str, Any] = {
        "schema": msg.SCHEMA, "version": msg.VERSION,
        "header": {"seq": int(h.seq), "stamp": float(h.stamp), "wall_time": float(h.wall_time),
                   "source": h.source,
                   "inputs": [[i.key, int(i.seq), float(i.stamp)] for i in h.inputs]},
    }
    for f in dataclasses.fields(msg):
        if f.name != "header":
            out[f.name] = _encode_value(f.metadata["kind"], getattr(msg, f.name))
    return msgpack.packb(out, use_bin_type=True)


def _fail(schema: str, name: str, why: str) -> DecodeError:
    return DecodeError(f"{schema}: field '{name}' {why}")


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _decode_header(schema: str, raw: Any) -> Header:
    if not isinstance(raw, dict):
        raise _fail(schema, "header", "must be a map")
    for key, ok in (("seq", lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0),
                    ("stamp", lambda v: _is_num(v) and math.isfinite(v)),
                    ("wall_time", lambda v: _is_num(v) and math.isfinite(v)),
                    ("source", lambda v: isinstance(v, str)),
                    ("inputs", lambda v: isinstance(v, list))):
        if key not in raw:
            raise _fail(schema, f"header.{key}", "is missing")
        if not ok(raw[key]):
            raise _fail(schema, f"header.{key}", f"has a bad value {raw[key]!r:.60}")
    inputs = []
    for i, ref in enumerate(raw["inputs"]):
        if not (isinstance(ref, list) and len(ref) == 3 and isinstance(ref[0], str)
                and isinstance(ref[1], int) and _is_num(ref[2])):
            raise _fail(schema, f"header.inputs[{i}]", "must be [key, seq, stamp]")
        inputs.append(InputRef(ref[0], ref[1], float(ref[2])))
    return Header(raw["seq"], float(raw["stamp"]), float(raw["wall_time"]), raw["source"],
                  tuple(inputs))


def _decode_array(schema: str, name: str, spec: ArraySpec, raw: Any,
                  dims: dict[str, int]) -> np.ndarray:
    if not isinstance(raw, dict) or set(raw) != {"dtype", "shape", "data"}:
        raise _fail(schema, name, "must be an array map {dtype, shape, data}")
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
    if not isinstance(data, bytes):
        raise _fail(schema, name, "data must be bytes")
    dt = np.dtype(spec.dtype)
    if len(data) != dt.itemsize * math.prod(shape):
        raise _fail(schema, name, f"has {len(data)} bytes, shape {tuple(shape)} needs "
                    f"{dt.itemsize * math.prod(shape)}")
    a = np.frombuffer(data, dtype=dt).reshape(shape)
    if spec.finite and dt.kind == "f" and not np.isfinite(a).all():
        raise _fail(schema, name, f"has {int((~np.isfinite(a)).sum())} non-finite values")
    if spec.nonneg and (a < 0).any():
        raise _fail(schema, name, "has negative values")
    return a


def decode(payload: bytes, expected: type[M] | None = None) -> M:
    """msgpack bytes to a validated message; `expected` pins the type."""
    try:
        raw = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several types on truncated/garbage input
        raise DecodeError(f"not a msgpack message: {type(exc).__name__}: {exc}") from None
    if not isinstance(raw, dict):
        raise DecodeError("not a message: the payload is not a msgpack map")
    schema = raw.get("schema")
    cls = MESSAGE_TYPES.get(schema) if isinstance(schema, str) else None
    if cls is None:
        raise DecodeError(f"unknown schema {schema!r:.60}")
    if expected is not None and cls is not expected:
        raise DecodeError(f"{schema}: expected a {expected.SCHEMA} message")
    if raw.get("version") != cls.VERSION:
        raise _fail(schema, "version", f"is {raw.get('version')!r}, expected {cls.VERSION}")
    kwargs: dict[str, Any] = {"header": _decode_header(schema, raw.get("header"))}
    dims: dict[str, int] = {}
    known = {"schema", "version", "header"}
    for f in dataclasses.fields(cls):
        if f.name == "header":
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
    try:
        raw = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except Exception as exc:
        raise DecodeError(f"not a msgpack message: {type(exc).__name__}: {exc}") from None
    if not isinstance(raw, dict) or not isinstance(raw.get("schema"), str):
        raise DecodeError("not a message: no schema name")
    return raw["schema"], _decode_header(raw["schema"], raw.get("header"))


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
                                   "data": {"type": "string", "contentEncoding": "base64"}}}
        return {"float": {"type": "number"}, "int": {"type": "integer", "minimum": 0},
                "str": {"type": "string"},
                "dict_float": {"type": "object", "additionalProperties": {"type": "number"}},
                }[kind]

    header = {"type": "object", "required": ["seq", "stamp", "wall_time", "source", "inputs"],
              "properties": {"seq": {"type": "integer", "minimum": 0},
                             "stamp": {"type": "number", "description": "simulation time, s"},
                             "wall_time": {"type": "number",
                                           "description": "publish wall time, s since epoch"},
                             "source": {"type": "string"},
                             "inputs": {"type": "array", "items": {
                                 "type": "array", "prefixItems": [
                                     {"type": "string"}, {"type": "integer"},
                                     {"type": "number"}]}}}}
    props: dict[str, Any] = {"schema": {"const": cls.SCHEMA},
                             "version": {"const": cls.VERSION}, "header": header}
    for f in dataclasses.fields(cls):
        if f.name != "header":
            props[f.name] = of(f.metadata["kind"])
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": cls.SCHEMA,
            "description": (cls.__doc__ or "").strip(), "type": "object",
            "required": list(props), "additionalProperties": False, "properties": props}
