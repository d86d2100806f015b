"""The PointPillars ONNX twin: the exported graph (:mod:`.pointpillars_export`) run by onnxruntime, with the numpy glue
of the torch victim (:mod:`robustbench3d.victims.pointpillars.glue`). Nothing on this path imports torch.

Directory layout: ``manifest.json`` (format :data:`~robustbench3d.victims.onnx.manifest.POINTPILLARS_FORMAT`:
``graph`` {name, file, sha256, inputs, outputs}, ``config`` (the network's), ``max_pillars``, ``decode``
{score_threshold, max_detections}, ``exporter``, ``source``, ``package_version``) and ``pointpillars.onnx``.
Loading checks the manifest, the graph file's sha256, that onnxruntime loads it and that its inputs and
outputs are the manifest's (:class:`~robustbench3d.victims.onnx.runtime.OnnxStage`); each failure names the file.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.fileio import read_user_text, sha256_file
from robustbench3d.kitti.dataset import Frame
from robustbench3d.kitti.labels import Labels
from robustbench3d.victims.base import ProposalsArg
from robustbench3d.victims.onnx import MANIFEST_FILE
from robustbench3d.victims.onnx.manifest import POINTPILLARS_FORMAT, stage_spec
from robustbench3d.victims.pointpillars.config import PointPillarsConfig, output_shape
from robustbench3d.victims.pointpillars.glue import DecodeOptions, check_args, crop_scan, decode_output, run_scan

GRAPH_FILE = "pointpillars.onnx"
GRAPH_INPUTS: tuple[str, ...] = ("features", "coords", "mask")
GRAPH_OUTPUT = "output"


class PointPillarsOnnx:
    """:class:`~robustbench3d.victims.base.Detector` of a PointPillars ONNX directory (``threads``: onnxruntime
    intra-op threads; ``score_threshold`` / ``max_detections`` default to the manifest's ``decode``)."""

    supported_proposals: tuple[str, ...] = ("detector",)

    def __init__(self, directory: str | Path, *, threads: int = 1, score_threshold: float | None = None,
                 max_detections: int | None = None):
        from robustbench3d.victims.onnx.runtime import THREADS_RANGE, OnnxStage

        lo, hi = THREADS_RANGE
        if isinstance(threads, bool) or not isinstance(threads, int) or not lo <= threads <= hi:
            raise RobustBenchError(f"victim argument 'threads': {threads!r} is not an integer in [{lo}, {hi}]")
        self.directory = Path(directory)
        path = self.directory / MANIFEST_FILE
        try:
            data = json.loads(read_user_text(path))
        except FileNotFoundError:
            raise DataFormatError(path, "missing; write it with the PointPillars ONNX export") from None
        except json.JSONDecodeError as exc:
            raise DataFormatError(path, f"not valid JSON ({exc})") from None
        if not isinstance(data, dict) or data.get("format") != POINTPILLARS_FORMAT:
            raise DataFormatError(path, f"field 'format': expected {POINTPILLARS_FORMAT!r}")
        try:
            self.cfg = PointPillarsConfig.from_dict(data["config"])
            self.max_pillars = int(data["max_pillars"])
            decode = data["decode"]
            options = check_args(decode["score_threshold"] if score_threshold is None else score_threshold,
                                 decode["max_detections"] if max_detections is None else max_detections)
        except (KeyError, TypeError, ValueError) as exc:
            raise DataFormatError(path, f"config / max_pillars / decode unusable ({type(exc).__name__}: "
                                        f"{exc})") from None
        self.options: DecodeOptions = options
        spec = stage_spec(data.get("graph"), "graph", path)
        graph = self.directory / spec.file
        if not graph.is_file():
            raise DataFormatError(graph, "graph file missing")
        if sha256_file(graph) != spec.sha256:
            raise DataFormatError(graph, f"sha256 does not match the manifest's {spec.sha256} (file changed or "
                                         "corrupt; re-export it)")
        m, (h, w) = self.cfg.grid.max_points, output_shape(self.cfg)
        want = [(n, s) for n, s in zip(GRAPH_INPUTS, [(self.max_pillars, m, 9), (self.max_pillars, 2),
                                                      (self.max_pillars, m)], strict=True)]
        got = [(t.name, t.shape) for t in spec.inputs]
        if got != want or [(t.name, t.shape) for t in spec.outputs] != [(GRAPH_OUTPUT, (1, 9, h, w))]:
            raise DataFormatError(path, f"graph inputs/outputs {got} do not fit the configuration ({want})")
        self.stage = OnnxStage(graph, spec, threads)

    def network(self, feats: np.ndarray, coords: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """(9, H, W) output of the graph on the glue's inputs, padded to ``max_pillars``."""
        p = len(feats)
        if p > self.max_pillars:
            raise RobustBenchError(f"{self.directory}: the scan fills {p} pillars, more than the graph's "
                                   f"max_pillars {self.max_pillars}; re-export with a larger max_pillars")
        pad = self.max_pillars - p
        f = np.concatenate([feats, np.zeros((pad, *feats.shape[1:]), np.float32)])
        c = np.concatenate([coords, np.tile([[self.cfg.grid.ny, 0]], (pad, 1))]).astype(np.float32)
        k = np.concatenate([mask, np.zeros((pad, mask.shape[1]), bool)]).astype(np.float32)
        return self.stage.run(f, c, k)[0][0]

    def detect(self, frames: Sequence[Frame], proposals: ProposalsArg = "detector") -> list[Labels]:
        """As :meth:`~robustbench3d.victims.pointpillars.detector.PointPillarsDetector.detect`."""
        if proposals != "detector":
            raise ValueError("pointpillars-onnx finds its own objects: proposals must be 'detector'")
        out = []
        for f in frames:
            o = run_scan(self.network, crop_scan(f.scan, f.calib, f.image_size, self.cfg.grid), self.cfg)
            out.append(decode_output(o, self.cfg, f.calib, f.image_size, self.options))
        return out
