"""``robustbench3d bench fpn-train``: time of one F-PN v1 training step per frustum on the CPU.

Rows: network (lite, full) x precision (fp32, bf16 autocast) x per-point layout (rows, conv), one
torch thread, the trainer's own step (:class:`~robustbench3d.victims.fpointnet.training.FPointNetTask`:
tensor batch draw, forward, loss, backward, Adam) on a synthetic frustum set. Reports the median
wall and CPU (process) time of a step divided by the batch size; CPU time is the figure to trust on
a shared machine.
"""

from __future__ import annotations

import statistics
import time

import numpy as np
import torch

from robustbench3d.victims.fpointnet.data import FrustumSet
from robustbench3d.victims.fpointnet.training import FPointNetTask, FPointNetTrainConfig


def synthetic_set(frustums: int, points: int, seed: int = 0) -> FrustumSet:
    """Frustums of ``points`` random points around a car-sized blob 15-40 m ahead."""
    rng = np.random.default_rng(seed)
    centre = np.stack([rng.uniform(-3, 3, frustums), np.full(frustums, 1.0), rng.uniform(15, 40, frustums)], axis=1)
    pts = (np.repeat(centre, points, axis=0) + rng.normal(0, [2.0, 0.7, 4.0], (frustums * points, 3)))
    refl = rng.uniform(0, 1, (frustums * points, 1))
    inside = (np.abs(pts - np.repeat(centre, points, axis=0)) < [2.0, 0.8, 1.0]).all(axis=1)
    return FrustumSet(points=np.concatenate([pts, refl], axis=1).astype(np.float32), seg=inside.astype(np.uint8),
                      offsets=np.arange(frustums + 1, dtype=np.int64) * points, box2d=np.zeros((frustums, 4)),
                      rot_angle=rng.uniform(-0.3, 0.3, frustums), center=centre,
                      ry=rng.uniform(-np.pi, np.pi, frustums),
                      size_lwh=np.tile([3.9, 1.6, 1.5], (frustums, 1)), types=np.array(["Car"] * frustums),
                      frame_ids=np.array(["000000"] * frustums))


def step_times(model: str, precision: str, layout: str, batch: int, steps: int, warmup: int = 1) -> dict[str, float]:
    """Median wall and CPU seconds of one training step (batch ``batch``) after ``warmup`` steps."""
    fs = synthetic_set(max(batch, 8), 1500)
    task = FPointNetTask(fs, None, FPointNetTrainConfig(model=model, precision=precision, layout=layout), seed=0,
                         total_steps=steps + warmup)
    task.model.train()
    wall, cpu = [], []
    for i in range(warmup + steps):
        rng = np.random.default_rng([0, i])
        t0, c0 = time.perf_counter(), time.process_time()
        task.schedule(0, i, i * batch)
        loss, _ = task.loss(np.arange(batch), rng, torch.Generator().manual_seed(i))
        task.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        task.optimizer.step()
        if i >= warmup:
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
    return {"wall": statistics.median(wall), "cpu": statistics.median(cpu)}


def run(quick: bool) -> list[dict]:
    batch, steps = (8, 2) if quick else (32, 5)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    rows = []
    try:
        for model in ("lite", "full"):
            for precision in ("fp32", "bf16"):
                for layout in ("rows", "conv"):
                    t = step_times(model, precision, layout, batch, steps)
                    rows.append({"benchmark": "fpn-train step", "network": model, "precision": precision,
                                 "layout": layout, "batch": batch, "threads": 1,
                                 "ms_per_frustum_cpu": round(1000 * t["cpu"] / batch, 2),
                                 "ms_per_frustum_wall": round(1000 * t["wall"] / batch, 2)})
    finally:
        torch.set_num_threads(threads)
    return rows
