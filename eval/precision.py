"""Score thresholds, interpolated precision and AP as the devkit computes them."""

from __future__ import annotations

import numpy as np

from robustbench3d.eval.rules import N_SAMPLE_PTS, RECALL_SAMPLES


def score_thresholds(tp_scores: np.ndarray, n_gt: int) -> np.ndarray:
    """The devkit's ``getThresholds``: up to 41 TP scores approximating recall 0, 1/40, ..., 1.

    TP scores are sorted in descending order; with ``l = (i + 1) / n_gt`` and ``r = (i + 2) / n_gt``
    (``r = l`` for the last), score i is taken unless ``r - c < c - l`` (the next recall is closer
    to the current recall step ``c``), the last score always; every take advances ``c`` by 1/40
    (summed in float64, as in C++). Takes beyond the 41st would index past the devkit's
    41-element precision array and are dropped.

    Args:
        tp_scores: scores of the true positives of pass 1.
        n_gt: number of counted ground-truth objects (recall denominator).
    """
    v = np.sort(np.asarray(tp_scores, dtype=np.float64))[::-1]
    m = len(v)
    if m == 0 or n_gt <= 0:
        return np.empty(0)
    left = np.arange(1, m + 1, dtype=np.float64) / float(n_gt)
    right = np.arange(2, m + 2, dtype=np.float64) / float(n_gt)
    right[-1] = left[-1]
    step = 1.0 / (N_SAMPLE_PTS - 1.0)
    taken: list[float] = []
    current = 0.0
    i = 0
    while i < m and len(taken) < N_SAMPLE_PTS:
        take = (right[i:] - current) >= (current - left[i:])
        take[-1] = True
        i += int(np.argmax(take))
        taken.append(v[i])
        current += step
        i += 1
    return np.array(taken)


def interpolate(values: np.ndarray) -> np.ndarray:
    """41 samples: ``values`` (one per threshold) padded with zeros, then max over the tail."""
    out = np.zeros(N_SAMPLE_PTS)
    vals = np.asarray(values, dtype=np.float64)[:N_SAMPLE_PTS]
    out[: len(vals)] = vals
    return np.maximum.accumulate(out[::-1])[::-1]


def ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """num / den, 0 where den == 0 (the devkit would produce NaN there)."""
    num = np.asarray(num, dtype=np.float64)
    den = np.asarray(den, dtype=np.float64)
    return np.divide(num, den, out=np.zeros(np.broadcast(num, den).shape), where=den != 0)


def average_precision(samples: np.ndarray) -> dict[str, float]:
    """AP in percent from the 41 interpolated samples: ``{"R11": ..., "R40": ...}``."""
    s = np.asarray(samples, dtype=np.float64)
    return {name: float(s[list(idx)].sum() / len(idx) * 100.0) for name, idx in RECALL_SAMPLES.items()}
