"""Per-difficulty status of ground truth and detections (the devkit's ``cleanData``).

Status codes, per difficulty (rows easy, moderate, hard):

* ground truth: 0 counts (class of interest, passes the filters), 1 ignored (neighbour class, or
  class of interest failing occlusion / truncation / height), -1 not involved (other classes,
  DontCare).
* detections: 1 ignored (2D height below the minimum, whatever the class), 0 counts (class of
  interest), -1 not involved.
"""

from __future__ import annotations

import numpy as np

from robustbench3d.eval.rules import MAX_OCCLUSION, MAX_TRUNCATION, MIN_HEIGHT, NEIGHBOURS
from robustbench3d.eval.table import TYPE_CODE, ObjectTable

_INT32_MIN = -(2**31)


def gt_status(gt: ObjectTable, cls: str) -> np.ndarray:
    """(3, N) int8 GT status for class ``cls``.

    A GT of the class is ignored if ``occluded > MAX_OCCLUSION``, ``truncated > MAX_TRUNCATION``
    or its image-box height ``bottom - top <= MIN_HEIGHT`` (px).
    """
    own = gt.of_type(cls)
    neighbour = np.isin(gt.type, [TYPE_CODE[n] for n in NEIGHBOURS[cls]])
    height = gt.bbox[:, 3] - gt.bbox[:, 1]
    out = np.full((3, len(gt)), -1, dtype=np.int8)
    for d in range(3):
        ignore = (gt.occluded > MAX_OCCLUSION[d]) | (gt.truncated > MAX_TRUNCATION[d]) | (height <= MIN_HEIGHT[d])
        out[d] = np.where(own & ~ignore, 0, np.where(neighbour | own, 1, -1))
    return out


def detection_height_px(dt: ObjectTable) -> np.ndarray:
    """(N,) int64 ``|top - bottom|`` truncated toward zero like the devkit's int32 cast (px).

    Values beyond the int32 range map to INT32_MIN, what the x86 conversion yields.
    """
    h = np.abs(dt.bbox[:, 1] - dt.bbox[:, 3])
    return np.where(h < 2.0**31, np.trunc(np.minimum(h, 2.0**31)), _INT32_MIN).astype(np.int64)


def det_status(dt: ObjectTable, cls: str) -> np.ndarray:
    """(3, N) int8 detection status for class ``cls`` (too small for the difficulty: 1)."""
    own = dt.of_type(cls)
    height = detection_height_px(dt)
    out = np.empty((3, len(dt)), dtype=np.int8)
    for d in range(3):
        out[d] = np.where(height < MIN_HEIGHT[d], 1, np.where(own, 0, -1))
    return out
