"""Benchmark runner: every victim x attack x proposal-source cell over one dataset split.

    >>> from robustbench3d.runner import RunConfig, run_benchmark
    >>> report = run_benchmark(RunConfig(victims=("lidar-cluster",), attacks=("none",),
    ...                                  proposals=("detector",), out="runs/a"))  # doctest: +SKIP

See :mod:`robustbench3d.runner.grid` for the output layout and resume rules,
:mod:`robustbench3d.runner.cell` for what one cell does, :mod:`robustbench3d.runner.outcome` for how it ends
(:class:`CellOutcome`, the run's :class:`RunReport`), and :mod:`robustbench3d.results` for the
summary schema and the long-format CSV.
"""

from robustbench3d.runner.config import PROPOSAL_SOURCES, CellKey, RunConfig
from robustbench3d.runner.grid import run_benchmark
from robustbench3d.runner.outcome import CellOutcome, RunReport
from robustbench3d.runner.table import summary_table

__all__ = ["PROPOSAL_SOURCES", "CellKey", "CellOutcome", "RunConfig", "RunReport", "run_benchmark", "summary_table"]
