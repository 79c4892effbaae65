"""The low-level ops every layer shares: box geometry (:mod:`~pcdet_atlas.ops.boxes`), exact
rotated IoU and NMS (:mod:`~pcdet_atlas.ops.iou3d_nms`) and the LiDAR sensor model
(:mod:`~pcdet_atlas.ops.lidar_model`). They import nothing above them (datasets, attacks, models,
evaluation)."""
