"""``robustbench3d bench objectness``: the shipped 2D detector's objectness oracle on crops against the whole
960x288 input (:func:`bench_objectness_crop`), forward + backward per car of the first val frames of the
embedded dataset, one car per call as attack training asks, at the candidate IoU thresholds 0.3 (mean loss)
and 0.5 (sum loss), with the crop's mean width. One torch thread. The training step these crops serve is
timed by ``bench attack``.
"""

from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np
import torch


def _progress(line: str) -> None:
    """One progress line on stderr (the table goes to stdout)."""
    print(f"  bench objectness: {line}", file=sys.stderr, flush=True)


def _embedded_val(frames: int) -> tuple[Any, list[str]]:
    """The embedded dataset's val split (its first ``frames`` frames generated where missing) and those ids."""
    from robustbench3d.datasets import resolve_dataset

    kitti = resolve_dataset(None, "val", lazy=True, max_frames=frames, progress=False, log=_progress).kitti()
    return kitti, list(kitti.frame_ids[:frames])


def bench_objectness_crop(frames: int = 8, thresholds: tuple[float, ...] = (0.3, 0.5)) -> list[dict[str, float]]:
    """CPU ms of the shipped ``fpointnet-v1-lite`` objectness oracle, forward + backward (loss = sum of the
    candidates' objectness and Car logits, gradient w.r.t. the image), per target car of the first ``frames``
    val frames, one car per call (as training asks), with and without crops, interleaved call by call. Per
    IoU threshold: calls, mean ms of each, their ratio and the mean width (px of the 960 px input) of the
    input slice the crop's first layer reads."""
    from robustbench3d.eval.rules import TARGET_CLASS
    from robustbench3d.victims import create_victim
    from robustbench3d.victims.yolo.detector import candidate_region, head_windows
    from robustbench3d.victims.yolo.letterbox import image_to_tensor, letterbox_geometry

    victim = create_victim("fpointnet-v1-lite")
    net, (w_in, h_in) = victim.yolo.net, victim.yolo.cfg.input_size
    kitti, ids = _embedded_val(frames)
    cases = []
    for fid in ids:
        frame = kitti.frame(fid)
        image = image_to_tensor(frame.image)
        cases += [(image, box[None]) for box in frame.labels.of_types((TARGET_CLASS,)).bbox]  # the attacks' targets

    def call(image: torch.Tensor, box: np.ndarray, thr: float, crop: bool) -> float:
        x = image.clone().requires_grad_(True)
        c0 = time.process_time()
        cands = victim.objectness(x, [box], iou_threshold=thr, crop=crop)
        torch.autograd.grad(cands.objectness_logit.sum() + cands.class_logit.sum(), x, allow_unused=True)
        return time.process_time() - c0

    rows: list[dict[str, float]] = []
    for thr in thresholds if cases else ():
        _progress(f"objectness crop vs whole input, IoU {thr}: {len(cases)} cars of {frames} frames")
        call(*cases[0], thr, True), call(*cases[0], thr, False)  # warm-up
        whole = crop = 0.0
        widths = []
        for image, box in cases:
            whole += call(image, box, thr, False)
            crop += call(image, box, thr, True)
            geo = letterbox_geometry((image.shape[-1], image.shape[-2]), (w_in, h_in))
            windows = head_windows(candidate_region(geo.to_input(box)[0], thr), net, (h_in, w_in))
            span = net.needed_windows(windows, h_in, w_in)[1] if any(w is not None for w in windows) else None
            widths.append(0 if span is None else span[1][1] - span[1][0])
        n = max(len(cases), 1)
        rows.append({"iou": thr, "calls": float(len(cases)), "whole_ms": 1e3 * whole / n, "crop_ms": 1e3 * crop / n,
                     "ratio": crop / whole if whole > 0 else float("nan"), "crop_px": float(np.mean(widths))})
    return rows


def run(quick: bool) -> list[dict]:
    """The table rows; --quick: the cars of the first val frame (a smoke run), else of the first 8."""
    frames = 1 if quick else 8
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return [{"case": f"2D objectness fwd+bwd per car, crop vs whole 960x288 input, candidate IoU {r['iou']:g}, "
                         f"{r['calls']:.0f} cars of {frames} val frames (crop {r['crop_px']:.0f} px wide)",
                 "whole_ms": round(r["whole_ms"], 1), "crop_ms": round(r["crop_ms"], 1), "ratio": round(r["ratio"], 3)}
                for r in bench_objectness_crop(frames)]
    finally:
        torch.set_num_threads(threads)
