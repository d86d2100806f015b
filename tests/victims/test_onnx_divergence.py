"""Lockstep tracing of differing frames (victims/onnx/divergence.py): flips are found where they
were planted, with the torch margin, and judged against the tie tolerances."""

from __future__ import annotations

import numpy as np
import pytest

from robustbench3d.kitti.dataset import Frame, KittiDataset
from robustbench3d.kitti.labels import Labels
from robustbench3d.victims.fpointnet.box_coding import NUM_HEADING_BIN
from robustbench3d.victims.fpointnet.frustum import box_mask, project_scan
from robustbench3d.victims.fpointnet.model import TorchFrustumStages
from robustbench3d.victims.onnx.divergence import (
    FrameDivergence,
    _membership_flips,
    _order_flips,
    _pair_flips,
    trace_frame,
)
from robustbench3d.victims.onnx.parity import Tolerances, box_parity

TIE = 2e-4


@pytest.fixture(scope="module")
def victim(lite_victim):
    return lite_victim  # the session's shared one (conftest): read only


@pytest.fixture(scope="module")
def frame(shared_split) -> Frame:
    root = shared_split(2, seed=0, val_fraction=0.5)
    ds = KittiDataset(root, split=None)
    frames = [ds.frame(f) for f in ds.frame_ids]
    return max(frames, key=lambda f: int((f.labels.type == "Car").sum()))


def trace(victim, frame, source, *, heads_o=None, stages_o=None, tie_atol=TIE) -> FrameDivergence:
    stages_t = TorchFrustumStages(victim.fpn)
    return trace_frame(frame, source, yolo_cfg=victim.yolo.cfg, car_class=victim.car_class,
                       heads_t=victim.yolo.run_heads, heads_o=heads_o or victim.yolo.run_heads, stages_t=stages_t,
                       stages_o=stages_o or stages_t, settings=victim.settings, num_points=victim.num_points,
                       num_object_points=victim.fpn.cfg.num_object_points, tie_atol=tie_atol, tie_px=1e-3)


def test_pair_and_order_flips_by_hand():
    t, o = np.array([0.30, 0.50001, 0.7]), np.array([0.30, 0.49999, 0.7])
    flips = _pair_flips("d", t, o, 0.5, np.array(["a", "b", "c"]))
    assert [(f.where, round(f.margin, 8)) for f in flips] == [("b", 1e-5)]
    assert _pair_flips("d", t, t, 0.5, np.array(["a", "b", "c"])) == []
    # ">=" decisions: a value exactly on the boundary is on the upper side
    assert _pair_flips("d", np.array([0.5]), np.array([0.4999]), 0.5, np.array(["x"]), strict=False)[0].margin == 0.0
    order = _order_flips("o", np.array([1.0, 0.90002, 0.9]), np.array([1.0, 0.89999, 0.9]), np.array(["p", "q", "r"]))
    assert [(f.where, round(f.margin, 8)) for f in order] == [("q vs r", 2e-5)]


def test_identical_backends_flip_nothing(victim, frame):
    for source in ("gt", "detector"):
        result = trace(victim, frame, source)
        assert result.flips == [] and not result.explained


def test_a_nudged_foreground_point_is_a_near_tie_only_within_the_tolerance(victim, frame):
    stages_t = TorchFrustumStages(victim.fpn)
    picked: dict[str, float] = {}

    class Nudged:
        """Torch stages, but the first frustum's point nearest the mask boundary changes side."""

        def segmentation(self, points, one_hot):
            logits = stages_t.segmentation(points, one_hot).copy()
            if not picked:
                margin = logits[0, :, 1] - logits[0, :, 0]
                p = int(np.argmin(np.abs(margin)))
                picked.update(point=p, margin=float(abs(margin[p])))
                logits[0, p, 1] -= 2 * margin[p]
            return logits

        center_delta = staticmethod(stages_t.center_delta)
        box_output = staticmethod(stages_t.box_output)

    result = trace(victim, frame, "gt", stages_o=Nudged())
    planted = ("segmentation-mask", f"proposal 0 point {picked['point']}")
    assert [(f.decision, f.where) for f in result.flips] == [planted]
    assert result.flips[0].margin == pytest.approx(picked["margin"], rel=1e-5)
    assert result.explained == (picked["margin"] <= TIE)
    picked.clear()
    strict = trace(victim, frame, "gt", stages_o=Nudged(), tie_atol=0.0)
    assert len(strict.flips) == 1 and (strict.explained is (strict.flips[0].margin == 0.0))


def test_a_shifted_objectness_is_not_a_tie(victim, frame):
    def shifted(images):
        heads = [h.copy() for h in victim.yolo.run_heads(images)]
        for h in heads:
            h[:, 4::6] += 3.0  # every prior's objectness logit (one class: 6 channels per anchor)
        return heads

    result = trace(victim, frame, "detector", heads_o=shifted)
    kinds = {f.decision for f in result.flips}
    assert "2d-threshold" in kinds and not result.explained
    assert max(f.margin for f in result.flips if f.decision == "2d-threshold") > 1e-2


