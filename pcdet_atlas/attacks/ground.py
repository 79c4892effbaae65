"""Local ground height under a phantom, from the frame's own scene points (docs/attacks.md).

The estimate is a robust low percentile (the 'lower' rule: an actual sample, no interpolation) of
the z of the scene points inside a small disc around the phantom centre: low, because cars, walls
and vegetation in the disc only add points above the ground; a percentile rather than the
minimum, because of range noise and stray low returns.

Fallback, documented and recorded: when the disc holds fewer than ``min_points`` points the disc
is widened once to ``fallback_radius``; when that also fails the ground is taken as
``fallback_z`` (default 0.0 m, the Waymo vehicle frame's origin lies on the ground under the ego),
i.e. the ground plane under the ego vehicle is assumed to extend to the phantom. The estimate's
``source`` says which; the injection attack counts its phantoms set on the fallback height in
the ``ground_fallbacks`` work counter of its process (:mod:`pcdet_atlas.attacks.counters`; the
frame's metadata does not record it).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from pcdet_atlas.config_values import fields_of, read_section, setting

__all__ = ["GROUND_SLACK_M", "GroundConfig", "GroundEstimator", "GroundEstimate"]

#: Widening of the discs' bounding squares, metres (a caller's ``rows`` must hold every point
#: within ``radius + GROUND_SLACK_M`` of the centre).
GROUND_SLACK_M = 1e-3


@dataclass(frozen=True)
class GroundEstimate:
    """``z`` (m, vehicle frame), how it was found (``'disc'``, ``'wide_disc'``, ``'fallback'``)
    and the number of scene points examined in the disc."""

    z: float
    source: str
    num_points: int


@dataclass(frozen=True, kw_only=True)
class GroundConfig:
    """The ``GROUND`` section of an injection config."""

    radius: float = setting(3.0, gt=0, doc="disc radius, m")
    percentile: float = setting(10.0, ge=0, le=100, doc="low percentile of z taken as ground")
    min_points: int = setting(10, ge=1, doc="fewest disc points to trust the estimate")
    fallback_radius: float = setting(8.0, doc="wider disc, m")
    fallback_z: float = setting(0.0, doc="last-resort ground height, m (vehicle frame)")
    max_abs_z: float = setting(
        5.0, gt=0, expected="a positive height in metres", doc="points with larger abs z ignored, m"
    )

    def __post_init__(self) -> None:
        if not self.fallback_radius >= self.radius:
            raise ValueError(
                f"need RADIUS <= FALLBACK_RADIUS, got {self.radius}, {self.fallback_radius}"
            )


class GroundEstimator:
    """Robust local ground height.

    Args:
        radius: disc radius around the phantom centre, metres.
        percentile: percentile of point z in the disc taken as the ground (0-100).
        min_points: fewest disc points for the estimate to be trusted.
        fallback_radius: wider disc tried when the first has too few points (m).
        fallback_z: ground height used when both discs are too sparse (m, vehicle frame).
        max_abs_z: points with |z| above this (m) are ignored (e.g. overhanging structure).
    """

    def __init__(
        self,
        radius: float = GroundConfig.radius,
        percentile: float = GroundConfig.percentile,
        min_points: int = GroundConfig.min_points,
        fallback_radius: float = GroundConfig.fallback_radius,
        fallback_z: float = GroundConfig.fallback_z,
        max_abs_z: float = GroundConfig.max_abs_z,
    ):
        if not radius > 0 or not fallback_radius >= radius:
            raise ValueError(f"need 0 < radius <= fallback_radius, got {radius}, {fallback_radius}")
        if not 0.0 <= percentile <= 100.0:
            raise ValueError(f"percentile must be in [0, 100], got {percentile}")
        if int(min_points) < 1:
            raise ValueError(f"min_points must be >= 1, got {min_points}")
        if not max_abs_z > 0:
            raise ValueError(f"max_abs_z must be > 0, got {max_abs_z}")
        self.radius = float(radius)
        self.percentile = float(percentile)
        self.min_points = int(min_points)
        self.fallback_radius = float(fallback_radius)
        self.fallback_z = float(fallback_z)
        self.max_abs_z = float(max_abs_z)

    @classmethod
    def from_config(cls, cfg: Mapping | None) -> GroundEstimator:
        """Build from a ``GROUND`` section (:class:`GroundConfig`; every key optional)."""
        return cls(**fields_of(read_section(GroundConfig, cfg, "GROUND")))

    def __call__(
        self,
        scene_xyz: np.ndarray,
        center_xy,
        rows: np.ndarray | None = None,
    ) -> GroundEstimate:
        """Ground height at ``center_xy`` (2,) from ``(N, 3+)`` scene points (vehicle frame).

        Args:
            rows: ascending indices of scene rows that hold every point within
                ``radius + 1 mm`` of the centre (e.g. the wedge of
                :func:`~pcdet_atlas.attacks.raycast.disc_wedges`); the first disc then looks at
                those rows only (the wide fallback disc scans every point). The estimate is the
                same as without them.
        """
        cx, cy = float(center_xy[0]), float(center_xy[1])
        xyz = np.asarray(scene_xyz)
        x, y = xyz[:, 0], xyz[:, 1]
        # cheap pre-filter on the disc's bounding square (widened by 1 mm, far above the float32
        # rounding of the bounds), then z and exact float64 distances on the survivors; the wide
        # disc's square is scanned only when the small disc is too sparse
        discs = ((self.radius, "disc", rows), (self.fallback_radius, "wide_disc", None))
        for radius, source, within in discs:
            px, py, pz = _disc_candidates(
                xyz, x, y, cx, cy, radius + GROUND_SLACK_M, self.max_abs_z, within
            )
            z = pz[(px - cx) ** 2 + (py - cy) ** 2 <= radius * radius]
            if z.size >= self.min_points:
                return GroundEstimate(_lower_percentile(z, self.percentile), source, int(z.size))
        return GroundEstimate(self.fallback_z, "fallback", int(pz.size))


def _disc_candidates(
    xyz: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    cx: float,
    cy: float,
    r: float,
    max_abs_z: float,
    rows: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``x``, ``y``, ``z`` (float64, ``(C,)`` each) of the points inside the square
    ``|x - cx|, |y - cy| <= r`` with ``|z| <= max_abs_z``, in ascending point order (1-D
    gathers from the columns; the values are those of ``xyz``); given ``rows``
    (ascending indices holding the whole disc), of those rows with ``|z| <= max_abs_z``, the
    square untested (the caller's disc test gives the same points either way)."""
    if rows is not None:  # a sector around the disc: few enough rows to skip the square
        z = xyz[:, 2][rows].astype(np.float64)
        ok = np.abs(z) <= max_abs_z
        sel = rows[ok]
        return x[sel].astype(np.float64), y[sel].astype(np.float64), z[ok]
    sel = ((x >= cx - r) & (x <= cx + r)).nonzero()[0]  # a slab: a few % of the scene
    ys = y[sel]
    sel = sel[(ys >= cy - r) & (ys <= cy + r)]
    z = xyz[:, 2][sel].astype(np.float64)
    ok = np.abs(z) <= max_abs_z
    sel = sel[ok]
    return x[sel].astype(np.float64), y[sel].astype(np.float64), z[ok]


def _lower_percentile(values: np.ndarray, percentile: float) -> float:
    """The ``percentile``-th percentile by the 'lower' rule (an actual sample, no interpolation):
    element ``floor(p / 100 * (n - 1))`` of the sorted values, found by partial sort of
    ``values`` in place (reordered)."""
    k = int(np.floor(percentile / 100.0 * (values.size - 1)))
    values.partition(k)  # in place: the caller's array is a fresh selection
    return float(values[k])
