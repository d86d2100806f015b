"""The attack's image loss terms by hand, in plain float64 arithmetic (references of ``tests/attacks``)."""

from __future__ import annotations

import math


def sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x))


def nl(a: float, b: float | None = None) -> float:
    """-log(1 - o c) (-log(1 - o) without ``b``) of objectness logit ``a`` and class logit ``b``."""
    return -math.log(1.0 - sigmoid(a) * (1.0 if b is None else sigmoid(b)))
