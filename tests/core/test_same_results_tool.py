"""tools/same_results.py: two run directories are the same results when every file is byte-identical but
for the runtime part of each JSON file's provenance."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("same_results", REPO / "tools" / "same_results.py")
assert _spec is not None and _spec.loader is not None
same_results = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(same_results)


def _run(root: Path, *, seconds: float, out: str, ap: float, dirty: bool) -> Path:
    cell = {"result": {"ap": ap}, "provenance": {"seconds": seconds, "cpu_seconds": 2 * seconds, "peak_rss_mb": 3.0,
                                                 "started": "a", "finished": "b", "git": {"dirty": dirty},
                                                 "executor": {"name": "local", "workers": [out]},
                                                 "run": {"out": out, "seed": 0}}}
    (root / "cells" / "c").mkdir(parents=True)
    (root / "cells" / "c" / "cell.json").write_text(json.dumps(cell))
    (root / "results.csv").write_text(f"ap\n{ap}\n")
    return root


def test_runtime_provenance_is_set_aside(tmp_path: Path) -> None:
    a = _run(tmp_path / "a", seconds=1.0, out="/x", ap=0.5, dirty=False)
    b = _run(tmp_path / "b", seconds=9.0, out="/y", ap=0.5, dirty=True)
    assert same_results.differences(a, b) == []
    assert same_results.main([str(a), str(b)]) == 0


def test_a_result_a_recorded_setting_or_a_file_that_differs_is_reported(tmp_path: Path) -> None:
    a = _run(tmp_path / "a", seconds=1.0, out="/x", ap=0.5, dirty=False)
    b = _run(tmp_path / "b", seconds=1.0, out="/x", ap=0.5000001, dirty=False)
    found = same_results.differences(a, b)
    assert "cells/c/cell.json/result/ap: 0.5 != 0.5000001" in found and "results.csv: bytes differ" in found
    cell = json.loads((a / "cells/c/cell.json").read_text())
    cell["provenance"]["run"]["seed"] = 1
    (b / "cells/c/cell.json").write_text(json.dumps(cell))
    (b / "results.csv").write_text((a / "results.csv").read_text())
    assert same_results.differences(a, b) == ["cells/c/cell.json/provenance/run/seed: 0 != 1"]
    (b / "extra.txt").write_text("")
    assert same_results.main([str(a), str(b)]) == 1


def test_across_executors_also_sets_aside_the_executor_and_torch_loaded(tmp_path: Path) -> None:
    a = _run(tmp_path / "a", seconds=1.0, out="/x", ap=0.5, dirty=False)
    b = _run(tmp_path / "b", seconds=1.0, out="/x", ap=0.5, dirty=False)
    cell = json.loads((a / "cells/c/cell.json").read_text())
    cell["provenance"]["executor"] = {"name": "ray", "address": "10.0.0.1:6379", "workers": ["n1"]}
    cell["provenance"]["determinism"] = {"torch_loaded": False, "OMP_NUM_THREADS": "1"}
    (b / "cells/c/cell.json").write_text(json.dumps(cell))
    (a / "cells/c/cell.json").write_text(json.dumps({**cell, "provenance": {
        **cell["provenance"], "executor": {"name": "local", "workers": ["p1"]},
        "determinism": {"torch_loaded": True, "OMP_NUM_THREADS": "1"}}}))
    assert sorted(same_results.differences(a, b)) == [
        "cells/c/cell.json/provenance/determinism/torch_loaded: True != False",
        "cells/c/cell.json/provenance/executor/address: only in the second",
        "cells/c/cell.json/provenance/executor/name: local != ray"]
    assert same_results.differences(a, b, across_executors=True) == []
    assert same_results.main(["--across-executors", str(a), str(b)]) == 0
    cell["provenance"]["determinism"]["OMP_NUM_THREADS"] = "2"
    (b / "cells/c/cell.json").write_text(json.dumps(cell))
    assert same_results.differences(a, b, across_executors=True) == [
        "cells/c/cell.json/provenance/determinism/OMP_NUM_THREADS: 1 != 2"]
