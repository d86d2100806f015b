"""Bootstrap intervals over frames: the fast re-accumulation equals the evaluator on resampled frame lists.

The slow reference literally builds each resample's frame list (``np.repeat(frames, w)``, duplicated
frames included) and runs the full evaluator on it; the fixture sets are the evaluator's own stress
sets (ties, difficulty boundaries, DontCare, neighbour classes, tiny detections, no orientation).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from eval_fixture_generator import load_generator
from eval_sets import set_labels
from hypothesis import given, settings
from hypothesis import strategies as st

from robustbench3d.eval.bootstrap import (
    FrameBootstrap,
    _recall_steps,
    ap_intervals,
    drop_intervals,
    percentile_interval,
    resample_weights,
    threshold_positions,
)
from robustbench3d.eval.kitti_eval import evaluate
from robustbench3d.eval.precision import score_thresholds
from robustbench3d.eval.table import ObjectTable
from robustbench3d.kitti import Labels
from robustbench3d.kitti.labels import parse_labels

GEN = load_generator()
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


def _reference(gts: list[Labels], dts: list[Labels], w: np.ndarray, keys) -> dict:
    """The full evaluator on the resample's literal frame list."""
    frames = np.repeat(np.arange(len(gts)), w)
    res = evaluate([gts[i] for i in frames], [dts[i] for i in frames], classes=CLASSES)
    return {k: res[k[0]][k[1]][k[2]][k[3]] for k in keys}


@pytest.mark.parametrize("name", sorted(SPECS))
def test_resampled_ap_equals_the_evaluator_on_the_resampled_frame_list(name: str) -> None:
    gts, dts = set_labels(SPECS[name])
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
    gts, dts = set_labels(SPECS["mixed"])
    prep = FrameBootstrap(gts, dts, classes=CLASSES)
    full = evaluate(gts, dts, classes=CLASSES)
    got = prep.resampled(np.ones((1, len(gts)), dtype=np.int64))
    for (c, m, r, d), v in got.items():
        assert v[0] == pytest.approx(full[c][m][r][d], abs=1e-9)


def test_intervals_are_percentiles_of_the_reference_and_the_drop_is_paired() -> None:
    gts, dts = set_labels(SPECS["mixed"])
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
    gts, dts = set_labels(SPECS["crowded"])
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
    gts, dts = set_labels(SPECS["crowded"])
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


# ---- hand-made cases (mutation testing) ---------------------------------------------------------
_DC = "DontCare -1 -1 -10 30.00 0.00 200.00 50.00 -1 -1 -1 -1000 -1000 -1000 -10"
_HAND_GT = [  # frame 0 has a DontCare region; every Car is easy (60 px high, unoccluded)
    ["Car 0.00 0 -1.57 100.00 150.00 200.00 210.00 1.5 1.6 3.9 0.0 1.5 20.0 -1.57", _DC],
    ["Car 0.00 0 -1.57 300.00 150.00 400.00 210.00 1.5 1.6 3.9 5.0 1.5 25.0 -1.57"],
    ["Car 0.00 0 -1.57 500.00 150.00 600.00 210.00 1.5 1.6 3.9 -5.0 1.5 30.0 -1.57"],
    ["Car 0.00 0 -1.57 700.00 150.00 800.00 210.00 1.5 1.6 3.9 8.0 1.5 15.0 -1.57"],
]
_HAND_DT = [  # frame 0: a TP (0.9) and a higher FP (0.95) covering DontCare by exactly 0.7 (= the Car threshold)
    ["Car -1 -1 -1.57 100.00 150.00 200.00 210.00 1.5 1.6 3.9 0.0 1.5 20.0 -1.57 0.9",
     "Car -1 -1 -1.57 0.00 0.00 100.00 50.00 1.5 1.6 3.9 10.0 1.5 40.0 -1.57 0.95"],
    ["Car -1 -1 -1.50 300.00 150.00 400.00 210.00 1.5 1.6 3.9 5.0 1.5 25.0 -1.50 0.8"],
    [],
    ["Car -1 -1 -1.57 700.00 150.00 800.00 210.00 1.5 1.6 3.9 8.0 1.5 15.0 -1.57 0.7",
     "Car -1 -1 -1.57 900.00 150.00 1000.00 210.00 1.5 1.6 3.9 -8.0 1.5 35.0 -1.57 0.85"],
]


