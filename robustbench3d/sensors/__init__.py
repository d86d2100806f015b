"""Sensor models shared by the synthetic data generator and the attacks.

Modules: :mod:`~robustbench3d.sensors.hdl64e` (the LiDAR's beams), :mod:`~robustbench3d.sensors.lidar_model`
(which hits return, range noise, reflectance), :mod:`~robustbench3d.sensors.camera_model` (shading, shadows
as a mask, specular, haze, tone mapping, sensor noise), :mod:`~robustbench3d.sensors.materials` (material ids
and their sensor properties) and :mod:`~robustbench3d.sensors.mesh` (icosphere, face normals).
"""

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
from robustbench3d.sensors.materials import MATERIALS, Mat, Material
from robustbench3d.sensors.mesh import face_normals, icosphere

__all__ = [
    "AZIMUTH_QUANTUM_DEG", "EGO_OCCLUSION_SECTORS", "FIRINGS_PER_REVOLUTION", "HDL64E", "LASER_ELEVATION_DEG",
    "LASER_ORIGIN_Z_M", "MATERIALS", "MAX_RANGE_M", "MOUNT_HEIGHT_M", "BeamRays", "Mat", "Material", "face_normals",
    "icosphere", "ring_ids_from_azimuth_wrap",
]
