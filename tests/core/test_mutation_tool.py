"""``tools/mutation.py``: the sample of mutant names and the Wilson interval the renderer's estimates use."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("mutation_tool", REPO / "tools" / "mutation.py")
assert _spec is not None and _spec.loader is not None
mutation = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(mutation)


def test_wilson_interval_matches_textbook_values():
    # p = 0.9, n = 100: 0.8256 - 0.9448; 0 of 10: 0 - 0.2775; 10 of 10: 0.7225 - 1 (Wilson 1927, z = 1.96)
    for (k, n), (lo, hi) in (((90, 100), (0.82563, 0.94477)), ((0, 10), (0.0, 0.27754)), ((10, 10), (0.72246, 1.0))):
        got = mutation.wilson(k, n)
        assert got == pytest.approx((lo, hi), abs=1e-5)
    assert mutation.wilson(0, 0) == (0.0, 1.0)


def _stage(tmp_path: Path) -> Path:
    meta = tmp_path / "mutants" / "pkg" / "mod.py.meta"
    meta.parent.mkdir(parents=True)
    codes = {f"pkg.mod.x_f__mutmut_{i}": (None if i % 3 else (1 if i % 2 else 0)) for i in range(1, 31)}
    meta.write_text(json.dumps({"exit_code_by_key": codes}), encoding="utf-8")
    return tmp_path


def test_sample_is_seeded_uniform_without_replacement_and_can_skip_the_mutants_run(tmp_path):
    dest = _stage(tmp_path)
    a = mutation.sample("pkg.mod", 8, seed=0, dest=dest)
    assert a == mutation.sample("pkg.mod", 8, seed=0, dest=dest) == sorted(set(a)) and len(a) == 8
    assert a != mutation.sample("pkg.mod", 8, seed=1, dest=dest)
    unrun = mutation.sample("pkg.mod", 100, seed=0, dest=dest, unchecked=True)
    assert len(unrun) == 20 and all(int(n.rsplit("_", 1)[1]) % 3 for n in unrun)  # every mutant not run, once
    with pytest.raises(SystemExit, match=r"pkg\.other: no mutants"):
        mutation.sample("pkg.other", 5, seed=0, dest=dest)
    counts = mutation.report(dest, only=set(a))["pkg.mod"]
    assert sum(counts.values()) == 8
    assert mutation.report(dest)["pkg.mod"]["not checked"] == 20
