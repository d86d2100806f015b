"""Bootstrap confidence intervals of AP over frames, and of the paired AP drop of two result sets.

A resample draws ``F`` frames with replacement from the ``F`` evaluated frames: its frame list is
``np.repeat(np.arange(F), w)`` for multinomial counts ``w`` (:func:`resample_weights`), and its AP is
what :func:`~robustbench3d.eval.kitti_eval.evaluate_tables` returns for that list (duplicated frames
are separate frames). The interval is the percentile interval of the resampled APs (95 %: the 2.5th
and 97.5th percentiles, numpy's linear interpolation). The paired drop resamples the same frames for
both result sets (same ``w``) and takes the percentiles of AP(clean) - AP(attacked).

Fast, exact: the evaluator's matching is per frame, so it runs once. For every class, overlap kind
and difficulty, the score thresholds any resample can pick are the pass-1 TP scores; each frame's
pass-2 TP count, AOS similarity and assigned-counting count are step functions of the threshold
that only move where one of the frame's own detections enters, so they are computed there (the
evaluator's :func:`~robustbench3d.eval.matching.assign_at_thresholds`) and stored as per-frame
events. A resample then only re-accumulates with frame weights: the weighted TP scores and GT count
give the devkit's thresholds (:func:`threshold_positions`, the closed form of
:func:`~robustbench3d.eval.precision.score_thresholds`), weighted event sums give TP, FP and
similarity there. Metrics the evaluator skips on all frames (no usable box, AOS without
orientation) carry no interval; a class without detections has AP 0 in every resample.

Vectorised over resamples (:meth:`_Curve.sample_rows`, chunks of rows bounded in memory), with the
float64 bits of the per-resample loop (:meth:`_Curve.samples`, kept as the reference of the tests and
the benchmark): the picks come from whole numbers (frame counts, TP and GT totals; computed in int64,
exactly), and the event sums (TP, FP and the fractional AOS similarity) with the loop's operations in
its order: each segment of events between two picked thresholds is the same numpy ``matmul`` of the
same event rows with the same weights (batched by segment length, which runs the same BLAS ``gemv``
per segment), and the running sum over segments is a cumulative sum along the picks.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from robustbench3d.eval.kitti_eval import ClassEvaluation, class_overlaps, evaluate_tables
from robustbench3d.eval.matching import (
    CandidatePairs,
    assign_at_thresholds,
    collect_tp_detections,
    true_positives,
)
from robustbench3d.eval.overlaps import PairOverlaps
from robustbench3d.eval.precision import ratio
from robustbench3d.eval.rules import (
    DIFFICULTIES,
    INVALID_ALPHA,
    METRICS,
    MIN_OVERLAP,
    N_SAMPLE_PTS,
    OVERLAP_OF_METRIC,
    RECALL_SAMPLES,
    TARGET_CLASS,
    normalise_names,
)
from robustbench3d.eval.table import ObjectTable
from robustbench3d.kitti.labels import Labels

#: (class, metric, recall sampling, difficulty) of one AP.
APKey = tuple[str, str, str, str]
#: Default number of resamples and confidence level.
RESAMPLES = 1000
LEVEL = 0.95
#: Third entropy word of the resampling generator (separates it from other uses of the seed).
BOOTSTRAP_STREAM = 0x424F4F54  # "BOOT"
#: Configurations evaluated per assign_at_thresholds call while building the events (memory bound).
_CONFIGS_PER_CALL = 256
#: Memory bounds of the vectorised accumulation, in float64 / int64 values: of the (resamples, TP scores
#: or frames) arrays of one chunk of resamples (2^21 values, 16 MiB: 1000 resamples in one chunk up to
#: ~2000 TP scores), and of the event rows and weights copied for one batch of segments (16 MiB).
_CHUNK_VALUES = 1 << 21
_SEGMENT_VALUES = 1 << 21


def _recall_steps() -> np.ndarray:
    """The devkit's recall steps ``c``, summed in float64 exactly as :func:`score_thresholds` does."""
    out, c, step = [], 0.0, 1.0 / (N_SAMPLE_PTS - 1.0)
    for _ in range(N_SAMPLE_PTS):
        out.append(c)
        c += step
    return np.array(out)


