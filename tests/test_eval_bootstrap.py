"""Bootstrap intervals over frames: the fast re-accumulation equals the evaluator on resampled frame lists.

The slow reference literally builds each resample's frame list (``np.repeat(frames, w)``, duplicated
frames included) and runs the full evaluator on it; the fixture sets are the evaluator's own stress
sets (ties, difficulty boundaries, DontCare, neighbour classes, tiny detections, no orientation).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robustbench3d.eval.bootstrap import (
    FrameBootstrap,
    ap_intervals,
    drop_intervals,
    percentile_interval,
    resample_weights,
    threshold_positions,
)
from robustbench3d.eval.kitti_eval import evaluate
from robustbench3d.eval.precision import score_thresholds
from robustbench3d.kitti import Labels
from robustbench3d.kitti.labels import parse_labels

FIXTURES = Path(__file__).parent / "fixtures" / "eval"


def _generator():
    spec = importlib.util.spec_from_file_location("eval_fixture_generate_bs", FIXTURES / "generate.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


GEN = _generator()
SPECS = {
    "mixed": GEN.SetSpec(seed=201, frames=40, gt_per_frame=7.0, boundary=0.6, small_other=0.3, duplicate=0.3,
                         score_decimals=1, dontcare_3d=0.5, fp_in_dontcare=0.8),
    "crowded": GEN.SetSpec(seed=202, frames=16, gt_per_frame=14.0, jitter2d=0.08, jitter3d=0.5, duplicate=0.4,
                           fp_per_frame=4.0, det_type_swap=0.4),
    "multiclass": GEN.SetSpec(seed=203, frames=12, type_weights={
        "Car": 0.3, "Van": 0.1, "Pedestrian": 0.25, "Person_sitting": 0.05, "Cyclist": 0.2, "DontCare": 0.1},
        score_decimals=2),
    "no_orientation": GEN.SetSpec(seed=204, frames=10, no_orientation=0.1, missing_results=0.3),
}
CLASSES = ("Car", "Pedestrian", "Cyclist")


def _labels(spec) -> tuple[list[Labels], list[Labels]]:
    ids, gt, dt = GEN.make_set(spec)
    gts = [parse_labels("\n".join(gt[i]), Path(f"{i}.txt"), scored=False) for i in ids]
    dts = [parse_labels("\n".join(dt[i]), Path(f"{i}.txt"), scored=True) if i in dt else Labels.empty(True)
           for i in ids]
    return gts, dts


def _reference(gts: list[Labels], dts: list[Labels], w: np.ndarray, keys) -> dict:
    """The full evaluator on the resample's literal frame list."""
    frames = np.repeat(np.arange(len(gts)), w)
    res = evaluate([gts[i] for i in frames], [dts[i] for i in frames], classes=CLASSES)
    return {k: res[k[0]][k[1]][k[2]][k[3]] for k in keys}


@pytest.mark.parametrize("name", sorted(SPECS))
def test_resampled_ap_equals_the_evaluator_on_the_resampled_frame_list(name: str) -> None:
    gts, dts = _labels(SPECS[name])
    prep = FrameBootstrap(gts, dts, classes=CLASSES)
    w = resample_weights(len(gts), 12, seed=7)
    w[0] = 0
    w[0, 0] = len(gts)  # one frame repeated F times
    got = prep.resampled(w)
    assert len(got) >= 12
    nonzero = 0
    for r in range(len(w)):
        ref = _reference(gts, dts, w[r], got.keys())
        for k, v in got.items():
            assert v[r] == pytest.approx(ref[k], abs=1e-9), (name, r, k)
            nonzero += ref[k] > 0
    assert nonzero > len(w)  # the cases exercise non-trivial curves
    if name in ("mixed", "crowded"):  # more GT than recall steps: the devkit's threshold picks matter
        assert max(int(c.n_gt.sum()) for cs in prep._curves.values() for c in cs) > 41


def test_unit_weights_reproduce_the_full_evaluation() -> None:
    gts, dts = _labels(SPECS["mixed"])
    prep = FrameBootstrap(gts, dts, classes=CLASSES)
    full = evaluate(gts, dts, classes=CLASSES)
    got = prep.resampled(np.ones((1, len(gts)), dtype=np.int64))
    for (c, m, r, d), v in got.items():
        assert v[0] == pytest.approx(full[c][m][r][d], abs=1e-9)


