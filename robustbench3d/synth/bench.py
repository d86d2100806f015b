"""``robustbench3d bench synth``: speed and memory of the synthetic-data pipeline.

Rows: per-stage CPU time of one frame (scene sampling, Embree geometry, LiDAR, camera, labels,
PNG encoding, file writes), PNG encoder settings, and the end-to-end ``data synth`` command with
one and two workers (wall time including start-up, CPU time of all processes, peak RSS of the largest
process). Targets: at least 4 frames/s with two workers on two cores, at most 1.5 GB per worker. The
machine is shared, so ``load_before`` (1-min load average) and the CPU-time column tell how much of
the two cores the run actually had.
"""

from __future__ import annotations

import os
import resource
import statistics
import sys
import tempfile
import time
import zlib
from pathlib import Path

TARGET_FPS = 4.0
TARGET_RSS_MB = 1500.0


def _stage_rows(frames: int) -> list[dict]:
    import numpy as np

    from robustbench3d.kitti.image import encode_png
    from robustbench3d.synth.annotate import annotate
    from robustbench3d.synth.camera import render_image
    from robustbench3d.synth.frame import SynthFrame, frame_generators
    from robustbench3d.synth.layout import sample_scene
    from robustbench3d.synth.lidar import simulate_scan
    from robustbench3d.synth.raytrace import SceneGeometry
    from robustbench3d.synth.writer import PNG_COMPRESS_LEVEL, PNG_STRATEGY, write_frame

    times: dict[str, list[float]] = {}

    def lap(name: str, t0: float) -> float:
        t = time.process_time()
        times.setdefault(name, []).append(t - t0)
        return t

    with tempfile.TemporaryDirectory() as tmp:
        for i in range(frames + 1):  # frame 0 warms caches (camera rays, textures)
            scene_rng, lidar_rng, camera_rng = frame_generators(12345, i)
            t = time.process_time()
            scene = sample_scene(scene_rng)
            t = lap("scene sampling (meshes, layout)", t)
            geometry = SceneGeometry(scene)
            geometry.intersect(np.zeros(3), np.array([[1.0, 0.0, 0.0]]))  # BVH build happens on first use
            t = lap("Embree geometry + BVH", t)
            scan, point_object = simulate_scan(scene, geometry, lidar_rng)
            t = lap("LiDAR scan", t)
            image, object_id = render_image(scene, geometry, camera_rng)
            t = lap("camera image", t)
            labels, records = annotate(scene, geometry, object_id, point_object)
            t = lap("labels (truncation, occlusion)", t)
            encode_png(image, PNG_COMPRESS_LEVEL, PNG_STRATEGY)
            t = lap("PNG encoding", t)
            frame = SynthFrame(image, scan, scene.calib, labels, scene, object_id, point_object, records)
            write_frame(Path(tmp), i, frame)  # encodes the PNG again, subtracted below
            lap("file writes", t)
            times["file writes"][-1] -= times["PNG encoding"][-1]
            if i == 0:
                times.clear()
    rows = [{"case": name, "ms_per_frame": 1e3 * statistics.median(vals), "frames": len(vals)}
            for name, vals in times.items()]
    total = sum(r["ms_per_frame"] for r in rows)
    rows.append({"case": "one frame, all stages (CPU)", "ms_per_frame": total, "frames": frames,
                 "frames_per_s": 1e3 / total})
    return rows


def _png_rows() -> list[dict]:
    import io

    from PIL import Image

    from robustbench3d.synth.frame import generate_frame

    image = generate_frame(12345, 1).image
    rows = []
    for level, strategy, name in ((0, zlib.Z_DEFAULT_STRATEGY, "stored"), (1, zlib.Z_DEFAULT_STRATEGY, "default"),
                                  (6, zlib.Z_DEFAULT_STRATEGY, "default"), (1, zlib.Z_RLE, "rle"),
                                  (1, zlib.Z_HUFFMAN_ONLY, "huffman (used)")):
        ts = []
        for _ in range(3):
            buf = io.BytesIO()
            t = time.process_time()
            Image.fromarray(image).save(buf, format="PNG", compress_level=level, compress_type=strategy)
            ts.append(time.process_time() - t)
        rows.append({"case": f"PNG level {level} {name}", "ms_per_frame": 1e3 * min(ts),
                     "kb_per_frame": len(buf.getvalue()) / 1024})
    return rows


def _end_to_end_rows(frames: int, workers_list: tuple[int, ...]) -> list[dict]:
    from robustbench3d.bench import run_timed_subprocess

    rows = []
    for workers in workers_list:
        with tempfile.TemporaryDirectory() as tmp:
            load = os.getloadavg()[0]
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            m = run_timed_subprocess([sys.executable, "-m", "robustbench3d", "data", "synth", "--out", tmp,
                                      "--frames", str(frames), "--seed", "2024", "--workers", str(workers),
                                      "--no-progress"])
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
        fps = frames / m.seconds
        # CPU seconds of all processes (start-up included): the rate two otherwise idle cores would give
        row = {"case": f"data synth, {workers} worker{'s' if workers > 1 else ''}, {frames} frames",
               "frames_per_s": fps, "cpu_ms_per_frame": 1e3 * cpu / frames,
               "fps_if_2_idle_cores": 2 * frames / cpu, "peak_rss_mb": m.peak_rss_mb, "load_before": load}
        if workers == 2:
            row.update(target=f">= {TARGET_FPS:g} frames/s, <= {TARGET_RSS_MB:g} MB", met=bool(
                fps >= TARGET_FPS and m.peak_rss_mb <= TARGET_RSS_MB))
        else:
            row.update(target=f"<= {TARGET_RSS_MB:g} MB", met=bool(m.peak_rss_mb <= TARGET_RSS_MB))
        rows.append(row)
    return rows


def run(quick: bool = False) -> list[dict]:
    """Benchmark rows (see the module docstring)."""
    rows = _stage_rows(3 if quick else 10)
    if not quick:
        rows += _png_rows()
    rows += _end_to_end_rows(6 if quick else 60, (2,) if quick else (1, 2))
    return rows
