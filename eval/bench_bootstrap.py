"""Benchmark of bootstrap AP intervals over frames (registered as "bootstrap").

Times 1000 resamples (all of a cell's APs: 2D, AOS, BEV, 3D x R40, R11 x three difficulties) of
one result set, preparation included, in CPU seconds (median of 3; 1 when quick), on:

* a real cell when there is one: ``$ROBUSTBENCH3D_BOOTSTRAP_CELL`` (a result directory), default
  ``runs/main/cells/fpointnet-v1-lite+none+detector/data`` under the working directory, against the
  embedded dataset's val split (``<cache>/datasets/synth``);
* always, the evaluator benchmark's synthetic val-like set made with 1009 frames (about 5k
  detections), so every machine has a number.

Loading the files is not timed. Target: <= 10 s per cell on one core.

Side by side, the resampling vectorised over resamples (``FrameBootstrap.resampled``) against the
per-resample loop it replaced (``FrameBootstrap._resampled_per_resample``, kept as the reference), in one
process, interleaved (loop, vectorised, loop, ...; 3 pairs, 1 when quick), CPU seconds, the median of the
pairs' ratios; every AP of both paths compared bit for bit (``identical``). Preparation is not timed (the
same code in both). Cases:

* the main job's bootstrap when its run is there: every ``ok`` cell of ``$ROBUSTBENCH3D_BOOTSTRAP_RUN``,
  default ``runs/main`` under the working directory (the run's frames, classes, metrics, seed and
  resamples, as the runner's ``metrics_ci``). Target: vectorised <= 0.2 x the loop;
* always, the synthetic 1009-frame set (1000 resamples, seed 0; no target: long event tables, where the
  loop's own per-resample work outweighs its Python overhead).
"""

from __future__ import annotations

import json
import os
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from robustbench3d.eval.bench import make_val_like_set
from robustbench3d.eval.bootstrap import RESAMPLES, FrameBootstrap, ap_intervals, resample_weights
from robustbench3d.eval.loading import load_dirs
from robustbench3d.kitti.labels import read_labels
from robustbench3d.kitti.splits import read_split
from robustbench3d.paths import dataset_dir

TARGET_SECONDS = 10.0
#: The vectorised resampling's CPU time over the per-resample loop's, on the main job's cells (issue #34).
TARGET_RATIO = 0.2
VAL_FRAMES = 1009
DEFAULT_CELL = Path("runs/main/cells/fpointnet-v1-lite+none+detector/data")
DEFAULT_RUN = Path("runs/main")


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


def _run_cells(run: Path) -> tuple[list[FrameBootstrap], int, int] | None:
    """The run's ``ok`` cells prepared as the runner's ``Intervals`` prepares them, with the resamples and
    seed of their ``metrics_ci`` (1000 and the run seed without); None when the run or its data is absent."""
    cells = []
    for path in sorted(run.glob("cells/*/cell.json")):
        cell = json.loads(path.read_text())
        if cell.get("status") == "ok" and (path.parent / "data").is_dir():
            cells.append((path.parent, cell))
    if not cells:
        return None
    dataset = cells[0][1]["dataset"]
    root = Path(dataset["root"])
    split = root / "ImageSets" / f"{dataset['split']}.txt"
    if not split.is_file():
        return None
    ids = read_split(split)[: dataset["frames"]]
    gt = [read_labels(root / "training" / "label_2" / f"{i}.txt", scored=False) for i in ids]
    meta = cells[0][1].get("metrics_ci", {}).get("meta", {})
    resamples, seed = meta.get("resamples", RESAMPLES), meta.get("seed", cells[0][1]["provenance"]["seed"])
    preps = []
    for cell_dir, cell in cells:
        dt = [read_labels(cell_dir / "data" / f"{i}.txt", scored=True) for i in ids]
        preps.append(FrameBootstrap(gt, dt, cell["metrics"]["meta"]["classes"], cell["metrics"]["meta"]["metrics"]))
    return preps, resamples, seed


def _side_by_side(preps: list[FrameBootstrap], resamples: int, seed: int, case: str, quick: bool,
                  target: float | None) -> dict[str, Any]:
    """Interleaved CPU times of the per-resample loop and the vectorised resampling on ``preps``."""
    w = resample_weights(preps[0].n_frames, resamples, seed)
    loop_s, vec_s, identical = [], [], True
    for _ in range(1 if quick else 3):
        c0 = time.process_time()
        want = [p._resampled_per_resample(w) for p in preps]
        c1 = time.process_time()
        got = [p.resampled(w) for p in preps]
        c2 = time.process_time()
        loop_s.append(c1 - c0)
        vec_s.append(c2 - c1)
        identical &= all(list(g) == list(r) and all(g[k].tobytes() == r[k].tobytes() for k in r)
                         for g, r in zip(got, want, strict=True))
    ratio = float(statistics.median(np.divide(vec_s, loop_s)))
    row: dict[str, Any] = {"case": case, "frames": preps[0].n_frames, "resamples": resamples,
                           "loop_cpu_s": statistics.median(loop_s), "vectorised_cpu_s": statistics.median(vec_s),
                           "ratio": ratio, "identical": identical}
    if target is not None:
        row.update(target=f"ratio <= {target}, identical", met=identical and ratio <= target)
    return row


def run(quick: bool = False) -> list[dict]:
    """Rows: the real cell (if present) and the synthetic 1009-frame set; then the side-by-side ratios
    on the main job's cells (if present) and on the synthetic set."""
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
        loaded = load_dirs(root / "label_2", root / "results", root / "val.txt")
        synthetic = FrameBootstrap(loaded.gt, loaded.dt, ("Car",))
    run_dir = Path(os.environ.get("ROBUSTBENCH3D_BOOTSTRAP_RUN", DEFAULT_RUN))
    found = _run_cells(run_dir) if run_dir.is_dir() else None
    if found is not None:
        preps, resamples, seed = found
        rows.append(_side_by_side(preps, resamples, seed, f"loop vs vectorised: {run_dir} ({len(preps)} cells)",
                                  quick, TARGET_RATIO))
    rows.append(_side_by_side([synthetic], RESAMPLES, 0, "loop vs vectorised: synthetic val-like set", quick, None))
    return rows

