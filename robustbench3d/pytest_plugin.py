"""pytest plugin: gate a registered victim's clean AP and AP drop in a user's own test suite.

Installed as the ``pytest11`` entry point ``robustbench3d`` (or loaded with ``-p robustbench3d.pytest_plugin``)::

    import pytest

    @pytest.mark.robustbench3d(victim="lidar-cluster", attacks=["benign-sphere"], frames=6)
    def test_robustness(robustbench3d_run):
        assert robustbench3d_run.clean_ap() >= 5.0                        # Car BEV R40 moderate, %
        assert robustbench3d_run.drop("benign-sphere") <= 10.0            # percentage points

The fixture ``robustbench3d_run`` runs :func:`robustbench3d.runner.run_benchmark` with the marker's
victim, attacks (the clean cell ``none`` is added), proposal sources and the first ``frames`` frames of
the split (default: the embedded dataset's val split; only those frames are generated on first use)
into a session temporary directory, and returns a :class:`BenchmarkResult`. Tests with the same marker
arguments share one run. Marker keywords: ``victim`` (required), ``attacks`` (default none),
``frames`` (default 8), ``proposals`` (default ``("detector",)``; any of ``detector``, ``gt``, ``gt-object``,
``gt-append``: :data:`robustbench3d.victims.spec.PROTOCOL_LABELS`), ``data`` (a KITTI-layout root),
``split`` ("val"), ``seed`` (0), ``victim_args`` / ``attack_args`` (factory keyword arguments,
``{name: {key: value}}`` or for the victim just ``{key: value}``). ``frames`` is an integer >= 1 and
``seed`` one in [0, 2**63 - 1] (:data:`robustbench3d.victims.zoo.SEED_RANGE`); anything else is a usage
error naming the keyword, raised before any run.

What a test saw is reported: each test's ``robustbench3d_run`` records, as JUnit properties of the test
(``user_properties``, written by ``--junitxml``), the run (``robustbench3d.victim``, ``.frames``, ``.cells``,
``.out``) and every number it hands out, named ``robustbench3d.clean_ap.PROPOSALS.CLASS.METRIC.RECALL.DIFFICULTY``
(``ap.ATTACK...``, ``drop.ATTACK...``, ``relative_drop.ATTACK...`` for the others), e.g.
``robustbench3d.clean_ap.gt.Car.bev.R40.moderate = 96.1``. A failing test adds a ``robustbench3d``
section to its failure report: the run, the frame count, the cells the test read with their flags and
evaluator notes, and the numbers it was handed.

Standard library and pytest only at import (pytest loads entry-point plugins in every session).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Generator, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from robustbench3d.metrics import HEADLINE
from robustbench3d.results import CellResult

MARKER = "robustbench3d"
DEFAULT_FRAMES = 8


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", f"{MARKER}(victim, attacks=('none',), frames={DEFAULT_FRAMES}, proposals=('detector',), data=None, "
                   "split='val', seed=0, victim_args=None, attack_args=None): what the robustbench3d_run fixture runs")


PROPERTY_PREFIX = "robustbench3d"


class _Seen:
    """What one test read from the run: the cells (in order) and the numbers handed out, each number
    also recorded as a JUnit property of the test (``item.user_properties``)."""

    def __init__(self, item: pytest.Item) -> None:
        self.item = item
        self.cells: list[str] = []
        self.values: dict[str, Any] = {}

    def record(self, key: str, value: Any) -> None:
        """Record one number handed out, once per test."""
        if key not in self.values:
            self.values[key] = value
            self.item.user_properties.append((key, value))

    def cell(self, name: str) -> None:
        if name not in self.cells:
            self.cells.append(name)


@dataclass(frozen=True)
class BenchmarkResult:
    """The cells of one benchmark run, read by attack and proposal source (AP in percent)."""

    out: Path
    victim: str
    cells: tuple[dict[str, Any], ...] = field(repr=False)
    #: The run's progress lines (dataset, cells, flags).
    log: tuple[str, ...] = field(default=(), repr=False)
    #: What the test holding this object read (set by the fixture; None outside a test).
    _seen: _Seen | None = field(default=None, repr=False, compare=False)

    def cell(self, attack: str = "none", proposals: str = "detector") -> dict[str, Any]:
        """The summary cell; a failed or skipped cell fails the test with its reason."""
        for c in self.cells:
            r = CellResult(c)
            if (r.attack, r.proposals) == (attack, proposals):
                if self._seen is not None:
                    self._seen.cell(r.name)
                if not r.ok:
                    pytest.fail(f"robustbench3d cell {self.victim} / {attack} / {proposals} is {r.status}: "
                                f"{r.reason}", pytrace=False)
                return c
        have = ", ".join(f"{r.attack}/{r.proposals}" for r in map(CellResult, self.cells))
        raise LookupError(f"no cell {attack}/{proposals} in this run (cells: {have}); add it to the marker")

    def ap(self, attack: str = "none", metric: str = HEADLINE.metric, difficulty: str = HEADLINE.difficulty,
           proposals: str = "detector", recall: str = HEADLINE.recall, cls: str = HEADLINE.cls) -> float:
        """AP in percent of one cell."""
        value = CellResult(self.cell(attack, proposals)).ap(cls, metric, recall, difficulty)
        kind = "clean_ap" if attack == "none" else f"ap.{attack}"
        return self._record(f"{kind}.{proposals}.{cls}.{metric}.{recall}.{difficulty}", value)

    def clean_ap(self, metric: str = HEADLINE.metric, difficulty: str = HEADLINE.difficulty,
                 proposals: str = "detector", recall: str = HEADLINE.recall, cls: str = HEADLINE.cls) -> float:
        """AP in percent of the clean cell (attack ``none``)."""
        return self.ap("none", metric, difficulty, proposals, recall, cls)

    def drop(self, attack: str, metric: str = HEADLINE.metric, difficulty: str = HEADLINE.difficulty,
             proposals: str = "detector", recall: str = HEADLINE.recall, cls: str = HEADLINE.cls,
             relative: bool = False) -> float | None:
        """Clean AP - attacked AP in percentage points (``relative``: as a fraction of the clean AP, None where
        it is 0), from the attacked cell's ``attack_effect``."""
        value = CellResult(self.cell(attack, proposals)).drop(cls, metric, recall, difficulty, relative=relative)
        kind = "relative_drop" if relative else "drop"
        return self._record(f"{kind}.{attack}.{proposals}.{cls}.{metric}.{recall}.{difficulty}", value)

    def _record(self, key: str, value: Any) -> Any:
        """``value``, recorded as the test's property ``robustbench3d.KEY``."""
        if self._seen is not None:
            self._seen.record(f"{PROPERTY_PREFIX}.{key}", value)
        return value

    def flags(self, attack: str = "none", proposals: str = "detector") -> list[dict[str, str]]:
        """The cell's sanity flags (:mod:`robustbench3d.runner.flags`)."""
        return [dict(f) for f in CellResult(self.cell(attack, proposals)).flags]

    @property
    def frames(self) -> int:
        return int(CellResult(self.cells[0]).frames)

    def for_test(self, item: pytest.Item) -> BenchmarkResult:
        """This run, recording what the test ``item`` reads (its properties and failure section)."""
        seen = _Seen(item)
        item.user_properties += [(f"{PROPERTY_PREFIX}.{key}", value) for key, value in (
            ("victim", self.victim), ("frames", self.frames),
            ("cells", ", ".join(cell_name(c) for c in self.cells)), ("out", str(self.out)))]
        item.stash[_SEEN_KEY] = (self, seen)
        return dataclasses.replace(self, _seen=seen)


