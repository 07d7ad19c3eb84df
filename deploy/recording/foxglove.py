"""`vamppi export-foxglove`: a recording rewritten in encodings Foxglove decodes.

Foxglove does not decode msgpack. The export reads every recorded message,
decodes it with our schemas and writes JSON messages with Foxglove's
well-known schemas (jsonschema encoding), on these topics:

| topic | schema | from |
|---|---|---|
| /tf | foxglove.FrameTransform | state: world -> base_link, base_link -> camera |
| /vehicle/pose | foxglove.PoseInFrame | state |
| /vehicle/path | foxglove.PosesInFrame | states so far, one pose per control tick |
| /map/mean, /map/variance | foxglove.Grid | map (float32 cells, row = y) |
| /planner/plan | foxglove.SceneUpdate | plan: the optimal trajectory, sampled rollouts |
| /sensor/depth | foxglove.RawImage | depth (32FC1, metres) |
| /events | foxglove.Log | events |
| /planner/stats | vamppi.StatsJson | stats (solve time, cost terms: plot them) |

Message log times are the recording's receive times; the `timestamp` inside
each message is the publisher's wall time. Frame `world` is the map frame; `camera` is
the depth camera's optical frame (x right, y down, z forward: where Foxglove places the
image), mounted as the sensor's configuration says.

`Converter` is the one place for each conversion: the export and the live view
(`vamppi view`, deploy/recording/view.py) both call it.
"""

from __future__ import annotations

import base64
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from mcap.writer import CompressionType, Writer

from common.config import ConfigError, load_config
from common.messages import DecodeError, Depth, Event, Map, Message, Plan, State, Stats, decode
from deploy.recording.record import iter_messages, package_versions, read_metadata, recorded_config
from services.sensor.core import CameraParams, camera_pose

# ----------------------------------------------------------------------------- schemas
_NUM = {"type": "number"}
_TIME = {"type": "object", "title": "time",
         "properties": {"sec": {"type": "integer", "minimum": 0},
                        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}}}
_VEC3 = {"type": "object", "title": "foxglove.Vector3",
         "properties": {"x": _NUM, "y": _NUM, "z": _NUM}}
_QUAT = {"type": "object", "title": "foxglove.Quaternion",
         "properties": {"x": _NUM, "y": _NUM, "z": _NUM, "w": _NUM}}
_POSE = {"type": "object", "title": "foxglove.Pose",
         "properties": {"position": _VEC3, "orientation": _QUAT}}
_COLOR = {"type": "object", "title": "foxglove.Color",
          "properties": {"r": _NUM, "g": _NUM, "b": _NUM, "a": _NUM}}
