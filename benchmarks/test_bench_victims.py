"""The victim's networks: the 2D detector, the frustum stages (torch) and the onnxruntime stages.

Victim: the shipped ``fpointnet-v1-lite`` (torch) and its shipped ONNX export (onnxruntime, one
intra-op thread); inputs from two procedural frames (seed 0) as the parity check builds them
(:func:`robustbench3d.victims.onnx.parity.stage_inputs`), each stage at its fixed batch.
"""

from __future__ import annotations

import importlib.util
from typing import Any

import numpy as np
import pytest

pytestmark = pytest.mark.bench

TORCH_STAGES = ("segmentation", "center_delta", "box_output")
ONNX_STAGES = ("detector_2d", "instance_segmentation", "center_regression", "box_estimation")


def test_yolo_detect_frame(benchmark: Any, cascade: Any, kitti_frames: list[Any]) -> None:
    """2D detection of one frame by the torch YOLO stage: letterbox, network, decoding, NMS."""
    image = kitti_frames[0].image
    out = benchmark(lambda: cascade.yolo.detect([image]))
    assert len(out) == 1


def test_fpointnet_frame_gt(benchmark: Any, cascade: Any, kitti_frames: list[Any]) -> None:
    """One frame with GT proposals through the torch cascade: frustum extraction, the three stages, decoding."""
    frame = kitti_frames[0]
    rows = benchmark(lambda: cascade.detect([frame], "gt"))
    assert len(rows) == 1


@pytest.mark.parametrize("stage", TORCH_STAGES)
def test_fpointnet_stage(benchmark: Any, cascade: Any, stage_inputs: dict[str, list[np.ndarray]], stage: str) -> None:
    """One torch frustum stage on the frustums of both frames (at most the parity check's 32)."""
    from robustbench3d.victims.fpointnet.model import TorchFrustumStages
    from robustbench3d.victims.onnx.manifest import BOX, CENTER, SEGMENTATION

    stages = TorchFrustumStages(cascade.fpn)
    key = {"segmentation": SEGMENTATION, "center_delta": CENTER, "box_output": BOX}[stage]
    inputs = stage_inputs[key]
    out = benchmark(lambda: getattr(stages, stage)(*inputs))
    assert len(out) == len(inputs[0]) and np.isfinite(out).all()


@pytest.fixture(scope="module")
def onnx_cascade() -> Any:
    """The shipped ONNX export of ``fpointnet-v1-lite`` (sessions with one intra-op thread)."""
    from robustbench3d.victims.onnx.registration import SHIPPED
    from robustbench3d.victims.onnx.runtime import OnnxCascade
    from robustbench3d.victims.shipped import weights_dir

    return OnnxCascade(weights_dir() / SHIPPED["fpointnet-v1-lite-onnx"], threads=1)


@pytest.mark.skipif(importlib.util.find_spec("onnxruntime") is None, reason="onnxruntime not installed")
@pytest.mark.parametrize("stage", ONNX_STAGES)
def test_onnx_stage(benchmark: Any, onnx_cascade: Any, stage_inputs: dict[str, list[np.ndarray]], stage: str) -> None:
    """One onnxruntime stage of the shipped export at its fixed batch."""
    session = onnx_cascade.stages[stage]
    batch = [x[:session.batch_size] for x in stage_inputs[stage]]
    assert len(batch[0]) == session.batch_size, f"fewer than {session.batch_size} inputs for {stage}"
    out = benchmark(lambda: session.run(*batch))
    assert all(np.isfinite(o).all() for o in out)
