"""Hand-computed cases for every coordinate step of the F-PN victim path (no real data needed):
FOV and frustum membership on the box edges, the frustum angle with a non-zero P2 baseline, the
rotation to the frustum frame and back, the glue between the networks, and the decoding of the
box-net output (centre, heading bin + residual, size cluster + residual) to a KITTI row whose
location is the bottom centre.

The calibration is made up so every number below can be checked with pencil and paper:
f = 700 px, c = (600, 180) px, P2[0,3] = 70 and P2[1,3] = 14 (a camera-2 baseline b_x = -0.1 m,
b_y = -0.02 m), velodyne -> rect a pure axis permutation (x_rect = -y_velo, y_rect = -z_velo,
z_rect = x_velo).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from robustbench3d.kitti.calib import Calibration
from robustbench3d.victims.fpointnet.box_coding import class_to_angle
from robustbench3d.victims.fpointnet.frustum import (
    Frustum,
    ProjectedScan,
    box_mask,
    extract_frustum,
    fov_mask,
    frustum_angle,
    project_rect_points,
    project_scan,
    rotate_from_frustum,
    rotate_to_frustum,
    rotation_angle,
)
from robustbench3d.victims.fpointnet.glue import (
    NUM_BOX_OUTPUTS,
    FrustumOutputs,
    gather_points,
    mask_centroid,
    object_point_indices,
    parse_box_output,
    run_box_stages,
    run_frustum_stages,
)
from robustbench3d.victims.fpointnet.to_kitti import as_numpy_outputs, decode, to_labels

PI = math.pi
#: Car template (l, w, h) typed from the reference table.
CAR_LWH = (3.88311640418, 1.62856739989, 1.52563191462)

CALIB = Calibration(
    P0=np.eye(3, 4), P1=np.eye(3, 4),
    P2=np.array([[700.0, 0.0, 600.0, 70.0], [0.0, 700.0, 180.0, 14.0], [0.0, 0.0, 1.0, 0.0]]),
    P3=np.eye(3, 4), R0_rect=np.eye(3),
    Tr_velo_to_cam=np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0]]),
    Tr_imu_to_velo=np.eye(3, 4),
)


# ---- FOV and frustum membership ---------------------------------------------------------------
def test_box_mask_is_half_open_on_its_edges():
    box = np.array([10.0, 20.0, 30.0, 40.0])
    uv = np.array([
        [10.0, 20.0],      # top-left corner: in
        [29.999, 39.999],  # just inside the bottom-right corner: in
        [20.0, 30.0],      # centre: in
        [30.0, 30.0],      # right edge: out
        [20.0, 40.0],      # bottom edge: out
        [30.0, 40.0],      # bottom-right corner: out
        [30.0, 20.0],      # top-right corner: out
        [10.0, 40.0],      # bottom-left corner: out
        [9.999, 30.0],     # left of the left edge: out
        [20.0, 19.999],    # above the top edge: out
    ])
    assert box_mask(uv, box).tolist() == [True, True, True, False, False, False, False, False, False, False]
    assert box_mask(uv, box.reshape(1, 4)).tolist() == box_mask(uv, box).tolist()  # (1, 4) accepted


def test_fov_mask_edges_and_clip_distance():
    uv = np.array([[0.0, 0.0], [99.999, 49.999], [100.0, 10.0], [10.0, 50.0], [-0.001, 10.0], [10.0, -0.001],
                   [10.0, 10.0], [10.0, 10.0]])
    velo_x = np.array([5.0, 5.0, 5.0, 5.0, 5.0, 5.0, 2.0, 2.001])
    assert fov_mask(velo_x, uv, (100, 50)).tolist() == [True, True, False, False, False, False, False, True]
    assert fov_mask(velo_x, uv, (100, 50), clip_distance=6.0).tolist() == [False] * 8


def test_project_scan_by_hand():
    # velodyne (x fwd, y left, z up) -> rect (-y, -z, x); u = (700 x + 600 z + 70) / z, v = (700 y + 180 z + 14) / z
    scan = np.array([[20.0, 0.0, 0.0, 0.5],     # rect (0, 0, 20): u = 603.5, v = 180.7
                     [10.0, -2.0, 1.0, 0.25],   # rect (2, -1, 10): u = 747, v = 111.4
                     [1.5, 0.0, 0.0, 0.75],     # velodyne x 1.5 <= 2: outside the FOV
                     [10.0, 9.0, 0.0, 0.0]],    # rect (-9, 0, 10): u = -23: left of the image
                    dtype=np.float32)
    proj = project_scan(scan, CALIB, (1242, 375))
    assert proj.points_rect[:2] == pytest.approx(np.array([[0, 0, 20, 0.5], [2, -1, 10, 0.25]]))
    assert proj.uv[:2] == pytest.approx(np.array([[603.5, 180.7], [747.0, 111.4]]))
    assert proj.uv[3, 0] == pytest.approx(-23.0)
    assert proj.in_fov.tolist() == [True, True, False, False]
    assert proj.points_rect.dtype == np.float64
    # the same points given in rect: same projection and FOV (the clip uses velodyne x)
    again = project_rect_points(proj.points_rect, CALIB, (1242, 375))
    assert np.allclose(again.uv, proj.uv) and again.in_fov.tolist() == [True, True, False, False]
    assert project_scan(scan, CALIB, (700, 375)).in_fov.tolist() == [True, False, False, False]  # u 747 >= 700


def test_extract_frustum_takes_fov_points_inside_the_half_open_box():
    uv = np.array([[10.0, 20.0], [30.0, 25.0], [15.0, 25.0], [15.0, 25.0], [5.0, 25.0]])
    points = np.arange(20, dtype=np.float64).reshape(5, 4)
    proj = ProjectedScan(points, uv, np.array([True, True, True, False, True]))
    box = np.array([10.0, 20.0, 30.0, 40.0])
    fr = extract_frustum(proj, box, CALIB)
    assert fr.indices.tolist() == [0, 2] and fr.indices.dtype == np.int64 and len(fr) == 2
    assert np.array_equal(fr.points, points[[0, 2]])
    assert fr.box2d.tolist() == box.tolist()
    # centre u = 20 -> x = (20 - 600)·20/700 - 0.1
    assert fr.frustum_angle == pytest.approx(-math.atan2(20.0, -580 * 20 / 700 - 0.1))
    assert fr.rot_angle == pytest.approx(PI / 2 + fr.frustum_angle)


# ---- frustum angle and rotation --------------------------------------------------------------
def test_frustum_angle_uses_the_p2_baseline():
    box = np.array([620.0, 100.0, 650.0, 200.0])  # centre u = 635
    # x = (635 - 600)·20/700 + (-70/700) = 1.0 - 0.1 = 0.9 m at depth 20 m
    assert frustum_angle(box, CALIB) == pytest.approx(-math.atan2(20.0, 0.9), abs=1e-12)
    # at depth 10 m: x = 35·10/700 - 0.1 = 0.4
    assert frustum_angle(box, CALIB, depth=10.0) == pytest.approx(-math.atan2(10.0, 0.4), abs=1e-12)
    # independent check: the rect point (0.9, 0, 20) projects onto the box centre column
    uv, _ = CALIB.rect_to_image(np.array([[0.9, 0.0, 20.0]]))
    assert uv[0, 0] == pytest.approx(635.0)
    # ... and the rotation by rot_angle puts it on +z
    rotated = rotate_to_frustum(np.array([0.9, 0.0, 20.0]), rotation_angle(frustum_angle(box, CALIB)))
    assert rotated == pytest.approx([0.0, 0.0, math.hypot(0.9, 20.0)], abs=1e-12)


def test_frustum_angle_of_a_centred_box_without_baseline_is_straight_ahead():
    calib = Calibration(**{**{k: getattr(CALIB, k) for k in ("P0", "P1", "P3", "R0_rect", "Tr_velo_to_cam",
                                                             "Tr_imu_to_velo")},
                           "P2": np.array([[700.0, 0, 600, 0], [0, 700, 180, 0], [0, 0, 1, 0]])})
    a = frustum_angle(np.array([590.0, 0.0, 610.0, 50.0]), calib)
    assert a == pytest.approx(-PI / 2) and rotation_angle(a) == pytest.approx(0.0, abs=1e-15)
    # a box whose centre ray points 45° to the right: x = z -> angle -π/4, rot_angle π/4
    a45 = frustum_angle(np.array([1290.0, 0.0, 1310.0, 50.0]), calib)  # u = 1300: x = 700·20/700 = 20
    assert a45 == pytest.approx(-PI / 4)
    assert rotate_to_frustum(np.array([1.0, 0.0, 1.0]), rotation_angle(a45)) == pytest.approx([0, 0, math.sqrt(2)])


def test_rotation_to_the_frustum_frame_and_back_by_hand():
    p = np.array([[1.0, 2.0, 3.0, 0.7]])
    # rot π/2: x' = x cos - z sin = -3, z' = x sin + z cos = 1; y and reflectance unchanged
    assert rotate_to_frustum(p, PI / 2)[0] == pytest.approx([-3.0, 2.0, 1.0, 0.7])
    # rot π/6: x' = √3/2 - 3/2, z' = 1/2 + 3√3/2
    s3 = math.sqrt(3)
    assert rotate_to_frustum(p, PI / 6)[0] == pytest.approx([s3 / 2 - 1.5, 2.0, 0.5 + 1.5 * s3, 0.7])
    # back: rotation by -rot_angle
    assert rotate_from_frustum(np.array([-3.0, 2.0, 1.0]), PI / 2) == pytest.approx([1.0, 2.0, 3.0])
    assert rotate_from_frustum(rotate_to_frustum(p, 0.3), 0.3) == pytest.approx(p)
    # a copy: the input is untouched
    assert p.tolist() == [[1.0, 2.0, 3.0, 0.7]]
    fr = Frustum(np.zeros(0, np.int64), np.zeros((0, 4)), np.zeros(4), frustum_angle=-PI / 3)
    assert fr.rot_angle == pytest.approx(PI / 6) and rotation_angle(0.25) == pytest.approx(PI / 2 + 0.25)


# ---- glue between the networks ----------------------------------------------------------------
def test_mask_centroid_and_gather_by_hand():
    logits = np.array([[[0.0, 1.0], [1.0, 0.0], [0.0, 2.0], [0.5, 0.5]],
                       [[1.0, 0.0], [1.0, 0.0], [1.0, 0.0], [1.0, 0.0]]], dtype=np.float32)
    xyz = np.array([[[1.0, 0, 0], [9, 9, 9], [3, 2, 4], [7, 7, 7]], [[1.0, 1, 1]] * 4])
    mask, count, centroid = mask_centroid(logits, xyz)
    assert mask.tolist() == [[True, False, True, False], [False] * 4]  # a tie (0.5, 0.5) is background
    assert count.tolist() == [2, 0]
    assert centroid.tolist() == [[2.0, 1.0, 2.0], [0.0, 0.0, 0.0]]
    # top-k: masked points by decreasing margin, repeated cyclically; empty rows gather point 0
    margin = np.array([[1.0, 9.0, 3.0, 2.0], [0.0] * 4])
    mask2 = np.array([[True, False, True, True], [False] * 4])
    idx = object_point_indices(mask2, margin, 5, "topk")
    assert idx.tolist() == [[2, 3, 0, 2, 3], [0, 0, 0, 0, 0]] and idx.dtype == np.int64
    pts = np.arange(24, dtype=np.float64).reshape(2, 4, 3)
    assert gather_points(pts, np.array([[3, 0], [1, 1]])).tolist() == [[[9, 10, 11], [0, 1, 2]],
                                                                       [[15, 16, 17], [15, 16, 17]]]


def test_random_gather_draws_from_the_mask_only():
    rng = np.random.default_rng(0)
    mask = np.zeros((2, 50), dtype=bool)
    mask[0, [3, 7, 11]] = True          # fewer masked points than wanted: all of them, then repeats
    mask[1, 10:40] = True               # more: distinct masked points
    idx = object_point_indices(mask, np.zeros((2, 50)), 8, "random", rng)
    assert set(idx[0].tolist()) == {3, 7, 11}
    assert len(set(idx[1].tolist())) == 8 and set(idx[1].tolist()) <= set(range(10, 40))
    with pytest.raises(ValueError, match="gather mode"):
        object_point_indices(mask, np.zeros((2, 50)), 8, "first")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="Generator"):
        object_point_indices(mask, np.zeros((2, 50)), 8, "random")


def _raw_box_output(centre: tuple[float, float, float], heading_bin: int, heading_res_norm: float,
                    size_res_norm: tuple[float, float, float]) -> np.ndarray:
    """A (1, 59) box-net output: heading bin logit ln 11 (p = 1/2), Car size logit ln 7 (p = 1/2)."""
    out = np.zeros((1, NUM_BOX_OUTPUTS), dtype=np.float32)
    out[0, 0:3] = centre
    out[0, 3 + heading_bin] = math.log(11.0)
    out[0, 15:27] = 0.9                       # residuals of the other bins: never used
    out[0, 15 + heading_bin] = heading_res_norm
    out[0, 27] = math.log(7.0)
    out[0, 35:59] = 0.3
    out[0, 35:38] = size_res_norm
    return out


def test_parse_box_output_scales_residuals():
    out = _raw_box_output((0.5, -0.25, 2.0), heading_bin=3, heading_res_norm=0.5, size_res_norm=(0.1, -0.2, 0.125))
    stage1 = np.array([[1.0, 2.0, 10.0]])
    o = parse_box_output(out, np.zeros((1, 2, 2)), np.zeros((1, 2), bool), np.array([0]), np.zeros((1, 3)),
                         np.zeros((1, 4), np.int64), np.zeros((1, 3), np.float32), stage1)
    assert o.center == pytest.approx(np.array([[1.5, 1.75, 12.0]]))
    assert o.heading_scores[0, 3] == pytest.approx(math.log(11.0)) and o.heading_scores.shape == (1, 12)
    assert o.heading_residuals[0, 3] == pytest.approx(0.5 * PI / 12)   # normalised x π/12
    assert o.size_scores[0, 0] == pytest.approx(math.log(7.0)) and o.size_scores.shape == (1, 8)
    assert o.size_residuals[0, 0] == pytest.approx([0.1 * CAR_LWH[0], -0.2 * CAR_LWH[1], 0.125 * CAR_LWH[2]])
    assert o.size_residuals[0, 7] == pytest.approx(0.3 * np.array([3.64300781, 1.54298177, 1.92320313]))
    with pytest.raises(ValueError, match="box output"):
        parse_box_output(out[:, :58], *(np.zeros(1),) * 7)


class _Stub:
    """Networks with known outputs: foreground where x > 0 (margin 2x), T-Net delta (0.5, 0, -1),
    a fixed box output; records what each stage received."""

    def __init__(self, box_out: np.ndarray):
        self.box_out, self.seen = box_out, {}

    def segmentation(self, points, one_hot):
        self.seen["seg"] = points
        return np.stack([np.zeros(points.shape[:2]), 2 * points[..., 0]], axis=-1).astype(np.float32)

    def center_delta(self, object_points, one_hot):
        self.seen["tnet"] = object_points
        return np.tile(np.array([0.5, 0.0, -1.0], np.float32), (len(object_points), 1))

    def box_output(self, object_points, one_hot):
        self.seen["box"] = object_points
        return np.repeat(self.box_out, len(object_points), axis=0)


def test_run_frustum_stages_chains_centroid_tnet_and_box_net():
    pts = np.array([[[1.0, 0, 10, 0.1], [3.0, 1, 12, 0.2], [-1.0, 0, 5, 0.3], [2.0, 2, 11, 0.4]]], np.float32)
    stub = _Stub(_raw_box_output((0.25, 0.0, 0.5), 0, 0.0, (0.0, 0.0, 0.0)))
    o = run_frustum_stages(stub, pts, np.array([[1.0, 0, 0]]), num_object_points=3, gather="topk")
    assert o.mask.tolist() == [[True, True, False, True]] and o.mask_count.tolist() == [3]
    assert o.mask_centroid == pytest.approx(np.array([[2.0, 1.0, 11.0]]))    # mean of points 0, 1, 3
    assert o.object_indices.tolist() == [[1, 3, 0]]                         # margins 6, 4, 2
    # T-Net sees the gathered points minus the centroid; the box net those minus the delta
    assert stub.seen["tnet"][0] == pytest.approx(np.array([[1, 0, 1], [0, 1, 0], [-1, -1, -1]]))
    assert stub.seen["box"][0] == pytest.approx(np.array([[0.5, 0, 2], [-0.5, 1, 1], [-1.5, -1, 0]]))
    assert stub.seen["seg"].dtype == np.float32 and stub.seen["seg"].shape == (1, 4, 4)
    assert o.center_delta == pytest.approx(np.array([[0.5, 0.0, -1.0]]))
    assert o.stage1_center == pytest.approx(np.array([[2.5, 1.0, 10.0]]))
    assert o.center == pytest.approx(np.array([[2.75, 1.0, 10.5]]))
    delta, out = run_box_stages(stub, stub.seen["tnet"].astype(np.float64), np.array([[1.0, 0, 0]], np.float32))
    assert delta.dtype == out.dtype == np.float32 and out.shape == (1, NUM_BOX_OUTPUTS)


# ---- decoding to KITTI rows ------------------------------------------------------------------
def _outputs(raw: np.ndarray, seg_logits: np.ndarray, mask: np.ndarray, centre: np.ndarray) -> FrustumOutputs:
    o = parse_box_output(raw, seg_logits, mask, mask.sum(axis=1), np.zeros((len(raw), 3)),
                         np.zeros((len(raw), 4), np.int64), np.zeros((len(raw), 3), np.float32), centre)
    return o


def test_decode_heading_bin_size_cluster_and_score_by_hand():
    l3 = math.log(3.0)
    seg = np.array([[[0, l3], [0, l3], [0, l3], [0, -l3]],       # masked points p = 3/4; the other 1/4
                    [[0, -l3], [0, -l3], [0, -l3], [0, -l3]]])   # empty mask: max p = 1/4
    mask = seg[..., 1] > seg[..., 0]
    raw = np.concatenate([_raw_box_output((0.0, 0.0, 0.0), 3, 0.5, (0.1, -0.2, 0.125)),
                          _raw_box_output((0.0, 0.0, 0.0), 11, 0.5, (0.0, 0.0, 0.0))])
    boxes = decode(_outputs(raw, seg, mask, np.array([[1.0, 0.5, 10.0], [0.0, 0.0, 5.0]])))
    # bin 3 (90°) + 0.5·15° = 97.5°; bin 11 (330°) + 7.5° = 337.5° -> label format -22.5°
    assert boxes.heading == pytest.approx(np.radians([97.5, -22.5]))
    assert boxes.size_lwh[0] == pytest.approx([CAR_LWH[0] * 1.1, CAR_LWH[1] * 0.8, CAR_LWH[2] * 1.125])
    assert boxes.size_lwh[1] == pytest.approx(CAR_LWH)
    assert boxes.center == pytest.approx(np.array([[1.0, 0.5, 10.0], [0.0, 0.0, 5.0]]))
    # (mean masked object prob) x (max heading prob) x (max size prob)
    assert boxes.score_3d == pytest.approx([0.75 * 0.5 * 0.5, 0.25 * 0.5 * 0.5], rel=1e-6)
    assert as_numpy_outputs(_outputs(raw, seg, mask, np.zeros((2, 3)))).center.shape == (2, 3)
    assert float(class_to_angle(6, 0.0)) == PI                           # exactly π stays π
    assert float(class_to_angle(6, 1e-9)) == pytest.approx(-PI + 1e-9)  # beyond π wraps
    assert float(class_to_angle(6, 1e-9, to_label_format=False)) == pytest.approx(PI + 1e-9)


def test_to_labels_rotates_back_and_moves_to_the_bottom_centre():
    l3 = math.log(3.0)
    seg = np.array([[[0, l3]] * 4, [[0, l3]] * 4])
    raw = np.concatenate([_raw_box_output((0.0, 0.0, 0.0), 3, 0.5, (0.1, -0.2, 0.125)),
                          _raw_box_output((0.0, 0.0, 0.0), 11, 0.5, (0.0, 0.0, 0.0))])
    boxes = decode(_outputs(raw, seg, seg[..., 1] > seg[..., 0], np.array([[1.0, 0.5, 10.0], [0.0, -1.0, 5.0]])))
    boxes2d = np.array([[100.0, 50.0, 200.0, 150.0], [300.0, 60.0, 340.0, 90.0]])
    rows = to_labels(boxes, np.array([PI / 6, -PI]), boxes2d, np.array([0.9, 0.4]))
    s3 = math.sqrt(3)
    h0 = CAR_LWH[2] * 1.125
    # frustum -> rect: rotate by -π/6: x = x'√3/2 + z'/2, z = -x'/2 + z'√3/2; then y += h/2
    assert rows.location[0] == pytest.approx([s3 / 2 + 5.0, 0.5 + h0 / 2, -0.5 + 5 * s3])
    # rotate by +π: (x, z) -> (-x, -z)
    assert rows.location[1] == pytest.approx([0.0, -1.0 + CAR_LWH[2] / 2, -5.0])
    assert rows.dimensions[0] == pytest.approx([h0, CAR_LWH[1] * 0.8, CAR_LWH[0] * 1.1])  # h, w, l
    # ry = heading + rot_angle wrapped to [-π, π): 97.5° + 30° = 127.5°; -22.5° - 180° -> 157.5°
    assert rows.rotation_y == pytest.approx(np.radians([127.5, 157.5]))
    alpha0 = math.radians(127.5) - math.atan2(s3 / 2 + 5.0, -0.5 + 5 * s3)
    assert rows.alpha == pytest.approx([alpha0, math.radians(157.5 - 180.0)])  # atan2(0, -5) = ±π
    assert rows.bbox.tolist() == boxes2d.tolist() and rows.score.tolist() == [0.9, 0.4]
    assert rows.type.tolist() == ["Car", "Car"] and rows.truncated.tolist() == [-1, -1]
    assert rows.occluded.tolist() == [-1, -1]
    assert len(to_labels(decode(_outputs(raw[:0], seg[:0], seg[:0, :, 0] > 0, np.zeros((0, 3)))),
                         np.zeros(0), np.zeros((0, 4)), np.zeros(0))) == 0


# ---- input handling of the frustum helpers ----------------------------------------------------
def test_frustum_helpers_accept_row_boxes_and_return_float64():
    box = np.array([[620, 100, 650, 200]])  # (1, 4) ints
    assert frustum_angle(box, CALIB) == pytest.approx(-math.atan2(20.0, 0.9), abs=1e-12)
    proj = ProjectedScan(np.zeros((1, 4)), np.array([[630.0, 150.0]]), np.array([True]))
    fr = extract_frustum(proj, box, CALIB)
    assert fr.box2d.shape == (4,) and fr.box2d.dtype == np.float64 and fr.indices.tolist() == [0]
    f32 = np.array([[1.0, 2.0, 3.0, 0.5]], dtype=np.float32)
    assert rotate_to_frustum(f32, 0.1).dtype == np.float64
    again = project_rect_points(f32, CALIB, (1242, 375))
    assert again.points_rect.dtype == np.float64 and np.array_equal(again.points_rect, f32.astype(np.float64))


def test_clip_distance_is_passed_through():
    scan = np.array([[3.0, 0.0, 0.0, 0.1], [5.0, 0.0, 0.0, 0.2]], dtype=np.float32)  # rect z 3 and 5, u = 623.3, 614
    assert project_scan(scan, CALIB, (1242, 375)).in_fov.tolist() == [True, True]
    assert project_scan(scan, CALIB, (1242, 375), clip_distance=4.0).in_fov.tolist() == [False, True]
    rect = project_scan(scan, CALIB, (1242, 375)).points_rect
    assert project_rect_points(rect, CALIB, (1242, 375), clip_distance=4.0).in_fov.tolist() == [False, True]


def test_resampling_of_a_single_point_and_the_empty_error():
    from robustbench3d.victims.fpointnet.frustum import resample_indices

    assert resample_indices(1, 4, np.random.default_rng(0)).tolist() == [0, 0, 0, 0]
    with pytest.raises(ValueError, match=r"^cannot resample an empty frustum$"):
        resample_indices(0, 4, np.random.default_rng(0))


class _FixedDraws:
    """A generator stand-in whose ``random(n)`` returns known values (and records ``n``)."""

    def __init__(self, values):
        self.values, self.sizes = np.asarray(values, dtype=np.float64), []

    def random(self, n):
        self.sizes.append(n)
        return self.values[:n]


def test_box_perturbation_by_hand():
    from robustbench3d.victims.fpointnet.frustum import perturb_box2d

    rng = _FixedDraws([0.75, 0.25, 1.0, 0.0, 0.5])
    box = np.array([[100.0, 50.0, 300.0, 150.0]])  # w 200, h 100, centre (200, 100)
    out = perturb_box2d(box, rng, ratio=0.1)  # type: ignore[arg-type]
    # cx + 200·0.1·(2·0.75 - 1) = 210; cy + 100·0.1·(2·0.25 - 1) = 95; h·(1 + 0.2·1 - 0.1) = 110; w·0.9 = 180
    assert out == pytest.approx([120.0, 40.0, 300.0, 150.0]) and rng.sizes == [4]


# ---- decoding: input types, batches and edge cases ----------------------------------------------
def test_decode_of_torch_outputs_and_mixed_batches():
    import torch

    from robustbench3d.victims.fpointnet.box_coding import angle_to_class

    l3, l1 = math.log(3.0), 0.0
    # row 0: masked p = 3/4 and 1/2 + ... (mean 5/8, max 3/4); row 1: one masked point (p 3/4); row 2: mean 3/4
    seg = np.array([[[0, l3], [0, 1e-9], [0, -l3], [0, -l3]],
                    [[0, l3], [0, -l3], [0, -l3], [0, -l3]],
                    [[0, l3], [0, l3], [0, l3], [0, l3]]], dtype=np.float32)
    seg[0, 1, 1] = l1 + 1e-6  # p just above 1/2
    mask = seg[..., 1] > seg[..., 0]
    raw = np.concatenate([_raw_box_output((0.0, 0.0, 0.0), 0, 0.0, (0.0, 0.0, 0.0))] * 3)
    raw[:, 3] = 500.0   # huge logits: the softmax must not overflow
    o = _outputs(raw, seg, mask, np.zeros((3, 3)))
    as_torch = type("Out", (), {f: (torch.tensor(np.asarray(getattr(o, f)), requires_grad=np.asarray(
        getattr(o, f)).dtype.kind == "f") if f != "mask_count" else np.asarray(getattr(o, f)))
        for f in FrustumOutputs.__dataclass_fields__})()
    boxes = decode(as_torch)  # torch tensors (with grad) and numpy arrays are both accepted
    p = 1 / (1 + np.exp(-np.float32(1e-6)))
    obj = np.array([(0.75 + p) / 2, 0.75, 0.75], dtype=np.float32)
    heading_p = np.float32(1.0)                   # logit 500 against zeros
    size_p = np.float32(7 / 14)
    assert boxes.score_3d == pytest.approx(obj * heading_p * size_p, rel=1e-6)
    assert boxes.center.dtype == np.float64 and boxes.score_3d.dtype == np.float64
    assert (boxes.score_3d.astype(np.float32).astype(np.float64) == boxes.score_3d).all()  # float32 arithmetic
    # the score is computed in the logits' dtype (float32): exactly this product
    prob = (1 / (1 + np.exp(-(seg[..., 1] - seg[..., 0])))).astype(np.float32)
    assert np.isfinite(boxes.score_3d).all() and boxes.score_3d[1] == pytest.approx(float(prob[1, 0]) * 0.5)
    # a heading just below 360° - 15° lands in the last bin (not a 13th one) with residual +15°
    cls, res = angle_to_class(6.021385919380436)
    assert int(cls) == 11 and float(res) == pytest.approx(PI / 12) and cls.dtype == np.int64


def test_to_labels_input_types():
    seg = np.array([[[0.0, 1.0]] * 4])
    boxes = decode(_outputs(_raw_box_output((0.0, 0.0, 0.0), 0, 0.0, (0.0, 0.0, 0.0)), seg, seg[..., 1] > 0,
                            np.array([[0.0, -1.0, 10.0]])))
    rows = to_labels(boxes, np.array([[0.5]]), np.array([[1, 2, 3, 4]]), np.array([[0.5]], dtype=np.float32))
    assert rows.rotation_y == pytest.approx([0.5]) and rows.bbox.dtype == np.float64
    assert rows.bbox.tolist() == [[1.0, 2.0, 3.0, 4.0]] and rows.score.dtype == np.float64
    assert rows.score.shape == (1,) and rows.type.dtype == object and rows.occluded.dtype == np.int64


# ---- glue: dtypes at the network boundaries, generators, ties ------------------------------------
class _Float64Stub(_Stub):
    """:class:`_Stub` whose networks answer in float64 (the glue must hand on float32)."""

    def segmentation(self, points, one_hot):
        self.seen["seg_one_hot"] = one_hot
        return super().segmentation(points, one_hot).astype(np.float64)

    def center_delta(self, object_points, one_hot):
        return super().center_delta(object_points, one_hot).astype(np.float64)

    def box_output(self, object_points, one_hot):
        return super().box_output(object_points, one_hot).astype(np.float64)


def test_glue_casts_at_the_network_boundaries():
    pts = np.array([[[1.0, 0, 10, 0.1], [3.0, 1, 12, 0.2], [-1.0, 0, 5, 0.3], [2.0, 2, 11, 0.4]]])  # float64
    stub = _Float64Stub(_raw_box_output((0.25, 0.0, 0.5), 0, 0.0, (0.0, 0.0, 0.0)))
    o = run_frustum_stages(stub, pts, np.array([[1.0, 0, 0]]), num_object_points=3, gather="random",
                           rng=[np.random.default_rng(1)])
    assert stub.seen["seg"].dtype == np.float32 and stub.seen["seg_one_hot"].dtype == np.float32
    assert stub.seen["tnet"].dtype == np.float32 and stub.seen["box"].dtype == np.float32
    assert o.seg_logits.dtype == np.float32 and o.center_delta.dtype == np.float32
    assert o.mask_centroid.dtype == np.float64 and o.center == pytest.approx(np.array([[2.75, 1.0, 10.5]]))
    assert sorted(o.object_indices[0].tolist()) == [0, 1, 3]  # all three masked points, shuffled
    delta, out = run_box_stages(stub, stub.seen["tnet"].astype(np.float64), np.array([[1.0, 0, 0]], np.float32))
    assert delta.dtype == out.dtype == np.float32


def test_mask_centroid_of_one_point_and_float32_input():
    logits = np.array([[[0.0, 1.0], [1.0, 0.0]]], dtype=np.float32)
    _, count, centroid = mask_centroid(logits, np.array([[[1.5, 2.0, 3.0], [9.0, 9.0, 9.0]]], dtype=np.float32))
    assert count.tolist() == [1] and centroid.tolist() == [[1.5, 2.0, 3.0]] and centroid.dtype == np.float64


def test_mask_centroid_accumulates_float32_points_in_float64():
    """2^24 + 1 is not a float32: summed in float32 the two masked x would give 2^24 and a centroid 2^23."""
    logits = np.array([[[0.0, 1.0], [0.0, 1.0], [1.0, 0.0]]], dtype=np.float32)
    xyz = np.array([[[2.0**24, 0.0, 1.0], [1.0, 0.0, 2.0], [5.0, 5.0, 5.0]]], dtype=np.float32)
    _, count, centroid = mask_centroid(logits, xyz)
    assert count.tolist() == [2] and centroid.tolist() == [[2.0**23 + 0.5, 0.0, 1.5]]


def test_decode_mean_object_probability_divides_in_float32():
    """Three masked points: the mean object probability is a float32 quotient (sum / 3 in float32), so the
    score (times heading p = 1 and size p = 1/2, both exact) is a float32 value; a float64 division is not."""
    l3 = math.log(3.0)
    seg = np.array([[[0, l3], [0, l3], [0, 2.0], [0, -l3]]], dtype=np.float32)  # a sum / 3 that is no float32
    mask = seg[..., 1] > seg[..., 0]
    raw = _raw_box_output((0.0, 0.0, 0.0), 0, 0.0, (0.0, 0.0, 0.0))
    raw[:, 3] = 500.0  # heading p = 1 exactly
    boxes = decode(_outputs(raw, seg, mask, np.zeros((1, 3))))
    p = 1 / (1 + np.exp(-np.array([l3, l3, 2.0])))
    assert boxes.score_3d == pytest.approx([p.mean() * 0.5], rel=1e-6)
    assert boxes.score_3d.astype(np.float32).astype(np.float64).tolist() == boxes.score_3d.tolist()


def _reference_gather(pos: np.ndarray, num: int, g: np.random.Generator) -> np.ndarray:
    """The original ``tf_gather_object_pc`` on masked positions ``pos``: ``num`` of them without
    replacement if there are more, else all of them plus repeats; then shuffled."""
    if len(pos) > num:
        choice = g.choice(len(pos), num, replace=False)
    else:
        choice = np.concatenate([np.arange(len(pos)), g.choice(len(pos), num - len(pos), replace=True)])
    g.shuffle(choice)
    return pos[choice]


def test_random_gather_follows_the_original_with_one_generator_per_row():
    mask = np.zeros((4, 30), dtype=bool)
    mask[1, [2, 5, 6, 9]] = True       # exactly num masked points
    mask[2, :20] = True                # more than num
    mask[3, [7]] = True                # fewer
    gens = [np.random.default_rng(s) for s in (10, 11, 12, 13)]
    twins = [np.random.default_rng(s) for s in (10, 11, 12, 13)]
    idx = object_point_indices(mask, np.zeros((4, 30)), 4, "random", gens)
    assert idx[0].tolist() == [0, 0, 0, 0]  # empty first row: the later rows are still gathered
    for i in (1, 2, 3):
        assert idx[i].tolist() == _reference_gather(np.flatnonzero(mask[i]), 4, twins[i]).tolist()
    with pytest.raises(ValueError, match=r"^gather mode 'random' needs a numpy Generator$"):
        object_point_indices(mask, np.zeros((4, 30)), 4, "random")


def test_topk_gather_breaks_ties_by_index():
    margin = np.random.default_rng(0).integers(0, 3, (1, 200)).astype(np.float64)
    idx = object_point_indices(np.ones((1, 200), dtype=bool), margin, 200, "topk")
    assert idx[0].tolist() == sorted(range(200), key=lambda j: (-margin[0, j], j))


def test_car_one_hot_rows_and_corners_of_several_boxes():
    from robustbench3d.victims.fpointnet.box_coding import car_one_hot, corners_from_center

    hot = car_one_hot(3)
    assert hot.shape == (3, 3) and hot.dtype == np.float32 and hot.tolist() == [[1, 0, 0]] * 3
    assert car_one_hot(0).shape == (0, 3)
    # two boxes at once: heading 0 (length along x) and π/2 (length along -z), l, w, h = 4, 2, 1
    c = corners_from_center(np.array([[0.0, 0, 0], [10.0, 1, 20]]), np.array([0.0, PI / 2]),
                            np.array([[4.0, 2.0, 1.0], [4.0, 2.0, 1.0]]))
    assert c.shape == (2, 8, 3)
    assert c[0, 0] == pytest.approx([2.0, 0.5, 1.0]) and c[0, 6] == pytest.approx([-2.0, -0.5, -1.0])
    # heading π/2: x' = z_local, z' = -x_local -> corner 0 (l/2, h/2, w/2) at (10 + 1, 1.5, 20 - 2)
    assert c[1, 0] == pytest.approx([11.0, 1.5, 18.0]) and c[1, 6] == pytest.approx([9.0, 0.5, 22.0])


def test_box_coding_input_shapes_and_precision():
    from robustbench3d.victims.fpointnet.box_coding import angle_to_class, corners_from_center, size_to_class

    c = corners_from_center(np.zeros((2, 3)), np.array([[0.0], [PI / 2]]), np.ones((2, 3)))  # (N, 1) headings
    assert c.shape == (2, 8, 3) and c[1, 0] == pytest.approx([0.5, 0.5, -0.5])
    cls, res = size_to_class(np.zeros((0, 3)), [])
    assert cls.dtype == np.int64 and cls.shape == (0,) and res.shape == (0, 3)
    # a float32 angle is binned in float64: bin 0, residual exactly the angle
    cls, res = angle_to_class(np.float32(0.1875))
    assert int(cls) == 0 and float(res) == pytest.approx(0.1875, abs=1e-15)


def test_decode_and_to_labels_of_float32_inputs():
    """float32 network outputs (a training forward pass) decode to float64 centres without warnings, also
    when a logit difference overflows float32 (its exp is the exact 0); a float32 rotation angle rotates
    in float64 (cos and sin of the float32 value, by hand)."""
    import dataclasses
    import warnings

    seg = np.array([[[-3e38, 3e38], [0.0, 1.0], [1.0, 0.0]]], dtype=np.float32)  # -6e38 overflows float32
    raw = _raw_box_output((0.0, 0.0, 0.0), 0, 0.0, (0.0, 0.0, 0.0))
    o = _outputs(raw, seg, seg[..., 1] > seg[..., 0], np.zeros((1, 3)))
    centre = np.array([[0.1, -0.7, 12.3]], dtype=np.float32)
    o = dataclasses.replace(o, center=centre)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        boxes = decode(o)
    p1 = 1 / (1 + math.exp(-1.0))
    assert boxes.score_3d == pytest.approx([(1.0 + p1) / 2 * 0.5 * 0.5], rel=1e-6)
    assert boxes.center.dtype == np.float64 and boxes.center.tolist() == centre.astype(np.float64).tolist()
    rot = np.array([0.3], dtype=np.float32)
    rows = to_labels(boxes, rot, np.array([[1.0, 2.0, 3.0, 4.0]]), np.array([0.5]))
    r = float(rot[0])
    x, y, z = (float(v) for v in centre[0])
    assert rows.location[0].tolist() == pytest.approx(
        [math.cos(r) * x + math.sin(r) * z, y + CAR_LWH[2] / 2, -math.sin(r) * x + math.cos(r) * z], rel=1e-14)


def test_decode_of_frustums_without_points():
    """A frustum with no points at all (N = 0) has no object probability to take a maximum of: its object
    probability is 0, so its score is 0 (the other outputs decode as usual)."""
    seg = np.zeros((1, 0, 2), dtype=np.float32)
    raw = _raw_box_output((0.0, 0.0, 0.0), 3, 0.5, (0.0, 0.0, 0.0))
    boxes = decode(_outputs(raw, seg, np.zeros((1, 0), dtype=bool), np.array([[1.0, 2.0, 3.0]])))
    assert boxes.score_3d.tolist() == [0.0] and boxes.heading == pytest.approx(np.radians([97.5]))
