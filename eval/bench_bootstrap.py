"""Benchmark of bootstrap AP intervals over frames (registered as "bootstrap").

Times 1000 resamples (all of a cell's APs: 2D, AOS, BEV, 3D x R40, R11 x three difficulties) of
one result set, preparation included, in CPU seconds (median of 3; 1 when quick), on:

* a real cell when there is one: ``$ROBUSTBENCH3D_BOOTSTRAP_CELL`` (a result directory), default
  ``runs/main/cells/fpointnet-v1-lite+none+detector/data`` under the working directory, against the
  embedded dataset's val split (``<cache>/datasets/synth``);
* always, the evaluator benchmark's synthetic val-like set made with 1009 frames (about 5k
  detections), so every machine has a number.

Loading the files is not timed. Target: <= 10 s per cell on one core.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from pathlib import Path

from robustbench3d.eval.bench import make_val_like_set
from robustbench3d.eval.bootstrap import RESAMPLES, FrameBootstrap, ap_intervals
from robustbench3d.eval.loading import load_dirs
from robustbench3d.paths import dataset_dir

TARGET_SECONDS = 10.0
VAL_FRAMES = 1009
DEFAULT_CELL = Path("runs/main/cells/fpointnet-v1-lite+none+detector/data")


def _time_cell(gt_dir: Path, pred_dir: Path, split: Path | None, case: str, quick: bool) -> dict:
    loaded = load_dirs(gt_dir, pred_dir, split)
    cpu, wall = [], []
    for _ in range(1 if quick else 3):
        t0, c0 = time.perf_counter(), time.process_time()
        ci = ap_intervals(FrameBootstrap(loaded.gt, loaded.dt, ("Car",)), resamples=RESAMPLES, seed=0)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - t0)
    lo, hi = ci["Car"]["bev"]["R40"]["moderate"]
    median = statistics.median(cpu)
    return {"case": case, "frames": loaded.gt.n_frames, "detections": len(loaded.dt), "resamples": RESAMPLES,
            "cpu_s": median, "wall_s": statistics.median(wall), "bev_R40_mod_ci": f"[{lo:.2f}, {hi:.2f}]",
            "target": f"<= {TARGET_SECONDS:.0f} s CPU", "met": median <= TARGET_SECONDS}


def run(quick: bool = False) -> list[dict]:
    """Rows: the real cell (if present) and the synthetic 1009-frame set."""
    rows = []
    cell = Path(os.environ.get("ROBUSTBENCH3D_BOOTSTRAP_CELL", DEFAULT_CELL))
    synth = dataset_dir("synth")
    if cell.is_dir() and (synth / "ImageSets" / "val.txt").is_file():
        rows.append(_time_cell(synth / "training" / "label_2", cell, synth / "ImageSets" / "val.txt",
                               f"real cell {cell.parent.name}", quick))
    with tempfile.TemporaryDirectory(prefix="rb3d-bootstrap-bench-") as tmp:
        root = Path(tmp)
        make_val_like_set(root, VAL_FRAMES)
        rows.append(_time_cell(root / "label_2", root / "results", root / "val.txt", "synthetic val-like set",
                               quick))
    return rows
