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
``frames`` (default 8), ``proposals`` (default ``("detector",)``), ``data`` (a KITTI-layout root),
``split`` ("val"), ``seed`` (0), ``victim_args`` / ``attack_args`` (factory keyword arguments,
``{name: {key: value}}`` or for the victim just ``{key: value}``). ``frames`` is an integer >= 1 and
``seed`` one in [0, 2**63 - 1] (:data:`robustbench3d.victims.zoo.SEED_RANGE`); anything else is a usage
error naming the keyword, raised before any run.

Standard library and pytest only at import (pytest loads entry-point plugins in every session).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

MARKER = "robustbench3d"
DEFAULT_FRAMES = 8


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", f"{MARKER}(victim, attacks=('none',), frames={DEFAULT_FRAMES}, proposals=('detector',), data=None, "
                   "split='val', seed=0, victim_args=None, attack_args=None): what the robustbench3d_run fixture runs")


@dataclass(frozen=True)
class BenchmarkResult:
    """The cells of one benchmark run, read by attack and proposal source (AP in percent)."""

    out: Path
    victim: str
    cells: tuple[dict[str, Any], ...] = field(repr=False)
    #: The run's progress lines (dataset, cells, flags).
    log: tuple[str, ...] = field(default=(), repr=False)

    def cell(self, attack: str = "none", proposals: str = "detector") -> dict[str, Any]:
        """The summary cell; a failed or skipped cell fails the test with its reason."""
        for c in self.cells:
            if (c["attack"], c["proposals"]) == (attack, proposals):
                if c["status"] != "ok":
                    pytest.fail(f"robustbench3d cell {self.victim} / {attack} / {proposals} is {c['status']}: "
                                f"{c['reason']}", pytrace=False)
                return c
        have = ", ".join(f"{c['attack']}/{c['proposals']}" for c in self.cells)
        raise LookupError(f"no cell {attack}/{proposals} in this run (cells: {have}); add it to the marker")

    def ap(self, attack: str = "none", metric: str = "bev", difficulty: str = "moderate",
           proposals: str = "detector", recall: str = "R40", cls: str = "Car") -> float:
        """AP in percent of one cell."""
        from robustbench3d.results import CellResult

        return CellResult(self.cell(attack, proposals)).ap(cls, metric, recall, difficulty)

    def clean_ap(self, metric: str = "bev", difficulty: str = "moderate", proposals: str = "detector",
                 recall: str = "R40", cls: str = "Car") -> float:
        """AP in percent of the clean cell (attack ``none``)."""
        return self.ap("none", metric, difficulty, proposals, recall, cls)

    def drop(self, attack: str, metric: str = "bev", difficulty: str = "moderate", proposals: str = "detector",
             recall: str = "R40", cls: str = "Car", relative: bool = False) -> float | None:
        """Clean AP - attacked AP in percentage points (``relative``: as a fraction of the clean AP, None where
        it is 0), from the attacked cell's ``attack_effect``."""
        from robustbench3d.results import CellResult

        return CellResult(self.cell(attack, proposals)).drop(cls, metric, recall, difficulty, relative=relative)

    def flags(self, attack: str = "none", proposals: str = "detector") -> list[dict[str, str]]:
        """The cell's sanity flags (:mod:`robustbench3d.runner.flags`)."""
        return list(self.cell(attack, proposals).get("flags") or [])

    @property
    def frames(self) -> int:
        return int(self.cells[0]["dataset"]["frames"])


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
    config = RunConfig(victims=(victim,), attacks=attacks, proposals=_names(kw.pop("proposals", None), ("detector",)),
                       out=out, data=kw.pop("data", None), split=kw.pop("split", "val"), max_frames=frames, seed=seed,
                       victim_args=victim_args, attack_args=kw.pop("attack_args", None) or {}, workers=1,
                       progress=False)
    if kw:
        raise pytest.UsageError(f"@pytest.mark.{MARKER}: unknown keyword(s) {', '.join(sorted(kw))}")
    return config


_RUNS = pytest.StashKey[dict[str, BenchmarkResult]]()


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
    return runs[key]


__all__ = ["BenchmarkResult", "robustbench3d_run"]