def _hand_labels(dt_lines=_HAND_DT) -> tuple[list[Labels], list[Labels]]:
    gts = [parse_labels("\n".join(lines), Path(f"{i}.txt"), scored=False) for i, lines in enumerate(_HAND_GT)]
    dts = [parse_labels("\n".join(lines), Path(f"{i}.txt"), scored=True) if lines else Labels.empty(True)
           for i, lines in enumerate(dt_lines)]
    return gts, dts


def test_recall_steps_are_the_41_devkit_steps_from_0_to_1() -> None:
    """The recall steps c_j = j / 40 (summed in float64, as the devkit): 41 of them, 0 first, 1 last."""
    steps = _recall_steps()
    assert steps.shape == (41,) and steps.dtype == np.float64 and steps[0] == 0.0
    assert np.allclose(steps, np.arange(41) / 40.0, rtol=0, atol=1e-12)


def test_dontcare_overlap_of_exactly_the_threshold_keeps_the_false_positive() -> None:
    """The devkit ignores an FP only when it covers DontCare by *more* than the class threshold: an
    overlap of exactly 0.7 (3500 / 5000 px) still counts, in every resample as in the evaluator."""
    gts, dts = _hand_labels()
    prep = FrameBootstrap(gts, dts)
    key = ("Car", "2d", "R11", "easy")
    w = np.array([[1, 1, 1, 1], [2, 0, 1, 1], [0, 1, 3, 0], [4, 0, 0, 0]])
    got = prep.resampled(w)[key]
    assert got.tolist() == pytest.approx([_reference(gts, dts, r, [key])[key] for r in w], abs=1e-9)
    _, no_fp = _hand_labels([_HAND_DT[0][:1], *_HAND_DT[1:]])
    assert _reference(gts, dts, w[3], [key])[key] < _reference(gts, no_fp, w[3], [key])[key]  # the FP counts


def test_tables_classes_and_metrics_are_passed_on() -> None:
    """Tables work like per-frame labels, and only the requested classes and metrics get intervals."""
    gts, dts = set_labels(SPECS["multiclass"])
    w = resample_weights(len(gts), 3, seed=2)
    by_table = FrameBootstrap(ObjectTable.from_labels(gts, scored=False), ObjectTable.from_labels(dts, scored=True),
                              classes=("Pedestrian",), metrics=("bev",))
    keys = by_table.keys()  # FrameBootstrap.keys(), a list
    assert len(keys) == 6 and {(k[0], k[1]) for k in keys} == {("Pedestrian", "bev")}
    by_labels = FrameBootstrap(gts, dts, classes=("Pedestrian",), metrics=("bev",))
    a, b = by_table.resampled(w), by_labels.resampled(w)
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def test_weights_and_the_self_check_refuse_what_they_must() -> None:
    """Negative counts are refused with the documented message; the unit-weight self-check accepts a
    discrepancy of up to 1e-9 (inclusive) and reports a larger one by key, with both values."""
    gts, dts = _hand_labels()
    prep = FrameBootstrap(gts, dts, metrics=("2d",))
    w = np.ones((1, 4))
    w[0, 1] = -1
    with pytest.raises(ValueError, match=r"^weights must be non-negative integer frame counts$"):
        prep.resampled(w)
    key = ("Car", "2d", "R40", "easy")
    prep.resampled = lambda w: {key: np.zeros(len(w))}
    prep.full = {"Car": {"2d": {"R40": {"easy": 1e-9}}}}
    prep._check()  # |0 - 1e-9| is not above 1e-9
    prep.full = {"Car": {"2d": {"R40": {"easy": 0.5}}}}
    with pytest.raises(AssertionError, match=r"^bootstrap accumulation gives 0\.0 for Car 2d R40 easy, "
                                             r"the evaluator 0\.5$"):
        prep._check()


