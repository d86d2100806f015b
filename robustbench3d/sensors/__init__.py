"""Sensor models shared by the synthetic data generator and the attacks."""

from robustbench3d.sensors.hdl64e import (
    AZIMUTH_QUANTUM_DEG,
    EGO_OCCLUSION_SECTORS,
    FIRINGS_PER_REVOLUTION,
    HDL64E,
    LASER_ELEVATION_DEG,
    LASER_ORIGIN_Z_M,
    MAX_RANGE_M,
    MOUNT_HEIGHT_M,
    BeamRays,
    ring_ids_from_azimuth_wrap,
)

__all__ = [
    "AZIMUTH_QUANTUM_DEG", "EGO_OCCLUSION_SECTORS", "FIRINGS_PER_REVOLUTION", "HDL64E", "LASER_ELEVATION_DEG",
    "LASER_ORIGIN_Z_M", "MAX_RANGE_M", "MOUNT_HEIGHT_M", "BeamRays", "ring_ids_from_azimuth_wrap",
]