def cell_name(cell: Mapping[str, Any]) -> str:
    """``victim+attack+proposals``, the name of a cell in a run's output and in ``check``."""
    return CellResult(cell).name


def _cell_lines(cell: Mapping[str, Any]) -> Iterator[str]:
    """A cell's status, sanity flags and evaluator notes / skipped metrics, for the failure section."""
    r = CellResult(cell)
    yield f"  {r.name}: {r.status}" + (f" ({r.reason})" if r.reason else "")
    for flag in r.flags:
        yield f"    flag {flag['code']}: {flag['message']}"
    meta = r.result.meta if r.result is not None else {}
    notes = [*meta.get("notes", []),
             *(f"skipped {s['class']} {s['metric']}: {s['reason']}" for s in meta.get("skipped", []))]
    yield from (f"    evaluator note: {n}" for n in notes) if notes else ["    evaluator notes: none"]


def describe(run: BenchmarkResult, seen: _Seen) -> str:
    """The ``robustbench3d`` section of a failing test's report: run, frames, cells read, numbers."""
    dataset = CellResult(run.cells[0]).dataset
    lines = [f"run: victim {run.victim}, {run.frames} frame(s) of split {dataset['split']!r} "
             f"({dataset['split_frames']} in the split) under {dataset['root']}; output {run.out}"]
    by_name = {cell_name(c): c for c in run.cells}
    if seen.cells:
        lines.append("cell(s) this test read:")
        lines += [line for name in seen.cells for line in _cell_lines(by_name[name])]
    else:
        lines.append(f"cell(s) this test read: none (the run's cells: {', '.join(by_name)})")
    if seen.values:
        lines.append("numbers handed to the test (AP in %, drops in percentage points):")
        lines += [f"  {key} = {value}" for key, value in seen.values.items()]
    return "\n".join(lines)


