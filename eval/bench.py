"""Benchmark of ``robustbench3d eval`` on a KITTI-val-sized synthetic set (registered as "eval").

The set is generated deterministically in a temporary directory: 3769 frames (the val split's
size), about 26k GT lines with KITTI's class mix (DontCare included) and about 19k Car
detections (85 % of the Cars found with jittered boxes, plus false positives). The command is
timed end to end in a fresh interpreter (``python -m robustbench3d eval ...``, imports included)
by :func:`robustbench3d.bench.run_timed_subprocess`. If ``ROBUSTBENCH3D_DEVKIT`` names a compiled
devkit binary taking ``GT_DIR RESULT_DIR FRAME_LIST``, it is timed on the same set and the speed
ratio is reported.
"""

from __future__ import annotations

import os
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

from robustbench3d.bench import run_timed_subprocess

TARGET_SECONDS = 2.5
TARGET_RSS_MB = 500.0
TARGET_SPEEDUP = 5.0
VAL_FRAMES = 3769

#: Type mix of KITTI's training labels (counts per 7481 frames).
_TYPE_COUNTS = {"Car": 28742, "Van": 2914, "Truck": 1094, "Pedestrian": 4487, "Person_sitting": 222,
                "Cyclist": 1627, "Tram": 511, "Misc": 973, "DontCare": 11295}
_DIMS = {"Car": (1.53, 1.63, 3.88), "Van": (2.2, 1.9, 5.1), "Truck": (3.2, 2.6, 10.0), "Tram": (3.5, 2.6, 16.0),
         "Pedestrian": (1.76, 0.66, 0.84), "Person_sitting": (1.27, 0.6, 0.8), "Cyclist": (1.74, 0.6, 1.76),
         "Misc": (1.9, 1.5, 3.6), "DontCare": (-1.0, -1.0, -1.0)}


def _fmt(rows: np.ndarray, types: list[str], score: np.ndarray | None) -> list[str]:
    if score is None:
        return [f"{t} {r[0]:.2f} {int(r[1])} " + " ".join(f"{v:.2f}" for v in r[2:]) for t, r in zip(types, rows,
                                                                                                       strict=True)]
    return [f"{t} -1 -1 " + " ".join(f"{v:.4f}" for v in r[2:]) + f" {s:.6f}"
            for t, r, s in zip(types, rows, score, strict=True)]


