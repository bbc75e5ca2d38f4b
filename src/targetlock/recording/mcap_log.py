"""``run.mcap``: a run as an MCAP file that Foxglove opens (plots, camera image, 3D scene, one timeline).

Messages are JSON with Foxglove's well-known schemas (``foxglove.FrameTransform``,
``foxglove.CompressedImage``, ``foxglove.ImageAnnotations``, ``foxglove.CameraCalibration``,
``foxglove.Log``) plus one ``targetlock.Row`` channel per time series, whose fields are the CSV's
columns. The file is written as the run goes: chunks are closed and flushed to disk at least every
``flush_seconds``, so a crash or a kill keeps everything up to the last flush (Foxglove and
``mcap recover`` read a file without its closing summary).

Times: message log times are the run's clock in nanoseconds (t = 0 at the start of the run).
Frames: ``base`` (shaft end of the bending section) → ``tip`` (camera, x right, y down, z forward)
from the chained kinematics; ``base`` → ``target`` where the twin knows the target.
"""
from __future__ import annotations

import base64
import json
import math
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

__all__ = ["McapLog", "SCHEMAS", "LOG_LEVELS", "pose_message", "stamp"]

LOG_LEVELS = {"debug": 1, "info": 2, "warning": 3, "error": 4, "fatal": 5}

_TIME = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
_VEC3 = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
_QUAT = {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}}
_VEC2 = {"type": "object", "properties": {k: {"type": "number"} for k in "xy"}}
_COLOR = {"type": "object", "properties": {k: {"type": "number"} for k in "rgba"}}
_NUMBERS = {"type": "array", "items": {"type": "number"}}

# The fields of Foxglove's schemas this module writes (JSON Schema encoding, as Foxglove publishes them).
SCHEMAS: dict[str, dict] = {
    "foxglove.FrameTransform": {"type": "object", "properties": {
        "timestamp": _TIME, "parent_frame_id": {"type": "string"}, "child_frame_id": {"type": "string"},
        "translation": _VEC3, "rotation": _QUAT}},
    "foxglove.CompressedImage": {"type": "object", "properties": {
        "timestamp": _TIME, "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"}, "format": {"type": "string"}}},
    "foxglove.CameraCalibration": {"type": "object", "properties": {
        "timestamp": _TIME, "frame_id": {"type": "string"}, "width": {"type": "integer"},
        "height": {"type": "integer"}, "distortion_model": {"type": "string"}, "D": _NUMBERS, "K": _NUMBERS,
        "R": _NUMBERS, "P": _NUMBERS}},
    "foxglove.ImageAnnotations": {"type": "object", "properties": {
        "circles": {"type": "array", "items": {"type": "object", "properties": {
            "timestamp": _TIME, "position": _VEC2, "diameter": {"type": "number"}, "thickness": {"type": "number"},
            "fill_color": _COLOR, "outline_color": _COLOR}}},
        "points": {"type": "array", "items": {"type": "object", "properties": {
            "timestamp": _TIME, "type": {"type": "integer"}, "points": {"type": "array", "items": _VEC2},
            "outline_color": _COLOR, "thickness": {"type": "number"}}}},
        "texts": {"type": "array", "items": {"type": "object", "properties": {
            "timestamp": _TIME, "position": _VEC2, "text": {"type": "string"}, "font_size": {"type": "number"},
            "text_color": _COLOR, "background_color": _COLOR}}}}},
    "foxglove.Log": {"type": "object", "properties": {
        "timestamp": _TIME, "level": {"type": "integer"}, "message": {"type": "string"},
        "name": {"type": "string"}, "file": {"type": "string"}, "line": {"type": "integer"}}},
}


