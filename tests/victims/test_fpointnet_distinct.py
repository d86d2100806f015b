"""The distinct-point F-PN stages equal the networks run as defined, bit for bit (one intra-op thread, the
runner's setting), on the shipped weights over val frames, and the kernel properties that equality rests on."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
import torch

from robustbench3d.datasets import resolve_dataset
from robustbench3d.victims.cascade import FPointNetCascade
from robustbench3d.victims.fpointnet.distinct_stages import (
    COLUMN_BLOCK,
    DistinctPointStages,
    distinct_columns,
    fc_rows,
)
from robustbench3d.victims.fpointnet.model import TorchFrustumStages, build_model
from robustbench3d.victims.fpointnet.pipeline import detect_frames
from robustbench3d.victims.shipped import shipped


@pytest.fixture(autouse=True)
def one_thread() -> Iterator[None]:
    saved = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(saved)


@pytest.fixture(scope="module", params=["fpointnet-v1-lite", "fpointnet-v1"])
def victim(request: pytest.FixtureRequest) -> FPointNetCascade:
    weights = shipped(request.param)
    assert weights is not None
    return FPointNetCascade.load(weights.path)


@pytest.fixture(scope="module")
def val_frames(shared_split) -> list:
    """Three procedural frames (seed 0, all val: the embedded dataset's generator, never trained on)."""
    root = shared_split(3, seed=0, val_fraction=1.0)
    kitti = resolve_dataset(root, "val", progress=False).kitti()
    return [kitti[i] for i in range(len(kitti))]


def _reference_detect(victim: FPointNetCascade, frames: list, proposals: str) -> list:
    return detect_frames(frames, proposals, detect_2d=victim.yolo.detect, car_class=victim.car_class,
                         stages=TorchFrustumStages(victim.fpn), settings=victim.settings,
                         num_points=victim.num_points, num_object_points=victim.fpn.cfg.num_object_points)


@pytest.mark.parametrize("proposals", ["detector", "gt"])
def test_detect_equals_the_networks_run_one_frustum_at_a_time(victim: FPointNetCascade, val_frames: list,
                                                              proposals: str) -> None:
    frames = val_frames
    got = victim.detect(frames, proposals)
    want = _reference_detect(victim, frames, proposals)
    assert sum(len(w) for w in want) > 10
    for g, w in zip(got, want, strict=True):
        for field in ("type", "alpha", "bbox", "dimensions", "location", "rotation_y", "score"):
            np.testing.assert_array_equal(getattr(g, field), getattr(w, field))


def _frustums(rng: np.random.Generator, b: int, n: int, c: int, distinct: list[int]) -> np.ndarray:
    """(b, n, c) float32 frustums, frustum i drawn with replacement from ``distinct[i]`` rows."""
    out = np.empty((b, n, c), dtype=np.float32)
    for i in range(b):
        pool = rng.normal(scale=5.0, size=(distinct[i], c)).astype(np.float32)
        out[i] = pool[rng.integers(0, distinct[i], n)]
    return out


@pytest.mark.parametrize("distinct", [[1, 512, 37, 200], [511, 3], [64]])
def test_every_stage_equals_the_reference_on_repeated_and_distinct_points(victim: FPointNetCascade,
                                                                           distinct: list[int]) -> None:
    rng = np.random.default_rng(len(distinct))
    b, n = len(distinct), victim.num_points
    one_hot = np.tile(np.float32([1, 0, 0]), (b, 1))
    fast, ref = DistinctPointStages(victim.fpn), TorchFrustumStages(victim.fpn)
    points = _frustums(rng, b, n, 4, [min(d, n) for d in distinct])
    np.testing.assert_array_equal(fast.segmentation(points, one_hot), ref.segmentation(points, one_hot))
    obj = _frustums(rng, b, 512, 3, distinct)
    np.testing.assert_array_equal(fast.center_delta(obj, one_hot), ref.center_delta(obj, one_hot))
    np.testing.assert_array_equal(fast.box_output(obj, one_hot), ref.box_output(obj, one_hot))


def test_distinct_columns_hold_each_distinct_row_once_and_invert() -> None:
    rng = np.random.default_rng(3)
    rows = _frustums(rng, 3, 50, 4, [5, 50, 1])
    rows[0, 0, 0] = -0.0  # +0 and -0 are different bytes, so different columns
    rows[0, 1] = rows[0, 0]
    rows[0, 1, 0] = 0.0
    lay = distinct_columns(rows)
    for i in range(3):
        brute = {r.tobytes() for r in rows[i]}
        assert lay.starts[i + 1] - lay.starts[i] == len(brute)
    assert lay.columns.shape[2] % COLUMN_BLOCK == 0
    assert lay.columns.shape[2] - lay.starts[-1] < COLUMN_BLOCK
    cols = lay.columns[0].numpy()
    for i in range(3):
        assert cols[:, lay.inverse[i]].T.tobytes() == rows[i].tobytes()
        assert np.all((lay.inverse[i] >= lay.starts[i]) & (lay.inverse[i] < lay.starts[i + 1]))


@pytest.mark.parametrize("length", [COLUMN_BLOCK, 3 * COLUMN_BLOCK, 8 * COLUMN_BLOCK, 37 * COLUMN_BLOCK])
def test_a_point_s_convolution_result_does_not_depend_on_its_column(victim: FPointNetCascade,
                                                                   length: int) -> None:
    """The kernel property: 1x1-convolution stacks of every network give a point the bits of its
    (1, C, N) reference at any column of a (1, C, L) input with L a multiple of COLUMN_BLOCK."""
    rng = np.random.default_rng(length)
    net = victim.fpn
    head = torch.nn.Sequential(*net.seg.head, net.seg.classifier)
    for stack, c, n in ((net.seg.point_mlp, 4, net.cfg.num_points), (net.seg.global_mlp, 64, net.cfg.num_points),
                        (head, net.seg.head[0].in_channels, net.cfg.num_points), (net.tnet.mlp, 3, 512),
                        (net.box.mlp, 3, 512)):
        x = torch.from_numpy(rng.normal(scale=3.0, size=(1, c, n)).astype(np.float32))
        k = min(n, length)
        chosen, where = rng.choice(n, k, replace=False), rng.permutation(length)[:k]
        y = torch.from_numpy(rng.normal(size=(1, c, length)).astype(np.float32))
        y[:, :, where] = x[:, :, chosen]
        with torch.inference_mode():
            assert torch.equal(stack(y)[:, :, where], stack(x)[:, :, chosen])


def test_fc_rows_equal_linear_on_one_row_batches(victim: FPointNetCascade) -> None:
    rng = np.random.default_rng(5)
    for net in (victim.fpn.tnet, victim.fpn.box):
        x = torch.from_numpy(rng.normal(size=(9, net.fc[0].in_features)).astype(np.float32))
        with torch.inference_mode():
            want = torch.cat([net.out(net.fc(x[i:i + 1])) for i in range(len(x))])
            assert torch.equal(fc_rows(net.out, fc_rows(net.fc, x)), want)


def test_a_rows_layout_network_runs_as_defined() -> None:
    model = build_model("lite", seed=1).set_layout("rows").eval()
    rng = np.random.default_rng(6)
    points = _frustums(rng, 2, 512, 4, [10, 300])
    one_hot = np.tile(np.float32([1, 0, 0]), (2, 1))
    stages = DistinctPointStages(model)
    assert not stages.distinct
    np.testing.assert_array_equal(stages.segmentation(points, one_hot),
                                  TorchFrustumStages(model).segmentation(points, one_hot))