def _names(value: str | Sequence[str] | None, default: tuple[str, ...]) -> tuple[str, ...]:
    if value is None:
        return default
    return (value,) if isinstance(value, str) else tuple(value)


def _marker_int(kw: dict[str, Any], key: str, default: int, lo: int, hi: int | None = None) -> int:
    """Pop the integer marker keyword ``key`` (``default`` if absent), refusing a non-integer (a bool, a
    float that ``int()`` would truncate, a string) or one outside [lo, hi] (hi None: no upper bound)."""
    value = kw.pop(key, default)
    bounds = f"in [{lo}, {hi}]" if hi is not None else f">= {lo}"
    if isinstance(value, bool) or not isinstance(value, int) or value < lo or (hi is not None and value > hi):
        raise pytest.UsageError(f"@pytest.mark.{MARKER}: {key}={value!r} is not an integer {bounds}")
    return value


def _marker_sources(kw: dict[str, Any]) -> tuple[str, ...]:
    """Pop the ``proposals`` marker keyword (default ``("detector",)``): proposal sources of
    :data:`~robustbench3d.victims.spec.PROPOSAL_SOURCES`; another name is a usage error listing them."""
    from robustbench3d.victims.spec import PROPOSAL_SOURCES, describe_sources

    sources = _names(kw.pop("proposals", None), ("detector",))
    bad = [s for s in sources if s not in PROPOSAL_SOURCES]
    if bad:
        raise pytest.UsageError(f"@pytest.mark.{MARKER}: proposals={bad[0]!r} is not a proposal source; choose from "
                                f"{describe_sources()}")
    return sources


def _config_from_marker(marker: pytest.Mark, out: Path) -> Any:
    from robustbench3d.runner import RunConfig

    kw = dict(marker.kwargs)
    victim = kw.pop("victim", marker.args[0] if marker.args else None)
    if not isinstance(victim, str):
        raise pytest.UsageError(f"@pytest.mark.{MARKER}: give the registered victim name, victim='NAME'")
    attacks = _names(kw.pop("attacks", None), ())
    attacks = ("none", *(a for a in attacks if a != "none"))
    victim_args = kw.pop("victim_args", None) or {}
    if victim_args and not all(isinstance(v, Mapping) for v in victim_args.values()):
        victim_args = {victim: victim_args}
    from robustbench3d.victims.zoo import SEED_RANGE

    frames = _marker_int(kw, "frames", DEFAULT_FRAMES, 1)
    seed = _marker_int(kw, "seed", 0, *SEED_RANGE)
    config = RunConfig(victims=(victim,), attacks=attacks, proposals=_marker_sources(kw),
                       out=out, data=kw.pop("data", None), split=kw.pop("split", "val"), max_frames=frames, seed=seed,
                       victim_args=victim_args, attack_args=kw.pop("attack_args", None) or {}, workers=1,
                       progress=False)
    if kw:
        raise pytest.UsageError(f"@pytest.mark.{MARKER}: unknown keyword(s) {', '.join(sorted(kw))}")
    return config


_RUNS = pytest.StashKey[dict[str, BenchmarkResult]]()
_SEEN_KEY = pytest.StashKey[tuple[BenchmarkResult, _Seen]]()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item,
                              call: pytest.CallInfo[None]) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    """Add the ``robustbench3d`` section (:func:`describe`) to a failing test that used the fixture."""
    report = yield
    found = item.stash.get(_SEEN_KEY, None)
    if found is not None and report.when == "call" and report.failed:
        text = describe(*found)
        if hasattr(report.longrepr, "addsection"):  # shown in the terminal and in --junitxml's failure text
            report.longrepr.addsection(MARKER, text)
        else:
            report.sections.append((MARKER, text))
    return report


@pytest.fixture
def robustbench3d_run(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> BenchmarkResult:
    """Run the benchmark the test's ``@pytest.mark.robustbench3d(...)`` describes (module doc)."""
    marker = request.node.get_closest_marker(MARKER)
    if marker is None:
        raise pytest.UsageError(f"the robustbench3d_run fixture needs @pytest.mark.{MARKER}(victim=...) on the test")
    runs = request.config.stash.setdefault(_RUNS, {})  # one run per marker arguments and session
    key = json.dumps([list(marker.args), marker.kwargs], sort_keys=True, default=str)
    if key not in runs:
        from robustbench3d.runner import run_benchmark

        out = tmp_path_factory.mktemp("robustbench3d")
        config = _config_from_marker(marker, out)
        lines: list[str] = []
        report = run_benchmark(config, lines.append)
        runs[key] = BenchmarkResult(out=out, victim=config.victims[0], cells=tuple(report.summary), log=tuple(lines))
    return runs[key].for_test(request.node)


__all__ = ["BenchmarkResult", "cell_name", "robustbench3d_run"]
