"""Frustum-PointNet v1 (Qi et al., CVPR 2018) reimplemented from the reference notes (§1):
frustum extraction, box coding, network, loss, KITTI output and training data."""
