"""Waymo's submission format: a serialized ``waymo.open_dataset.Objects`` protobuf (``.bin``).

The official toolkit's ``create_submission`` and mmdetection3d's Waymo metric write detections
this way: one ``Objects`` message whose ``objects`` each carry a ``context_name``, a
``frame_timestamp_micros``, a ``score`` and a ``Label`` with a 3D ``box`` (``center_x``,
``center_y``, ``center_z``, ``length``, ``width``, ``height``, ``heading``) and a ``type``.
The message schema is declared here (the field numbers of waymo-open-dataset's
``protos/metrics.proto`` and ``label.proto``; only the fields read or written) and read with the
``protobuf`` runtime: no TensorFlow, no waymo package. Fields this schema omits
(``camera_name``, ``no_label_zone_objects``, keypoints, ...) are kept as unknown fields and
ignored.

A frame without detections has no object in the format, so :func:`read_waymo_bin` returns only
the frames that have one; ``tools/evaluate_predictions.py`` reads a split frame absent from the
file as a frame without detections, as the Waymo metric reads a submission.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import DecodeError
from google.protobuf.unknown_fields import UnknownFieldSet

from pcdet_atlas.datasets.waymo_format import WAYMO_CLASSES
from pcdet_atlas.utils.files import write_atomic

__all__ = [
    "BOX_FIELDS",
    "PredictionError",
    "objects_message_class",
    "read_waymo_bin",
    "write_waymo_bin",
]

#: ``Label.Box`` fields in ``boxes_lidar`` column order (x, y, z, dx, dy, dz, heading)
BOX_FIELDS = ("center_x", "center_y", "center_z", "length", "width", "height", "heading")
_BOX_NUMBERS = {"center_x": 1, "center_y": 2, "center_z": 3, "width": 4, "length": 5,
                "height": 6, "heading": 7}  # fmt: skip
_SPEED_FIELDS = ("speed_x", "speed_y")  # Label.Metadata: boxes_lidar columns 7 and 8
_LABEL_TYPE_FIELD = 3


class PredictionError(ValueError):
    """Predictions that cannot be scored; the message names the file, the frame and the field."""


def _schema() -> descriptor_pb2.FileDescriptorProto:
    """``Label`` (box, metadata speeds, type), ``Object`` and ``Objects`` of package
    ``waymo.open_dataset``, with waymo-open-dataset's field numbers."""
    F = descriptor_pb2.FieldDescriptorProto
    opt = F.LABEL_OPTIONAL

    def field(msg, name, number, ftype, type_name=None, label=opt, default=None):
        f = msg.field.add(name=name, number=number, type=ftype, label=label)
        if type_name:
            f.type_name = type_name
        if default is not None:
            f.default_value = default

    proto = descriptor_pb2.FileDescriptorProto(
        name="pcdet_atlas/waymo_submission.proto", package="waymo.open_dataset", syntax="proto2"
    )
    label = proto.message_type.add(name="Label")
    box = label.nested_type.add(name="Box")
    for name, number in _BOX_NUMBERS.items():
        field(box, name, number, F.TYPE_DOUBLE)
    meta = label.nested_type.add(name="Metadata")
    for name, number in (("speed_x", 1), ("speed_y", 2), ("accel_x", 3), ("accel_y", 4),
                         ("speed_z", 5), ("accel_z", 6)):  # fmt: skip
        field(meta, name, number, F.TYPE_DOUBLE)
    types = label.enum_type.add(name="Type")
    for number, name in enumerate(WAYMO_CLASSES):  # TYPE_UNKNOWN = 0, TYPE_VEHICLE = 1, ...
        types.value.add(name=f"TYPE_{name.upper()}", number=number)
    field(label, "box", 1, F.TYPE_MESSAGE, ".waymo.open_dataset.Label.Box")
    field(label, "metadata", 2, F.TYPE_MESSAGE, ".waymo.open_dataset.Label.Metadata")
    field(label, "type", _LABEL_TYPE_FIELD, F.TYPE_ENUM, ".waymo.open_dataset.Label.Type")
    field(label, "id", 4, F.TYPE_STRING)
    obj = proto.message_type.add(name="Object")
    field(obj, "object", 1, F.TYPE_MESSAGE, ".waymo.open_dataset.Label")
    field(obj, "score", 2, F.TYPE_FLOAT, default="1")
    field(obj, "overlap_with_nlz", 3, F.TYPE_BOOL)
    field(obj, "context_name", 4, F.TYPE_STRING)
    field(obj, "frame_timestamp_micros", 5, F.TYPE_INT64)
    objects = proto.message_type.add(name="Objects")
    field(objects, "objects", 1, F.TYPE_MESSAGE, ".waymo.open_dataset.Object",
          label=F.LABEL_REPEATED)  # fmt: skip
    return proto


_POOL = descriptor_pool.DescriptorPool()  # private: no clash with an installed waymo package
_POOL.Add(_schema())


def objects_message_class() -> type:
    """The ``waymo.open_dataset.Objects`` message class of the declared schema."""
    return message_factory.GetMessageClass(
        _POOL.FindMessageTypeByName("waymo.open_dataset.Objects")
    )


def _object_label(path: Path, k: int, obj) -> str:
    return (
        f"{path} [object {k} ({obj.context_name!r}, {obj.frame_timestamp_micros})]"
        if obj.HasField("context_name")
        else f"{path} [object {k}]"
    )


