"""Fixtures of the performance regression suite (``pytest -m bench``; see the README).

Every benchmark here is marked ``bench`` and deselected by the default run. Timings are CPU time
of this process (``--benchmark-timer time.process_time``, set in pyproject's addopts): on a shared
machine other processes steal wall time but hardly change CPU time. Everything runs on one thread
(torch, BLAS, onnxruntime) so CPU time is the work done, not the parallelism found. Heavy cases use
``benchmark.pedantic`` with a fixed number of rounds to keep the suite short.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

#: Timed rounds of the reference kernel before and after each benchmark.
REFERENCE_ROUNDS = 25


def reference_kernel() -> float:
    """Three 192x192 float64 matrix products (compiled numeric code) and a 60k-step integer loop (the
    interpreter), about equal shares of CPU time; returns a checksum. Changing it changes every stored
    value: re-record the baseline (``python tools/perf_compare.py --write-baseline``)."""
    import numpy as np

    a = (np.arange(192 * 192, dtype=np.float64).reshape(192, 192) % 97) / 97.0
    m = a
    for _ in range(3):
        m = (m @ a) / 192.0
    s = 0
    for i in range(60_000):
        s += (i * i) % 7
    return float(m.sum()) + s


def reference_seconds(rounds: int = REFERENCE_ROUNDS) -> float:
    """Minimum CPU time of :func:`reference_kernel` over ``rounds`` calls."""
    best = math.inf
    for _ in range(rounds):
        t0 = time.process_time()
        reference_kernel()
        best = min(best, time.process_time() - t0)
    return best


@pytest.fixture(autouse=True)
def _reference(request: pytest.FixtureRequest) -> Iterator[None]:
    """Time the reference kernel right before and right after each benchmark, in the same process, and
    store the smaller minimum as ``extra_info["reference_s"]``: the comparer divides the benchmark's
    time by it, so a machine (or a stretch of load) that slows everything cancels out."""
    if "benchmark" not in request.fixturenames:
        yield
        return
    bench = request.getfixturevalue("benchmark")
    before = reference_seconds()
    yield
    bench.extra_info["reference_s"] = min(before, reference_seconds())


@pytest.fixture(scope="session", autouse=True)
def _one_thread() -> None:
    """One torch thread for the whole session (set only when a benchmark runs)."""
    import torch

    torch.set_num_threads(1)


@pytest.fixture(scope="session")
def rounds() -> Callable[[int], int]:
    """Round count of a heavy benchmark: ``n`` times ``$ROBUSTBENCH3D_BENCH_ROUNDS_SCALE`` (default 1; the
    comparer's second try sets 3)."""
    raw = os.environ.get("ROBUSTBENCH3D_BENCH_ROUNDS_SCALE", "1")
    if not raw.isdigit() or int(raw) < 1:
        raise ValueError(f"ROBUSTBENCH3D_BENCH_ROUNDS_SCALE must be a positive integer, got {raw!r}")
    return lambda n: n * int(raw)


@pytest.fixture(scope="session")
def val3769(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The evaluator benchmark's KITTI-val-sized set (3769 frames, seed 2026): label_2/, results/, val.txt."""
    from robustbench3d.eval.bench import VAL_FRAMES, make_val_like_set

    root = tmp_path_factory.mktemp("val3769")
    make_val_like_set(root, VAL_FRAMES)
    return root


@pytest.fixture(scope="session")
def val1009_loaded(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """The same kind of set with 1009 frames (the embedded val split's size), loaded."""
    from robustbench3d.eval.bench import make_val_like_set
    from robustbench3d.eval.loading import load_dirs

    root = tmp_path_factory.mktemp("val1009")
    make_val_like_set(root, 1009)
    return load_dirs(root / "label_2", root / "results", root / "val.txt")


@pytest.fixture(scope="session")
def val3769_loaded(val3769: Path) -> Any:
    """:func:`~robustbench3d.eval.loading.load_dirs` of :func:`val3769`."""
    from robustbench3d.eval.loading import load_dirs

    return load_dirs(val3769 / "label_2", val3769 / "results", val3769 / "val.txt")


@pytest.fixture(scope="session")
def kitti_frames(tmp_path_factory: pytest.TempPathFactory) -> list[Any]:
    """Two procedural frames (seed 0) written in KITTI layout and read back as dataset frames."""
    from robustbench3d.kitti.dataset import KittiDataset
    from robustbench3d.testing import synth_dataset

    root = synth_dataset(tmp_path_factory.mktemp("frames") / "data", 2, seed=0)
    ds = KittiDataset(root, split=None)
    return [ds.frame(f) for f in ds.frame_ids]


@pytest.fixture(scope="session")
def cascade() -> Any:
    """The shipped torch victim ``fpointnet-v1-lite``."""
    from robustbench3d.victims.zoo import fpointnet_v1_lite

    return fpointnet_v1_lite()


@pytest.fixture(scope="session")
def stage_inputs(cascade: Any, kitti_frames: list[Any]) -> dict[str, list[Any]]:
    """Inputs of each network stage (letterboxed images, frustums, object points) on :func:`kitti_frames`."""
    import numpy as np

    from robustbench3d.victims.onnx.parity import stage_inputs as make_inputs

    return make_inputs(cascade, kitti_frames, np.random.default_rng(0))
