"""Range-consistent intensity and elongation for replayed trace points (docs/attacks.md).

A trace point was recorded at range ``r_src`` from its sensor; replayed into a new scene it lies
at ``r_new``. Its raw intensity and elongation are corrected by power laws in the range ratio::

    intensity_new  = clip(intensity_src  * (r_src / r_new) ** intensity_exponent,  0, max)
    elongation_new = clip(elongation_src * (r_new / r_src) ** elongation_exponent, 0, max)

Defaults, and why (assumptions, configurable in the attack YAML under ``INTENSITY``):

* ``intensity_exponent = 2``: an extended diffuse (Lambertian) target returns power ~ 1 / r^2
  when the beam footprint is filled. Waymo's intensity is reported uncalibrated, so the true
  exponent of a given sensor is an assumption; set 0 to replay intensities unchanged.
* ``elongation_exponent = 1``: elongation measures pulse stretching, which grows with the beam
  footprint on a slanted surface, i.e. linearly with range.

Values are raw (as in OpenPCDet's ``.npy``); the dataset applies its own ``tanh`` afterwards,
exactly as it does to real points. Ranges are clamped to ``min_range`` to avoid blow-ups.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from pcdet_atlas.config_values import fields_of, read_section, setting

__all__ = ["IntensityConfig", "RangeIntensityModel"]


@dataclass(frozen=True, kw_only=True)
class IntensityConfig:
    """The ``INTENSITY`` section of an injection config."""

    intensity_exponent: float = setting(2.0, doc="exponent of `r_src / r_new` on intensity")
    elongation_exponent: float = setting(1.0, doc="exponent of `r_new / r_src` on elongation")
    min_range: float = setting(
        1.0, gt=0, expected="a positive range in metres", doc="ranges clamped below this, m"
    )
    max_intensity: float = setting(
        1.0e4, ge=0, expected="a non-negative upper clip (raw)", doc="upper clip (raw)"
    )
    max_elongation: float = setting(
        1.0e4, ge=0, expected="a non-negative upper clip (raw)", doc="upper clip (raw)"
    )


class RangeIntensityModel:
    """Power-law range correction of raw intensity and elongation.

    Args:
        intensity_exponent: exponent of ``r_src / r_new`` applied to intensity.
        elongation_exponent: exponent of ``r_new / r_src`` applied to elongation.
        min_range: ranges below this (m) are clamped before the ratio.
        max_intensity: upper clip of the corrected raw intensity.
        max_elongation: upper clip of the corrected raw elongation.
    """

    def __init__(
        self,
        intensity_exponent: float = IntensityConfig.intensity_exponent,
        elongation_exponent: float = IntensityConfig.elongation_exponent,
        min_range: float = IntensityConfig.min_range,
        max_intensity: float = IntensityConfig.max_intensity,
        max_elongation: float = IntensityConfig.max_elongation,
    ):
        if not min_range > 0:
            raise ValueError(f"min_range must be > 0, got {min_range}")
        if not (max_intensity >= 0 and max_elongation >= 0):
            raise ValueError(
                f"max_intensity and max_elongation must be >= 0, got {max_intensity}, "
                f"{max_elongation}"
            )
        self.intensity_exponent = float(intensity_exponent)
        self.elongation_exponent = float(elongation_exponent)
        self.min_range = float(min_range)
        self.max_intensity = float(max_intensity)
        self.max_elongation = float(max_elongation)

    @classmethod
    def from_config(cls, cfg: Mapping | None) -> RangeIntensityModel:
        """Build from an ``INTENSITY`` section (:class:`IntensityConfig`; every key optional)."""
        return cls(**fields_of(read_section(IntensityConfig, cfg, "INTENSITY")))

    def __call__(
        self,
        intensity: np.ndarray,
        elongation: np.ndarray,
        src_range: np.ndarray,
        new_range: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Corrected ``(K,)`` raw intensity and elongation (float32) for ``(K,)`` inputs (m)."""
        r_src = np.maximum(np.asarray(src_range, dtype=np.float64), self.min_range)
        r_new = np.maximum(np.asarray(new_range, dtype=np.float64), self.min_range)
        ratio = r_src / r_new
        inten = np.asarray(intensity, np.float64) * ratio**self.intensity_exponent
        elong = np.asarray(elongation, np.float64) * (1.0 / ratio) ** self.elongation_exponent
        return (
            np.clip(inten, 0.0, self.max_intensity).astype(np.float32),
            np.clip(elong, 0.0, self.max_elongation).astype(np.float32),
        )
