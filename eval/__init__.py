"""KITTI object-detection evaluator (official devkit semantics, CPU, float64)."""
