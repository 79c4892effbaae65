"""Dynamic pillar feature encoder (OpenPCDet's ``DynamicPillarVFE``) in plain torch.

The model pillarizes the raw points itself (:func:`voxelize`), decorates every point with its
offset from the pillar's mean and from the pillar's geometric centre, and runs PointNet layers
whose per-pillar max is taken with ``scatter_reduce``. No points are dropped inside the range.
As in OpenPCDet, the range bounds x and y only: a point below or above the z range falls in the
pillar under it; ``DROP_OUTSIDE_Z: True`` drops such points instead (the shipped synthetic
pillar checkpoints were trained so; docs/model_zoo.md).

In eval mode the PFN layers run in an equivalent, cheaper form
(:meth:`DynamicPillarVFE._pfn_eval`): BatchNorm folded into the linear layers, a layer's input
``[h, max[idx]]`` split into its per-point and per-pillar parts (the pillar part is multiplied
once per pillar, not once per point), and the last layer's ReLU and pillar term applied after
the max (``max_i relu(a_i + g) = relu(max_i a_i + g)`` for a per-pillar ``g``). Same function,
other float32 rounding; ``fold_eval = False`` runs the layers one by one instead.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import nn

from pcdet_atlas.config import ConfigError
from pcdet_atlas.config_values import setting
from pcdet_atlas.models.model_utils.scatter import scatter_max, scatter_mean
from pcdet_atlas.models.model_utils.voxelize import (
    VoxelGrid,
    check_point_columns,
    check_voxel_size_placeholder,
    voxelize,
)
from pcdet_atlas.models.stage_config import StageConfig, read_stage
from pcdet_atlas.registry import MODEL_STAGES


class PFNLayer(nn.Module):
    """Linear -> BN -> ReLU per point, then max per pillar (concatenated back unless last)."""

    def __init__(self, in_channels: int, out_channels: int, use_norm: bool, last_layer: bool):
        super().__init__()
        self.last_layer = last_layer
        width = out_channels if last_layer else out_channels // 2
        self.linear = nn.Linear(in_channels, width, bias=not use_norm)
        self.norm = nn.BatchNorm1d(width, eps=1e-3, momentum=0.01) if use_norm else nn.Identity()

    def forward(self, x: torch.Tensor, pillar_idx: torch.Tensor, num_pillars: int) -> torch.Tensor:
        """x: (N, in) point features; pillar_idx: (N,) -> (N, out) or, if last, (P, out)."""
        x = torch.relu(self.norm(self.linear(x)))  # (N, width)
        x_max = scatter_max(x, pillar_idx, num_pillars)  # (P, width)
        if self.last_layer:
            return x_max
        return torch.cat([x, x_max.index_select(0, pillar_idx)], dim=1)

    def folded(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(W, b)`` with ``norm(linear(x)) == x @ W.T + b`` in eval mode (BN's running
        statistics folded into the weights), ``(width, in)`` and ``(width,)``."""
        weight = self.linear.weight
        bias = self.linear.bias if self.linear.bias is not None else weight.new_zeros(len(weight))
        if isinstance(self.norm, nn.BatchNorm1d):
            scale = self.norm.weight * torch.rsqrt(self.norm.running_var + self.norm.eps)
            return weight * scale[:, None], (bias - self.norm.running_mean) * scale + self.norm.bias
        return weight, bias


@dataclass(frozen=True, kw_only=True)
class PointNetVFEConfig(StageConfig):
    """``MODEL.VFE`` keys of the PointNet VFEs (OpenPCDet's, its spelling of ABSLOTE included)."""

    voxel_size: tuple[float, float, float] | None = setting(
        None, gt=0, doc="voxel size, m (else the DATA_PROCESSOR placeholder's)"
    )
    num_filters: tuple[int, ...] = setting((64, 64), ge=1, doc="widths of the PFN layers")
    use_norm: bool = setting(True, doc="BatchNorm in the PFN layers")
    with_distance: bool = setting(False, doc="add the point's range as a feature")
    use_absolute_xyz: bool = setting(True, key="USE_ABSLOTE_XYZ", doc="keep absolute x, y, z")


