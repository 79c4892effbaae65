"""Box coding of two-stage heads (MSF, PTT): OpenPCDet's ``ResidualCoder`` and the canonical ROI
frame its ROI heads regress in.

A refinement target is the ground-truth box seen from its proposal (ROI): centre relative to the
ROI centre and rotated by ``-roi_heading``, heading relative to the ROI's and flipped by pi into
``[-pi/2, pi/2]`` (a box and its 180-degree turn are the same box), then residual-coded against
the ROI with centre 0 and heading 0. Decoding reverses it. Boxes follow docs/conventions.md.
"""

from __future__ import annotations

import math

import torch

from pcdet_atlas.utils.common import limit_period

__all__ = ["ResidualCoder", "decode_roi_boxes", "encode_roi_targets", "rotate_xy"]

#: Smallest box size the coder divides by, m.
MIN_SIZE_M = 1e-5


class ResidualCoder:
    """OpenPCDet's residual box coder of ``(N, 7 + C)`` boxes against anchors of the same shape:
    ``(x, y)`` offsets over the anchor's BEV diagonal, ``z`` over its height, log size ratios,
    the heading difference, and plain differences of the ``C`` extra columns (velocity)."""

    def __init__(self, code_size: int = 7):
        if code_size < 7:
            raise ValueError(f"ResidualCoder: code_size must be >= 7, got {code_size}")
        self.code_size = int(code_size)

    def encode(self, boxes: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
        """``(N, code_size)`` codes of ``boxes`` against ``anchors`` (both ``(N, code_size)``)."""
        self._check(boxes, "boxes")
        self._check(anchors, "anchors")
        a_size = anchors[:, 3:6].clamp_min(MIN_SIZE_M)
        b_size = boxes[:, 3:6].clamp_min(MIN_SIZE_M)
        diagonal = torch.sqrt(a_size[:, 0] ** 2 + a_size[:, 1] ** 2)
        xy = (boxes[:, 0:2] - anchors[:, 0:2]) / diagonal[:, None]
        z = (boxes[:, 2:3] - anchors[:, 2:3]) / a_size[:, 2:3]
        size = torch.log(b_size / a_size)
        rest = boxes[:, 6:] - anchors[:, 6:]  # heading, then the extra columns
        return torch.cat([xy, z, size, rest], dim=1)

    def decode(self, codes: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
        """The boxes ``(N, code_size)`` whose :meth:`encode` against ``anchors`` is ``codes``."""
        self._check(codes, "codes")
        self._check(anchors, "anchors")
        a_size = anchors[:, 3:6].clamp_min(MIN_SIZE_M)
        diagonal = torch.sqrt(a_size[:, 0] ** 2 + a_size[:, 1] ** 2)
        xy = codes[:, 0:2] * diagonal[:, None] + anchors[:, 0:2]
        z = codes[:, 2:3] * a_size[:, 2:3] + anchors[:, 2:3]
        size = torch.exp(codes[:, 3:6]) * a_size
        rest = codes[:, 6:] + anchors[:, 6:]
        return torch.cat([xy, z, size, rest], dim=1)

    def _check(self, t: torch.Tensor, name: str) -> None:
        if t.dim() != 2 or t.shape[1] != self.code_size:
            raise ValueError(
                f"ResidualCoder: {name} must be (N, {self.code_size}), got {tuple(t.shape)}"
            )


def rotate_xy(xy: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """``(N, 2)`` points rotated counter-clockwise by ``(N,)`` angles (radians)."""
    cos, sin = torch.cos(angle), torch.sin(angle)
    return torch.stack([xy[:, 0] * cos - xy[:, 1] * sin, xy[:, 0] * sin + xy[:, 1] * cos], dim=1)


def encode_roi_targets(
    gt_boxes: torch.Tensor, rois: torch.Tensor, coder: ResidualCoder
) -> torch.Tensor:
    """Refinement targets ``(N, code_size)`` of ``gt_boxes`` for their ``rois`` (both
    ``(N, code_size)``, row-aligned) in the canonical ROI frame (module docstring).

    Extra columns (velocity) are rotated with the centre when there are exactly two of them.
    """
    roi_heading = rois[:, 6]
    local = gt_boxes.clone()
    local[:, 0:3] = gt_boxes[:, 0:3] - rois[:, 0:3]
    local[:, 0:2] = rotate_xy(local[:, 0:2], -roi_heading)
    if coder.code_size == 9:
        local[:, 7:9] = rotate_xy(gt_boxes[:, 7:9], -roi_heading)
    heading = torch.remainder(gt_boxes[:, 6] - roi_heading, 2 * math.pi)  # [0, 2 pi)
    opposite = (heading > math.pi / 2) & (heading < math.pi * 1.5)
    heading = torch.where(opposite, torch.remainder(heading + math.pi, 2 * math.pi), heading)
    heading = torch.where(heading > math.pi, heading - 2 * math.pi, heading)
    local[:, 6] = heading.clamp(-math.pi / 2, math.pi / 2)
    anchors = rois.clone()
    anchors[:, 0:3] = 0
    anchors[:, 6] = 0
    if coder.code_size == 9:
        anchors[:, 7:9] = 0
    return coder.encode(local, anchors)


def decode_roi_boxes(codes: torch.Tensor, rois: torch.Tensor, coder: ResidualCoder) -> torch.Tensor:
    """Boxes ``(N, code_size)`` in the vehicle frame from refinement ``codes`` of ``rois``
    (the inverse of :func:`encode_roi_targets` up to the heading's pi flip); the heading is
    wrapped into ``[-pi, pi)``."""
    roi_heading = rois[:, 6]
    anchors = rois.clone()
    anchors[:, 0:3] = 0
    if coder.code_size == 9:
        anchors[:, 7:9] = 0
    boxes = coder.decode(codes, anchors)  # heading: relative code + the ROI's heading
    boxes[:, 0:2] = rotate_xy(boxes[:, 0:2], roi_heading)
    boxes[:, 0:3] = boxes[:, 0:3] + rois[:, 0:3]
    if coder.code_size == 9:
        boxes[:, 7:9] = rotate_xy(boxes[:, 7:9], roi_heading)
    boxes[:, 6] = limit_period(boxes[:, 6])
    return boxes
