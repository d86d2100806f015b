"""k-means anchors with the IoU distance d = 1 − IoU(box, centroid) of (w, h) boxes sharing a centre
(YOLOv2/v3). Seeded k-means++ initialisation, mean update, until assignments stop changing."""

from __future__ import annotations

import numpy as np


def wh_iou_np(wh: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    """(N, K) IoU of centred boxes (N, 2) and centroids (K, 2), (w, h) > 0."""
    inter = np.minimum(wh[:, None, 0], centroids[None, :, 0]) * np.minimum(wh[:, None, 1], centroids[None, :, 1])
    union = (wh[:, 0] * wh[:, 1])[:, None] + (centroids[:, 0] * centroids[:, 1])[None, :] - inter
    return inter / np.maximum(union, 1e-12)


def kmeans_anchors(wh: np.ndarray, k: int, rng: np.random.Generator, max_iter: int = 300) -> tuple[np.ndarray, float]:
    """Cluster box sizes (N, 2) (w, h in pixels) into ``k`` anchors.

    Returns (anchors (k, 2) sorted by area, mean IoU of each box with its best anchor).
    """
    wh = np.asarray(wh, dtype=np.float64).reshape(-1, 2)
    wh = wh[(wh > 0).all(axis=1)]
    if len(wh) < k:
        raise ValueError(f"need at least {k} boxes with positive size for {k} anchors, got {len(wh)}")
    centroids = wh[[rng.integers(len(wh))]]
    while len(centroids) < k:  # k-means++: sample proportional to the squared distance
        d = (1.0 - wh_iou_np(wh, centroids).max(axis=1)) ** 2
        total = d.sum()
        pick = rng.integers(len(wh)) if total <= 0 else rng.choice(len(wh), p=d / total)
        centroids = np.vstack([centroids, wh[pick]])
    assign = np.full(len(wh), -1)
    for _ in range(max_iter):
        new = wh_iou_np(wh, centroids).argmax(axis=1)
        if np.array_equal(new, assign):
            break
        assign = new
        for j in range(k):
            members = wh[assign == j]
            if len(members):
                centroids[j] = members.mean(axis=0)
    centroids = centroids[np.argsort(centroids[:, 0] * centroids[:, 1], kind="stable")]
    return centroids, float(wh_iou_np(wh, centroids).max(axis=1).mean())
