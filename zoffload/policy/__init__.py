"""Decision cores: the per-scan scale (voxel size) policy and, later, offloading strategies."""
