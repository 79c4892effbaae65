"""Waymo's submission ``.bin`` (``waymo.open_dataset.Objects``): the declared schema reads bytes
encoded by hand with waymo-open-dataset's field numbers (metrics.proto ``Object``/``Objects``,
label.proto ``Label``/``Box``/``Metadata``), the writer round-trips, and bad input is one clear
error naming the file and the object."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import torch

from pcdet_atlas.datasets.waymo_submission import (
    PredictionError,
    read_waymo_bin,
    write_waymo_bin,
)


def varint(value: int) -> bytes:
    out = b""
    while True:
        byte, value = value & 0x7F, value >> 7
        out += bytes([byte | (0x80 if value else 0)])
        if not value:
            return out


def tag(number: int, wire_type: int) -> bytes:
    return varint(number << 3 | wire_type)


def length_field(number: int, payload: bytes) -> bytes:
    return tag(number, 2) + varint(len(payload)) + payload


def wire_object(context=b"ctx", stamp=1000, score=0.5, type_=1, box=(1, 2, 3, 4, 5, 6, 0.5),
                speeds=None, drop=()) -> bytes:  # fmt: skip
    """One ``Object`` encoded field by field (``drop``: field names left out)."""
    # Label.Box: center_x=1, center_y=2, center_z=3, width=4, length=5, height=6, heading=7
    x, y, z, length, width, height, heading = box
    numbered = {"center_x": (1, x), "center_y": (2, y), "center_z": (3, z), "width": (4, width),
                "length": (5, length), "height": (6, height), "heading": (7, heading)}  # fmt: skip
    box_bytes = b"".join(
        tag(n, 1) + struct.pack("<d", v) for f, (n, v) in numbered.items() if f not in drop
    )
    label = length_field(1, box_bytes)  # Label.box = 1
    if speeds is not None:  # Label.metadata = 2: speed_x = 1, speed_y = 2
        meta = tag(1, 1) + struct.pack("<d", speeds[0]) + tag(2, 1) + struct.pack("<d", speeds[1])
        label += length_field(2, meta)
    if "type" not in drop:
        label += tag(3, 0) + varint(type_)  # Label.type = 3
    obj = length_field(1, label)  # Object.object = 1
    if "score" not in drop:
        obj += tag(2, 5) + struct.pack("<f", score)  # Object.score = 2 (float)
    if "context_name" not in drop:
        obj += length_field(4, context)  # Object.context_name = 4
    if "frame_timestamp_micros" not in drop:
        obj += tag(5, 0) + varint(stamp)  # Object.frame_timestamp_micros = 5
    obj += tag(6, 0) + varint(1)  # camera_name = 6: not in the declared schema, ignored
    return length_field(1, obj)  # Objects.objects = 1


def test_reads_bytes_encoded_with_waymos_field_numbers(tmp_path):
    path = tmp_path / "sub.bin"
    path.write_bytes(
        wire_object(type_=1, box=(1, 2, 3, 4, 5, 6, 0.5))
        + wire_object(type_=4, score=0.25, box=(7, 8, 9, 1, 2, 3, -1))
        + wire_object(stamp=2000, type_=2, speeds=(1.5, -2.0))
    )
    frames = read_waymo_bin(path)
    assert [f["metadata"] for f in frames] == [
        {"context_name": "ctx", "timestamp_micros": 1000},
        {"context_name": "ctx", "timestamp_micros": 2000},
    ]
    assert frames[0]["name"].tolist() == ["Vehicle", "Cyclist"]
    assert frames[0]["score"].tolist() == [0.5, 0.25]
    # boxes_lidar columns: x, y, z, dx = length, dy = width, dz = height, heading
    assert frames[0]["boxes_lidar"].tolist() == [[1, 2, 3, 4, 5, 6, 0.5], [7, 8, 9, 1, 2, 3, -1]]
    assert frames[1]["name"].tolist() == ["Pedestrian"]
    assert frames[1]["boxes_lidar"].tolist() == [[1, 2, 3, 4, 5, 6, 0.5, 1.5, -2.0]]


def test_writer_round_trips_float32_predictions_exactly(tmp_path):
    gen = torch.Generator().manual_seed(3)
    frames = [
        {"name": np.array(["Vehicle", "Pedestrian", "Cyclist"]),
         "score": torch.rand(3, generator=gen).numpy(),
         "boxes_lidar": torch.randn(3, 7, generator=gen).numpy(),
         "metadata": {"context_name": "seq_a", "timestamp_micros": 10}},
        {"name": np.array([]), "score": np.zeros(0, np.float32), "boxes_lidar": np.zeros((0, 7)),
         "metadata": {"context_name": "seq_a", "timestamp_micros": 20}},
        {"name": np.array(["Sign"]), "score": np.array([1.0], np.float32),
         "boxes_lidar": torch.randn(1, 9, generator=gen).numpy(),
         "metadata": {"context_name": "seq_b", "timestamp_micros": 30}},
    ]  # fmt: skip
    back = read_waymo_bin(write_waymo_bin(frames, tmp_path / "sub.bin"))
    assert len(back) == 2  # a frame without detections has no object
    for want, got in zip([frames[0], frames[2]], back):
        assert got["metadata"] == want["metadata"]
        assert got["name"].tolist() == want["name"].tolist()
        np.testing.assert_array_equal(got["score"], want["score"])
        np.testing.assert_array_equal(got["boxes_lidar"].astype(np.float32), want["boxes_lidar"])


@pytest.mark.parametrize(
    "payload, pattern",
    [
        (b"", r"sub\.bin: holds no object"),
        (b"\x0a\xff\xff\xff", r"sub\.bin: not a serialized waymo\.open_dataset\.Objects"),
        (wire_object(type_=7), r"\[object 0 \('ctx', 1000\)\]: type 7, not a Label\.Type value"),
        (wire_object(type_=0), r"\[object 0 \('ctx', 1000\)\]: type TYPE_UNKNOWN \(0\)"),
        (wire_object(drop=("type",)), r"\[object 0 \('ctx', 1000\)\]: no 'type'"),
        (wire_object() + wire_object(drop=("score",)), r"\[object 1 .*\]: no field 'score'"),
        (wire_object(drop=("context_name",)), r"sub\.bin \[object 0\]: no field 'context_name'"),
        (wire_object(drop=("frame_timestamp_micros",)), r"no field 'frame_timestamp_micros'"),
        (wire_object(drop=("heading", "width")), r"no field\(s\) \['width', 'heading'\] in "
         r"'object\.box'"),
        (wire_object() + wire_object(speeds=(1, 2)), r"\[object 1 .*\]: 'object\.metadata' "
         r"speed_x/speed_y on some objects of the frame only"),
    ],
)  # fmt: skip
def test_bad_submissions_are_clear_errors(tmp_path, payload, pattern):
    path = tmp_path / "sub.bin"
    path.write_bytes(payload)
    with pytest.raises(PredictionError, match=pattern):
        read_waymo_bin(path)


def test_writer_refuses_what_the_format_cannot_hold(tmp_path):
    frame = {"name": np.array(["Truck"]), "score": np.array([0.5]), "boxes_lidar": np.zeros((1, 7)),
             "metadata": {"context_name": "c", "timestamp_micros": 1}}  # fmt: skip
    with pytest.raises(PredictionError, match=r"frame 0: class name 'Truck' is no Waymo type"):
        write_waymo_bin([frame], tmp_path / "sub.bin")
    with pytest.raises(PredictionError, match=r"frame 0: no 'metadata' with 'context_name'"):
        write_waymo_bin([{**frame, "metadata": "seq_000"}], tmp_path / "sub.bin")
