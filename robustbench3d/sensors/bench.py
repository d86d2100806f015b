"""``robustbench3d bench lidar``: the LiDAR object render of attacked frames against Embree, side by side.

The render is the call an attack's ``apply`` makes (:meth:`robustbench3d.attacks.roof.RoofObjectAttack.apply`):
:func:`~robustbench3d.sensors.lidar_render.render_lidar` of the shipped ``adv-object`` placed on every target car
of the first val frames of the embedded dataset (velodyne frame, the attack's own placement, no noise or dropout),
each scan's beam pattern read from a warm disk cache into a cold memory one (as a cell meets each frame once).
Embree's cost is a scene built from the same triangles (float32) and one ``EmbreeScene.run`` of the same culled
rays (the union of the meshes' culls, float32, converted beforehand: the reference pays no conversion).

Both run in a worker process, interleaved round by round (render, Embree); the table gives per frame the median
render and Embree milliseconds and the median of the rounds' ratios (target: render <= :data:`TARGET_EMBREE_RATIO`
x Embree). With :data:`BASELINE_ENV` set to another installation's Python (e.g. a checkout of an older commit),
the same worker code runs there too, interleaved with the others, and the table adds the median ratio of the
render to that baseline's and whether both renders gave the same bytes (a sha256 of every output array).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
from dataclasses import dataclass
from typing import Any

#: Render of an attacked frame / Embree build + cast of its culled rays (issue #34).
TARGET_EMBREE_RATIO = 1.5
#: Environment variable naming a baseline Python interpreter (its ``robustbench3d`` is timed beside this one).
BASELINE_ENV = "ROBUSTBENCH3D_BENCH_LIDAR_BASELINE"

# The worker: standard library + robustbench3d's public attack and sensor API only, so that an older installation
# runs it unchanged. Commands on stdin ("render", "embree", "digest", "quit"), one JSON line per answer on stdout.
_WORKER = r'''
import hashlib, json, sys, tempfile, time
from robustbench3d.runner.shards import worker_setup
worker_setup()
import numpy as np
import torch
torch.set_num_threads(1)
from robustbench3d.attacks import create_attack
from robustbench3d.attacks.base import target_cars
from robustbench3d.datasets import resolve_dataset
from robustbench3d.sensors import lidar_render as lr
from robustbench3d.sensors.pattern_cache import PatternCache

frames = int(sys.argv[1])
kitti = resolve_dataset(None, "val", lazy=True, max_frames=frames, progress=False).kitti()
attack = create_attack("adv-object")
calls = []
for i, fid in enumerate(kitti.frame_ids[:frames]):
    frame = kitti.frame(fid)
    placed = attack.place(target_cars(frame.labels), np.random.default_rng(i))
    faces, colors = attack.obj.faces.copy(), attack.obj.colors.copy()
    calls.append((frame.scan, [(frame.calib.rect_to_velo_points(v), faces, colors) for v, _ in placed]))
directory = tempfile.mkdtemp(prefix="rb3d-bench-lidar-")

def render_all():
    return [lr.render_lidar(scan, meshes, patterns=PatternCache(directory)) for scan, meshes in calls]

def embree_rays():
    out = []
    for scan, meshes in calls:
        prep, mts, culls = lr._prepared(scan, meshes, None, PatternCache(directory))[:3]
        idx = np.unique(np.concatenate(culls))
        origins, dirs = prep.pattern.ray_geometry(idx)
        offset = np.cumsum([0] + [len(v) for v, _, _ in meshes])[:-1]
        out.append((np.ascontiguousarray(np.concatenate([v for v, _, _ in meshes]), np.float32),
                    np.ascontiguousarray(np.concatenate([f + o for (_, f, _), o in zip(meshes, offset)]), np.int32),
                    np.ascontiguousarray(origins, np.float32), np.ascontiguousarray(dirs, np.float32), len(idx)))
    return out

render_all()  # compiles the kernels, writes the pattern files
rays = None
for line in sys.stdin:
    cmd = line.strip()
    if cmd == "render":
        c, t = time.process_time(), time.perf_counter()
        render_all()
        answer = {"s": time.perf_counter() - t, "cpu": time.process_time() - c}
    elif cmd == "embree":
        from embreex import rtcore, rtcore_scene
        from embreex.mesh_construction import TriangleMesh
        if rays is None:
            rays, device = embree_rays(), rtcore.EmbreeDevice()
        c, t = time.process_time(), time.perf_counter()
        for v, f, o, d, _ in rays:
            scene = rtcore_scene.EmbreeScene(device)
            TriangleMesh(scene, v, f)
            scene.run(o, d, output=1)
        answer = {"s": time.perf_counter() - t, "cpu": time.process_time() - c, "rays": sum(r[4] for r in rays),
                  "faces": sum(len(r[1]) for r in rays)}
    elif cmd == "digest":
        h = hashlib.sha256()
        for r in render_all():
            for a in (r.scan, r.added, r.removed_index, r.object_index, r.face_index, r.ray_index):
                h.update(np.ascontiguousarray(a).tobytes())
        answer = {"sha256": h.hexdigest(), "package": lr.__file__}
    else:
        break
    print(json.dumps(answer), flush=True)
'''


@dataclass
class _Worker:
    """One worker process running :data:`_WORKER` under ``python``."""

    python: str
    frames: int

    def __post_init__(self) -> None:
        # -P: the working directory is not put on sys.path (a checkout there would shadow the interpreter's own)
        self.proc = subprocess.Popen([self.python, "-P", "-c", _WORKER, str(self.frames)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONHASHSEED": "0"})

    def ask(self, cmd: str) -> dict[str, Any]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(cmd + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"bench lidar: the worker under {self.python} stopped (exit {self.proc.wait()})")
        return json.loads(line)

    def close(self) -> None:
        """Ends the worker (its loop stops at end of input)."""
        if self.proc.stdin is not None and not self.proc.stdin.closed:
            self.proc.stdin.close()
        self.proc.wait()


def _median_ratio(a: list[float], b: list[float]) -> float:
    return statistics.median(x / y for x, y in zip(a, b, strict=True))


def measure(frames: int, rounds: int, baseline: str | None = None) -> dict[str, Any]:
    """``rounds`` interleaved rounds (the order alternating round by round) of the render and Embree (and the
    baseline's render): per frame the median CPU and wall ms of each (``render_cpu_ms``, ``embree_wall_ms``, ...),
    the medians of the rounds' ratios (``render_over_embree_cpu``, ``..._wall``, ``render_over_baseline_cpu``,
    ...), and with a baseline whether its outputs are the same bytes (``same_bytes``) and its package path."""
    workers = [_Worker(sys.executable, frames)] + ([_Worker(baseline, frames)] if baseline else [])
    try:
        steps = [("render", 0, "render"), ("embree", 0, "embree")] + ([("baseline", 1, "render")] if baseline else [])
        got: dict[str, list[dict[str, Any]]] = {name: [] for name, _, _ in steps}
        for r in range(rounds):
            for name, w, cmd in steps if r % 2 == 0 else steps[::-1]:
                got[name].append(workers[w].ask(cmd))
        out: dict[str, Any] = {"frames": frames, "rounds": rounds, "rays": got["embree"][0]["rays"],
                               "faces": got["embree"][0]["faces"]}
        for name, answers in got.items():
            for clock, key in (("cpu", "cpu"), ("wall", "s")):
                out[f"{name}_{clock}_ms"] = 1e3 * statistics.median(a[key] for a in answers) / frames
        for other in [n for n in got if n != "render"]:
            for clock, key in (("cpu", "cpu"), ("wall", "s")):
                out[f"render_over_{other}_{clock}"] = _median_ratio([a[key] for a in got["render"]],
                                                                   [a[key] for a in got[other]])
        if baseline:
            digests = [w.ask("digest") for w in workers]
            out["same_bytes"] = digests[0]["sha256"] == digests[1]["sha256"]
            out["baseline_package"] = digests[1]["package"]
        return out
    finally:
        for w in workers:
            w.close()


def run(quick: bool) -> list[dict]:
    """Rows of ``robustbench3d bench lidar`` (module docstring): CPU ms (wall beside them), ratios of CPU time."""
    baseline = os.environ.get(BASELINE_ENV) or None
    m = measure(8 if quick else 40, 5 if quick else 15, baseline)
    ratio = m["render_over_embree_cpu"]
    rows = [{"case": f"LiDAR object render / Embree build+cast, {m['frames']} attacked val frames, "
                     f"{m['rays'] // m['frames']} rays and {m['faces'] // m['frames']} faces per frame",
             "render_ms": round(m["render_cpu_ms"], 2), "other_ms": round(m["embree_cpu_ms"], 2),
             "ratio": round(ratio, 2), "wall_ratio": round(m["render_over_embree_wall"], 2),
             "target": f"<= {TARGET_EMBREE_RATIO:g}x", "met": ratio <= TARGET_EMBREE_RATIO}]
    if baseline:
        rows.append({"case": f"LiDAR object render / the baseline's ({m['baseline_package']})",
                     "render_ms": round(m["render_cpu_ms"], 2), "other_ms": round(m["baseline_cpu_ms"], 2),
                     "ratio": round(m["render_over_baseline_cpu"], 3),
                     "wall_ratio": round(m["render_over_baseline_wall"], 3), "same_bytes": m["same_bytes"]})
    return rows
