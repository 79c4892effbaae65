"""OpenPCDet's dataset registry (the dict ``__all__``) and ``build_dataloader``."""

from torch.utils.data import DataLoader

from pcdet.datasets.dataset import DatasetTemplate
from pcdet.datasets.waymo.waymo_dataset import WaymoDataset

__all__ = {"DatasetTemplate": DatasetTemplate, "WaymoDataset": WaymoDataset}  # noqa: PLE0605


def build_dataloader(dataset_cfg, class_names, batch_size, dist, root_path=None, workers=4,
                     seed=None, logger=None, training=True, merge_all_iters_to_one_epoch=False,
                     total_epochs=0):  # fmt: skip
    dataset = __all__[dataset_cfg.DATASET](
        dataset_cfg=dataset_cfg, class_names=class_names, root_path=root_path,
        training=training, logger=logger,
    )  # fmt: skip
    if merge_all_iters_to_one_epoch:
        dataset.merge_all_iters_to_one_epoch(merge=True, epochs=total_epochs)
    if dist:
        raise NotImplementedError("the stand-in runs in one process")
    loader = DataLoader(
        dataset, batch_size=batch_size, num_workers=workers, shuffle=training,
        collate_fn=dataset.collate_batch, drop_last=False, sampler=None, timeout=0,
    )  # fmt: skip
    return dataset, loader, None
