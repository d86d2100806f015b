"""Run files: a run's configuration as TOML with the keys of its provenance (``RunConfig.as_dict()``, each
cell's ``provenance.run`` in ``summary.json``; :data:`RUN_KEYS`), read with every key checked
(:func:`load_run_file`), written (:func:`run_file_text`) and recovered from a finished run
(:func:`config_from_run`). ``robustbench3d run --config FILE / --config-from RUN_DIR / --print-config`` use them.

TOML has no null: a missing ``data`` is the embedded dataset, ``max_frames = "all"`` every frame of the split.
Standard library only at module level.
"""

from __future__ import annotations

import json
import re
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.eval.rules import TARGET_CLASS
from robustbench3d.ranges import BATCH_RANGE, FRAMES_RANGE, SEED_RANGE
from robustbench3d.results import CellResult

#: The keys of a run file: exactly those of ``RunConfig.as_dict()`` (a cell's ``provenance.run``).
RUN_KEYS = ("victims", "attacks", "proposals", "out", "data", "split", "max_frames", "seed", "batch_size",
            "victim_args", "attack_args", "classes", "bootstrap")
#: The values of the keys neither the run file nor the command line gives (``run``'s option defaults;
#: ``max_frames``: :func:`~robustbench3d.runner.config.default_max_frames`).
DEFAULTS: dict[str, Any] = {"attacks": ["none"], "proposals": ["detector"], "data": None, "split": "val",
                            "seed": 0, "batch_size": 4, "victim_args": {}, "attack_args": {}, "classes": [TARGET_CLASS],
                            "bootstrap": 1000}
#: How a run file spells ``max_frames = None`` (every frame of the split): TOML has no null.
ALL_FRAMES = "all"
#: Largest run file read (bytes): a run file is a few hundred bytes; a bigger file is not one.
RUN_FILE_MAX_BYTES = 1 << 20
NAME_LISTS = ("victims", "attacks", "proposals", "classes")
STRINGS = ("out", "data", "split")
ARG_TABLES = ("victim_args", "attack_args")
#: Options that are not run-file keys (how a run executes, not what it computes): named when one is a key.
_EXECUTION = "--workers, --executor, --jobs, --address, --force, --no-progress"


def _key_line(text: str, key: str) -> int | None:
    """The first line (1-based) of ``text`` that assigns top-level ``key`` or opens a table under it."""
    pattern = re.compile(rf"""^\s*\[*\s*(["']?){re.escape(key)}\1\s*[=.\]]""")
    return next((n for n, line in enumerate(text.splitlines(), start=1) if pattern.match(line)), None)


def _toml_error(path: Path, exc: ValueError, text: str) -> DataFormatError:
    """tomllib's syntax error as :class:`DataFormatError` at its line (its message ends ``(at line L, column
    C)``, or ``(at end of document)``: the last line)."""
    message = str(exc)
    where = re.search(r"\(at line (\d+), column (\d+)\)$", message)
    if where is not None:
        problem = f"{message[:where.start()].rstrip()} (column {where.group(2)})"
        return DataFormatError(path, f"not valid TOML: {problem}", line=int(where.group(1)))
    end = message.endswith("(at end of document)")
    return DataFormatError(path, f"not valid TOML: {message}", line=max(1, len(text.splitlines())) if end else None)


def _plain_json(value: Any, where: str) -> str | None:
    """Where in ``value`` (a factory-argument value) a TOML-only type sits (dates, times), or None."""
    if isinstance(value, dict):
        return next((bad for k, v in value.items() if (bad := _plain_json(v, f"{where}.{k}")) is not None), None)
    if isinstance(value, list):
        return next((bad for i, v in enumerate(value) if (bad := _plain_json(v, f"{where}[{i}]")) is not None), None)
    return None if value is None or isinstance(value, str | int | float | bool) else where


def _check_value(key: str, value: Any) -> str | None:
    """What is wrong with run-file ``key``'s ``value`` (one phrase), or None."""
    from robustbench3d.ranges import RESAMPLES_RANGE

    if key in NAME_LISTS:
        if not (isinstance(value, list) and value and all(isinstance(v, str) and v.strip() for v in value)):
            return "expected a non-empty list of names, e.g. [\"none\", \"adv-shape\"]"
        if key == "classes":
            from robustbench3d.eval.rules import CLASSES

            if unknown := [v for v in value if v not in CLASSES]:
                return f"unknown class {unknown[0]!r}; choose from {', '.join(CLASSES)}"
        return None
    if key in STRINGS:
        return None if isinstance(value, str) and value.strip() else "expected a non-empty string"
    if key in ARG_TABLES:
        if not (isinstance(value, dict) and all(isinstance(v, dict) for v in value.values())):
            return "expected tables of keyword arguments, e.g. [victim_args.fpointnet-v1] weights = \"cascade.pt\""
        bad = _plain_json(value, key)
        return None if bad is None else f"{bad} is a TOML date or time; give it as a string"
    if key == "max_frames" and value == ALL_FRAMES:
        return None
    low, high, what = {"max_frames": (*FRAMES_RANGE, f'frames, or "{ALL_FRAMES}"'), "seed": (*SEED_RANGE, "run seed"),
                       "batch_size": (*BATCH_RANGE, "frames per detect call"),
                       "bootstrap": (0, RESAMPLES_RANGE[1], f"0: none, else {RESAMPLES_RANGE[0]}..")}[key]
    if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
        return f"must be an integer in {low}..{high} ({what}), got {value!r}"
    if key == "bootstrap" and 0 < value < RESAMPLES_RANGE[0]:
        return f"must be 0 (no intervals) or in {RESAMPLES_RANGE[0]}..{high} (bootstrap resamples), got {value!r}"
    return None