def stamp(t: float) -> dict[str, int]:
    """Foxglove time of ``t`` seconds."""
    ns = int(round(t * 1e9))
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) of a 3x3 rotation matrix (Shepperd's method). Written out because
    it runs twice per control tick in a recorded run, where scipy's Rotation costs ~0.15 ms a call."""
    m00, m11, m22 = float(r[0, 0]), float(r[1, 1]), float(r[2, 2])
    tr = m00 + m11 + m22
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        return ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s)
    if m00 >= m11 and m00 >= m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        return (0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s)
    if m11 >= m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        return ((r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s)
    s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
    return ((r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s)


def pose_message(t: float, parent: str, child: str, pose: np.ndarray) -> dict:
    """``foxglove.FrameTransform`` of a 4x4 homogeneous pose (m) of ``child`` in ``parent``."""
    x, y, z, w = quaternion(pose[:3, :3])
    return {"timestamp": stamp(t), "parent_frame_id": parent, "child_frame_id": child,
            "translation": {"x": float(pose[0, 3]), "y": float(pose[1, 3]), "z": float(pose[2, 3])},
            "rotation": {"x": float(x), "y": float(y), "z": float(z), "w": float(w)}}


def _finite(v: Any) -> Any:
    """JSON has no NaN: a missing value is null."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


class McapLog:
    """An MCAP file written as a run goes; channels are registered on first use.

    ``path``: the file (created, or refused if it exists and ``overwrite`` is false);
    ``flush_seconds``: longest wall time between flushes to disk (s)."""

    def __init__(self, path: str | Path, *, flush_seconds: float = 0.5, overwrite: bool = True) -> None:
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        self._fh = self.path.open("wb" if overwrite else "xb")
        # small chunks: each flush closes one, and a crash loses at most the open one
        self._w = Writer(self._fh, chunk_size=256 * 1024, compression=CompressionType.ZSTD)
        self._w.start(profile="", library="targetlock")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._seq: dict[int, int] = {}
        self._flush_seconds = flush_seconds
        self._last_flush = time.monotonic()
        self.closed = False

    def _channel(self, topic: str, schema: str, schema_body: dict | None = None) -> int:
        ch = self._channels.get(topic)
        if ch is None:
            sid = self._schemas.get(schema)
            if sid is None:
                body = schema_body if schema_body is not None else SCHEMAS[schema]
                sid = self._w.register_schema(name=schema, encoding="jsonschema", data=json.dumps(body).encode())
                self._schemas[schema] = sid
            ch = self._w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
            self._channels[topic] = ch
            self._seq[ch] = 0
        return ch

    def write(self, topic: str, schema: str, t: float, message: dict, *, schema_body: dict | None = None) -> None:
        """Log ``message`` (a dict in ``schema``) on ``topic`` at run time ``t`` (s)."""
        if self.closed:
            return
        ch = self._channel(topic, schema, schema_body)
        ns = max(int(round(t * 1e9)), 0)
        self._seq[ch] += 1
        self._w.add_message(channel_id=ch, log_time=ns, publish_time=ns, sequence=self._seq[ch],
                            data=json.dumps(message, separators=(",", ":")).encode())
        if time.monotonic() - self._last_flush > self._flush_seconds:
            self.flush()

    def row(self, topic: str, t: float, columns: Sequence[str], values: Sequence[float]) -> None:
        """One time-series row (the CSV's columns) as a ``targetlock.Row`` message."""
        body = {"type": "object", "properties": {c: {"type": ["number", "null"]} for c in columns}}
        # one schema per topic: its columns (e.g. topic /timeseries → schema targetlock.timeseries)
        self.write(topic, "targetlock." + topic.strip("/").replace("/", "."), t,
                   {c: _finite(float(v)) for c, v in zip(columns, values)}, schema_body=body)

    def transform(self, t: float, parent: str, child: str, pose: np.ndarray) -> None:
        self.write("/tf", "foxglove.FrameTransform", t, pose_message(t, parent, child, pose))

    def image(self, t: float, jpeg: bytes, frame_id: str = "tip") -> None:
        self.write("/camera/image", "foxglove.CompressedImage", t,
                   {"timestamp": stamp(t), "frame_id": frame_id, "data": base64.b64encode(jpeg).decode("ascii"),
                    "format": "jpeg"})

    def calibration(self, t: float, camera: Any, frame_id: str = "tip") -> None:
        """``camera``: :class:`targetlock.model.camera.CameraParams` (pinhole + radial distortion)."""
        k = camera.matrix
        p = np.hstack([k, np.zeros((3, 1))])
        self.write("/camera/calibration", "foxglove.CameraCalibration", t, {
            "timestamp": stamp(t), "frame_id": frame_id, "width": int(camera.width), "height": int(camera.height),
            "distortion_model": "plumb_bob", "D": [float(v) for v in camera.dist_coeffs],
            "K": [float(v) for v in k.ravel()], "R": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
            "P": [float(v) for v in p.ravel()]})

    def annotations(self, t: float, *, target_px: Sequence[float] | None, centre_px: Sequence[float],
                    label: str = "") -> None:
        """The tracked target (circle), the image centre (cross) and the error vector, in image pixels."""
        ts = stamp(t)
        green, blue = {"r": 0.1, "g": 0.9, "b": 0.2, "a": 1.0}, {"r": 0.2, "g": 0.6, "b": 1.0, "a": 1.0}
        cx, cy = float(centre_px[0]), float(centre_px[1])
        points = [{"timestamp": ts, "type": 4, "thickness": 1.5, "outline_color": blue,
                   "points": [{"x": cx - 10, "y": cy}, {"x": cx + 10, "y": cy}, {"x": cx, "y": cy - 10},
                              {"x": cx, "y": cy + 10}]}]
        circles = []
        if target_px is not None and all(math.isfinite(float(v)) for v in target_px):
            tx, ty = float(target_px[0]), float(target_px[1])
            circles.append({"timestamp": ts, "position": {"x": tx, "y": ty}, "diameter": 24.0, "thickness": 2.0,
                            "fill_color": {"r": 0, "g": 0, "b": 0, "a": 0}, "outline_color": green})
            points.append({"timestamp": ts, "type": 3, "thickness": 1.5, "outline_color": green,
                           "points": [{"x": cx, "y": cy}, {"x": tx, "y": ty}]})
        texts = [{"timestamp": ts, "position": {"x": 8.0, "y": 20.0}, "text": label, "font_size": 14.0,
                  "text_color": {"r": 1, "g": 1, "b": 1, "a": 1}, "background_color": {"r": 0, "g": 0, "b": 0, "a": 0.5}}]
        self.write("/camera/annotations", "foxglove.ImageAnnotations", t,
                   {"circles": circles, "points": points, "texts": texts if label else []})

    def log(self, t: float, level: str, message: str, name: str = "targetlock") -> None:
        """A log message (drive and safety state changes, target lost/back) on ``/log``."""
        self.write("/log", "foxglove.Log", t, {"timestamp": stamp(t), "level": LOG_LEVELS[level],
                                               "message": message, "name": name, "file": "", "line": 0})

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self._w.add_metadata(name, {k: str(v) for k, v in data.items()})

    def flush(self) -> None:
        if not self.closed:
            self._w.flush()
            self._last_flush = time.monotonic()

    def close(self) -> None:
        """Write the summary (indexes, statistics) and close the file."""
        if not self.closed:
            self._w.finish()
            self._fh.close()
            self.closed = True

    def __enter__(self) -> "McapLog":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
