"""Sensor models shared by the synthetic data generator and the attacks.

Modules: :mod:`~robustbench3d.sensors.hdl64e` (the LiDAR's beams), :mod:`~robustbench3d.sensors.lidar_model`
(which hits return, range noise, reflectance), :mod:`~robustbench3d.sensors.camera_model` (shading, shadows
as a mask, specular, haze, tone mapping, sensor noise), :mod:`~robustbench3d.sensors.materials` (material ids
and their sensor properties) and :mod:`~robustbench3d.sensors.mesh` (icosphere, face normals, row-wise
cross and dot products).

The differentiable renderers of the attacks, from the top (each imports only modules below it):

* camera: ``camera_render`` (the entry points) -> ``camera_shade`` (shading, compositing, its autograd
  function) and ``camera_cull`` (which (sample, face) pairs are tested, and the search among them);
  ``camera_depth`` (the occluding scene depth);
* LiDAR: ``lidar_render`` -> ``lidar_beams`` (the scan's beam pattern) and ``pattern_cache``;
* ray/triangle core of both: ``raycast`` (the casts) -> ``cluster_search`` (the dense search in torch),
  ``pair_search`` (the search of a cull's candidate pairs), ``ray_rows`` (the recompute with gradients)
  -> ``ray_faces`` (the per-face test table, back faces);
* compiled (numba) kernels and their thin wrappers only (the numpy references are in the modules calling them):
  ``ray_kernels``, ``camera_kernels``, ``lidar_kernels``, ``lidar_table_kernels`` -> ``array_kernels`` (the
  conventions they share: bit for bit numpy's arithmetic, bounds checked by the wrappers, ``cache=True``).
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
