"""KITTI object-detection evaluator (official devkit semantics, CPU, float64).

``evaluate`` (in-memory) and ``evaluate_dirs`` (label/result directories) live in
:mod:`robustbench3d.eval.kitti_eval`; they are loaded lazily so that the CLI start-up (which
imports :mod:`robustbench3d.commands.eval`) stays free of numpy.
"""

from __future__ import annotations

from typing import Any

__all__ = ["evaluate", "evaluate_dirs"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from robustbench3d.eval import kitti_eval

        return getattr(kitti_eval, name)
    raise AttributeError(f"module 'robustbench3d.eval' has no attribute {name!r}")
