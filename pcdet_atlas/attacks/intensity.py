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

import numpy as np

from pcdet_atlas.config import ConfigError, check_known_keys
from pcdet_atlas.config_values import config_files, config_value

__all__ = ["RangeIntensityModel"]


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
        intensity_exponent: float = 2.0,
        elongation_exponent: float = 1.0,
        min_range: float = 1.0,
        max_intensity: float = 1.0e4,
        max_elongation: float = 1.0e4,
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
        """Keys (all optional): ``INTENSITY_EXPONENT``, ``ELONGATION_EXPONENT``, ``MIN_RANGE``,
        ``MAX_INTENSITY``, ``MAX_ELONGATION``."""
        cfg = cfg or {}
        keys = {
            "INTENSITY_EXPONENT": "intensity_exponent",
            "ELONGATION_EXPONENT": "elongation_exponent",
            "MIN_RANGE": "min_range",
            "MAX_INTENSITY": "max_intensity",
            "MAX_ELONGATION": "max_elongation",
        }
        check_known_keys(cfg, keys, "INTENSITY")
        clip = {"valid": lambda v: v >= 0, "expected": "a non-negative upper clip (raw)"}
        checks = {
            "MIN_RANGE": {"valid": lambda r: r > 0, "expected": "a positive range in metres"},
            "MAX_INTENSITY": clip,
            "MAX_ELONGATION": clip,
        }
        kwargs = {name: config_value(cfg, key, float, "INTENSITY", **checks.get(key, {}))
                  for key, name in keys.items() if key in cfg}  # fmt: skip
        try:
            return cls(**kwargs)
        except ValueError as err:
            raise ConfigError(f"INTENSITY ({config_files(cfg)}): {err}") from err

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
