"""The performance comparer's logic (tools/perf_compare.py) on synthetic pytest-benchmark reports."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("perf_compare", REPO / "tools" / "perf_compare.py")
assert _spec is not None and _spec.loader is not None
pc = importlib.util.module_from_spec(_spec)
sys.modules["perf_compare"] = pc  # dataclasses look their module up there
_spec.loader.exec_module(pc)


def report(times: dict[str, float], reference: float | dict[str, float] = 0.002,
           timer: str = "process_time") -> dict[str, Any]:
    """A pytest-benchmark JSON report: the given minimum times (seconds; medians 1.5x as long) and each
    benchmark's reference kernel time (one for all, or per benchmark)."""
    ref = reference if isinstance(reference, dict) else dict.fromkeys(times, reference)
    return {"machine_info": {"cpu": {"brand_raw": "test cpu", "count": 2}, "python_version": "3.11"},
            "commit_info": {"id": "abc"}, "datetime": "2026-01-01T00:00:00",
            "benchmarks": [{"name": n, "fullname": f"benchmarks/test_x.py::{n}", "options": {"timer": timer},
                            "extra_info": {"reference_s": ref[n]}, "stats": {"min": t, "median": 1.5 * t}}
                           for n, t in times.items()]}


def normalised(rep: dict[str, Any]) -> dict[str, float]:
    return pc.normalise(pc.timings(rep))


def test_normalise_divides_by_the_runs_reference() -> None:
    assert normalised(report({"a": 0.010, "b": 0.001})) == pytest.approx({"a": 5.0, "b": 0.5})
    # the run's reference is the fastest of its timings beside the benchmarks (one slowed by load: ignored)
    assert normalised(report({"a": 0.010, "b": 0.001}, {"a": 0.004, "b": 0.002})) == pytest.approx(
        {"a": 5.0, "b": 0.5})
    with pytest.raises(pc.BaselineError, match="no benchmark"):
        pc.normalise({})
    for bad in (None, 0.0, -1.0, True):
        with pytest.raises(pc.BaselineError, match=r"benchmarks\.a\.extra_info\.reference_s"):
            pc.timings(report({"a": 0.01}, {"a": bad}))  # type: ignore[dict-item]


def test_same_normalised_values_on_a_machine_twice_as_fast() -> None:
    slow = normalised(report({"a": 0.02}, 0.004))
    fast = normalised(report({"a": 0.01}, 0.002))
    assert slow == pytest.approx({"a": 5.0}) and fast == pytest.approx({"a": 5.0})
    assert pc.decide({"a": 5.0}, slow, None).ok


def test_repeated_30_percent_slowdown_fails() -> None:
    v = pc.decide({"a": 5.0, "b": 0.5}, {"a": 6.5, "b": 0.5}, {"a": 6.6})
    assert v.failed == ["a"] and not v.ok
    assert v.first["a"] == pytest.approx(0.30) and v.second["a"] == pytest.approx(0.32)


def test_30_percent_slowdown_that_does_not_repeat_passes() -> None:
    v = pc.decide({"a": 5.0, "b": 0.5}, {"a": 6.5, "b": 0.5}, {"a": 5.1})
    assert v.ok and v.noise == ["a"] and v.failed == []


def test_20_percent_slowdown_passes_without_a_rerun() -> None:
    assert pc.slower({"a": 6.0}, {"a": 5.0}) == {}
    v = pc.decide({"a": 5.0}, {"a": 6.0}, None)
    assert v.ok and v.first["a"] == pytest.approx(0.20) and v.second == {}


def test_a_suspect_that_was_not_rerun_fails_and_missing_ones_fail() -> None:
    assert pc.decide({"a": 5.0}, {"a": 7.0}, None).failed == ["a"]
    v = pc.decide({"a": 5.0, "gone": 1.0}, {"a": 5.0, "new": 2.0}, None)
    assert not v.ok and v.missing == ["gone"] and v.new == ["new"]


def test_best_of_keeps_each_benchmarks_smallest_value() -> None:
    assert pc.best_of([{"a": 2.0, "b": 1.0}, {"a": 1.5, "c": 3.0}, {"b": 1.2}]) == {"a": 1.5, "b": 1.0, "c": 3.0}
    assert pc.best_of([]) == {}


def test_timings_reject_duplicates_and_other_timers() -> None:
    bad = report({"a": 0.01, "b": 0.02})
    bad["benchmarks"].append(bad["benchmarks"][0])
    with pytest.raises(pc.BaselineError, match="two benchmarks named 'a'"):
        pc.timings(bad)
    with pytest.raises(pc.BaselineError, match="perf_counter"):
        pc.timings(report({"a": 0.002}, timer="perf_counter"))
    assert pc.timings(report({"a": 0.002}), statistic="median")["a"].seconds == pytest.approx(0.003)


class FakeSuite:
    """Stands in for :func:`run_suite`: returns the queued reports and records what was asked to run."""

    def __init__(self, *reports: dict[str, Any]):
        self.reports = list(reports)
        self.calls: list[list[str] | None] = []

    def __call__(self, out: Path, node_ids: list[str] | None = None) -> dict[str, Any]:
        self.calls.append(None if node_ids is None else sorted(node_ids))
        return self.reports.pop(0)


