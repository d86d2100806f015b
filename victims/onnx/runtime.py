"""The ONNX victim: an exported F-PN cascade run by onnxruntime (CPU provider) and numpy.

:class:`OnnxCascade` implements :class:`~robustbench3d.victims.base.Detector` with the same numpy
pipeline as the torch cascade (:func:`robustbench3d.victims.fpointnet.pipeline.detect_frames`);
only the four networks run in onnxruntime. Nothing on this path imports torch.

Loading checks, each failure naming the file: the manifest (structure, all four stages, shapes
that fit the configuration), every stage file's sha256, that onnxruntime can load it (a corrupt
protobuf fails here), and that the graph's inputs and outputs are the manifest's (names, fixed
shapes, float32).

Sessions use one intra-op thread by default (``threads``, in :data:`THREADS_RANGE`), sequential
execution and onnxruntime's deterministic compute, so identical inputs give identical outputs. The
victim arguments ``seed``, ``gather`` and ``threads`` are checked before anything is read.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from robustbench3d.errors import DataFormatError
from robustbench3d.kitti.dataset import Frame
from robustbench3d.kitti.labels import Labels
from robustbench3d.victims.base import PROPOSAL_SOURCES, Proposals, ProposalsArg
from robustbench3d.victims.fpointnet.pipeline import CascadeSettings, detect_frames, make_proposals
from robustbench3d.victims.onnx import require
from robustbench3d.victims.onnx.manifest import (
    BOX,
    CENTER,
    DETECTOR_2D,
    SEGMENTATION,
    Manifest,
    StageSpec,
    TensorSpec,
    read_manifest,
    verify_files,
)
from robustbench3d.victims.yolo.config import YoloConfig
from robustbench3d.victims.yolo.postprocess import Detections2D, detect_images, head_masks

_ORT_FLOAT = "tensor(float)"
#: Range of the victim argument ``threads`` (onnxruntime intra-op threads per session). onnxruntime
#: reads 0 as "its own default" (every core: results no longer reproduce run to run in timing, and a
#: worker pool oversubscribes the machine) and refuses negatives only when a session is built, with an
#: error that reads like a corrupt stage file; 256 is past any core count a benchmark runs on.
THREADS_RANGE = (1, 256)


class OnnxStage:
    """One stage graph in an onnxruntime session: fixed batch, partial batches zero-padded."""

    def __init__(self, path: str | Path, spec: StageSpec, threads: int = 1):
        ort = require("onnxruntime")
        self.path = Path(path)
        self.spec = spec
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.use_deterministic_compute = True
        opts.log_severity_level = 3
        try:
            self.session = ort.InferenceSession(str(self.path), opts, providers=["CPUExecutionProvider"])
        except Exception as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise DataFormatError(self.path, f"onnxruntime cannot load stage {spec.name!r}: {first}") from None
        self._check(self.session.get_inputs(), spec.inputs, "inputs")
        self._check(self.session.get_outputs(), spec.outputs, "outputs")
        self.input_names = [t.name for t in spec.inputs]
        self.output_names = [t.name for t in spec.outputs]

    def _check(self, got: Sequence[Any], want: Sequence[TensorSpec], which: str) -> None:
        actual = [(v.name, tuple(v.shape), v.type) for v in got]
        expected = [(t.name, t.shape, _ORT_FLOAT) for t in want]
        if actual != expected:
            raise DataFormatError(self.path, f"stage {self.spec.name!r}: graph {which} {actual} differ from the "
                                             f"manifest's {expected}")

    @property
    def batch_size(self) -> int:
        return self.spec.batch_size

    def run(self, *arrays: np.ndarray) -> list[np.ndarray]:
        """Outputs for inputs of any leading size n (run in graph-batch chunks; n >= 1)."""
        if len(arrays) != len(self.input_names):
            raise ValueError(f"stage {self.spec.name!r} takes {len(self.input_names)} inputs, got {len(arrays)}")
        n = len(arrays[0])
        for a, t in zip(arrays, self.spec.inputs, strict=True):
            if len(a) != n or tuple(a.shape[1:]) != t.shape[1:]:
                raise ValueError(f"stage {self.spec.name!r}: input {t.name!r} of shape {a.shape} does not fit "
                                 f"(n, {', '.join(map(str, t.shape[1:]))})")
        b = self.batch_size
        parts: list[list[np.ndarray]] = [[] for _ in self.output_names]
        for start in range(0, n, b):
            feed = {}
            for name, a in zip(self.input_names, arrays, strict=True):
                chunk = np.ascontiguousarray(a[start:start + b], dtype=np.float32)
                if len(chunk) < b:
                    chunk = np.concatenate([chunk, np.zeros((b - len(chunk), *chunk.shape[1:]), np.float32)])
                feed[name] = chunk
            outs = self.session.run(self.output_names, feed)
            for i, o in enumerate(outs):
                parts[i].append(o[:min(b, n - start)])
        return [np.concatenate(p) for p in parts]


class OnnxFrustumStages:
    """:class:`~robustbench3d.victims.fpointnet.glue.FrustumStages` on onnxruntime sessions."""

    def __init__(self, segmentation: OnnxStage, center: OnnxStage, box: OnnxStage):
        self.seg, self.center, self.box = segmentation, center, box

    def segmentation(self, points: np.ndarray, one_hot: np.ndarray) -> np.ndarray:
        return self.seg.run(points, one_hot)[0]

    def center_delta(self, object_points: np.ndarray, one_hot: np.ndarray) -> np.ndarray:
        return self.center.run(object_points, one_hot)[0]

    def box_output(self, object_points: np.ndarray, one_hot: np.ndarray) -> np.ndarray:
        return self.box.run(object_points, one_hot)[0]


class OnnxCascade:
    """An ONNX victim directory as a :class:`~robustbench3d.victims.base.Detector`.

    Args:
        directory: holds ``manifest.json`` and the four stage files.
        seed: base seed of the frustum resampling (default: the exported victim's).
        gather: object-point gather, "random" or "topk" (default: the exported victim's).
        threads: onnxruntime intra-op threads per session.
    """

    supported_proposals: tuple[str, ...] = PROPOSAL_SOURCES

    def __init__(self, directory: str | Path, *, seed: int | None = None, gather: str | None = None,
                 threads: int = 1):
        from robustbench3d.victims.zoo import SEED_RANGE, gather_arg, int_arg

        if seed is not None:
            int_arg("seed", seed, *SEED_RANGE)
        if gather is not None:
            gather_arg(gather)
        threads = int_arg("threads", threads, *THREADS_RANGE)
        self.directory = Path(directory)
        self.manifest: Manifest = read_manifest(self.directory)
        verify_files(self.directory, self.manifest)
        cfg = self.manifest.config
        manifest_path = self.directory / "manifest.json"
        try:
            self.yolo_cfg = YoloConfig.from_dict(cfg["yolo"])
            settings = CascadeSettings.from_dict(cfg["settings"])
        except (TypeError, ValueError, KeyError) as exc:
            raise DataFormatError(manifest_path, f"config: {type(exc).__name__}: {exc}") from None
        overrides: dict[str, Any] = {}
        if seed is not None:
            overrides["seed"] = int(seed)
        if gather is not None:
            overrides["gather"] = gather
        self.settings = CascadeSettings.from_dict({**settings.to_dict(), **overrides})
        if "Car" not in self.yolo_cfg.class_names:
            raise DataFormatError(manifest_path, f"config: the 2D detector has no 'Car' class "
                                                 f"({self.yolo_cfg.class_names})")
        self.car_class = self.yolo_cfg.class_names.index("Car")
        heads = self.manifest.stage(DETECTOR_2D).outputs
        masks = head_masks(self.yolo_cfg)
        channels = [len(mask) * (5 + self.yolo_cfg.num_classes) for mask in masks]
        if [t.shape[1] for t in heads] != channels:
            raise DataFormatError(manifest_path, f"stage {DETECTOR_2D!r}: head channels {[t.shape[1] for t in heads]} "
                                                 f"do not fit the {self.yolo_cfg.layout!r} layout ({channels})")
        self.num_points = int(cfg["fpointnet"]["num_points"])
        self.num_object_points = int(cfg["fpointnet"]["num_object_points"])
        self.stages = {s.name: OnnxStage(self.directory / s.file, s, threads) for s in self.manifest.stages}
        self.frustum_stages = OnnxFrustumStages(self.stages[SEGMENTATION], self.stages[CENTER], self.stages[BOX])

    def run_heads(self, images: np.ndarray) -> list[np.ndarray]:
        """Raw 2D head tensors of (B, 3, H_in, W_in) letterboxed images."""
        return self.stages[DETECTOR_2D].run(images)

    def detect_2d(self, images: Sequence[np.ndarray]) -> list[Detections2D]:
        """2D detections of (H, W, 3) uint8 images (original pixels)."""
        return detect_images(images, self.run_heads, self.yolo_cfg, self.stages[DETECTOR_2D].batch_size)

    def proposals(self, frames: Sequence[Frame], source: ProposalsArg) -> list[Proposals]:
        """2D proposals per frame, as :meth:`FPointNetCascade.proposals`."""
        return make_proposals(frames, source, self.detect_2d, self.car_class, self.settings.gt_types)

    def detect(self, frames: Sequence[Frame], proposals: ProposalsArg = "detector") -> list[Labels]:
        """KITTI Car rows per frame (rect frame; score = 2D score, or the 3D score for GT boxes,
        i.e. proposals with ``source`` "gt", "gt-object" or "gt-append"; the last adds each box's
        ``extra_points`` to its frustum), as :meth:`FPointNetCascade.detect`."""
        return detect_frames(frames, proposals, detect_2d=self.detect_2d, car_class=self.car_class,
                             stages=self.frustum_stages, settings=self.settings, num_points=self.num_points,
                             num_object_points=self.num_object_points)
