"""Pure-torch building blocks shared by the model stages (scatter, voxelization, CenterNet)."""
