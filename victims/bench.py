"""``robustbench3d bench victim``: per-frame inference cost, peak memory and determinism of the
F-PN cascades (torch, one thread).

Frames: a small embedded-style dataset generated into a temporary directory by the tests' builder
(:func:`robustbench3d.testing.synth_dataset`, seed 0; 8 frames, 3 when quick). Each victim runs in
its own fresh interpreter (:func:`robustbench3d.bench.run_timed_subprocess`) so its peak RSS is its
own: it loads, detects every frame once as a warm-up, then times each frame with the victim's own
2D detector as proposal source (2D detection alone, then the whole frame: 2D + every frustum) and
with GT boxes, and runs detection a second time to check that the rows are identical. Rows: median
ms per frame, frustums per frame, peak RSS and the determinism verdict. The full v1 network runs
with seeded untrained weights (its compute does not depend on them).
"""

from __future__ import annotations

import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

#: victim name -> factory kwargs used by the benchmark
CASES: dict[str, dict[str, Any]] = {
    "fpointnet-v1-lite": {},
    "fpointnet-v1": {"allow_untrained": True},
}


def _rows_equal(a: list[Any], b: list[Any]) -> bool:
    import numpy as np

    fields = ("bbox", "dimensions", "location", "rotation_y", "score")
    return len(a) == len(b) and all(
        len(x) == len(y) and all(np.array_equal(getattr(x, f), getattr(y, f)) for f in fields)
        for x, y in zip(a, b, strict=True))


def worker(data_dir: str, victim: str, kwargs_json: str) -> None:
    """Measure one victim on the frames in ``data_dir``; print one JSON object (subprocess side)."""
    import torch

    from robustbench3d.kitti.dataset import KittiDataset
    from robustbench3d.victims import create_victim

    torch.set_num_threads(1)
    ds = KittiDataset(Path(data_dir), split=None)
    frames = [ds.frame(f) for f in ds.frame_ids]
    model = create_victim(victim, **json.loads(kwargs_json))
    first = model.detect(frames, "detector")  # warm-up, and the reference for the determinism check
    out: dict[str, Any] = {"frames": len(frames)}
    t2d, tdet, tgt = [], [], []
    for fr in frames:
        t0 = time.perf_counter()
        model.proposals([fr], "detector")
        t2d.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        model.detect([fr], "detector")
        tdet.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        model.detect([fr], "gt")
        tgt.append(time.perf_counter() - t0)
    out["ms_2d"] = statistics.median(t2d) * 1e3
    out["ms_detector"] = statistics.median(tdet) * 1e3
    out["ms_gt"] = statistics.median(tgt) * 1e3
    out["frustums_detector"] = sum(len(r) for r in first) / len(frames)
    out["frustums_gt"] = sum(len(r) for r in model.detect(frames, "gt")) / len(frames)
    out["identical"] = _rows_equal(first, model.detect(frames, "detector"))
    print(json.dumps(out))


def run(quick: bool) -> list[dict]:
    from robustbench3d.bench import run_timed_subprocess
    from robustbench3d.testing import synth_dataset

    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="robustbench3d-bench-victim-") as tmp:
        data = synth_dataset(Path(tmp) / "data", 3 if quick else 8, seed=0)  # the tests' builder
        for victim, kwargs in CASES.items():
            code = ("import sys; from robustbench3d.victims.bench import worker; "
                    "worker(sys.argv[1], sys.argv[2], sys.argv[3])")
            m = run_timed_subprocess([sys.executable, "-c", code, str(data), victim, json.dumps(kwargs)],
                                     env={"OMP_NUM_THREADS": "1"})
            r = json.loads(m.stdout.strip().splitlines()[-1])
            weights = "untrained (same compute)" if kwargs.get("allow_untrained") else "shipped"
            rows.append({"victim": victim, "weights": weights, "frames": r["frames"],
                         "2d_ms": r["ms_2d"], "frame_ms_detector": r["ms_detector"],
                         "frustums_detector": r["frustums_detector"], "frame_ms_gt": r["ms_gt"],
                         "frustums_gt": r["frustums_gt"], "peak_rss_mb": m.peak_rss_mb,
                         "deterministic": r["identical"]})
    return rows
