"""robustbench3d: physical adversarial roof objects vs camera+LiDAR 3D car detectors.

Layout: ``robustbench3d`` (core: data types, KITTI IO, geometry, sensors, registry, CLI),
``robustbench3d.eval`` (KITTI evaluator), ``robustbench3d.victims`` (models under attack),
``robustbench3d.attacks`` (attack objects). Heavy dependencies (torch, onnxruntime) are only
imported by the modules that need them.
"""

__version__ = "0.1.0"


def __getattr__(name: str):
    if name == "benchmark":
        from robustbench3d.api import benchmark

        return benchmark
    raise AttributeError(f"module 'robustbench3d' has no attribute {name!r}")


__all__ = ["__version__", "benchmark"]