def test_intervals_are_percentiles_of_the_reference_and_the_drop_is_paired() -> None:
    gts, dts = _labels(SPECS["mixed"])
    rng = np.random.default_rng(3)
    worse = []
    for d in dts:  # an "attacked" set: a third of the detections removed, scores perturbed
        keep = rng.random(len(d)) > 0.33
        worse.append(Labels(d.type[keep], d.truncated[keep], d.occluded[keep], d.alpha[keep], d.bbox[keep],
                            d.dimensions[keep], d.location[keep], d.rotation_y[keep],
                            np.round(d.score[keep] * rng.uniform(0.8, 1.0, int(keep.sum())), 3)))
    clean, attacked = FrameBootstrap(gts, dts, CLASSES), FrameBootstrap(gts, worse, CLASSES)
    n = 16
    w = resample_weights(len(gts), n, seed=5)
    key = ("Car", "bev", "R40", "moderate")
    ref_clean = np.array([_reference(gts, dts, w[r], [key])[key] for r in range(n)])
    ref_att = np.array([_reference(gts, worse, w[r], [key])[key] for r in range(n)])
    ci = ap_intervals(clean, resamples=n, seed=5)
    assert ci["Car"]["bev"]["R40"]["moderate"] == pytest.approx(list(np.percentile(ref_clean, [2.5, 97.5])),
                                                                abs=1e-9)
    drop = drop_intervals(clean, attacked, resamples=n, seed=5)
    assert drop["Car"]["bev"]["R40"]["moderate"] == pytest.approx(
        list(np.percentile(ref_clean - ref_att, [2.5, 97.5])), abs=1e-9)
    assert drop["meta"]["resamples"] == n and drop["meta"]["seed"] == 5 and drop["meta"]["level"] == 0.95
    # Paired: the interval of the difference is not that of independently resampled sets.
    unpaired = ref_clean - np.array([_reference(gts, worse, w[(r + 1) % n], [key])[key] for r in range(n)])
    assert np.std(ref_clean - ref_att) < np.std(unpaired)


def test_deterministic_with_an_explicit_seed() -> None:
    gts, dts = _labels(SPECS["crowded"])
    prep = FrameBootstrap(gts, dts)
    a, b = ap_intervals(prep, 40, seed=1), ap_intervals(prep, 40, seed=1)
    c = ap_intervals(prep, 40, seed=2)
    assert a == b
    assert a != c
    assert np.array_equal(resample_weights(9, 3, 4), resample_weights(9, 3, 4))
    assert (resample_weights(9, 50, 4).sum(axis=1) == 9).all()


@settings(max_examples=300, deadline=None, derandomize=True)  # the same examples on every run
@given(m=st.integers(0, 300), n_gt=st.integers(0, 400), decimals=st.integers(0, 4), seed=st.integers(0, 2**32 - 1))
def test_threshold_positions_equal_the_devkit_walk(m: int, n_gt: int, decimals: int, seed: int) -> None:
    scores = np.sort(np.round(np.random.default_rng(seed).random(m), decimals))[::-1]
    want = score_thresholds(scores, n_gt)
    assert scores[threshold_positions(m, n_gt)].tolist() == want.tolist()


def test_bad_input_is_refused_clearly() -> None:
    gts, dts = _labels(SPECS["crowded"])
    prep = FrameBootstrap(gts, dts)
    with pytest.raises(ValueError, match="weights must be"):
        prep.resampled(np.ones((2, len(gts) + 1)))
    with pytest.raises(ValueError, match="non-negative integer"):
        prep.resampled(np.full((1, len(gts)), 0.5))
    with pytest.raises(ValueError, match="confidence level"):
        percentile_interval(np.arange(3.0), level=1.0)
    with pytest.raises(ValueError, match="resamples"):
        resample_weights(5, 0)
    with pytest.raises(ValueError, match="same frames"):
        drop_intervals(prep, FrameBootstrap(gts[:-1], dts[:-1]))
    with pytest.raises(ValueError, match="frames"):
        FrameBootstrap(gts, dts[:-1])
