"""The synthetic evaluation sets' generator (tests/fixtures/eval/generate.py), loaded once per test session."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from robustbench3d.kitti import Labels

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


def set_labels(spec: Any) -> tuple[list[Labels], list[Labels]]:
    """The ground truth and detections of the generated set ``spec`` (a generator ``SetSpec``), one
    :class:`Labels` a frame (a frame without a result file: no detections)."""
    from robustbench3d.kitti import Labels
    from robustbench3d.kitti.labels import parse_labels

    ids, gt, dt = load_generator().make_set(spec)
    gts = [parse_labels("\n".join(gt[i]), Path(f"{i}.txt"), scored=False) for i in ids]
    dts = [parse_labels("\n".join(dt[i]), Path(f"{i}.txt"), scored=True) if i in dt else Labels.empty(True)
           for i in ids]
    return gts, dts
