"""Ranges of the numeric options shared by several commands (``run``, ``tradeoff``, ``data synth``, the
attack commands), and the one-line check that enforces them up front. Standard library only: a foundation
every layer may import (docs/ranges.md lists every range of the project).
"""

from __future__ import annotations

import math
import os
from numbers import Integral, Real
from typing import Any

#: Frame counts (``run --max-frames``, ``tradeoff --frames``, ``data synth --frames``): KITTI frame ids have
#: six digits (000000..999999), so no split holds more; a count above a split's size evaluates all of it.
FRAMES_RANGE = (1, 1_000_000)
#: Seeds: 32-bit, the seeds numpy's legacy API, torch and most tools take, so a run's seed can be reused
#: elsewhere; four billion seeds are more than any study draws.
SEED_RANGE = (0, 2**32 - 1)
#: ``--batch-size``: frames per ``detect`` call. A batch holds its frames' scans and images (about 2.2 MB
#: each) and the victim's activations at once; past 256 memory grows, not speed.
BATCH_RANGE = (1, 256)
#: Worker processes (``run --jobs``/``--workers``, ``data synth --workers``): beyond any one machine's cores;
#: each process holds a victim (about 0.4 GB) or a synth worker's scene (up to 1.5 GB), so memory runs out first.
PROCESSES_RANGE = (1, 1024)
#: Bootstrap resamples (``run --bootstrap`` besides 0 = none, ``tradeoff --resamples``): below 10 the 95 %
#: percentile interval is just the extreme resamples (quick checks use 20 to 50); past 100000 the interval's
#: Monte-Carlo error (under 0.1 AP point from 10000 on) no longer shrinks visibly while the time grows linearly.
RESAMPLES_RANGE = (10, 100_000)


def check_range(option: str, value: Any, low: float, high: float, what: str, *, integer: bool = True) -> None:
    """Refuse ``value`` of ``option`` outside ``low..high`` (or not an integer when ``integer``; NaN and
    infinities always): one line naming the option, the range and what it counts."""
    from robustbench3d.errors import RobustBenchError

    kind = Integral if integer else Real
    ok = isinstance(value, kind) and not isinstance(value, bool)
    ok = ok and (integer or math.isfinite(value)) and low <= value <= high
    if not ok:
        raise RobustBenchError(f"{option} must be {'an integer ' if integer else ''}in {low}..{high} ({what}), "
                               f"got {value!r}")


def check_bootstrap(value: Any, option: str = "--bootstrap") -> None:
    """``--bootstrap``: 0 (no intervals) or a resample count in :data:`RESAMPLES_RANGE`."""
    from robustbench3d.errors import RobustBenchError

    low, high = RESAMPLES_RANGE
    if not (isinstance(value, Integral) and not isinstance(value, bool) and (value == 0 or low <= value <= high)):
        raise RobustBenchError(f"{option} must be 0 (no intervals) or in {low}..{high} (bootstrap resamples), "
                               f"got {value!r}")


def default_processes() -> int:
    """The default process count: the CPUs, within :data:`PROCESSES_RANGE`."""
    return min(os.cpu_count() or 1, PROCESSES_RANGE[1])
