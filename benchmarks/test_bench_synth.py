"""Synthesis of one procedural frame (scene, Embree geometry, LiDAR scan, camera image, labels)."""

from __future__ import annotations

from typing import Any

import pytest

pytestmark = pytest.mark.bench


def test_synth_frame(benchmark: Any, rounds: Any) -> None:
    """:func:`~robustbench3d.synth.frame.generate_frame` of frame 1 of seed 12345 (frame 0 warms the caches)."""
    from robustbench3d.synth.frame import generate_frame

    generate_frame(12345, 0)
    frame = benchmark.pedantic(lambda: generate_frame(12345, 1), rounds=rounds(5))
    assert len(frame.scan) > 0 and frame.image.ndim == 3
