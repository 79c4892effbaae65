"""The config sections the centre-based dense heads share (CenterHead, CenterFormerHead),
declared once (:mod:`pcdet_atlas.config_values`); OpenPCDet's key names, lower-case where
OpenPCDet writes them so."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from pcdet_atlas.config import ConfigError
from pcdet_atlas.config_values import read_section, section, setting

__all__ = [
    "HeadBranchConfig",
    "SeparateHeadConfig",
    "CenterTargetConfig",
    "LossWeightsConfig",
    "LossConfig",
    "check_one_head",
    "branch_num_convs",
]


@dataclass(frozen=True, kw_only=True)
class HeadBranchConfig:
    """One entry of ``SEPARATE_HEAD_CFG.HEAD_DICT``."""

    out_channels: int | None = setting(None, key="out_channels", doc="the branch's channels")
    num_conv: int = setting(2, key="num_conv", ge=1, doc="convs of the branch")


@dataclass(frozen=True, kw_only=True)
class SeparateHeadConfig:
    """``SEPARATE_HEAD_CFG``: the box code's branches and their convs."""

    head_order: tuple[str, ...] = setting(
        ("center", "center_z", "dim", "rot"), doc="branches of the box code, in order"
    )
    head_dict: dict[str, Mapping] = setting(
        default_factory=dict,
        check=lambda d: all(isinstance(v, Mapping) for v in d.values()),
        expected="{branch: {out_channels: n, num_conv: n}}",
        doc="per branch: out_channels, num_conv",
    )


@dataclass(frozen=True, kw_only=True)
class CenterTargetConfig:
    """``TARGET_ASSIGNER_CONFIG``: heatmap targets."""

    feature_map_stride: int = setting(1, ge=1, doc="voxels per head cell along x and y")
    num_max_objs: int = setting(500, ge=1, doc="boxes per sample in the targets")
    gaussian_overlap: float = setting(0.1, gt=0, lt=1, doc="overlap of the Gaussian radius")
    min_radius: int = setting(2, ge=0, doc="smallest Gaussian radius, cells")


@dataclass(frozen=True, kw_only=True)
class LossWeightsConfig:
    """``LOSS_CONFIG.LOSS_WEIGHTS``."""

    cls_weight: float = setting(1.0, key="cls_weight", ge=0, doc="heatmap loss weight")
    loc_weight: float = setting(2.0, key="loc_weight", ge=0, doc="box regression loss weight")
    code_weights: tuple[float, ...] | None = setting(
        None, key="code_weights", ge=0, doc="L1 weight per regression channel"
    )


@dataclass(frozen=True, kw_only=True)
class LossConfig:
    """``LOSS_CONFIG``."""

    loss_weights: LossWeightsConfig = section(LossWeightsConfig)


def check_one_head(groups, class_names, section_name: str = "MODEL.DENSE_HEAD") -> None:
    """``CLASS_NAMES_EACH_HEAD`` must be one head over all ``CLASS_NAMES``."""
    if groups is not None and [list(g) for g in groups] != [list(class_names)]:
        raise ConfigError(
            f"{section_name}.CLASS_NAMES_EACH_HEAD: only one head over all CLASS_NAMES "
            f"{list(class_names)} is supported, got {[list(g) for g in groups]}"
        )


def branch_num_convs(
    separate: SeparateHeadConfig, names: list[str], channels: Mapping[str, int], prefix: str
) -> dict[str, int]:
    """``{branch: num_conv}`` of ``names`` from ``HEAD_DICT`` (each entry read as a
    :class:`HeadBranchConfig`; ``out_channels`` must be the branch's)."""
    out = {}
    for name in names:
        entry = read_section(
            HeadBranchConfig, separate.head_dict.get(name), f"{prefix}.HEAD_DICT.{name}"
        )
        if entry.out_channels not in (None, channels[name]):
            raise ConfigError(
                f"{prefix}.HEAD_DICT.{name}.out_channels = {entry.out_channels}: expected "
                f"{channels[name]}"
            )
        out[name] = entry.num_conv
    return out
