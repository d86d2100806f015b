"""Evaluation parameters of the official KITTI object devkit (``cpp/evaluate_object.cpp``, 2019+).

Pure data, standard library only (imported by the CLI at start-up).
"""

from __future__ import annotations

from collections.abc import Iterable

#: Bumped whenever a change could alter a reported number.
EVALUATOR_VERSION = "1.0.0"

#: Classes the devkit evaluates, in its order.
CLASSES: tuple[str, ...] = ("Car", "Pedestrian", "Cyclist")
#: The benchmark's target class: the objects attacks are placed on and every headline number is about (its AP,
#: drop and attack success rate; the evaluator's default class). Defined here, the lowest layer, once.
TARGET_CLASS = "Car"
#: Ground-truth types that are ignored (neither TP nor FN; detections on them are not FP).
NEIGHBOURS: dict[str, tuple[str, ...]] = {"Car": ("Van",), "Pedestrian": ("Person_sitting",), "Cyclist": ()}

DIFFICULTIES: tuple[str, ...] = ("easy", "moderate", "hard")
#: Minimum 2D box height in image pixels. GT counts only if ``y2 - y1 > MIN_HEIGHT``; a
#: detection is ignored if ``int(|y1 - y2|) < MIN_HEIGHT`` (the devkit truncates it to int32).
MIN_HEIGHT: tuple[int, ...] = (40, 25, 25)
#: GT with ``occluded > MAX_OCCLUSION`` is ignored.
MAX_OCCLUSION: tuple[int, ...] = (0, 1, 2)
#: GT with ``truncated > MAX_TRUNCATION`` is ignored.
MAX_TRUNCATION: tuple[float, ...] = (0.15, 0.3, 0.5)

#: Metric keys as they appear in reports. "aos" rides on the 2D matching.
METRICS: tuple[str, ...] = ("2d", "aos", "bev", "3d")
#: Overlap function per metric: image boxes, bird's-eye (rect x-z plane) footprints, 3D boxes.
OVERLAP_OF_METRIC: dict[str, str] = {"2d": "2d", "aos": "2d", "bev": "bev", "3d": "3d"}
#: The devkit's MIN_OVERLAP[metric][class] table (image, ground, 3D) x (car, pedestrian, cyclist).
MIN_OVERLAP: dict[str, dict[str, float]] = {
    "2d": {"Car": 0.7, "Pedestrian": 0.5, "Cyclist": 0.5},
    "bev": {"Car": 0.7, "Pedestrian": 0.5, "Cyclist": 0.5},
    "3d": {"Car": 0.7, "Pedestrian": 0.5, "Cyclist": 0.5},
}

#: Precision is sampled at up to this many score thresholds (recall 0, 1/40, ..., 1).
N_SAMPLE_PTS = 41
#: Indices into the 41 samples: R40 drops recall 0, R11 takes every fourth (0, 0.1, ..., 1).
RECALL_SAMPLES: dict[str, tuple[int, ...]] = {
    "R40": tuple(range(1, 41)),
    "R11": tuple(range(0, 41, 4)),
}
#: A detection score must exceed the devkit's NO_DETECTION sentinel to be matched at all.
NO_DETECTION = -10000000.0
#: Alpha value meaning "no orientation"; one such detection disables AOS (as in the devkit).
INVALID_ALPHA = -10.0
#: Location value meaning "no 3D box" in results.
INVALID_LOCATION = -1000.0


def normalise_names(values: Iterable[str], allowed: tuple[str, ...], what: str) -> tuple[str, ...]:
    """Requested names (case-insensitive) in the canonical order of ``allowed``.

    Raises:
        ValueError: an unknown name, or none at all.
    """
    lookup = {a.lower(): a for a in allowed}
    picked = set()
    for v in values:
        if v.lower() not in lookup:
            raise ValueError(f"unknown {what} {v!r}; expected some of {', '.join(allowed)}")
        picked.add(lookup[v.lower()])
    if not picked:
        raise ValueError(f"no {what} requested")
    return tuple(a for a in allowed if a in picked)