def test_resample_weights_follow_the_documented_generator_and_limits() -> None:
    """Rows are ``default_rng([seed, 0x424F4F54]).multinomial`` draws (seed 0 by default); one frame, one
    resample and seed 0 are valid; the refusals name the bad value."""
    ref = np.random.default_rng([0, 0x424F4F54]).multinomial(6, np.full(6, 1 / 6), size=4)
    got = resample_weights(6, 4)
    assert got.dtype == np.int64 and got.tolist() == ref.tolist()
    assert resample_weights(6, 4, seed=0).tolist() == ref.tolist()
    assert resample_weights(1, 3).tolist() == [[1], [1], [1]]
    assert resample_weights(5, 1).shape == (1, 5)
    with pytest.raises(ValueError, match=r"^cannot resample 0 frames$"):
        resample_weights(0, 3)
    with pytest.raises(ValueError, match=r"^resamples must be at least 1, got 0$"):
        resample_weights(3, 0)
    with pytest.raises(ValueError, match=r"^seed must be non-negative, got -1$"):
        resample_weights(3, 2, seed=-1)


def test_percentile_interval_by_hand_in_float64() -> None:
    """Linear interpolation by hand, in float64 even for float32 values (whose difference 2^24 + 1 is no
    float32); the level must lie strictly inside (0, 1)."""
    v = np.array([1.0, 2.0**24 + 2], dtype=np.float32)
    d = 2.0**24 + 1
    assert percentile_interval(v) == pytest.approx([1 + 0.025 * d, 1 + 0.975 * d], rel=1e-15)
    assert percentile_interval([0, 10, 20], level=0.5) == pytest.approx([5.0, 15.0])
    for bad in (0.0, 1.0):
        with pytest.raises(ValueError, match=rf"^confidence level must be in \(0, 1\), got {bad}$"):
            percentile_interval(v, level=bad)


def test_interval_tables_by_hand() -> None:
    """ap_intervals / drop_intervals: the level's percentiles of the evaluator's APs on the literal
    resampled frame lists (seed 0 by default), and the documented meta block."""
    gts, dts = _hand_labels()
    _, worse = _hand_labels([_HAND_DT[0][1:], [], [], _HAND_DT[3]])  # the TPs of frames 0 and 1 lost
    clean, attacked = FrameBootstrap(gts, dts, metrics=("2d",)), FrameBootstrap(gts, worse, metrics=("2d",))
    n, key = 7, ("Car", "2d", "R11", "easy")
    w = np.random.default_rng([0, 0x424F4F54]).multinomial(4, np.full(4, 0.25), size=n)
    ref_c = np.array([_reference(gts, dts, r, [key])[key] for r in w])
    ref_a = np.array([_reference(gts, worse, r, [key])[key] for r in w])
    assert np.ptp(ref_c) > 0 and np.ptp(ref_c - ref_a) > 0
    meta = {"method": "percentile bootstrap over frames", "level": 0.8, "resamples": n, "seed": 0,
            "frames": 4, "rng": "numpy.random.default_rng([seed, 0x424f4f54]).multinomial"}
    ci = ap_intervals(clean, n, level=0.8)
    assert ci["Car"]["2d"]["R11"]["easy"] == pytest.approx(list(np.percentile(ref_c, [10, 90])), abs=1e-9)
    assert ci["meta"] == {**meta, "statistic": "AP"}
    drop = drop_intervals(clean, attacked, n, level=0.8)
    assert drop["Car"]["2d"]["R11"]["easy"] == pytest.approx(list(np.percentile(ref_c - ref_a, [10, 90])),
                                                              abs=1e-9)
    assert drop["meta"] == {**meta, "statistic": "AP(clean) - AP(attacked), the same resampled frames for both"}


def test_threshold_positions_of_an_unbounded_gt_count_match_the_devkit() -> None:
    """n_gt = inf reaches no recall step above 0, and the windowed search cannot place it (no finite
    estimate): the full search must still give the devkit's picks (the first and the last score)."""
    for m in (1, 2, 5, 50):
        scores = np.linspace(1.0, 0.1, m)
        with np.errstate(invalid="ignore"):  # the estimate's cast of inf
            got = threshold_positions(m, np.inf)
        assert scores[got].tolist() == score_thresholds(scores, np.inf).tolist() == scores[[0, m - 1][:m]].tolist()
