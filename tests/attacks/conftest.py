"""Fixtures of the attack tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest


@pytest.fixture
def table() -> Iterator[dict]:
    """IMAGE_LOSSES, restored to its entries after the test."""
    from robustbench3d.attacks.losses import IMAGE_LOSSES

    saved = dict(IMAGE_LOSSES)
    yield IMAGE_LOSSES
    IMAGE_LOSSES.clear()
    IMAGE_LOSSES.update(saved)