def load_run_file(path: str | Path) -> dict[str, Any]:
    """The settings of run file ``path`` (keys of :data:`RUN_KEYS`; ``max_frames`` may be ``"all"``).

    Raises:
        DataFormatError: one line naming the file and, where known, the line and key: a missing or
            unreadable file, bad TOML, an unknown key, a value of the wrong type or out of its range.
    """
    from robustbench3d.fileio import data_file_errors, read_data_text

    path = Path(path)
    with data_file_errors(path):
        size = path.stat().st_size
    if size > RUN_FILE_MAX_BYTES:
        raise DataFormatError(path, f"{size} bytes: not a run file (a run file is under {RUN_FILE_MAX_BYTES} bytes)")
    text = read_data_text(path)
    try:
        data = _tomllib().loads(text)
    except ValueError as exc:  # tomllib.TOMLDecodeError
        raise _toml_error(path, exc, text) from None
    for key, value in data.items():
        if key not in RUN_KEYS:
            raise DataFormatError(path, f"unknown key; a run file has the keys {', '.join(RUN_KEYS)} (execution "
                                        f"settings are options: {_EXECUTION})", _key_line(text, key), key)
        problem = _check_value(key, value)
        if problem is not None:
            raise DataFormatError(path, problem, _key_line(text, key), key)
    return data


def _tomllib() -> Any:
    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover - Python 3.10: the tomli backport, a dependency there
        import tomli as tomllib
    return tomllib


def merge_args(base: Mapping[str, Mapping[str, Any]], over: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """Factory arguments per name: ``over``'s keys replace ``base``'s, the others are kept."""
    out = {name: dict(kwargs) for name, kwargs in base.items()}
    for name, kwargs in over.items():
        out.setdefault(name, {}).update(kwargs)
    return out


def run_file_text(settings: Mapping[str, Any]) -> str:
    """The run file of ``settings`` (:func:`run_settings`): a comment, then TOML (``tomli_w``) with the keys
    in :data:`RUN_KEYS` order (tables last); ``data`` None is left out, ``max_frames`` None is ``"all"``.

    Raises:
        RobustBenchError: a factory argument is null (TOML cannot hold it).
    """
    import tomli_w

    for key in ARG_TABLES:
        for name, kwargs in settings[key].items():
            for arg, value in kwargs.items():
                if value is None:
                    raise RobustBenchError(f"--print-config: {key}.{name}.{arg} is null, which TOML cannot hold; "
                                           "leave the argument out (its factory default) or give a value")
    data = {k: v for k, v in settings.items() if not (k == "data" and v is None)}
    if data["max_frames"] is None:
        data["max_frames"] = ALL_FRAMES
    return ("# robustbench3d run file: `robustbench3d run --config FILE` runs it; options given with --config\n"
            "# override its values. Keys: those of the run's provenance (RunConfig.as_dict()); no data: the\n"
            f"# embedded dataset; max_frames = \"{ALL_FRAMES}\": every frame of the split.\n" + tomli_w.dumps(data))


def _covers(run: Mapping[str, Any], cells: list[CellResult]) -> bool:
    return all(c.victim in run["victims"] and c.attack in run["attacks"] and c.proposals in run["proposals"]
               for c in cells)


def config_from_run(run_dir: str | Path) -> dict[str, Any]:
    """The run file's settings of a finished run: from ``RUN_DIR/summary.json``, the recorded run
    configuration (``provenance.run``) whose grid holds every cell of the summary, the most recently
    finished if several do (a directory that several runs added cells to has none: refused)."""
    from robustbench3d.results import read_summary

    path = Path(run_dir) / "summary.json"
    cells = [CellResult(c) for c in read_summary(path)]
    runs = sorted((c.provenance["finished"], json.dumps(c.provenance["run"], sort_keys=True))
                  for c in cells if isinstance(c.provenance.get("run"), dict))
    found = [json.loads(run) for _, run in reversed(runs) if _covers(json.loads(run), cells)]
    if not found:
        raise DataFormatError(path, f"no recorded run configuration (provenance.run) covers all {len(cells)} cells "
                                    "(cells of several runs): write the run file by hand (see --print-config)")
    settings = dict(found[0])
    if settings["max_frames"] is None:
        settings["max_frames"] = ALL_FRAMES
    if settings["data"] is None:
        del settings["data"]
    return settings
