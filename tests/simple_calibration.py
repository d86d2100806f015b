"""A KITTI-like calibration for tests that write small datasets: the real 2011_09_26 P2 with an
axis-permutation velodyne->camera transform (camera 0.08 m above and 0.27 m ahead of the LiDAR)."""

from __future__ import annotations

import numpy as np

from robustbench3d.kitti import Calibration

SIMPLE_CALIB = Calibration(
    P0=np.eye(3, 4), P1=np.eye(3, 4),
    P2=np.array([[721.5377, 0.0, 609.5593, 44.85728], [0.0, 721.5377, 172.854, 0.2163791],
                 [0.0, 0.0, 1.0, 0.002745884]]),
    P3=np.eye(3, 4), R0_rect=np.eye(3),
    Tr_velo_to_cam=np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, -0.08], [1.0, 0.0, 0.0, -0.27]]),
    Tr_imu_to_velo=np.eye(3, 4),
)
