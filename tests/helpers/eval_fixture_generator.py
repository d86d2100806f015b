"""The synthetic evaluation sets' generator (tests/fixtures/eval/generate.py), loaded once per test session."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

GENERATE = Path(__file__).parents[1] / "fixtures" / "eval" / "generate.py"
MODULE = "eval_fixture_generate"


def load_generator() -> ModuleType:
    """The generator module (registered in ``sys.modules``: its dataclasses look their module up while built)."""
    if MODULE not in sys.modules:
        spec = importlib.util.spec_from_file_location(MODULE, GENERATE)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[MODULE] = module
        spec.loader.exec_module(module)
    return sys.modules[MODULE]
