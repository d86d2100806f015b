"""The PointPillars network as one fixed-shape ONNX graph (the ONNX twin), and torch-vs-onnxruntime parity.

Graph ``pointpillars.onnx``: inputs ``features`` (P_max, M, 9), ``coords`` (P_max, 2) and ``mask`` (P_max, M),
all float32 (coordinates and mask cast inside the graph; float32 holds every pillar index exactly), output
``output`` (1, 9, H, W). The runtime pads a scan's P <= P_max pillars with zero features, an all-False mask
and coordinates (ny, 0), which land in the spare canvas row the scatter drops
(:func:`~robustbench3d.victims.pointpillars.model.scatter_to_bev`), so padding changes nothing.
Everything else -- cropping, pillarisation, decoding -- is the numpy glue the torch victim runs
(:mod:`~robustbench3d.victims.pointpillars.glue`).

The export reuses the cascade exporter's pieces (:mod:`robustbench3d.victims.onnx.export`: exporter call,
metadata stripping, checker, deterministic serialisation, fixed-shape float32 I/O check), so the same
weights, exporter, opset and library versions give the same bytes.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from robustbench3d import __version__
from robustbench3d.errors import RobustBenchError
from robustbench3d.fileio import atomic_write_bytes, atomic_write_text
from robustbench3d.kitti.dataset import Frame
from robustbench3d.kitti.labels import Labels
from robustbench3d.victims.onnx import MANIFEST_FILE
from robustbench3d.victims.onnx.export import (
    StageModule,
    canonical_bytes,
    export_proto,
    exporter_record,
    graph_io,
)
from robustbench3d.victims.onnx.manifest import POINTPILLARS_FORMAT, StageSpec
from robustbench3d.victims.onnx.options import ExportOptions
from robustbench3d.victims.onnx.pointpillars import GRAPH_FILE, GRAPH_INPUTS, GRAPH_OUTPUT
from robustbench3d.victims.pointpillars.detector import PointPillarsDetector
from robustbench3d.victims.pointpillars.model import PointPillars
from robustbench3d.victims.pointpillars.pillars import NUM_POINT_FEATURES

#: Default fixed pillar count of the graph: the embedded scans fill about 2,500 pillars of the field of
#: view; an attacked scan adds a few hundred at most.
DEFAULT_MAX_PILLARS = 12_000
#: Range of ``max_pillars``: the grid's field of view holds about 33,000 pillars (0.32 m); the graph's
#: first activation is max_pillars x 32 x 64 float32 (8 KiB a pillar).
MAX_PILLARS_RANGE = (256, 60_000)


class GraphModule(nn.Module):
    """The network with float32 coordinates and mask (cast to int64 / bool inside), batch 1."""

    def __init__(self, model: PointPillars):
        super().__init__()
        self.model = model

    def forward(self, features: torch.Tensor, coords: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return self.model(features, coords.to(torch.int64), mask > 0.5)


def export_pointpillars(victim: PointPillarsDetector, out: str | Path, options: ExportOptions, *,
                        max_pillars: int = DEFAULT_MAX_PILLARS, source: dict[str, Any] | None = None,
                        reproduce_command: str = "") -> Path:
    """Write ``out/pointpillars.onnx`` and then ``out/manifest.json`` (an old manifest is removed first, so an
    interrupted export never passes as complete); returns the manifest path. ``source``: what was exported;
    ``reproduce_command``: the command line that rebuilds the directory."""
    lo, hi = MAX_PILLARS_RANGE
    if not lo <= max_pillars <= hi:
        raise RobustBenchError(f"max_pillars {max_pillars}: expected {lo}..{hi}")
    out = Path(out)
    model = victim.model.float().eval()
    cfg = victim.cfg
    gen = torch.Generator().manual_seed(0)
    m = cfg.grid.max_points
    coords = torch.stack([torch.randint(0, cfg.grid.ny, (max_pillars,), generator=gen),
                          torch.randint(0, cfg.grid.nx, (max_pillars,), generator=gen)], dim=1).float()
    example = (torch.randn(max_pillars, m, NUM_POINT_FEATURES, generator=gen), coords,
               (torch.rand(max_pillars, m, generator=gen) > 0.5).float())
    stage = StageModule("pointpillars", GraphModule(model).eval(), example, GRAPH_INPUTS, (GRAPH_OUTPUT,))
    data = canonical_bytes(export_proto(stage, options.exporter, options.opset), stage.name)
    import onnx

    inputs, outputs = graph_io(onnx.load_from_string(data), stage.name)
    out.mkdir(parents=True, exist_ok=True)
    (out / MANIFEST_FILE).unlink(missing_ok=True)
    atomic_write_bytes(out / GRAPH_FILE, data)
    manifest = {
        "format": POINTPILLARS_FORMAT,
        "graph": StageSpec(stage.name, GRAPH_FILE, hashlib.sha256(data).hexdigest(), inputs, outputs).to_dict(),
        "exporter": exporter_record(options),
        "config": cfg.to_dict(),
        "max_pillars": max_pillars,
        "decode": {"score_threshold": victim.options.score_threshold,
                   "max_detections": victim.options.max_detections},
        "source": source or {},
        "package_version": __version__,
        "reproduce": {"command": reproduce_command, "byte_deterministic": True,
                      "note": "The graph is byte-deterministic for the torch, onnx and onnxscript versions recorded "
                              "under 'exporter' and the same weights."},
    }
    path = out / MANIFEST_FILE
    atomic_write_text(path, json.dumps(manifest, indent=2) + "\n")
    return path


@dataclass(frozen=True)
class PointPillarsParity:
    """Torch vs onnxruntime on some frames: the largest |difference| of the output maps (all channels and
    the heatmap logits alone), detections per frame (counts equal?), the largest differences of matched
    detections' scores, locations (m), dimensions (m) and rotation_y (rad), and the Car BEV AP R40
    moderate of both (NaN without labels)."""

    frames: int
    max_output_diff: float
    max_heatmap_diff: float
    same_counts: bool
    max_score_diff: float
    max_location_diff: float
    max_dimension_diff: float
    max_rotation_diff: float
    ap_torch: float
    ap_onnx: float


def _max_abs(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b), initial=0.0))


def parity(torch_victim: PointPillarsDetector, onnx_victim: Any, frames: list[Frame],
           labels: list[Labels] | None = None) -> PointPillarsParity:
    """Compare the two victims' outputs and detections on ``frames`` (``labels`` for AP, optional).

    Detections pair up by rank (both sort by score); where the counts differ the ranks compared are
    the common prefix and ``same_counts`` is False."""
    from robustbench3d.victims.pointpillars.glue import crop_scan

    out_d = hm_d = score_d = loc_d = dim_d = rot_d = 0.0
    same = True
    dets_t, dets_o = [], []
    for f in frames:
        pts = crop_scan(f.scan, f.calib, f.image_size, torch_victim.cfg.grid)
        from robustbench3d.victims.pointpillars.glue import run_scan

        a = run_scan(torch_victim.network, pts, torch_victim.cfg)
        b = run_scan(onnx_victim.network, pts, torch_victim.cfg)
        out_d, hm_d = max(out_d, _max_abs(a, b)), max(hm_d, _max_abs(a[0], b[0]))
        dt, do = torch_victim.detect([f])[0], onnx_victim.detect([f])[0]
        dets_t.append(dt)
        dets_o.append(do)
        same &= len(dt) == len(do)
        k = min(len(dt), len(do))
        assert dt.score is not None and do.score is not None
        score_d = max(score_d, _max_abs(dt.score[:k], do.score[:k]))
        loc_d = max(loc_d, _max_abs(dt.location[:k], do.location[:k]))
        dim_d = max(dim_d, _max_abs(dt.dimensions[:k], do.dimensions[:k]))
        diff = np.abs((dt.rotation_y[:k] - do.rotation_y[:k] + np.pi) % (2 * np.pi) - np.pi)
        rot_d = max(rot_d, float(diff.max(initial=0.0)))
    ap_t = ap_o = float("nan")
    if labels is not None:
        from robustbench3d.eval.kitti_eval import evaluate

        ap_t = float(evaluate(labels, dets_t, metrics=("bev",))["Car"]["bev"]["R40"]["moderate"])
        ap_o = float(evaluate(labels, dets_o, metrics=("bev",))["Car"]["bev"]["R40"]["moderate"])
    return PointPillarsParity(len(frames), out_d, hm_d, same, score_d, loc_d, dim_d, rot_d, ap_t, ap_o)
