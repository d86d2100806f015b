"""``robustbench3d bench onnx``: torch vs onnxruntime latency of the F-PN cascade, side by side.

The full v1 cascade ("fpointnet-v1" networks, seeded untrained weights: the same compute as
trained ones) is exported with the dynamo exporter to a temporary directory; both victims run on
a few generated frames. One thread each (``torch.set_num_threads(1)``, one onnxruntime intra-op
thread); torch and onnxruntime calls are interleaved and the median of the repeats is reported.
Rows: each stage graph at its fixed batch, the 2D detection of one frame (letterbox, network,
decoding, NMS), and a whole frame with GT proposals (F-PN on every car). ``ratio`` is torch / onnx
(above 1: onnxruntime is faster). The numpy glue is the same code on both sides.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any


def _median_ms(fn: Callable[[], Any], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def _interleaved(torch_fn: Callable[[], Any], onnx_fn: Callable[[], Any], repeats: int) -> tuple[float, float]:
    """Median ms of both, measured alternately (one warm-up call each)."""
    torch_fn(), onnx_fn()
    t, o = [], []
    for _ in range(repeats):
        t.append(_median_ms(torch_fn, 1))
        o.append(_median_ms(onnx_fn, 1))
    return statistics.median(t), statistics.median(o)


def run(quick: bool) -> list[dict]:
    import numpy as np
    import torch

    from robustbench3d.kitti.dataset import KittiDataset
    from robustbench3d.synth.writer import generate_dataset
    from robustbench3d.victims.cascade import FPointNetCascade
    from robustbench3d.victims.onnx.export import ExportOptions, export_cascade
    from robustbench3d.victims.onnx.parity import stage_inputs, torch_stage_outputs
    from robustbench3d.victims.onnx.runtime import OnnxCascade
    from robustbench3d.victims.yolo.preprocess import letterbox_image

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    repeats = 3 if quick else 7
    frames_n = 2 if quick else 4
    rows: list[dict] = []
    try:
        with tempfile.TemporaryDirectory(prefix="robustbench3d-bench-onnx-") as tmp:
            generate_dataset(Path(tmp) / "data", frames_n, seed=0, val_fraction=0.5, workers=1, progress=False)
            ds = KittiDataset(Path(tmp) / "data", split=None)
            frames = [ds.frame(f) for f in ds.frame_ids]
            victim = FPointNetCascade.untrained("full", "mini", seed=0)
            export_cascade(victim, Path(tmp) / "onnx", ExportOptions("dynamo"), source={"victim": "fpointnet-v1"},
                           reproduce_command="(benchmark export)")
            onnx_victim = OnnxCascade(Path(tmp) / "onnx", seed=victim.settings.seed, gather=victim.settings.gather)
            inputs = stage_inputs(victim, frames, np.random.default_rng(0))
            for name, session in onnx_victim.stages.items():
                batch = [x[:session.batch_size] for x in inputs[name]]
                if len(batch[0]) < session.batch_size:
                    continue
                t, o = _interleaved(lambda n=name, b=batch: torch_stage_outputs(victim, n, b),
                                    lambda s=session, b=batch: s.run(*b), repeats)
                rows.append({"case": f"{name} (batch {session.batch_size})", "torch_ms": t, "onnx_ms": o,
                             "ratio": t / o})
            image = frames[0].image
            t, o = _interleaved(lambda: victim.yolo.detect([image]), lambda: onnx_victim.detect_2d([image]), repeats)
            rows.append({"case": "2D detection, 1 frame (letterbox+net+NMS)", "torch_ms": t, "onnx_ms": o,
                         "ratio": t / o})
            lb = _median_ms(lambda: letterbox_image(image, victim.yolo.cfg.input_size), repeats)
            rows.append({"case": "  of which numpy letterbox (shared)", "torch_ms": lb, "onnx_ms": lb, "ratio": 1.0})
            cars = sum(len(r) for r in victim.detect(frames, "gt"))
            t, o = _interleaved(lambda: victim.detect(frames, "gt"), lambda: onnx_victim.detect(frames, "gt"), repeats)
            rows.append({"case": f"frame, GT proposals ({cars / len(frames):.1f} cars/frame)",
                         "torch_ms": t / len(frames), "onnx_ms": o / len(frames), "ratio": t / o})
    finally:
        torch.set_num_threads(threads)
    return rows