_STEPS = _recall_steps()
_WINDOW = np.arange(-2, 3)


def _takes(i: np.ndarray, c: np.ndarray, n: float) -> np.ndarray:
    """The devkit's take test at sorted position ``i`` for recall step ``c`` (same float operations)."""
    return ((i + 2).astype(np.float64) / n - c) >= (c - (i + 1).astype(np.float64) / n)


def threshold_positions(m: int, n_gt: float) -> np.ndarray:
    """Positions (into the m TP scores sorted descending) that ``score_thresholds`` picks, in its order.

    The take test is monotone in the position, so the first position taken at recall step j alone is
    ``g_j`` (found next to ``n c_j - 1.5``, then checked with the devkit's own float expression; the last
    position always takes), and the walk gives ``i_j = min(j + max_{k<=j}(g_k - k), m - 1)`` until it
    reaches ``m - 1`` or 41 picks.
    """
    if m <= 0 or n_gt <= 0:
        return np.empty(0, dtype=np.int64)
    n = float(n_gt)
    est = np.ceil(n * _STEPS - 1.5).astype(np.int64)
    cand = np.clip(est[:, None] + _WINDOW[None, :], 0, m - 1)
    ok = _takes(cand, _STEPS[:, None], n) | (cand == m - 1)
    first = np.where(ok.any(axis=1), cand[np.arange(len(est)), ok.argmax(axis=1)], m - 1)
    # The window must bracket the switch: the position before it must not take (else search fully).
    bad = (cand[:, 0] > 0) & _takes(cand[:, 0] - 1, _STEPS, n) | ~ok.any(axis=1) & (cand[:, -1] < m - 1)
    for j in np.flatnonzero(bad):
        pos = np.arange(m)
        t = _takes(pos, _STEPS[j], n)
        t[-1] = True
        first[j] = int(np.argmax(t))
    walk = np.arange(N_SAMPLE_PTS) + np.maximum.accumulate(first - np.arange(N_SAMPLE_PTS))
    walk = np.minimum(walk, m - 1)
    end = int(np.argmax(walk == m - 1)) + 1 if (walk == m - 1).any() else N_SAMPLE_PTS
    return walk[:end]


