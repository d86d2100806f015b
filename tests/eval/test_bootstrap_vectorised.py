"""The bootstrap's accumulation vectorised over resamples gives the per-resample loop's float64 bits.

The reference is the per-resample loop (``_Curve.samples`` / ``FrameBootstrap._resampled_per_resample``,
the accumulation as it was before the vectorisation), whose APs the evaluator on literal resampled frame
lists checks (tests/eval/test_eval_bootstrap.py). Equality here is exact: ``tobytes`` of the float64 arrays
(so -0.0 differs from 0.0), on the evaluator's stress sets, hand-made frames (a class without
detections, a frame without GT, frames drawn zero times) and event tables made up to reach every
segment length of the similarity sums (1 to beyond 2048 events, and tables of at most three events).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from eval_fixture_generator import load_generator
from eval_sets import set_labels

from robustbench3d.eval.bootstrap import (
    FrameBootstrap,
    _Curve,
    _positions_rows,
    resample_weights,
    threshold_positions,
)
from robustbench3d.kitti import Labels
from robustbench3d.kitti.labels import parse_labels

CLASSES = ("Car", "Pedestrian", "Cyclist")




GEN = load_generator()
SPECS = {
    "ties": GEN.SetSpec(seed=401, frames=30, gt_per_frame=8.0, duplicate=0.3, score_decimals=1, dontcare_3d=0.5,
                        fp_in_dontcare=0.8),
    "crowded": GEN.SetSpec(seed=402, frames=14, gt_per_frame=14.0, jitter2d=0.08, jitter3d=0.5, fp_per_frame=4.0),
    "multiclass": GEN.SetSpec(seed=403, frames=12, score_decimals=2, type_weights={
        "Car": 0.3, "Van": 0.1, "Pedestrian": 0.25, "Person_sitting": 0.05, "Cyclist": 0.2, "DontCare": 0.1}),
    "no_orientation": GEN.SetSpec(seed=404, frames=10, no_orientation=0.1, missing_results=0.3),
}


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _weights(n_frames: int, resamples: int, seed: int) -> np.ndarray:
    """Multinomial rows plus rows that draw frames zero times or many times, and an all-zero row."""
    w = resample_weights(n_frames, resamples, seed)
    w[0] = 0
    w[0, 0] = n_frames  # one frame only: every other frame drawn zero times
    w[1] = 0  # nothing drawn
    w[2] = np.arange(n_frames) % 3  # a third of the frames drawn zero times, others once or twice
    w[3] = 7  # every frame many times (long runs of equal scores)
    return w


def _assert_rows_equal_loop(prep: FrameBootstrap, w: np.ndarray) -> int:
    """Every curve's raw samples, row by row, bit for bit; returns how many AOS samples are not zero."""
    wf = w.astype(np.float64)
    nonzero = 0
    for (cls, kind), curves in prep._curves.items():
        with_aos = "aos" in prep.full[cls] and kind == "2d" and prep._aos
        for curve in curves:
            prec, aos = curve.sample_rows(wf, with_aos)
            for r in range(len(w)):
                p, a = curve.samples(wf[r], with_aos)
                assert _same_bits(prec[r], p), (cls, kind, r)
                assert (aos is None) == (a is None)
                if a is not None:
                    assert _same_bits(aos[r], a), (cls, kind, r)
                    nonzero += int(np.count_nonzero(a))
    return nonzero


@pytest.mark.parametrize("name", sorted(SPECS))
def test_vectorised_aps_equal_the_per_resample_loop_bit_for_bit(name: str) -> None:
    gts, dts = set_labels(SPECS[name])
    prep = FrameBootstrap(gts, dts, classes=CLASSES)
    w = _weights(len(gts), 23, seed=11)
    want = prep._resampled_per_resample(w)
    for chunk in (None, 1, 5, 23, 64):  # 23 is no multiple of 5: a short last chunk
        got = prep.resampled(w, chunk=chunk)
        assert list(got) == list(want)
        for k in want:
            assert _same_bits(got[k], want[k]), (name, chunk, k)
    assert sum(np.count_nonzero(v) for v in want.values()) > len(want)  # non-trivial curves


