"""The low-level ops every layer shares: box geometry (:mod:`~pcdet_atlas.ops.boxes`), exact
rotated IoU and NMS (:mod:`~pcdet_atlas.ops.iou3d_nms`), the LiDAR sensor model
(:mod:`~pcdet_atlas.ops.lidar_model`) and a pure-torch sparse 3D convolution with spconv 2.x's
interface (:mod:`~pcdet_atlas.ops.spconv`). They import nothing above them (datasets, attacks,
models, evaluation)."""
