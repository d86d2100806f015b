"""Evaluator on the KITTI-val-sized synthetic set (3769 frames, ~19k Car detections) and bootstrap on a
1009-frame one (the embedded val split's size), both made by :func:`robustbench3d.eval.bench.make_val_like_set`."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

import pytest

pytestmark = pytest.mark.bench
_needs_bootstrap = pytest.mark.skipif(importlib.util.find_spec("robustbench3d.eval.bootstrap") is None,
                                      reason="robustbench3d.eval.bootstrap not present")


def test_eval_load_val3769(benchmark: Any, rounds: Any, val3769: Path) -> None:
    """Parse 3769 GT and 3769 result files (the evaluator's loading)."""
    from robustbench3d.eval.loading import load_dirs

    def run() -> Any:
        return load_dirs(val3769 / "label_2", val3769 / "results", val3769 / "val.txt")

    loaded = benchmark.pedantic(run, rounds=rounds(5), warmup_rounds=1)
    assert loaded.gt.n_frames == 3769


def test_eval_evaluate_val3769(benchmark: Any, rounds: Any, val3769_loaded: Any) -> None:
    """Every Car AP (2D, AOS, BEV, 3D; R40, R11; three difficulties) of the loaded tables."""
    from robustbench3d.eval.kitti_eval import evaluate_tables

    def run() -> Any:
        return evaluate_tables(val3769_loaded.gt, val3769_loaded.dt, ("Car",))

    result = benchmark.pedantic(run, rounds=rounds(5), warmup_rounds=1)
    assert 0.0 < result["Car"]["bev"]["R40"]["moderate"] <= 100.0


@_needs_bootstrap
def test_bootstrap_prepare_val1009(benchmark: Any, rounds: Any, val1009_loaded: Any) -> None:
    """Bootstrap preparation on a 1009-frame set (the size of the embedded val split): the per-frame
    matching and threshold events, run once per cell."""
    from robustbench3d.eval.bootstrap import FrameBootstrap

    prep = benchmark.pedantic(lambda: FrameBootstrap(val1009_loaded.gt, val1009_loaded.dt, ("Car",)), rounds=rounds(5))
    assert prep.keys()


@_needs_bootstrap
def test_bootstrap_resample_val1009(benchmark: Any, rounds: Any, val1009_loaded: Any) -> None:
    """200 bootstrap resamples of every Car AP on the 1009-frame set (only the accumulation is resampled)."""
    from robustbench3d.eval.bootstrap import FrameBootstrap, ap_intervals

    prep = FrameBootstrap(val1009_loaded.gt, val1009_loaded.dt, ("Car",))
    ci = benchmark.pedantic(lambda: ap_intervals(prep, resamples=200, seed=0), rounds=rounds(5), warmup_rounds=1)
    lo, hi = ci["Car"]["bev"]["R40"]["moderate"]
    assert 0.0 <= lo <= hi <= 100.0
