"""The compiled letterbox resize equals its numpy reference bit for bit; a frustum drawn from the FOV rows
equals the whole-scan mask."""

from __future__ import annotations

import numpy as np
import pytest

from robustbench3d.testing import SIMPLE_CALIB
from robustbench3d.victims.fpointnet.frustum import ProjectedScan, box_mask, extract_frustum
from robustbench3d.victims.yolo import preprocess


@pytest.mark.parametrize(("shape", "axis", "size"), [((3, 375, 1242), 2, 960), ((3, 375, 960), 1, 290),
                                                     ((3, 40, 50), 2, 120), ((3, 41, 50), 1, 7),
                                                     ((2, 5, 9), 2, 1), ((1, 1, 1), 1, 3)])
def test_compiled_resize_equals_the_numpy_taps(shape: tuple[int, ...], axis: int, size: int) -> None:
    rng = np.random.default_rng(sum(shape) + size)
    x = rng.integers(0, 256, size=shape).astype(np.float32) / np.float32(255.0)
    x[..., ::7] = 0.5  # flat runs, as the letterbox fill
    got, want = preprocess._resize_axis(x, axis, size), preprocess._resize_axis_numpy(x, axis, size)
    assert got.dtype == want.dtype == np.float32 and got.shape == want.shape
    assert got.tobytes() == want.tobytes()


def test_letterbox_of_an_image_uses_the_compiled_taps_with_the_reference_bits() -> None:
    rng = np.random.default_rng(1)
    image = rng.integers(0, 256, size=(375, 1242, 3), dtype=np.uint8)
    canvas, geo = preprocess.letterbox_image(image, (960, 288))
    x = np.ascontiguousarray(image.transpose(2, 0, 1), dtype=np.float32) / np.float32(255.0)
    rw, rh = geo.resized
    ref = preprocess._resize_axis_numpy(preprocess._resize_axis_numpy(x, 2, rw), 1, rh)
    px, py = geo.pad
    assert canvas[:, py:py + rh, px:px + rw].tobytes() == ref.tobytes()


def test_a_frustum_from_the_fov_rows_equals_the_whole_scan_mask() -> None:
    rng = np.random.default_rng(2)
    n = 5000
    uv = rng.uniform(-100, 1400, size=(n, 2))
    uv[:50] = [[300.0, 100.0]] * 50  # on the box's edges: half-open
    uv[50:60] = [[500.0, 200.0]] * 10
    in_fov = rng.random(n) < 0.7
    proj = ProjectedScan(rng.normal(size=(n, 4)), uv, in_fov, in_fov | (rng.random(n) < 0.5))
    for box in ([300.0, 100.0, 500.0, 200.0], [0.0, 0.0, 1242.0, 375.0], [700.0, 50.0, 700.5, 60.0]):
        got = extract_frustum(proj, np.array(box), SIMPLE_CALIB)
        want = np.flatnonzero(in_fov & box_mask(uv, np.array(box)))
        assert got.indices.dtype == np.int64 and np.array_equal(got.indices, want)
        assert np.array_equal(got.points, proj.points_rect[want])