@pytest.mark.parametrize("name", sorted(SPECS))
def test_raw_precision_and_aos_samples_equal_the_loop(name: str) -> None:
    gts, dts = set_labels(SPECS[name])
    prep = FrameBootstrap(gts, dts, classes=CLASSES)
    nonzero = _assert_rows_equal_loop(prep, _weights(len(gts), 17, seed=3))
    if prep._aos:
        assert nonzero > 0  # the similarity sums are exercised


_CAR = "Car 0.00 0 -1.57 {l:.2f} 150.00 {r:.2f} 210.00 1.5 1.6 3.9 {x:.1f} 1.5 {z:.1f} -1.57"
_PED = "Pedestrian 0.00 0 0.10 620.00 140.00 660.00 220.00 1.7 0.6 0.8 2.0 1.6 12.0 0.10"


def _hand_set() -> tuple[list[Labels], list[Labels]]:
    """Five frames: Pedestrians in the GT but never detected (a class without detections); frame 3 has
    no GT at all but two detections (false positives only); frame 4 has neither."""
    gt_lines = [
        [_CAR.format(l=100, r=200, x=0.0, z=20.0), _PED],
        [_CAR.format(l=300, r=400, x=5.0, z=25.0), _CAR.format(l=700, r=800, x=8.0, z=15.0)],
        [_CAR.format(l=500, r=600, x=-5.0, z=30.0), _PED],
        [],
        [],
    ]
    dt_lines = [
        [_CAR.format(l=100, r=200, x=0.0, z=20.0).replace("-1.57 100", "-1.40 100") + " 0.9",
         _CAR.format(l=900, r=1000, x=-8.0, z=35.0) + " 0.95"],
        [_CAR.format(l=302, r=401, x=5.1, z=25.2) + " 0.8", _CAR.format(l=700, r=800, x=8.0, z=15.0) + " 0.8"],
        [_CAR.format(l=500, r=600, x=-5.0, z=30.0).replace("-1.57 500", "0.30 500") + " 0.6"],
        [_CAR.format(l=300, r=400, x=5.0, z=25.0) + " 0.85", _CAR.format(l=20, r=90, x=-9.0, z=40.0) + " 0.4"],
        [],
    ]
    gts = [parse_labels("\n".join(lines), Path(f"{i}.txt"), scored=False) for i, lines in enumerate(gt_lines)]
    dts = [parse_labels("\n".join(lines), Path(f"{i}.txt"), scored=True) if lines else Labels.empty(True)
           for i, lines in enumerate(dt_lines)]
    return gts, dts


def test_hand_frames_class_without_detections_frame_without_gt_and_zero_draws() -> None:
    gts, dts = _hand_set()
    prep = FrameBootstrap(gts, dts, classes=("Car", "Pedestrian"))
    assert all(len(c.tp_score) == 0 for c in prep._curves[("Pedestrian", "2d")])  # no Pedestrian detection
    assert all(c.n_gt[3] == 0 for cs in prep._curves.values() for c in cs)  # frame 3: no GT
    w = np.array([[1, 1, 1, 1, 1], [0, 0, 0, 5, 0], [0, 0, 0, 0, 5], [2, 0, 0, 3, 0], [0, 4, 1, 0, 0],
                  [5, 0, 0, 0, 0], [1, 2, 0, 2, 0]])
    want = prep._resampled_per_resample(w)
    for chunk in (None, 1, 3):
        got = prep.resampled(w, chunk=chunk)
        assert all(_same_bits(got[k], want[k]) for k in want)
    assert all(not got[k].any() for k in got if k[0] == "Pedestrian")  # AP 0 without detections
    assert not got[("Car", "2d", "R40", "moderate")][1].any()  # only the false-positive frame: AP 0
    assert _assert_rows_equal_loop(prep, w) > 0


