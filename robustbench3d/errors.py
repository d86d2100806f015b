"""Error types. Every data error names the file, and where it applies, the line and field."""

from __future__ import annotations

from pathlib import Path


class RobustBenchError(Exception):
    """Base class of all errors raised deliberately by robustbench3d."""


class DataFormatError(RobustBenchError, ValueError):
    """A file does not follow the format it claims (KITTI labels, calib, scans, images...).

    The message reads ``<file>:<line>: field '<field>': <problem>``; line and field are omitted
    when they do not apply (e.g. a scan whose size is not a multiple of 16 bytes).
    """

    def __init__(self, path: str | Path, problem: str, line: int | None = None, field: str | None = None):
        self.path = Path(path)
        self.line = line
        self.field = field
        self.problem = problem
        where = str(self.path) + (f":{line}" if line is not None else "")
        what = f"field '{field}': " if field is not None else ""
        super().__init__(f"{where}: {what}{problem}")