def make_val_like_set(root: Path, n_frames: int = VAL_FRAMES, seed: int = 2026) -> dict[str, int]:
    """Write ``label_2/``, ``results/`` (a file per frame) and ``val.txt`` under ``root``.

    Returns counts: frames, gt_lines, car_detections.
    """
    rng = np.random.default_rng(seed)
    names = list(_TYPE_COUNTS)
    p = np.array([_TYPE_COUNTS[n] for n in names], dtype=np.float64)
    per_frame = rng.poisson(p.sum() / 7481, n_frames)
    n = int(per_frame.sum())
    frame = np.repeat(np.arange(n_frames), per_frame)
    kind = np.searchsorted(np.cumsum(p / p.sum()), rng.random(n), side="right").clip(0, len(names) - 1)
    types = [names[k] for k in kind]
    dc = kind == names.index("DontCare")
    # Columns 2..15: truncated, occluded, alpha, left, top, right, bottom, h, w, l, x, y, z, ry.
    gt = np.empty((n, 14))
    height = np.exp(rng.normal(np.log(45), 0.6, n)).clip(8, 300)
    left = rng.uniform(0, 1150, n)
    top = rng.uniform(140, 220, n)
    gt[:, 0] = np.where(rng.random(n) < 0.8, 0.0, rng.uniform(0, 0.9, n))
    gt[:, 1] = rng.integers(0, 4, n)
    gt[:, 3:7] = np.stack([left, top, left + height * rng.uniform(0.5, 2.5, n), top + height], axis=1)
    gt[:, 7:10] = np.array([_DIMS[t] for t in types]) * np.where(dc, 1.0, 1 + rng.normal(0, 0.07, n))[:, None]
    gt[:, 10:13] = np.stack([rng.uniform(-25, 25, n), rng.uniform(1.3, 2.1, n), rng.uniform(4, 75, n)], axis=1)
    gt[:, 13] = rng.uniform(-np.pi, np.pi, n)
    gt[:, 2] = np.angle(np.exp(1j * (gt[:, 13] - np.arctan2(gt[:, 10], gt[:, 12]))))
    gt[dc, 0], gt[dc, 1], gt[dc, 2] = -1, -1, -10
    gt[dc, 10:13], gt[dc, 13] = -1000, -10

    car = np.flatnonzero((kind == names.index("Car")) & (rng.random(n) < 0.85))
    m = len(car)
    det = gt[car].copy()
    size = np.stack([det[:, 5] - det[:, 3], det[:, 6] - det[:, 4]] * 2, axis=1)
    det[:, 3:7] += rng.normal(0, 0.03, (m, 4)) * size
    det[:, 7:10] *= 1 + rng.normal(0, 0.04, (m, 3))
    det[:, 10:13] += rng.normal(0, 1, (m, 3)) * [0.1, 0.03, 0.15]
    det[:, 13] += rng.normal(0, 0.04, m)
    det_frame = frame[car]
    det_score = rng.uniform(0.3, 1.0, m)
    n_fp = int(0.5 * m)
    fp = gt[rng.integers(0, n, n_fp)].copy()
    fp[:, 7:10] = _DIMS["Car"]
    fp[:, 10:13] = np.stack([rng.uniform(-25, 25, n_fp), rng.uniform(1.3, 2.1, n_fp), rng.uniform(4, 75, n_fp)], 1)
    fp[:, 13] = rng.uniform(-np.pi, np.pi, n_fp)
    fp[:, 2] = rng.uniform(-np.pi, np.pi, n_fp)
    fp_frame = rng.integers(0, n_frames, n_fp)
    det = np.concatenate([det, fp])
    det_frame = np.concatenate([det_frame, fp_frame])
    det_score = np.concatenate([det_score, rng.uniform(0, 0.8, n_fp)])
    order = np.argsort(det_frame, kind="stable")
    det, det_frame, det_score = det[order], det_frame[order], det_score[order]

    (root / "label_2").mkdir(parents=True)
    (root / "results").mkdir(parents=True)
    gt_lines = _fmt(gt, types, None)
    det_lines = _fmt(det, ["Car"] * len(det), det_score)
    gt_bounds = np.searchsorted(frame, np.arange(n_frames + 1))
    det_bounds = np.searchsorted(det_frame, np.arange(n_frames + 1))
    ids = [f"{i:06d}" for i in range(n_frames)]
    for i, fid in enumerate(ids):
        (root / "label_2" / f"{fid}.txt").write_text(
            "".join(f"{s}\n" for s in gt_lines[gt_bounds[i]:gt_bounds[i + 1]]))
        (root / "results" / f"{fid}.txt").write_text(
            "".join(f"{s}\n" for s in det_lines[det_bounds[i]:det_bounds[i + 1]]))
    (root / "val.txt").write_text("".join(f"{i}\n" for i in ids))
    return {"frames": n_frames, "gt_lines": n, "car_detections": len(det)}


def run(quick: bool = False) -> list[dict]:
    """Time the eval command (median of 3 runs; 1 in quick mode) and, if given, the devkit."""
    n_frames = 500 if quick else VAL_FRAMES
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="rb3d-eval-bench-") as tmp:
        root = Path(tmp)
        counts = make_val_like_set(root, n_frames)
        cmd = [sys.executable, "-m", "robustbench3d", "eval", "--gt", str(root / "label_2"),
               "--pred", str(root / "results"), "--split", str(root / "val.txt"), "--classes", "Car",
               "--json", str(root / "out.json")]
        runs = [run_timed_subprocess(cmd) for _ in range(1 if quick else 3)]
        seconds = statistics.median(r.seconds for r in runs)
        rss = max(r.peak_rss_mb for r in runs)
        row = {"case": f"eval CLI, {counts['frames']} frames", "gt_lines": counts["gt_lines"],
               "car_dets": counts["car_detections"], "seconds": seconds, "best_s": min(r.seconds for r in runs),
               "frames_per_s": counts["frames"] / seconds, "peak_rss_mb": rss}
        if not quick:
            row["target"] = f"<= {TARGET_SECONDS} s, <= {TARGET_RSS_MB:.0f} MB"
            row["met"] = seconds <= TARGET_SECONDS and rss <= TARGET_RSS_MB
        rows.append(row)
        devkit = os.environ.get("ROBUSTBENCH3D_DEVKIT")
        if devkit:
            ref = run_timed_subprocess([devkit, str(root / "label_2"), str(root / "results"), str(root / "val.txt")])
            dk_row = {"case": f"official devkit, {counts['frames']} frames", "seconds": ref.seconds,
                      "frames_per_s": counts["frames"] / ref.seconds, "peak_rss_mb": ref.peak_rss_mb,
                      "speedup": ref.seconds / seconds}
            if not quick:
                dk_row["target"] = f"speedup >= {TARGET_SPEEDUP:.0f}x"
                dk_row["met"] = ref.seconds / seconds >= TARGET_SPEEDUP
            rows.append(dk_row)
    return rows
