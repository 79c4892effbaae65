"""OpenPCDet's detector registry (``__all__``, by ``MODEL.NAME``) and ``build_detector``."""

from pcdet.models.detectors.point_count_oracle import PointCountOracle

__all__ = {"PointCountOracle": PointCountOracle}  # noqa: PLE0605


def build_detector(model_cfg, num_class, dataset):
    return __all__[model_cfg.NAME](model_cfg=model_cfg, num_class=num_class, dataset=dataset)
