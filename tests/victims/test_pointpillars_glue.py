"""PointPillars glue against independent references: the BEV scatter against a Python loop, the pillar
assignment against a brute-force per-point assignment, the point features against hand computation, the
box conventions and the target encode/decode round trip on hand cases, the heatmap peaks on a hand map."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from robustbench3d.kitti.labels import Labels
from robustbench3d.testing import SIMPLE_CALIB
from robustbench3d.victims.pointpillars.config import PointPillarsConfig, output_shape
from robustbench3d.victims.pointpillars.model import scatter_to_bev
from robustbench3d.victims.pointpillars.pillars import (
    PillarGrid,
    assign_pillars,
    pillar_features,
    pillar_features_np,
)
from robustbench3d.victims.pointpillars.targets import (
    decode_cells,
    encode,
    labels_to_velo_boxes,
    peaks,
    velo_boxes_to_rect,
)

torch.set_num_threads(1)
GRID = PillarGrid(x_min=0.0, x_max=4.0, y_min=-2.0, y_max=2.0, z_min=-3.0, z_max=1.0, pillar_size=0.5, max_points=3)


def test_scatter_matches_python_loop():
    """Each pillar's feature vector lands at (frame, :, iy, ix); every other cell is zero."""
    rng = np.random.default_rng(0)
    b, ny, nx, c = 2, 5, 7, 3
    cells = rng.choice(b * ny * nx, size=20, replace=False)
    frame, rest = cells // (ny * nx), cells % (ny * nx)
    coords = np.stack([rest // nx, rest % nx], axis=1)
    feats = rng.normal(size=(20, c))
    got = scatter_to_bev(torch.from_numpy(feats), torch.from_numpy(coords), torch.from_numpy(frame), b, ny, nx)
    want = np.zeros((b, c, ny, nx))
    for p in range(20):
        for ch in range(c):
            want[frame[p], ch, coords[p, 0], coords[p, 1]] = feats[p, ch]
    np.testing.assert_array_equal(got.numpy(), want)


def test_scatter_drops_padding_pillars():
    """A pillar at (ny, 0) -- the ONNX twin's padding -- changes no cell."""
    feats = torch.tensor([[1.0, 2.0], [5.0, 6.0]])
    coords = torch.tensor([[1, 2], [3, 0]])  # ny = 3: the second is padding
    got = scatter_to_bev(feats, coords, None, 1, 3, 4)
    want = torch.zeros(1, 2, 3, 4)
    want[0, :, 1, 2] = torch.tensor([1.0, 2.0])
    assert torch.equal(got, want)


def _brute_force(points: np.ndarray, grid: PillarGrid) -> dict[tuple[int, int], list[int]]:
    """(iy, ix) -> the rows kept there: every point inside the region, by its own floor, first M in scan order."""
    out: dict[tuple[int, int], list[int]] = {}
    for i, (x, y, z, _) in enumerate(points.tolist()):
        if not (grid.x_min <= x < grid.x_max and grid.y_min <= y < grid.y_max and grid.z_min <= z < grid.z_max):
            continue
        key = (math.floor((y - grid.y_min) / grid.pillar_size), math.floor((x - grid.x_min) / grid.pillar_size))
        rows = out.setdefault(key, [])
        if len(rows) < grid.max_points:
            rows.append(i)
    return out


def test_assignment_matches_brute_force():
    rng = np.random.default_rng(1)
    pts = np.concatenate([rng.uniform([-0.5, -2.5, -3.5, 0], [4.5, 2.5, 1.5, 1], (400, 4)),
                          np.tile([[1.1, 0.2, 0.0, 0.5]], (6, 1))])  # six points in one pillar: three dropped
    a = assign_pillars(pts, GRID)
    want = _brute_force(pts, GRID)
    got: dict[tuple[int, int], list[int]] = {}
    for row, p, s in zip(a.rows.tolist(), a.pillar.tolist(), a.slot.tolist(), strict=True):
        key = tuple(a.coords[p].tolist())
        got.setdefault(key, []).append(row)
        assert got[key].index(row) == s
    assert got == want
    flat = a.coords[:, 0] * GRID.nx + a.coords[:, 1]
    assert np.all(np.diff(flat) > 0)


def test_features_by_hand():
    """Two points in pillar (iy 5, ix 2) = x [1.0, 1.5), y [0.5, 1.0): features x, y, z, r, offsets to the
    mean (1.2, 0.7, -1.0) and to the pillar centre (1.25, 0.75); the third slot empty."""
    pts = np.array([[1.1, 0.6, -1.5, 0.25], [1.3, 0.8, -0.5, 0.75]])
    a = assign_pillars(pts, GRID)
    assert a.coords.tolist() == [[5, 2]]
    want = np.array([[1.1, 0.6, -1.5, 0.25, -0.1, -0.1, -0.5, -0.15, -0.15],
                     [1.3, 0.8, -0.5, 0.75, 0.1, 0.1, 0.5, 0.05, 0.05],
                     [0.0] * 9])
    for feats, mask in (pillar_features_np(pts, a, GRID),
                        [t.numpy() for t in pillar_features(torch.from_numpy(pts), a, GRID, torch.float64)]):
        np.testing.assert_allclose(feats[0], want, atol=1e-6)
        assert mask.tolist() == [[True, True, False]]


def test_torch_and_numpy_features_agree():
    rng = np.random.default_rng(2)
    pts = rng.uniform([0, -2, -3, 0], [4, 2, 1, 1], (300, 4))
    a = assign_pillars(pts, GRID)
    f_np, m_np = pillar_features_np(pts, a, GRID)
    f_t, m_t = pillar_features(torch.from_numpy(pts), a, GRID, torch.float64)
    np.testing.assert_allclose(f_np, f_t.numpy(), atol=1e-6)
    assert np.array_equal(m_np, m_t.numpy())


def _car(location, dims_hwl, ry) -> Labels:
    n = len(ry)
    return Labels(type=np.array(["Car"] * n, dtype=object), truncated=np.zeros(n), occluded=np.zeros(n, np.int64),
                  alpha=np.zeros(n), bbox=np.zeros((n, 4)), dimensions=np.asarray(dims_hwl, float),
                  location=np.asarray(location, float), rotation_y=np.asarray(ry, float))


def test_label_to_velodyne_by_hand():
    """SIMPLE_CALIB: velodyne (x, y, z) = rect (z + 0.27, -x, -y - 0.08). A car with bottom centre rect
    (2, 1.5, 20), h 1.5: centre rect (2, 0.75, 20) -> velodyne (20.27, -2, -0.83); ry 0 (heading rect +x =
    velodyne -y) -> yaw -pi/2; ry -pi/2 (heading rect +z = velodyne +x) -> yaw 0."""
    lab = _car([[2.0, 1.5, 20.0], [0.0, 1.5, 10.0]], [[1.5, 1.6, 4.0], [1.4, 1.7, 3.9]], [0.0, -np.pi / 2])
    boxes = labels_to_velo_boxes(lab, SIMPLE_CALIB)
    np.testing.assert_allclose(boxes[0], [20.27, -2.0, -0.83, 4.0, 1.6, 1.5, -np.pi / 2], atol=1e-9)
    np.testing.assert_allclose(boxes[1], [10.27, 0.0, -0.88, 3.9, 1.7, 1.4, 0.0], atol=1e-9)
    loc, dims, ry = velo_boxes_to_rect(boxes, SIMPLE_CALIB)
    np.testing.assert_allclose(loc, lab.location, atol=1e-9)
    np.testing.assert_allclose(dims, lab.dimensions, atol=1e-12)
    np.testing.assert_allclose(ry, lab.rotation_y, atol=1e-12)


def test_encode_decode_round_trip_by_hand():
    """Default grid (0.32 m pillars, stride 2: 0.64 m cells from x 0, y -40): a box centred at x 10.0, y 1.0
    sits in cell column floor(10 / 0.64) = 15, row floor(41 / 0.64) = 64, offsets 0.625 and 0.0625."""
    cfg = PointPillarsConfig()
    boxes = np.array([[10.0, 1.0, -0.9, 4.2, 1.7, 1.5, 0.3], [30.5, -12.3, -1.1, 3.8, 1.6, 1.45, -2.9]])
    t = encode(boxes, cfg)
    h, w = output_shape(cfg)
    assert t.index[0] == 64 * w + 15
    np.testing.assert_allclose(t.regression[0, :2], [0.625, 0.0625], atol=1e-6)
    assert t.heatmap[64, 15] == 1.0 and t.heatmap.max() == 1.0
    assert t.heatmap[64, 16] < 1.0
    out = np.zeros((9, h, w))
    out[1:, t.index // w, t.index % w] = t.regression.T
    np.testing.assert_allclose(decode_cells(out, t.index // w, t.index % w, cfg), boxes, atol=2e-6)


def test_encode_leaves_out_boxes_off_the_grid():
    cfg = PointPillarsConfig()
    t = encode(np.array([[-1.0, 0.0, -1.0, 4.0, 1.6, 1.5, 0.0], [10.0, 45.0, -1.0, 4.0, 1.6, 1.5, 0.0]]), cfg)
    assert len(t.index) == 0 and t.heatmap.max() == 0.0


def test_peaks_by_hand():
    """Local maxima of a hand map above the threshold, best first: the plateau keeps both cells."""
    z = np.full((5, 6), -5.0)
    z[1, 1], z[1, 2] = 3.0, 1.0  # (1, 2) is below its neighbour
    z[3, 4] = 2.0
    z[4, 0] = z[4, 1] = 0.5  # plateau
    z[0, 5] = -1.0  # a peak below the threshold
    rows, cols = peaks(z, threshold_logit=0.0, max_detections=10)
    assert list(zip(rows.tolist(), cols.tolist(), strict=True)) == [(1, 1), (3, 4), (4, 0), (4, 1)]
    rows, _ = peaks(z, threshold_logit=0.0, max_detections=2)
    assert len(rows) == 2


@pytest.mark.parametrize("ry", [-3.0, -1.0, 0.0, 2.5])
def test_yaw_round_trip(ry):
    lab = _car([[1.0, 1.6, 15.0]], [[1.5, 1.6, 4.0]], [ry])
    _, _, back = velo_boxes_to_rect(labels_to_velo_boxes(lab, SIMPLE_CALIB), SIMPLE_CALIB)
    assert back[0] == pytest.approx(ry, abs=1e-12)
