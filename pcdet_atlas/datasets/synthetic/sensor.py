"""Return model of the synthetic LiDAR: which rays return, range noise, intensity, elongation.

Given the exact first hit of every ray (:func:`.raycast.raycast_scan`) and the albedo and
surface class of what was hit, :meth:`SensorModel.returns` decides per ray:

- **dropped returns**: a base rate, extra for glass (windows) and foliage, and a weak-return
  model: received power ``~ albedo * cos(incidence) / range^2``; the detection probability is
  ``1 - exp(-P / P0)``, so dark, grazing, far surfaces (far ground, black cars at 60 m) thin out;
- **range noise**: Gaussian, ``std = a + b * range`` (+ extra on foliage), along the ray, so
  every point stays on its beam's elevation;
- **intensity** (raw, before the loader's ``tanh``): ``albedo * (0.3 + 0.7 cos) * g(range)``
  with multiplicative speckle; retro-reflective surfaces (signs, lane paint) return far more;
- **elongation** (raw): pulse stretching, growing with incidence angle and range, larger on
  foliage and glass (several surfaces inside the footprint).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch

from pcdet_atlas.config_values import read_section, setting
from pcdet_atlas.datasets.synthetic.actors import (
    SURFACE_FOLIAGE,
    SURFACE_GLASS,
    SURFACE_RETRO,
)

__all__ = ["SensorModel"]


@dataclass(frozen=True, kw_only=True)
class SensorModel:
    """Noise and radiometry constants (documented defaults, tuned to look like Waymo TOP); also
    the declaration of a config section of them (:meth:`from_config`)."""

    range_std_m: float = setting(0.015, ge=0, doc="range noise std at 0 m, m")
    range_std_per_m: float = setting(0.0003, ge=0, doc="range noise std growth, m per m")
    drop_prob: float = setting(0.02, ge=0, le=1, doc="base share of dropped returns")
    glass_drop_prob: float = setting(0.5, ge=0, le=1, doc="dropped returns on glass")
    foliage_drop_prob: float = setting(0.3, ge=0, le=1, doc="dropped returns on foliage")
    foliage_range_std_m: float = setting(0.08, ge=0, doc="extra range noise on foliage, m")
    weak_return_power: float = setting(
        8.0e-5, gt=0, doc="P0 of the detection model, albedo * cos * (10 m / r)^2"
    )
    retro_intensity: float = setting(6.0, ge=0, doc="intensity gain of retro-reflectors")

    @classmethod
    def from_config(cls, cfg: Mapping | None, section: str = "SENSOR") -> SensorModel:
        """The sensor of a config section (``RANGE_STD_M``, ...; absent keys at the defaults).

        Raises:
            ConfigError: naming the file, the key, the value and what was expected.
        """
        return read_section(cls, cfg, section)

    def to_dict(self) -> dict:
        return {f: getattr(self, f) for f in self.__dataclass_fields__}

    def returns(
        self,
        range_m: torch.Tensor,
        cos_incidence: torch.Tensor,
        albedo: torch.Tensor,
        surface: torch.Tensor,
        max_range: float,
        rng: np.random.Generator,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Noisy returns of ``R`` rays.

        Args:
            range_m: ``(R,)`` exact first-hit range (``inf`` = no hit), m.
            cos_incidence: ``(R,)`` |cos| of the angle between ray and surface normal.
            albedo: ``(R,)`` diffuse reflectivity of the hit surface.
            surface: ``(R,)`` long surface class (see :mod:`.actors`).
            max_range: returns are clipped to this range, m.
            rng: numpy generator for this frame (draws are made on the CPU, so results do not
                depend on the device).
        Returns:
            ``valid`` ``(R,)`` bool, ``range`` ``(R,)`` noisy range, ``intensity`` ``(R,)`` and
            ``elongation`` ``(R,)`` raw values (all on ``range_m``'s device).
        """
        device, dtype = range_m.device, range_m.dtype
        num = range_m.shape[0]

        def draw(kind):
            if kind == "u":
                arr = rng.random(num, dtype=np.float32)
            else:
                arr = rng.standard_normal(num, dtype=np.float32)
            return torch.from_numpy(arr).to(device, dtype)

        u_drop, n_range, n_int, n_elong = draw("u"), draw("n"), draw("n"), draw("n")
        hit = torch.isfinite(range_m)
        r = torch.where(hit, range_m, torch.zeros_like(range_m))
        cos = cos_incidence.clamp(0.0, 1.0)
        glass = surface == SURFACE_GLASS
        foliage, retro = surface == SURFACE_FOLIAGE, surface == SURFACE_RETRO

        power = albedo * cos.clamp(min=0.02) * (10.0 / r.clamp(min=1.0)) ** 2
        power = torch.where(retro, power * 50.0, power)
        p_detect = 1.0 - torch.exp(-power / self.weak_return_power)
        p_drop = 1.0 - (1.0 - self.drop_prob) * p_detect
        p_drop = torch.where(glass, 1.0 - (1.0 - p_drop) * (1.0 - self.glass_drop_prob), p_drop)
        p_drop = torch.where(foliage, 1.0 - (1.0 - p_drop) * (1.0 - self.foliage_drop_prob), p_drop)
        valid = hit & (u_drop >= p_drop)

        std = self.range_std_m + self.range_std_per_m * r
        std = torch.where(foliage, std + self.foliage_range_std_m, std)
        noisy = (r + std * n_range).clamp(min=0.5, max=max_range - 1e-3)

        gain = 0.6 + 0.8 * torch.exp(-r / 20.0)
        intensity = albedo * (0.3 + 0.7 * cos) * gain * torch.exp(0.15 * n_int)
        intensity = torch.where(
            retro, self.retro_intensity * (0.5 + cos) * torch.exp(0.2 * n_int), intensity
        )
        grazing = (1.0 - cos) ** 2
        elong = 0.02 + 0.25 * grazing + 0.002 * r + 0.02 * n_elong.abs()
        elong = torch.where(foliage, elong + 0.3, elong)
        elong = torch.where(glass, elong + 0.08, elong)
        return valid, noisy, intensity.clamp(min=0.0), elong.clamp(min=0.0)