_DURATION = {"type": "object", "title": "duration",
             "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
_STR = {"type": "string"}
_BYTES = {"type": "string", "contentEncoding": "base64"}
_ARR = {"type": "array", "items": {"type": "object"}}


def _obj(title: str, props: dict[str, Any]) -> dict[str, Any]:
    return {"title": title, "type": "object", "properties": props}


SCHEMAS: dict[str, dict[str, Any]] = {
    "foxglove.FrameTransform": _obj("foxglove.FrameTransform", {
        "timestamp": _TIME, "parent_frame_id": _STR, "child_frame_id": _STR,
        "translation": _VEC3, "rotation": _QUAT}),
    "foxglove.PoseInFrame": _obj("foxglove.PoseInFrame", {
        "timestamp": _TIME, "frame_id": _STR, "pose": _POSE}),
    "foxglove.PosesInFrame": _obj("foxglove.PosesInFrame", {
        "timestamp": _TIME, "frame_id": _STR, "poses": {"type": "array", "items": _POSE}}),
    "foxglove.Grid": _obj("foxglove.Grid", {
        "timestamp": _TIME, "frame_id": _STR, "pose": _POSE,
        "column_count": {"type": "integer", "minimum": 0},
        "cell_size": {"type": "object", "title": "foxglove.Vector2",
                      "properties": {"x": _NUM, "y": _NUM}},
        "row_stride": {"type": "integer", "minimum": 0},
        "cell_stride": {"type": "integer", "minimum": 0},
        "fields": {"type": "array", "items": _obj("foxglove.PackedElementField", {
            "name": _STR, "offset": {"type": "integer", "minimum": 0},
            "type": {"type": "integer", "description": "foxglove.NumericType: 7 = FLOAT32"}})},
        "data": _BYTES}),
    "foxglove.RawImage": _obj("foxglove.RawImage", {
        "timestamp": _TIME, "frame_id": _STR, "width": {"type": "integer"},
        "height": {"type": "integer"}, "encoding": _STR, "step": {"type": "integer"},
        "data": _BYTES}),
    "foxglove.Log": _obj("foxglove.Log", {
        "timestamp": _TIME, "level": {"type": "integer", "description": "2 = INFO, 3 = WARNING"},
        "message": _STR, "name": _STR, "file": _STR, "line": {"type": "integer"}}),
    "foxglove.SceneUpdate": _obj("foxglove.SceneUpdate", {
        "deletions": _ARR,
        "entities": {"type": "array", "items": _obj("foxglove.SceneEntity", {
            "timestamp": _TIME, "frame_id": _STR, "id": _STR, "lifetime": _DURATION,
            "frame_locked": {"type": "boolean"}, "metadata": _ARR, "arrows": _ARR,
            "cubes": _ARR, "spheres": _ARR, "cylinders": _ARR,
            "lines": {"type": "array", "items": _obj("foxglove.LinePrimitive", {
                "type": {"type": "integer", "description": "0 = LINE_STRIP"}, "pose": _POSE,
                "thickness": _NUM, "scale_invariant": {"type": "boolean"},
                "points": {"type": "array", "items": _VEC3}, "color": _COLOR,
                "colors": _ARR, "indices": {"type": "array", "items": {"type": "integer"}}})},
            "triangles": _ARR, "texts": _ARR, "models": _ARR})}}),
    "vamppi.StatsJson": _obj("vamppi.StatsJson", {
        "stamp": _NUM, "controller": _STR, "samples": {"type": "integer"}, "solve_ms": _NUM,
        "cost_min": _NUM, "cost_mean": _NUM, "terms": {"type": "object"}}),
}

TOPICS: dict[str, str] = {
    "/tf": "foxglove.FrameTransform", "/vehicle/pose": "foxglove.PoseInFrame",
    "/vehicle/path": "foxglove.PosesInFrame", "/map/mean": "foxglove.Grid",
    "/map/variance": "foxglove.Grid", "/planner/plan": "foxglove.SceneUpdate",
    "/sensor/depth": "foxglove.RawImage", "/events": "foxglove.Log",
    "/planner/stats": "vamppi.StatsJson",
}


# ----------------------------------------------------------------------------- converters
def _time(wall_s: float) -> dict[str, int]:
    ns = max(int(round(wall_s * 1e9)), 0)
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _pose(x: float, y: float, z: float, yaw: float) -> dict[str, Any]:
    return {"position": {"x": x, "y": y, "z": z},
            "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)}}


def _line(points: np.ndarray, z: float, rgba: tuple[float, float, float, float],
          thickness: float) -> dict[str, Any]:
    return {"type": 0, "pose": _pose(0.0, 0.0, 0.0, 0.0), "thickness": thickness,
            "scale_invariant": False,
            "points": [{"x": float(p[0]), "y": float(p[1]), "z": z} for p in points],
            "color": dict(zip("rgba", rgba, strict=True)), "colors": [], "indices": []}


def _entity(t: dict[str, int], ident: str, lines: list[dict[str, Any]]) -> dict[str, Any]:
    return {"timestamp": t, "frame_id": "world", "id": ident,
            "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": False, "metadata": [],
            "arrows": [], "cubes": [], "spheres": [], "cylinders": [], "lines": lines,
            "triangles": [], "texts": [], "models": []}


def _finite(v: float) -> float | None:
    """JSON has no inf or nan: null instead."""
    return v if math.isfinite(v) else None


def grid(m: Map, layer: str) -> dict[str, Any]:
    a = np.ascontiguousarray(getattr(m, layer), dtype="<f4")
    h, w = a.shape
    return {"timestamp": _time(m.header.wall_time), "frame_id": "world",
            "pose": _pose(float(m.origin[0]), float(m.origin[1]), 0.0, 0.0),
            "column_count": w, "cell_size": {"x": m.resolution, "y": m.resolution},
            "row_stride": 4 * w, "cell_stride": 4,
            "fields": [{"name": layer, "offset": 0, "type": 7}],
            "data": base64.b64encode(a.tobytes()).decode()}


def quaternion(r: np.ndarray) -> dict[str, float]:
    """The unit quaternion of a rotation matrix, from its largest component (accurate for
    every rotation)."""
    t = float(np.trace(r))
    if t > 0:
        s = 2 * math.sqrt(t + 1)
        w, x, y, z = (
            s / 4, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s)
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2 * math.sqrt(1 + r[0, 0] - r[1, 1] - r[2, 2])
        w, x, y, z = (
            (r[2, 1] - r[1, 2]) / s, s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s)
    elif r[1, 1] > r[2, 2]:
        s = 2 * math.sqrt(1 + r[1, 1] - r[0, 0] - r[2, 2])
        w, x, y, z = (
            (r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s)
    else:
        s = 2 * math.sqrt(1 + r[2, 2] - r[0, 0] - r[1, 1])
        w, x, y, z = (
            (r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4)
    return {"x": float(x), "y": float(y), "z": float(z), "w": float(w)}


def camera_mount(camera: CameraParams) -> dict[str, Any]:
    """base_link -> camera (the optical frame) as the sensor renders from it
    (services.sensor.core.camera_pose of the vehicle at the origin, heading x)."""
    pos, rot = camera_pose(camera, 0.0, 0.0, 0.0, 0.0)
    return {"translation": {"x": float(pos[0]), "y": float(pos[1]), "z": float(pos[2])},
            "rotation": quaternion(rot)}


def camera_of(cfg_dict: dict[str, Any]) -> CameraParams:
    """The camera of a configuration (a recording's, as JSON); the defaults' if unreadable."""
    try:
        cfg = load_config(overrides={f"sensor.{k}": v
                                     for k, v in cfg_dict.get("sensor", {}).items()})
    except ConfigError:
        cfg = load_config()
    return CameraParams.from_config(cfg.sensor)


class Converter:
    """Our messages -> (topic, JSON-able Foxglove message) pairs; keeps the path."""

    def __init__(self, map_stride: int = 1, rollouts: int = 30,
                 camera: CameraParams | None = None):
        self.map_stride, self.rollouts = max(1, map_stride), rollouts
        self.mount = camera_mount(camera or camera_of({}))
        self.maps = 0
        self.path: list[dict[str, Any]] = []
        self._last_tick = -1

    def convert(self, msg: Message) -> list[tuple[str, dict[str, Any]]]:
        t = _time(msg.header.wall_time)
        if isinstance(msg, State):
            x = msg.x
            pose = _pose(float(x[3]), float(x[4]), float(msg.z), float(x[5]))
            out = [("/tf", {"timestamp": t, "parent_frame_id": "world",
                            "child_frame_id": "base_link",
                            "translation": pose["position"], "rotation": pose["orientation"]}),
                   ("/tf", {"timestamp": t, "parent_frame_id": "base_link",
                            "child_frame_id": "camera", **self.mount}),
                   ("/vehicle/pose", {"timestamp": t, "frame_id": "world", "pose": pose})]
            if msg.tick != self._last_tick:
                self._last_tick = msg.tick
                self.path.append(pose)
                out.append(("/vehicle/path", {"timestamp": t, "frame_id": "world",
                                              "poses": list(self.path)}))
            return out
        if isinstance(msg, Map):
            self.maps += 1
            if (self.maps - 1) % self.map_stride:
                return []
            return [("/map/mean", grid(msg, "mean")), ("/map/variance", grid(msg, "variance"))]
        if isinstance(msg, Plan):
            z = 0.3
            lines = [_line(r, z, (0.6, 0.6, 0.6, 0.35), 0.03)
                     for r in msg.rollouts[:self.rollouts]]
            lines.append(_line(msg.optimal[:, 3:5], z + 0.05, (0.1, 0.4, 1.0, 1.0), 0.12))
            return [("/planner/plan", {"deletions": [], "entities": [
                _entity(t, "plan", lines)]})]
        if isinstance(msg, Depth):
            h, w = msg.depth.shape
            return [("/sensor/depth", {"timestamp": t, "frame_id": "camera", "width": w,
                                       "height": h, "encoding": "32FC1", "step": 4 * w,
                                       "data": base64.b64encode(np.ascontiguousarray(
                                           msg.depth, "<f4").tobytes()).decode()})]
        if isinstance(msg, Event):
            text = msg.kind + (f": {msg.outcome}" if msg.outcome else "") + (
                f" ({msg.detail})" if msg.detail else "")
            if math.isfinite(msg.time_to_goal_s):
                text += f", time to goal {msg.time_to_goal_s:.2f} s"
            level = 3 if msg.kind in ("collision", "error", "stale", "timeout", "stopping") else 2
            return [("/events", {"timestamp": t, "level": level, "message": text,
                                 "name": msg.header.source, "file": "", "line": 0})]
        if isinstance(msg, Stats):
            return [("/planner/stats", {"stamp": msg.header.stamp, "controller": msg.controller,
                                        "samples": msg.samples, "solve_ms": msg.solve_ms,
                                        "cost_min": _finite(msg.cost_min),
                                        "cost_mean": _finite(msg.cost_mean),
                                        "terms": {k: _finite(v) for k, v in msg.terms.items()}})]
        return []             # cmd: its controls are in the plan; clock: nothing to show


def export(src: str | Path, dst: str | Path, map_stride: int = 1,
           rollouts: int = 30) -> dict[str, Any]:
    """Write `dst` from the recording `src`; returns message counts per topic."""
    conv = Converter(map_stride, rollouts, camera_of(recorded_config(src, "sensor")))
    counts = {topic: 0 for topic in TOPICS}
    skipped = 0
    with open(dst, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="", library=f"vamppi {package_versions()['vamppi']} export-foxglove")
        for name, data in read_metadata(src).items():
            w.add_metadata(name, data)
        schema_ids = {name: w.register_schema(name, "jsonschema", json.dumps(s).encode())
                      for name, s in SCHEMAS.items()}
        channels = {topic: w.register_channel(topic, "json", schema_ids[schema])
                    for topic, schema in TOPICS.items()}
        for m in iter_messages(src):
            try:
                msg = decode(m.data)
            except DecodeError:
                skipped += 1
                continue
            for topic, body in conv.convert(msg):
                w.add_message(channels[topic], log_time=m.log_time_ns,
                              data=json.dumps(body, allow_nan=False).encode(),
                              publish_time=m.publish_time_ns)
                counts[topic] += 1
        w.finish()
    return {"input": str(src), "output": str(dst), "messages": counts,
            "undecodable_skipped": skipped}


_JSON_TYPES: dict[str, tuple[type, ...]] = {
    "object": (dict,), "array": (list,), "string": (str,), "boolean": (bool,),
    "integer": (int,), "number": (int, float)}


def violations(schema: dict[str, Any], value: Any, where: str = "$") -> list[str]:
    """Where `value` breaks `schema` (the JSON Schema subset of SCHEMAS: type, properties,
    items, minimum, maximum, base64 contentEncoding); [] if it conforms. Null stands for
    a non-finite number (JSON has none)."""
    kind = schema.get("type")
    if value is None and kind == "number":
        return []
    if kind is not None and (not isinstance(value, _JSON_TYPES[kind]) or (
            kind in ("integer", "number") and isinstance(value, bool))):
        return [f"{where}: {type(value).__name__} is not {kind}"]
    out = []
    if kind in ("integer", "number"):
        if "minimum" in schema and value < schema["minimum"]:
            out.append(f"{where}: {value} < {schema['minimum']}")
        if "maximum" in schema and value > schema["maximum"]:
            out.append(f"{where}: {value} > {schema['maximum']}")
    if schema.get("contentEncoding") == "base64":
        try:
            base64.b64decode(value, validate=True)
        except ValueError:
            out.append(f"{where}: not base64")
    for name, sub in schema.get("properties", {}).items():
        if isinstance(value, dict) and name in value:
            out += violations(sub, value[name], f"{where}.{name}")
    if kind == "array" and "items" in schema:
        for i, item in enumerate(value):
            out += violations(schema["items"], item, f"{where}[{i}]")
    return out