def _positions_rows(m: np.ndarray, n_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`threshold_positions` of every row (``m[r]`` TP scores, ``n_gt[r]`` GT; same float operations).

    Returns ``(pos, count)``: (R, 41) positions, of which the first ``count[r]`` are row r's picks.
    """
    live = (m > 0) & (n_gt > 0)
    top = np.where(live, m, 1)[:, None] - 1  # (R, 1): the last position
    n = np.where(live, n_gt, 1.0)[:, None].astype(np.float64)
    est = np.ceil(n * _STEPS - 1.5).astype(np.int64)
    cand = np.clip(est[:, :, None] + _WINDOW, 0, top[:, :, None])
    ok = _takes(cand, _STEPS[:, None], n[:, :, None]) | (cand == top[:, :, None])
    found = ok.any(axis=2)
    first = np.where(found, np.take_along_axis(cand, ok.argmax(axis=2)[:, :, None], axis=2)[:, :, 0], top)
    bad = (cand[:, :, 0] > 0) & _takes(cand[:, :, 0] - 1, _STEPS, n) | ~found & (cand[:, :, -1] < top)
    for r, j in zip(*np.nonzero(bad & live[:, None]), strict=True):
        t = _takes(np.arange(top[r, 0] + 1), _STEPS[j], n[r, 0])
        t[-1] = True
        first[r, j] = int(np.argmax(t))
    steps = np.arange(N_SAMPLE_PTS)
    walk = np.minimum(steps + np.maximum.accumulate(first - steps, axis=1), top)
    last = walk == top
    count = np.where(last.any(axis=1), last.argmax(axis=1) + 1, N_SAMPLE_PTS)
    return walk, np.where(live, count, 0)


def _search_rows(cw: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Per row r, ``np.searchsorted(cw[r], pos[r], side="right")`` (clipped to the last index) for
    non-decreasing int64 rows ``cw`` >= 0 and positions ``0 <= pos``: one search over the rows laid
    end to end, each shifted above the previous one."""
    rows, width = cw.shape
    span = int(cw[:, -1].max()) + int(pos.max()) + 1
    shift = np.arange(rows, dtype=np.int64)[:, None] * span
    at = np.searchsorted((cw + shift).ravel(), (pos + shift).ravel(), side="right").reshape(pos.shape)
    return np.minimum(at - np.arange(rows)[:, None] * width, width - 1)


@dataclass(frozen=True)
class _Curve:
    """What one class x overlap kind x difficulty needs to re-accumulate under frame weights.

    Attributes:
        tp_score: (M,) pass-1 TP scores, descending; tp_frame: their frames.
        tp_config: (M,) index of each TP score into ``thresholds``.
        thresholds: (T,) distinct TP scores, descending (every threshold a resample can pick).
        n_gt: (F,) counted GT per frame.
        ev_config, ev_frame: (E,) events sorted by threshold index: from ``thresholds[ev_config]``
            downwards, frame ``ev_frame`` changes its TP count, FP count and AOS similarity sum by
            ``ev_values[:, e]`` (rows tp, fp, similarity).
    """

    tp_score: np.ndarray
    tp_frame: np.ndarray
    tp_config: np.ndarray
    thresholds: np.ndarray
    n_gt: np.ndarray
    ev_config: np.ndarray
    ev_frame: np.ndarray
    ev_values: np.ndarray

    def samples(self, w: np.ndarray, with_aos: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Raw (not yet interpolated) precision and AOS at the thresholds picked under weights ``w``
        (one resample; the reference of :meth:`sample_rows`)."""
        prec = np.zeros(N_SAMPLE_PTS)
        aos = np.zeros(N_SAMPLE_PTS) if with_aos else None
        if not len(self.tp_score):
            return prec, aos
        cw = np.cumsum(w[self.tp_frame])
        pos = threshold_positions(round(float(cw[-1])), float(w @ self.n_gt))
        if not len(pos):
            return prec, aos
        k = self.tp_config[np.searchsorted(cw, pos, side="right")]
        # Prefix sums of the weighted events up to each picked threshold (ends: non-decreasing).
        ends = np.searchsorted(self.ev_config, k, side="right")
        ew = w[self.ev_frame]
        values = self.ev_values[: 3 if with_aos else 2]
        vals = np.empty((len(values), len(ends)))
        run = np.zeros(len(values))
        start = 0
        for j, end in enumerate(ends.tolist()):
            if end > start:
                run = run + values[:, start:end] @ ew[start:end]
                start = end
            vals[:, j] = run
        tp, fp = vals[0], vals[1]
        prec[: len(k)] = ratio(tp, tp + fp)
        if aos is not None:
            aos[: len(k)] = ratio(vals[2], tp + fp)
        return prec, aos

    def sample_rows(self, w: np.ndarray, with_aos: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """:meth:`samples` of every row of ``w`` ((R, F) float64 frame counts) as (R, 41) arrays, bit for bit."""
        prec = np.zeros((len(w), N_SAMPLE_PTS))
        aos = np.zeros((len(w), N_SAMPLE_PTS)) if with_aos else None
        if not len(self.tp_score):
            return prec, aos
        counts = w.astype(np.int64)
        cw = np.cumsum(counts[:, self.tp_frame], axis=1)
        # The picks depend on the TP count and the GT count only: once per distinct pair.
        m, n_gt = cw[:, -1], counts @ self.n_gt
        pairs, inverse = np.unique(m * (int(n_gt.max()) + 1) + n_gt, return_inverse=True)
        first = np.zeros(len(pairs), dtype=np.int64)
        first[inverse] = np.arange(len(m))
        pos, count = (v[inverse] for v in _positions_rows(m[first], n_gt[first].astype(np.float64)))
        picked = np.arange(N_SAMPLE_PTS) < count[:, None]
        k = self.tp_config[_search_rows(cw, pos)]
        # Events up to each picked threshold; after a row's last pick they stay put (no further segment).
        ends = np.maximum.accumulate(np.where(picked, np.searchsorted(self.ev_config, k, side="right"), 0), axis=1)
        sums = self._running_sums(w, ends, 3 if with_aos else 2)
        tp, fp = sums[:, :, 0], sums[:, :, 1]
        prec[:] = np.where(picked, ratio(tp, tp + fp), 0.0)
        if aos is not None:
            aos[:] = np.where(picked, ratio(sums[:, :, 2], tp + fp), 0.0)
        return prec, aos

    def _running_sums(self, w: np.ndarray, ends: np.ndarray, n_values: int) -> np.ndarray:
        """(R, 41, n_values): the first ``n_values`` event rows weighted by ``w`` and summed up to ``ends[r, j]``
        events, with the operations of :meth:`samples`.

        :meth:`samples` adds, at each pick that takes new events, ``values[:, start:end] @ ew[start:end]``
        to a running sum. Here every such segment of every row is the same ``matmul`` of the same
        (n_values, length) event rows and weights, batched by segment length (the rows copied with a row
        stride that, like the original's, equals the length only when there are that few events; a
        batched ``matmul`` runs the same BLAS ``gemv``, or for one event the same loop, per segment), and
        the running sums are cumulative sums along the picks, in the same order.
        """
        before = np.concatenate([np.zeros((len(ends), 1), dtype=np.int64), ends[:, :-1]], axis=1)
        rows, cols = np.nonzero(ends > before)
        starts, lengths = before[rows, cols], ends[rows, cols] - before[rows, cols]
        values = self.ev_values[:n_values]
        added = np.zeros((*ends.shape, n_values))
        order = np.argsort(lengths, kind="stable")
        uniq, first = np.unique(lengths[order], return_index=True)
        bounds = np.r_[first, len(order)].tolist()
        for length, lo, hi in zip(uniq.tolist(), bounds[:-1], bounds[1:], strict=True):
            stride = max(length, min(values.shape[1], 4))
            step = max(1, _SEGMENT_VALUES // ((n_values + 1) * stride))
            for b in range(lo, hi, step):
                at = order[b:min(b + step, hi)]
                idx = starts[at, None] + np.arange(length)
                a = np.empty((len(at), n_values, stride))
                for i in range(n_values):
                    a[:, i, :length] = values[i][idx]
                x = w[rows[at, None], self.ev_frame[idx]]
                added[rows[at], cols[at]] = np.matmul(a[:, :, :length], x[:, :, None])[:, :, 0]
        return np.cumsum(np.concatenate([np.zeros((len(ends), 1, n_values)), added], axis=1), axis=1)[:, 1:]


def _pairs_of_kind(ce: ClassEvaluation, pairs: PairOverlaps, kind: str) -> tuple[np.ndarray, ...]:
    """The candidate pairs of the class and kind, as :meth:`ClassEvaluation.threshold_counts` selects them."""
    thr = MIN_OVERLAP[kind][ce.cls]
    ov = pairs.values[kind]
    keep = (ov > thr) & np.isin(pairs.gt, ce.gt_rows) & np.isin(pairs.det, ce.det_rows)
    return (np.searchsorted(ce.gt_rows, pairs.gt[keep]), np.searchsorted(ce.det_rows, pairs.det[keep]), ov[keep])


def _curves(ce: ClassEvaluation, pairs: PairOverlaps, dontcare: PairOverlaps, kind: str, n_frames: int,
            det_frame: np.ndarray) -> list[_Curve]:
    """The three difficulties' :class:`_Curve` of one class and overlap kind."""
    gi, di, ov = _pairs_of_kind(ce, pairs, kind)
    cand = CandidatePairs.build(gi, di, ov, ce.gt_frame)
    tp_dets = collect_tp_detections(cand, ce.gt_status, ce.det_status, ce.score)
    thr = MIN_OVERLAP[kind][ce.cls]
    fp_candidate = ~np.isin(ce.det_rows, dontcare.det[dontcare.values[kind] > thr])
    pair_frame = ce.gt_frame[gi]
    paired = np.unique(di)

    per_diff = []
    configs: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (frame, difficulty, threshold index)
    for d in range(3):
        order = np.argsort(-ce.score[tp_dets[d]], kind="stable")
        tp_score = ce.score[tp_dets[d]][order]
        thresholds = np.unique(tp_score)[::-1]
        tp_config = len(thresholds) - 1 - np.searchsorted(thresholds[::-1], tp_score)
        # A detection is usable at threshold index k once thresholds[k] <= its score.
        usable = paired[ce.det_status[d, paired] != -1]
        entry = len(thresholds) - np.searchsorted(thresholds[::-1], ce.score[usable], side="right")
        frame = det_frame[usable]
        keep = entry < len(thresholds)
        fk = np.unique(np.stack([frame[keep], entry[keep]]), axis=1)  # sorted by frame, then entry
        configs.append((fk[0], np.full(fk.shape[1], d), fk[1]))
        counting = (ce.det_status[d] == 0) & fp_candidate
        fp_order = np.argsort(ce.score[counting], kind="stable")
        n_gt = np.bincount(ce.gt_frame[ce.gt_status[d] == 0], minlength=n_frames)
        per_diff.append((tp_score, det_frame[tp_dets[d]][order], tp_config, thresholds, n_gt,
                         ce.score[counting][fp_order], det_frame[counting][fp_order]))

    cfg_frame = np.concatenate([c[0] for c in configs]).astype(np.int64)
    cfg_diff = np.concatenate([c[1] for c in configs]).astype(np.int64)
    cfg_k = np.concatenate([c[2] for c in configs]).astype(np.int64)
    cfg_thr = np.concatenate([per_diff[d][3][c[2]] for d, c in enumerate(configs)]) if len(cfg_k) else np.empty(0)
    tp_n = np.zeros(len(cfg_k))
    sim = np.zeros(len(cfg_k))
    assigned = np.zeros(len(cfg_k))
    # Frames are independent, so configurations of one frame run against that frame's pairs only:
    # batches of consecutive frames, each configuration counting the assignments in its own frame.
    order = np.argsort(cfg_frame, kind="stable")
    for lo in range(0, len(cfg_k), _CONFIGS_PER_CALL):
        sel = order[lo:lo + _CONFIGS_PER_CALL]
        f_lo, f_hi = cfg_frame[sel[0]], cfg_frame[sel[-1]]
        m = (pair_frame >= f_lo) & (pair_frame <= f_hi)
        sub = CandidatePairs.build(gi[m], di[m], ov[m], ce.gt_frame)
        c_diff, c_thr, c_frame = cfg_diff[sel], cfg_thr[sel], cfg_frame[sel]
        a = assign_at_thresholds(sub, c_diff, c_thr, ce.det_status, ce.score)
        own = ce.gt_frame[a.gt] == c_frame[a.config]
        tp = true_positives(a, c_diff, ce.gt_status, ce.det_status) & own
        s = (1.0 + np.cos(ce.gt_alpha[a.gt[tp]] - ce.det_alpha[a.det[tp]])) / 2.0
        ac = own & (ce.det_status[c_diff[a.config], a.det] == 0) & fp_candidate[a.det]
        tp_n[sel] = np.bincount(a.config[tp], minlength=len(sel))
        sim[sel] = np.bincount(a.config[tp], weights=s, minlength=len(sel))
        assigned[sel] = np.bincount(a.config[ac], minlength=len(sel))

    out = []
    for d in range(3):
        tp_score, tp_frame, tp_config, thresholds, n_gt, fp_score, fp_frame = per_diff[d]
        at = np.flatnonzero(cfg_diff == d)  # sorted by frame, then threshold index
        f, k = cfg_frame[at], cfg_k[at]
        first = np.r_[True, f[1:] != f[:-1]]

        def delta(v: np.ndarray, first: np.ndarray = first) -> np.ndarray:
            return v - np.where(first, 0.0, np.r_[0.0, v[:-1]])

        # FP = counting detections at or above the threshold (each enters once) - assigned ones.
        entry = len(thresholds) - np.searchsorted(thresholds[::-1], fp_score, side="right")
        inside = entry < len(thresholds)
        n_in = int(inside.sum())
        ev_k = np.r_[k, entry[inside]]
        ev_f = np.r_[f, fp_frame[inside]]
        values = np.concatenate([np.stack([delta(tp_n[at]), -delta(assigned[at]), delta(sim[at])]),
                                 np.stack([np.zeros(n_in), np.ones(n_in), np.zeros(n_in)])], axis=1)
        # One event per (threshold index, frame), sorted by threshold index.
        uniq, inverse = np.unique(np.stack([ev_k, ev_f]), axis=1, return_inverse=True)
        summed = np.stack([np.bincount(inverse.reshape(-1), weights=v, minlength=uniq.shape[1]) for v in values])
        out.append(_Curve(tp_score, tp_frame, tp_config, thresholds, n_gt, uniq[0], uniq[1], summed))
    return out


def _tables(gt: Sequence[Labels] | ObjectTable, dt: Sequence[Labels] | ObjectTable) -> tuple[ObjectTable, ObjectTable]:
    gt_t = gt if isinstance(gt, ObjectTable) else ObjectTable.from_labels(gt, scored=False)
    dt_t = dt if isinstance(dt, ObjectTable) else ObjectTable.from_labels(dt, scored=True)
    if gt_t.n_frames != dt_t.n_frames:
        raise ValueError(f"{gt_t.n_frames} ground-truth frames but {dt_t.n_frames} detection frames")
    return gt_t, dt_t


class FrameBootstrap:
    """One result set against its ground truth, prepared for AP under any frame weights.

    Args:
        gt, dt: per-frame :class:`Labels` (or tables) of the same frames; detections with scores.
        classes, metrics: as in :func:`~robustbench3d.eval.kitti_eval.evaluate_tables` (None: the
            classes with a detection, Car if none).
    """

    def __init__(self, gt: Sequence[Labels] | ObjectTable, dt: Sequence[Labels] | ObjectTable,
                 classes: Sequence[str] | None = (TARGET_CLASS,), metrics: Sequence[str] = METRICS):
        gt_t, dt_t = _tables(gt, dt)
        self.n_frames = gt_t.n_frames
        #: The evaluator's result on all frames (the point estimates; decides which metrics exist).
        self.full = evaluate_tables(gt_t, dt_t, classes, metrics)
        self.classes = tuple(self.full["meta"]["classes"])
        wanted = normalise_names(metrics, METRICS, "metric")
        kinds = {OVERLAP_OF_METRIC[m] for m in wanted}
        self._aos = not bool(np.any(dt_t.alpha == INVALID_ALPHA))
        pairs, dontcare = class_overlaps(gt_t, dt_t, self.classes, kinds)
        self._curves: dict[tuple[str, str], list[_Curve]] = {}
        for cls in self.classes:
            ce = ClassEvaluation(gt_t, dt_t, cls)
            det_frame = dt_t.frame[ce.det_rows]
            for kind in sorted({OVERLAP_OF_METRIC[m] for m in self.full[cls]}):
                self._curves[(cls, kind)] = _curves(ce, pairs, dontcare, kind, self.n_frames, det_frame)
        self._check()

    def keys(self) -> list[APKey]:
        """(class, metric, recall sampling, difficulty) of every AP the evaluator reported."""
        return [(c, m, r, d) for c in self.classes for m, t in self.full[c].items() for r, v in t.items() for d in v]

    def resampled(self, weights: np.ndarray, chunk: int | None = None) -> dict[APKey, np.ndarray]:
        """AP (percent) per key (:meth:`keys`) for each row of ``weights`` ((R, F) frame counts).

        ``chunk``: resamples per vectorised step (None: as many as :data:`_CHUNK_VALUES` allows); the
        result does not depend on it.
        """
        if chunk is not None and (not isinstance(chunk, int | np.integer) or chunk < 1):
            raise ValueError(f"chunk must be a positive number of resamples, got {chunk!r}")
        w = self._weights(weights)

        def rows(curve: _Curve, with_aos: bool) -> tuple[np.ndarray, np.ndarray]:
            prec, aos = np.zeros((len(w), N_SAMPLE_PTS)), np.zeros((len(w), N_SAMPLE_PTS))
            step = chunk or max(1, _CHUNK_VALUES // max(len(curve.tp_score), self.n_frames,
                                                        len(_WINDOW) * N_SAMPLE_PTS))
            for lo in range(0, len(w), step):
                p, a = curve.sample_rows(w[lo:lo + step], with_aos)
                prec[lo:lo + step] = p
                if a is not None:
                    aos[lo:lo + step] = a
            return prec, aos

        return self._aps(rows)

    def _resampled_per_resample(self, weights: np.ndarray) -> dict[APKey, np.ndarray]:
        """:meth:`resampled`, one resample at a time (:meth:`_Curve.samples`): the reference of the
        vectorised path in the tests and the benchmark."""
        w = self._weights(weights)

        def rows(curve: _Curve, with_aos: bool) -> tuple[np.ndarray, np.ndarray]:
            prec, aos = np.zeros((len(w), N_SAMPLE_PTS)), np.zeros((len(w), N_SAMPLE_PTS))
            for r in range(len(w)):
                p, a = curve.samples(w[r], with_aos)
                prec[r] = p
                if a is not None:
                    aos[r] = a
            return prec, aos

        return self._aps(rows)

    def _weights(self, weights: np.ndarray) -> np.ndarray:
        w = np.asarray(weights, dtype=np.float64)
        if w.ndim != 2 or w.shape[1] != self.n_frames:
            raise ValueError(f"weights must be (resamples, {self.n_frames}), got shape {w.shape}")
        if np.any(w < 0) or np.any(w != np.round(w)):
            raise ValueError("weights must be non-negative integer frame counts")
        return w

    def _aps(self, rows: Callable[[_Curve, bool], tuple[np.ndarray, np.ndarray]]) -> dict[APKey, np.ndarray]:
        """APs from the (R, 41) raw precision and AOS samples ``rows(curve, with_aos)`` of every curve."""
        out: dict[APKey, np.ndarray] = {}
        for (cls, kind), curves in self._curves.items():
            metrics = [m for m in self.full[cls] if OVERLAP_OF_METRIC[m] == kind]
            with_aos = "aos" in metrics and self._aos
            for d, curve in enumerate(curves):
                prec, aos = rows(curve, with_aos)
                for m in metrics:
                    samples = np.maximum.accumulate((aos if m == "aos" else prec)[:, ::-1], axis=1)[:, ::-1]
                    for name, idx in RECALL_SAMPLES.items():
                        out[(cls, m, name, DIFFICULTIES[d])] = samples[:, list(idx)].sum(axis=1) / len(idx) * 100.0
        return {k: out[k] for k in self.keys()}

    def _check(self) -> None:
        """The re-accumulation with unit weights must reproduce the evaluator (guards the event tables)."""
        got = self.resampled(np.ones((1, self.n_frames)))
        for (c, m, r, d), v in got.items():
            want = self.full[c][m][r][d]
            if abs(float(v[0]) - want) > 1e-9:
                raise AssertionError(f"bootstrap accumulation gives {float(v[0])} for {c} {m} {r} {d}, "
                                     f"the evaluator {want}")


def resample_weights(n_frames: int, resamples: int = RESAMPLES, seed: int = 0) -> np.ndarray:
    """(resamples, n_frames) int64 multinomial frame counts, each row summing to ``n_frames``.

    Drawn from ``numpy.random.default_rng([seed, BOOTSTRAP_STREAM])``: the same for every result set
    of the same frames and seed, which makes differences of two sets paired.
    """
    if n_frames < 1:
        raise ValueError(f"cannot resample {n_frames} frames")
    if resamples < 1:
        raise ValueError(f"resamples must be at least 1, got {resamples}")
    if seed < 0:
        raise ValueError(f"seed must be non-negative, got {seed}")
    rng = np.random.default_rng([int(seed), BOOTSTRAP_STREAM])
    return rng.multinomial(n_frames, np.full(n_frames, 1.0 / n_frames), size=resamples).astype(np.int64)


def percentile_interval(values: np.ndarray, level: float = LEVEL) -> list[float]:
    """``[lo, hi]``: the (1 - level) / 2 and (1 + level) / 2 quantiles of ``values``."""
    if not 0.0 < level < 1.0:
        raise ValueError(f"confidence level must be in (0, 1), got {level}")
    lo, hi = np.percentile(np.asarray(values, dtype=np.float64), [50 * (1 - level), 50 * (1 + level)])
    return [float(lo), float(hi)]


def interval_table(resampled: dict[APKey, np.ndarray], n_frames: int, resamples: int, seed: int,
                   level: float = LEVEL, paired: bool = False) -> dict[str, Any]:
    """``{cls: {metric: {recall: {difficulty: [lo, hi]}}}, "meta": {...}}`` from resampled values per
    (class, metric, recall, difficulty) key (APs, or paired differences when ``paired``)."""
    out: dict[str, Any] = {}
    for (c, m, r, d), v in resampled.items():
        out.setdefault(c, {}).setdefault(m, {}).setdefault(r, {})[d] = percentile_interval(v, level)
    what = "AP(clean) - AP(attacked), the same resampled frames for both" if paired else "AP"
    out["meta"] = {"method": "percentile bootstrap over frames", "statistic": what, "level": level,
                   "resamples": resamples, "seed": seed, "frames": n_frames,
                   "rng": f"numpy.random.default_rng([seed, {BOOTSTRAP_STREAM:#x}]).multinomial"}
    return out


def ap_intervals(prep: FrameBootstrap, resamples: int = RESAMPLES, seed: int = 0, level: float = LEVEL
                 ) -> dict[str, Any]:
    """Intervals (:func:`interval_table`) of every AP of ``prep``."""
    w = resample_weights(prep.n_frames, resamples, seed)
    return interval_table(prep.resampled(w), prep.n_frames, resamples, seed, level)


def drop_intervals(clean: FrameBootstrap, attacked: FrameBootstrap, resamples: int = RESAMPLES, seed: int = 0,
                   level: float = LEVEL) -> dict[str, Any]:
    """Intervals of the paired drop AP(clean) - AP(attacked) (percentage points), for every AP both have."""
    if clean.n_frames != attacked.n_frames:
        raise ValueError(f"paired drop needs the same frames: {clean.n_frames} clean, {attacked.n_frames} attacked")
    w = resample_weights(clean.n_frames, resamples, seed)
    return interval_table(paired_differences(clean.resampled(w), attacked.resampled(w)), clean.n_frames,
                          resamples, seed, level, paired=True)


def paired_differences(clean: dict[APKey, np.ndarray], attacked: dict[APKey, np.ndarray]) -> dict[APKey, np.ndarray]:
    """Per key both hold, clean - attacked (resampled with the same weights)."""
    return {k: clean[k] - attacked[k] for k in clean if k in attacked}


__all__ = ["LEVEL", "RESAMPLES", "FrameBootstrap", "ap_intervals", "drop_intervals", "interval_table",
           "paired_differences", "percentile_interval", "resample_weights", "threshold_positions"]

