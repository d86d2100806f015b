"""Messages of the long commands: the ``robustbench3d`` logger, written through ``tqdm.write``.

Every line a command prints while it works (per-cell lines, kept or replaced cells, warnings) goes to the
``robustbench3d`` logger (modules log to children such as ``robustbench3d.runner``). A command that sets
it up (:func:`cli_logging`) hands the lines to :class:`TqdmHandler`, which writes each one through
``tqdm.write``: the progress bars on stderr are cleared first and redrawn below it, so a line never
garbles a bar. The levels of ``-q``/``-v`` (:func:`add_verbosity_arguments`):

======  ===================  =======================================================
flag    logger level         what stderr shows
======  ===================  =======================================================
``-q``  WARNING              warnings and errors only (and no progress bars)
(none)  INFO                 per-cell lines, what was kept or replaced, bars
``-v``  DEBUG                also the details (per shard, per cell fingerprint)
======  ===================  =======================================================

Library callers keep their own line sinks (:class:`LineLog` takes a ``print_fn``). Standard library only at
module level (tqdm is imported when a line is written): a foundation every layer may import.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import IO

#: The package's logger name; modules log to ``robustbench3d.<part>``.
LOGGER = "robustbench3d"

#: ``-q`` / (none) / ``-v`` -> logger level.
LEVELS = {-1: logging.WARNING, 0: logging.INFO, 1: logging.DEBUG}


def tqdm_write(line: str, file: IO[str] | None = None) -> None:
    """Write ``line`` (and a newline) to ``file`` (default: the current ``sys.stderr``) through
    ``tqdm.write``: open progress bars on that stream are cleared before and redrawn after it."""
    from tqdm import tqdm

    stream = file if file is not None else sys.stderr
    tqdm.write(line, file=stream)
    stream.flush()


class TqdmHandler(logging.Handler):
    """A logging handler that writes each formatted record through :func:`tqdm_write` (to ``stream``, or
    to ``sys.stderr`` as it is when the record is written, so captured streams see it)."""

    def __init__(self, stream: IO[str] | None = None, level: int = logging.NOTSET) -> None:
        super().__init__(level)
        self.stream = stream

    def emit(self, record: logging.LogRecord) -> None:
        try:
            tqdm_write(self.format(record), self.stream)
        except Exception:  # logging's contract: a failing handler never raises into the caller
            self.handleError(record)


@contextlib.contextmanager
def cli_logging(verbosity: int = 0, stream: IO[str] | None = None) -> Iterator[logging.Logger]:
    """For the duration of a command: the ``robustbench3d`` logger at the level of ``verbosity`` (-1: ``-q``,
    0, 1: ``-v``; :data:`LEVELS`), writing plain message lines through a :class:`TqdmHandler` and not to the
    root logger; the logger's earlier handlers, level and propagation are restored afterwards."""
    logger = logging.getLogger(LOGGER)
    saved = (logger.handlers[:], logger.level, logger.propagate)
    handler = TqdmHandler(stream)
    handler.setFormatter(logging.Formatter("%(message)s"))
    logger.handlers, logger.propagate = [handler], False
    logger.setLevel(LEVELS[max(-1, min(1, verbosity))])
    try:
        yield logger
    finally:
        logger.handlers, logger.propagate = saved[0], saved[2]
        logger.setLevel(saved[1])


def add_verbosity_arguments(parser: argparse.ArgumentParser) -> None:
    """``-q/--quiet`` and ``-v/--verbose`` (exclusive); :func:`verbosity` reads them."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument("-q", "--quiet", action="store_true",
                       help="only warnings and errors on stderr (no progress bars, no per-cell lines); "
                            "the result tables on stdout as always")
    group.add_argument("-v", "--verbose", action="store_true",
                       help="also the details on stderr (per shard and per cell: fingerprints, directories)")


def verbosity(args: argparse.Namespace) -> int:
    """-1 with ``--quiet``, 1 with ``--verbose``, else 0."""
    return -1 if getattr(args, "quiet", False) else 1 if getattr(args, "verbose", False) else 0


@dataclass(frozen=True)
class LineLog:
    """A line sink with levels, callable as ``log(line)`` (info).

    With ``sink`` (a caller's ``print_fn``): info and warning lines go to it, debug lines only to the logger.
    Without: every line goes to ``logger`` when logging is set up anywhere (a handler on it or a parent:
    :func:`cli_logging`, an application's own configuration), else info and warning lines to stderr through
    :func:`tqdm_write` (a library call with no logging set up still shows its lines).
    """

    logger: logging.Logger
    sink: Callable[[str], None] | None = None

    def __call__(self, line: str) -> None:
        self._emit(logging.INFO, line)

    def warning(self, line: str) -> None:
        """A line the user should see even with ``-q`` (a replaced cell, a left-out cell, a traceback)."""
        self._emit(logging.WARNING, line)

    def debug(self, line: str) -> None:
        """A detail line: only with ``-v`` (never to ``sink``)."""
        self.logger.debug(line)

    def _emit(self, level: int, line: str) -> None:
        if self.sink is not None:
            self.sink(line)
        elif self.logger.hasHandlers():
            self.logger.log(level, line)
        else:
            tqdm_write(line)


def line_log(name: str, print_fn: Callable[[str], None] | None = None) -> LineLog:
    """The :class:`LineLog` of module ``name`` (a ``robustbench3d.*`` logger) over ``print_fn`` (None: logging)."""
    return print_fn if isinstance(print_fn, LineLog) else LineLog(logging.getLogger(name), print_fn)


def warn(log: Callable[[str], None], line: str) -> None:
    """``log.warning(line)`` for a :class:`LineLog`, else ``log(line)`` (a plain ``print_fn``)."""
    (log.warning if isinstance(log, LineLog) else log)(line)


__all__ = ["LEVELS", "LOGGER", "LineLog", "TqdmHandler", "add_verbosity_arguments", "cli_logging", "line_log",
           "tqdm_write", "verbosity", "warn"]