def test_main_writes_a_baseline_then_compares(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    base = tmp_path / "baseline.json"
    monkeypatch.setattr(pc, "run_suite", FakeSuite(report({"a": 0.010, "b": 0.001})))
    assert pc.main(["--baseline", str(base), "--write-baseline"]) == 0
    stored = json.loads(base.read_text())
    assert stored["ratios"] == pytest.approx({"a": 5.0, "b": 0.5}) and stored["reference_s"] == 0.002
    assert stored["statistic"] == "min" and stored["medians_s"]["a"] == pytest.approx(0.015)

    # machine twice as slow, same code: passes without a rerun
    suite = FakeSuite(report({"a": 0.020, "b": 0.002}, 0.004))
    monkeypatch.setattr(pc, "run_suite", suite)
    assert pc.main(["--baseline", str(base)]) == 0 and suite.calls == [None]

    # "b" 30 % slower in the full run and in each of the three reruns: only "b" is rerun, exit 1
    assert pc.RERUN_PROCESSES == 3
    suite = FakeSuite(report({"a": 0.010, "b": 0.0013}), report({"b": 0.00131}), report({"b": 0.00129}),
                      report({"b": 0.00133}))
    monkeypatch.setattr(pc, "run_suite", suite)
    assert pc.main(["--baseline", str(base)]) == 1
    assert suite.calls == [None] + [["benchmarks/test_x.py::b"]] * 3
    out = capsys.readouterr().out
    assert "SLOWER (repeated)" in out and "+29.0%" in out  # the best of the three reruns: 0.00129 / 0.001

    # 30 % slower once, back to normal on the first rerun: no second rerun, exit 0
    suite = FakeSuite(report({"a": 0.010, "b": 0.0013}), report({"b": 0.00102}))
    monkeypatch.setattr(pc, "run_suite", suite)
    assert pc.main(["--baseline", str(base)]) == 0 and len(suite.calls) == 2
    assert "noise (not repeated)" in capsys.readouterr().out

    # "a" and "b" slower; the first rerun clears "a" only, the second (a fresh process) clears "b" while its
    # "a" is slow again: each keeps its best, no third rerun, exit 0
    suite = FakeSuite(report({"a": 0.013, "b": 0.0013}), report({"a": 0.0101, "b": 0.0014}),
                      report({"a": 0.014, "b": 0.00105}))
    monkeypatch.setattr(pc, "run_suite", suite)
    assert pc.main(["--baseline", str(base)]) == 0
    assert suite.calls == [None] + [["benchmarks/test_x.py::a", "benchmarks/test_x.py::b"]] * 2
    capsys.readouterr()

    # "b" took 30 % longer only because everything did (the reference too): no rerun, exit 0
    suite = FakeSuite(report({"a": 0.013, "b": 0.0013}, 0.0026))
    monkeypatch.setattr(pc, "run_suite", suite)
    assert pc.main(["--baseline", str(base)]) == 0 and suite.calls == [None]


def test_main_rejects_a_bad_baseline(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    base = tmp_path / "baseline.json"
    assert pc.main(["--baseline", str(base)]) == 2
    assert "no baseline" in capsys.readouterr().err
    good = {"format": 1, "timer": pc.TIMER, "statistic": "min", "reference": pc.REFERENCE, "ratios": {"a": 1.0}}
    base.write_text(json.dumps({**good, "ratios": {"a": -1}}))
    assert pc.main(["--baseline", str(base)]) == 2
    err = capsys.readouterr().err
    assert str(base) in err and "ratios.a" in err
    base.write_text(json.dumps({**good, "statistic": "median"}))
    assert pc.main(["--baseline", str(base)]) == 2
    assert "statistic: 'median'" in capsys.readouterr().err


def test_run_suite_reruns_only_the_given_benchmarks_with_more_rounds(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[tuple[list[str], dict[str, str]]] = []

    class Done:
        returncode = 0

    def fake_run(cmd: list[str], cwd: Path, env: dict[str, str]) -> Done:
        seen.append((cmd, env))
        (tmp_path / "r.json").write_text(json.dumps(report({"a": 0.01})))
        return Done()

    monkeypatch.setattr(pc.subprocess, "run", fake_run)
    assert pc.run_suite(tmp_path / "r.json")["benchmarks"][0]["name"] == "a"
    pc.run_suite(tmp_path / "r.json", ["benchmarks/test_x.py::a[p]"])
    (full, full_env), (rerun, rerun_env) = seen
    assert "benchmarks" in full and "--benchmark-max-time=3" not in full and pc.ROUNDS_SCALE_ENV not in full_env
    assert "benchmarks/test_x.py::a[p]" in rerun and "benchmarks" not in rerun
    assert "--benchmark-max-time=3" in rerun and rerun_env[pc.ROUNDS_SCALE_ENV] == "3"
    assert full_env["OMP_NUM_THREADS"] == "1" and f"--benchmark-timer={pc.TIMER}" in full
    monkeypatch.setattr(pc.subprocess, "run", lambda cmd, cwd, env: type("Failed", (), {"returncode": 1})())
    with pytest.raises(SystemExit, match="pytest exit 1"):
        pc.run_suite(tmp_path / "r.json")