def _type_name(obj, where: str) -> str:
    label = obj.object
    if not label.HasField("type"):
        raw = [f.data for f in UnknownFieldSet(label) if f.field_number == _LABEL_TYPE_FIELD]
        value = f"type {raw[-1]}, not a Label.Type value" if raw else "no 'type'"
        known = ", ".join(f"{name}={i}" for i, name in enumerate(WAYMO_CLASSES))
        raise PredictionError(f"{where}: {value} (known: {known})")
    if label.type == 0:
        raise PredictionError(f"{where}: type TYPE_UNKNOWN (0) is no detection class")
    return WAYMO_CLASSES[label.type]


def read_waymo_bin(path: str | Path) -> list[dict]:
    """The frames of a submission ``.bin`` that have objects, in order of first appearance:
    per frame ``name`` ``(K,)``, ``score`` ``(K,)``, ``boxes_lidar`` ``(K, 7)`` (``(K, 9)``
    where every object of the frame has ``metadata.speed_x`` and ``speed_y``) and ``metadata``
    (``context_name``, ``timestamp_micros``).

    Raises:
        PredictionError: naming the file (and the object, its context and timestamp): not a
            serialized ``Objects``, no object at all, an object without ``context_name``,
            ``frame_timestamp_micros``, ``score`` or a box field, a type that is TYPE_UNKNOWN or
            no ``Label.Type``, or speeds on some objects of a frame only.
    """
    path = Path(path)
    message = objects_message_class()()
    try:
        message.ParseFromString(path.read_bytes())
    except DecodeError as err:
        raise PredictionError(
            f"{path}: not a serialized waymo.open_dataset.Objects protobuf ({err})"
        ) from None
    if not message.objects:
        raise PredictionError(f"{path}: holds no object (an Objects message with 'objects')")
    frames: dict[tuple[str, int], dict] = {}
    for k, obj in enumerate(message.objects):
        where = _object_label(path, k, obj)
        for field in ("context_name", "frame_timestamp_micros", "score"):
            if not obj.HasField(field):
                raise PredictionError(f"{where}: no field {field!r}")
        box = obj.object.box
        missing = [f for f in BOX_FIELDS if not box.HasField(f)]
        if missing:
            raise PredictionError(f"{where}: no field(s) {missing} in 'object.box'")
        name = _type_name(obj, where)
        speeds = obj.object.metadata
        has_speed = all(speeds.HasField(f) for f in _SPEED_FIELDS)
        key = (obj.context_name, int(obj.frame_timestamp_micros))
        frame = frames.setdefault(key, {"name": [], "score": [], "boxes_lidar": [],
                                        "speeds": has_speed, "first": k})  # fmt: skip
        if frame["speeds"] != has_speed:
            raise PredictionError(
                f"{where}: 'object.metadata' speed_x/speed_y on some objects of the frame only "
                f"(object {frame['first']} {'has' if frame['speeds'] else 'has not'} them)"
            )
        frame["name"].append(name)
        frame["score"].append(obj.score)
        row = [getattr(box, f) for f in BOX_FIELDS]
        frame["boxes_lidar"].append(row + [getattr(speeds, f) for f in _SPEED_FIELDS] * has_speed)
    return [
        {
            "name": np.array(f["name"]),
            "score": np.array(f["score"], dtype=np.float32),
            "boxes_lidar": np.array(f["boxes_lidar"], dtype=np.float64),
            "metadata": {"context_name": context, "timestamp_micros": stamp},
        }
        for (context, stamp), f in frames.items()
    ]


def write_waymo_bin(frames: Sequence[Mapping], path: str | Path) -> Path:
    """Write per-frame predictions (``name``, ``score``, ``boxes_lidar`` ``(K, 7)`` or
    ``(K, 9)`` and ``metadata`` with ``context_name`` and ``timestamp_micros``, as
    ``result.pkl`` holds them) as a submission ``.bin``; a frame without detections writes
    nothing.

    Raises:
        PredictionError: a frame without ``metadata`` context and timestamp, or a class name
            that is no Waymo type.
    """
    path = Path(path)
    message = objects_message_class()()
    for k, frame in enumerate(frames):
        meta = frame.get("metadata")
        if not isinstance(meta, Mapping) or not {"context_name", "timestamp_micros"} <= set(meta):
            raise PredictionError(
                f"frame {k}: no 'metadata' with 'context_name' and 'timestamp_micros' (the "
                "submission format finds frames by them)"
            )
        boxes = np.asarray(frame["boxes_lidar"], dtype=np.float64)
        for name, score, row in zip(frame["name"], frame["score"], boxes):
            if str(name) not in WAYMO_CLASSES[1:]:
                raise PredictionError(
                    f"frame {k}: class name {str(name)!r} is no Waymo type (known: "
                    f"{WAYMO_CLASSES[1:]})"
                )
            obj = message.objects.add(
                context_name=str(meta["context_name"]),
                frame_timestamp_micros=int(meta["timestamp_micros"]), score=float(score),
            )  # fmt: skip
            obj.object.type = WAYMO_CLASSES.index(str(name))
            for field, value in zip(BOX_FIELDS, row[:7]):
                setattr(obj.object.box, field, float(value))
            if len(row) == 9:
                obj.object.metadata.speed_x, obj.object.metadata.speed_y = map(float, row[7:])
    write_atomic(path, lambda f: f.write(message.SerializeToString()))
    return path