def test_membership_flip_is_measured_from_the_box_edge(victim, frame):
    projected = project_scan(frame.scan, frame.calib, frame.image_size)
    box = frame.labels.bbox[frame.labels.type == "Car"][0].astype(np.float64)
    inside = np.flatnonzero(projected.in_fov & box_mask(projected.uv, box))
    p = int(inside[np.argmin(projected.uv[inside, 0])])  # the leftmost point of the box
    u = projected.uv[p, 0]
    bt, bo = box.copy(), box.copy()
    bt[0], bo[0] = u - 1e-7, u + 1e-7  # the point is inside the torch box, outside the other
    flips = _membership_flips(frame, bt[None], bo[None], victim.settings)
    assert [f.where for f in flips] == [f"proposal 0 point {p}"]
    assert flips[0].decision == "frustum-membership" and flips[0].margin == pytest.approx(1e-7, rel=1e-3)


def test_box_parity_passes_a_differing_frame_only_when_traced_to_a_tie(frame):
    rows = Labels.empty(with_score=True)
    other = frame.labels.select(np.array([0]))
    other = Labels(**{**other.__dict__, "score": np.array([0.5])})
    tol = Tolerances()

    def tie(f):
        return FrameDivergence(f.frame_id, "gt", [], explained=True)

    def real(f):
        return FrameDivergence(f.frame_id, "gt", [], explained=False)

    assert not box_parity([frame], "gt", [rows], [other], tol).ok
    assert not box_parity([frame], "gt", [rows], [other], tol, real).ok
    passed = box_parity([frame], "gt", [rows], [other], tol, tie)
    assert passed.ok and passed.near_tie_frames == 1 and passed.identical_frames == 0


def test_a_heading_bin_flip_is_found_with_the_torch_gap(victim, frame):
    stages_t = TorchFrustumStages(victim.fpn)
    gaps: list[float] = []

    class Swapped:
        """Torch stages, but the first frustum's two best heading bins trade places."""

        segmentation = staticmethod(stages_t.segmentation)
        center_delta = staticmethod(stages_t.center_delta)

        def box_output(self, object_points, one_hot):
            out = stages_t.box_output(object_points, one_hot).copy()
            if not gaps:
                scores = out[0, 3:3 + NUM_HEADING_BIN]
                first, second = np.argsort(-scores, kind="stable")[:2]
                gaps.append(float(scores[first] - scores[second]))
                scores[first], scores[second] = scores[second], scores[first]
            return out

    result = trace(victim, frame, "gt", stages_o=Swapped())
    assert [f.decision for f in result.flips] == ["heading-bin"] and result.flips[0].where.startswith("proposal 0 ")
    assert result.flips[0].margin == pytest.approx(gaps[0], rel=1e-6)
    assert result.explained == (gaps[0] <= TIE)


@pytest.mark.parametrize("disagrees_on_same_points", [False, True])
def test_after_a_mask_flip_heading_is_compared_on_the_torch_object_points(victim, frame, disagrees_on_same_points):
    """A flipped mask point changes the resampled object points, so the own-path box nets see
    different inputs; the tracer compares heading and size on the torch object points instead and
    reports a heading flip only when the box nets disagree there too."""
    stages_t = TorchFrustumStages(victim.fpn)
    calls: list[int] = []
    seg_calls: list[int] = []

    class FlippedMask:
        """Torch stages; the first frustum's point nearest the mask boundary changes side, and the
        box net swaps proposal 0's two best heading bins on its own path (first call) — and on
        the lockstep call too when ``disagrees_on_same_points``."""

        center_delta = staticmethod(stages_t.center_delta)

        def segmentation(self, points, one_hot):
            logits = stages_t.segmentation(points, one_hot).copy()
            seg_calls.append(len(logits))
            if len(seg_calls) == 1:  # the first chunk's first row only
                margin = logits[0, :, 1] - logits[0, :, 0]
                p = int(np.argmin(np.abs(margin)))
                logits[0, p, 1] -= 2 * margin[p]
            return logits

        def box_output(self, object_points, one_hot):
            out = stages_t.box_output(object_points, one_hot).copy()
            calls.append(len(out))
            if len(calls) == 1 or (len(calls) == 2 and disagrees_on_same_points):  # own path, lockstep
                scores = out[0, 3:3 + NUM_HEADING_BIN]
                first, second = np.argsort(-scores, kind="stable")[:2]
                scores[first], scores[second] = scores[second], scores[first]
            return out

    result = trace(victim, frame, "gt", stages_o=FlippedMask())
    assert calls[1] == 1  # one lockstep call, for the one proposal whose mask flipped
    decisions = [(f.decision, f.where.split(" point ")[0].split(" bins ")[0]) for f in result.flips]
    expected = [("segmentation-mask", "proposal 0")] + [("heading-bin", "proposal 0")] * disagrees_on_same_points
    assert decisions == expected
