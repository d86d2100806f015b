"""Example robustbench3d victim plugin: a LiDAR-only clustering / L-shape box-fitting car detector.

The entry point ``lidar-cluster = "rb3d_lidar_cluster:SPEC"`` in the ``robustbench3d.victims``
group makes it available as ``robustbench3d.victims.create_victim("lidar-cluster")``.
"""

from __future__ import annotations

from typing import Any

from rb3d_lidar_cluster.detector import ClusterSettings, LidarClusterDetector
from robustbench3d.victims.spec import Capabilities, EntryInfo, VictimSpec


def build(**settings: Any) -> LidarClusterDetector:
    """Factory: keyword arguments override :class:`ClusterSettings` fields."""
    return LidarClusterDetector(ClusterSettings(**settings))


SPEC = VictimSpec(
    factory=build,
    info=EntryInfo(
        capabilities=Capabilities(modalities=("lidar",), backend="other", gradients=False, deterministic=True),
        weights_sha256=None,
        summary="LiDAR-only ground removal + BEV clustering + L-shape box fit (no learning)",
    ),
)

__all__ = ["SPEC", "ClusterSettings", "LidarClusterDetector", "build"]