@dataclass(frozen=True, kw_only=True)
class DynamicPillarVFEConfig(PointNetVFEConfig):
    """``MODEL.VFE`` of DynamicPillarVFE."""

    drop_outside_z: bool = setting(False, doc="drop points outside the z range")


def voxel_size_of(settings, cfg: Mapping, model_info: Mapping) -> tuple[float, float, float]:
    """``MODEL.VFE.VOXEL_SIZE``, else the DATA_PROCESSOR placeholder's; both given: equal."""
    voxel_size = settings.voxel_size
    if voxel_size is None:
        voxel_size = model_info.get("voxel_size")
    if voxel_size is None:
        raise ConfigError(
            "MODEL.VFE needs VOXEL_SIZE, or DATA_CONFIG.DATA_PROCESSOR a "
            "transform_points_to_voxels_placeholder stating it (as OpenPCDet's configs do)"
        )
    check_voxel_size_placeholder(cfg, voxel_size, model_info)
    return voxel_size


@MODEL_STAGES.register("DynPillarVFE")  # OpenPCDet's name of this stage
@MODEL_STAGES.register()
class DynamicPillarVFE(nn.Module):
    """Points -> one feature vector per non-empty pillar.

    Reads ``batch_dict['points']`` (N, 1 + C) and writes ``pillar_features`` (P, F) and
    ``voxel_coords`` (P, 4) ``[batch, 0, y, x]``.
    """

    #: the grid has one z cell (a subclass on 3D voxels sets False)
    pillar_grid = True

    CONFIG = DynamicPillarVFEConfig

    def __init__(
        self,
        *,
        num_point_features: int,
        point_cloud_range: Sequence[float],
        voxel_size: Sequence[float],
        num_filters: Sequence[int] = (64, 64),
        use_norm: bool = True,
        with_distance: bool = False,
        use_absolute_xyz: bool = True,
        drop_outside_z: bool = False,
    ):
        """
        Args:
            num_point_features: C, point columns after the batch index (x, y, z first).
            point_cloud_range: (6,) metres. voxel_size: (3,) metres; the z size must span the
                whole z range (pillars).
            num_filters: output widths of the PFN layers.
            with_distance: add the point's xyz norm as a feature.
            use_absolute_xyz: keep x, y, z themselves as features (else only the offsets).
            drop_outside_z: drop the points below or above the z range (OpenPCDet keeps them).
        """
        super().__init__()
        self.grid = VoxelGrid(tuple(map(float, point_cloud_range)), tuple(map(float, voxel_size)))
        if self.pillar_grid and self.grid.grid_size[2] != 1:
            raise ValueError(
                f"DynamicPillarVFE: VOXEL_SIZE z ({voxel_size[2]}) must equal the z extent of "
                f"POINT_CLOUD_RANGE ({point_cloud_range[5] - point_cloud_range[2]}) for pillars"
            )
        if num_point_features < 3:
            raise ValueError(f"num_point_features must be >= 3, got {num_point_features}")
        if not num_filters:
            raise ValueError("DynamicPillarVFE: NUM_FILTERS must not be empty")
        self.num_point_features = num_point_features
        self.with_distance = with_distance
        self.use_absolute_xyz = use_absolute_xyz
        self.drop_outside_z = bool(drop_outside_z)
        in_ch = num_point_features + 6 - (0 if use_absolute_xyz else 3) + int(with_distance)
        widths = [in_ch, *num_filters]
        self.pfn_layers = nn.ModuleList(
            PFNLayer(widths[i], widths[i + 1], use_norm, last_layer=i == len(widths) - 2)
            for i in range(len(widths) - 1)
        )
        self.num_output_features = widths[-1]
        #: eval mode runs the equivalent folded form (:meth:`_pfn_eval`); False: layer by layer
        self.fold_eval = True

    @classmethod
    def from_config(cls, cfg: Mapping, model_info: Mapping) -> DynamicPillarVFE:
        settings = read_stage(cls, cfg, "MODEL.VFE")
        return cls(
            num_point_features=model_info["num_point_features"],
            point_cloud_range=model_info["point_cloud_range"],
            voxel_size=voxel_size_of(settings, cfg, model_info),
            num_filters=settings.num_filters,
            use_norm=settings.use_norm,
            with_distance=settings.with_distance,
            use_absolute_xyz=settings.use_absolute_xyz,
            # a declaration without DROP_OUTSIDE_Z (a voxel grid's) always drops outside z
            drop_outside_z=getattr(settings, "drop_outside_z", True),
        )

    def get_output_feature_dim(self) -> int:
        return self.num_output_features

    def forward(self, batch_dict: dict) -> dict:
        points = batch_dict["points"]  # (N, 1 + C)
        check_point_columns(points, self.num_point_features, type(self).__name__)
        vox = voxelize(points, self.grid, bound_z=self.drop_outside_z)
        pts = points[vox.point_mask, 1:].float()  # (N_in, C)
        idx = vox.point_voxel_idx
        num_pillars = vox.voxel_coords.shape[0]
        xyz = pts[:, :3]
        pillar_mean = scatter_mean(xyz, idx, num_pillars, vox.voxel_num_points)  # (P, 3)
        vs, pcr = self.grid.voxel_size, self.grid.point_cloud_range
        coords = vox.voxel_coords  # (P, 4) b, z, y, x
        centre = torch.stack(
            [
                coords[:, 3].to(xyz.dtype) * vs[0] + (vs[0] / 2 + pcr[0]),
                coords[:, 2].to(xyz.dtype) * vs[1] + (vs[1] / 2 + pcr[1]),
                coords[:, 1].to(xyz.dtype) * vs[2] + (vs[2] / 2 + pcr[2]),
            ],
            dim=1,
        )  # (P, 3) pillar centres
        # one gather of both per-pillar references to the points
        ref = torch.cat([pillar_mean, centre], dim=1).index_select(0, idx)  # (N_in, 6)
        f_cluster = xyz - ref[:, :3]
        f_center = xyz - ref[:, 3:]
        feats = [pts if self.use_absolute_xyz else pts[:, 3:], f_cluster, f_center]
        if self.with_distance:
            feats.append(torch.linalg.norm(xyz, dim=1, keepdim=True))
        x = torch.cat(feats, dim=1)  # (N_in, in_ch)
        if self.training or not (self.fold_eval and self._foldable):
            for layer in self.pfn_layers:
                x = layer(x, idx, num_pillars)
        else:
            x = self._pfn_eval(x, idx, num_pillars)
        batch_dict["pillar_features"] = x  # (P, F)
        batch_dict["voxel_coords"] = vox.voxel_coords  # (P, 4)
        return batch_dict

    @property
    def _foldable(self) -> bool:
        """BN with running statistics (or no norm) in every layer: the eval form applies."""
        return all(
            isinstance(layer.norm, nn.Identity)
            or (isinstance(layer.norm, nn.BatchNorm1d) and layer.norm.track_running_stats)
            for layer in self.pfn_layers
        )

    def _pfn_eval(self, x: torch.Tensor, idx: torch.Tensor, num_pillars: int) -> torch.Tensor:
        """The PFN layers in eval mode, ``(N, in) -> (P, F)``, without the per-point concat.

        A non-last layer's output ``[h, m[idx]]`` (``m``: per-pillar max of ``h``) enters the
        next linear as ``h @ Wa.T + (m @ Wb.T)[idx]``; the last layer's
        ``max_i relu(a_i + g)`` over a pillar (``g`` per pillar) is ``relu(max_i a_i + g)``.
        """
        *hidden, last = self.pfn_layers
        point, pillar = x, None  # per-point input; per-pillar input (the max part) or None
        for layer in hidden:
            z, g = _split_linear(layer, point, pillar)
            z = z.add_(g if pillar is None else g.index_select(0, idx))
            point = torch.relu_(z)
            pillar = scatter_max(point, idx, num_pillars)
        z, g = _split_linear(last, point, pillar)
        return torch.relu_(scatter_max(z, idx, num_pillars).add_(g))


def _split_linear(
    layer: PFNLayer, point: torch.Tensor, pillar: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """``layer``'s folded linear of ``[point, pillar[idx]]`` as its per-point part ``(N, w)``
    and its per-pillar part with the bias, ``(P, w)`` (``(w,)`` when there is no pillar input)."""
    weight, bias = layer.folded()
    if pillar is None:
        return point @ weight.T, bias
    split = point.shape[1]
    return point @ weight[:, :split].T, torch.addmm(bias, pillar, weight[:, split:].T)