def _made_up_curve(rng: np.random.Generator, n_frames: int, n_tp: int, n_thr: int, n_events: int,
                   together: bool = False) -> _Curve:
    """A :class:`_Curve` with made-up tables of the documented shapes (not from an evaluation): sorted TP
    scores with ties, events sorted by threshold index (``together``: all at the first threshold), whole
    TP / FP changes, fractional similarities."""
    tp_config = np.sort(rng.integers(0, n_thr, n_tp))
    tp_config[0], tp_config[-1] = 0, n_thr - 1
    thresholds = np.sort(rng.random(n_thr))[::-1]
    ev_values = np.stack([rng.integers(-1, 3, n_events).astype(np.float64),
                          rng.integers(-1, 3, n_events).astype(np.float64),
                          rng.random(n_events) * rng.integers(1, 4, n_events)])
    return _Curve(tp_score=thresholds[tp_config], tp_frame=rng.integers(0, n_frames, n_tp), tp_config=tp_config,
                  thresholds=thresholds, n_gt=rng.integers(0, 4, n_frames),
                  ev_config=np.sort(rng.integers(0, 1 if together else n_thr, n_events)),
                  ev_frame=rng.integers(0, n_frames, n_events), ev_values=ev_values)


@pytest.mark.parametrize(("n_tp", "n_thr", "n_events", "together"), [
    (40, 30, 1, True), (40, 30, 2, True), (40, 30, 3, True), (5, 3, 3, True),  # one segment of all events
    (40, 30, 3, False), (40, 30, 2, False),  # at most three events, in shorter segments
    (60, 50, 200, False), (300, 120, 900, False),  # short and medium segments
    (80, 6, 9000, False),  # few thresholds, many events: segments beyond 2048 events
])
def test_made_up_event_tables_of_every_segment_length(n_tp: int, n_thr: int, n_events: int, together: bool) -> None:
    rng = np.random.default_rng(n_tp * 7919 + n_events)
    n_frames = 30
    curve = _made_up_curve(rng, n_frames, n_tp, n_thr, n_events, together)
    w = _weights(n_frames, 29, seed=n_events).astype(np.float64)
    lengths = set()
    for with_aos in (True, False):
        prec, aos = curve.sample_rows(w, with_aos)
        for r in range(len(w)):
            p, a = curve.samples(w[r], with_aos)
            assert _same_bits(prec[r], p) and (a is None or _same_bits(aos[r], a)), (with_aos, r)
            cw = np.cumsum(w[r][curve.tp_frame])
            pos = threshold_positions(round(float(cw[-1])), float(w[r] @ curve.n_gt))
            ends = np.searchsorted(curve.ev_config, curve.tp_config[np.searchsorted(cw, pos, side="right")],
                                   side="right")
            lengths |= set(np.diff(np.r_[0, np.unique(ends)]).tolist()) - {0}
    if n_events == 9000:
        assert max(lengths) > 2048
    if together:
        assert lengths == {n_events}


def test_threshold_positions_of_many_rows_equal_one_at_a_time() -> None:
    """Every (TP count, GT count) pair, 0 included, including GT counts far below and above the TP count
    and the unbounded GT count whose window search fails (the full search of the scalar function)."""
    m = np.repeat(np.arange(0, 90), 14)
    n = np.tile([0, 1, 2, 3, 7, 40, 41, 80, 81, 160, 1000, 4321, 10**6, np.inf], 90)
    with np.errstate(invalid="ignore"):  # the estimate's cast of inf, in both
        pos, count = _positions_rows(m, n)
        for r in range(len(m)):
            want = threshold_positions(int(m[r]), float(n[r]))
            assert count[r] == len(want) and pos[r, : count[r]].tolist() == want.tolist(), (m[r], n[r])


def test_chunk_must_be_a_positive_count() -> None:
    gts, dts = _hand_set()
    prep = FrameBootstrap(gts, dts)
    for bad in (0, -3, 2.5):
        with pytest.raises(ValueError, match=r"^chunk must be a positive number of resamples, got "):
            prep.resampled(np.ones((2, 5)), chunk=bad)
