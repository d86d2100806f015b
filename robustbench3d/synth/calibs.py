"""KITTI calibrations of the two recording days in the real sample frames.

The numbers are copied from the published KITTI object calib files (``training/calib``):
``DAY_0926`` from frames 000001-000005 (recording day 2011_09_26, images 1242x375) and
``DAY_0000`` from frame 000000 (another recording day, images 1224x370). The synthetic frames use
them unchanged, so P2, the rectification and the velodyne -> camera transform (hence the LiDAR
origin in rect) are those of real KITTI.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robustbench3d.kitti.calib import Calibration


def _m(values: str, rows: int, cols: int) -> np.ndarray:
    return np.array([float(v) for v in values.split()], dtype=np.float64).reshape(rows, cols)


_TR_IMU_TO_VELO = ("9.999976e-01 7.553071e-04 -2.035826e-03 -8.086759e-01 -7.854027e-04 9.998898e-01 "
                   "-1.482298e-02 3.195559e-01 2.024406e-03 1.482454e-02 9.998881e-01 -7.997231e-01")


@dataclass(frozen=True, eq=False)
class CameraDay:
    """A recording day: its calibration and its image size (width, height) in pixels."""

    name: str
    calib: Calibration
    image_size: tuple[int, int]


# 2011_09_26 (sample frames 000001-000005).
DAY_0926 = CameraDay("2011_09_26", Calibration(
    P0=_m("7.215377e+02 0 6.095593e+02 0 0 7.215377e+02 1.728540e+02 0 0 0 1 0", 3, 4),
    P1=_m("7.215377e+02 0 6.095593e+02 -3.875744e+02 0 7.215377e+02 1.728540e+02 0 0 0 1 0", 3, 4),
    P2=_m("7.215377e+02 0 6.095593e+02 4.485728e+01 0 7.215377e+02 1.728540e+02 2.163791e-01 0 0 1 "
          "2.745884e-03", 3, 4),
    P3=_m("7.215377e+02 0 6.095593e+02 -3.395242e+02 0 7.215377e+02 1.728540e+02 2.199936e+00 0 0 1 "
          "2.729905e-03", 3, 4),
    R0_rect=_m("9.999239e-01 9.837760e-03 -7.445048e-03 -9.869795e-03 9.999421e-01 -4.278459e-03 "
               "7.402527e-03 4.351614e-03 9.999631e-01", 3, 3),
    Tr_velo_to_cam=_m("7.533745e-03 -9.999714e-01 -6.166020e-04 -4.069766e-03 1.480249e-02 7.280733e-04 "
                      "-9.998902e-01 -7.631618e-02 9.998621e-01 7.523790e-03 1.480755e-02 -2.717806e-01", 3, 4),
    Tr_imu_to_velo=_m(_TR_IMU_TO_VELO, 3, 4),
), (1242, 375))

# The recording day of sample frame 000000 (1224x370 images).
DAY_0000 = CameraDay("frame000000_day", Calibration(
    P0=_m("7.070493e+02 0 6.040814e+02 0 0 7.070493e+02 1.805066e+02 0 0 0 1 0", 3, 4),
    P1=_m("7.070493e+02 0 6.040814e+02 -3.797842e+02 0 7.070493e+02 1.805066e+02 0 0 0 1 0", 3, 4),
    P2=_m("7.070493e+02 0 6.040814e+02 4.575831e+01 0 7.070493e+02 1.805066e+02 -3.454157e-01 0 0 1 "
          "4.981016e-03", 3, 4),
    P3=_m("7.070493e+02 0 6.040814e+02 -3.341081e+02 0 7.070493e+02 1.805066e+02 2.330660e+00 0 0 1 "
          "3.201153e-03", 3, 4),
    R0_rect=_m("9.999128e-01 1.009263e-02 -8.511932e-03 -1.012729e-02 9.999406e-01 -4.037671e-03 "
               "8.470675e-03 4.123522e-03 9.999556e-01", 3, 3),
    Tr_velo_to_cam=_m("6.927964e-03 -9.999722e-01 -2.757829e-03 -2.457729e-02 -1.162982e-03 2.749836e-03 "
                      "-9.999955e-01 -6.127237e-02 9.999753e-01 6.931141e-03 -1.143899e-03 -3.321029e-01", 3, 4),
    Tr_imu_to_velo=_m(_TR_IMU_TO_VELO, 3, 4),
), (1224, 370))

CAMERA_DAYS: tuple[CameraDay, ...] = (DAY_0926, DAY_0000)
#: Probability of each day in :data:`CAMERA_DAYS` (most KITTI object frames are 1242x375).
CAMERA_DAY_WEIGHTS = (0.7, 0.3)


def sample_camera_day(rng: np.random.Generator) -> CameraDay:
    """One of the recording days, with :data:`CAMERA_DAY_WEIGHTS`."""
    return CAMERA_DAYS[int(rng.choice(len(CAMERA_DAYS), p=CAMERA_DAY_WEIGHTS))]
