"""Mutation testing of the numeric core with mutmut (see docs/mutation-testing.md).

mutmut imports the mutated code from ``mutants/<path>`` and names mutants after the file path, so
it needs the installed package layout (``eval/`` is ``robustbench3d/eval`` there, ``victims/`` is
``robustbench3d/victims``). ``stage`` copies the sources into that layout under ``build/mutation``
(with ``tests/`` and ``pyproject.toml``, whose ``[tool.mutmut]`` table configures the run);
``report`` prints the kill rate per module from mutmut's results there::

    python tools/mutation.py stage
    cd build/mutation && ROBUSTBENCH3D_KITTI_SAMPLES=/nonexistent OMP_NUM_THREADS=1 \\
        mutmut run --max-children 1 "robustbench3d.victims.fpointnet.frustum.*"
    python tools/mutation.py report
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
STAGE = REPO / "build" / "mutation"
#: Source directory -> its place in the installed layout (``[tool.setuptools] package-dir``).
LAYOUT = {"robustbench3d": "robustbench3d", "eval": "robustbench3d/eval", "victims": "robustbench3d/victims",
          "attacks": "robustbench3d/attacks"}
_IGNORE = shutil.ignore_patterns("__pycache__", "*.pyc", ".pytest_cache")


def stage(dest: Path = STAGE) -> Path:
    """Copy the sources (installed layout), ``tests/`` and ``pyproject.toml`` to ``dest``; files
    keep their times, so mutmut re-mutates only what changed. ``dest/mutants`` is kept."""
    dest.mkdir(parents=True, exist_ok=True)
    for src, target in LAYOUT.items():
        shutil.copytree(REPO / src, dest / target, ignore=_IGNORE, dirs_exist_ok=True)
    shutil.copytree(REPO / "tests", dest / "tests", ignore=_IGNORE, dirs_exist_ok=True)
    shutil.copy2(REPO / "pyproject.toml", dest / "pyproject.toml")
    return dest


#: mutmut exit-code statuses (``mutmut.__main__.status_by_exit_code``) grouped for the report.
_KILLED = {"killed", "timeout", "segfault", "caught by type check"}


def report(dest: Path = STAGE) -> dict[str, Counter[str]]:
    """Per mutated module: counts of mutmut statuses, from ``dest/mutants/**/*.py.meta``."""
    from mutmut.__main__ import status_by_exit_code

    out: dict[str, Counter[str]] = {}
    for meta in sorted((dest / "mutants").rglob("*.py.meta")):
        data = json.loads(meta.read_text(encoding="utf-8"))
        codes = data.get("exit_code_by_key", {})
        if not codes:
            continue
        module = str(meta.relative_to(dest / "mutants"))[: -len(".py.meta")].replace("/", ".")
        out[module] = Counter(status_by_exit_code[c] for c in codes.values())
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("command", choices=("stage", "report"))
    parser.add_argument("--dest", type=Path, default=STAGE, help=f"staging directory (default {STAGE})")
    args = parser.parse_args(argv)
    if args.command == "stage":
        print(stage(args.dest))
        return 0
    for module, counts in report(args.dest).items():
        total = sum(counts.values())
        if counts["not checked"] == total:
            print(f"{module:50s} not run ({total} mutants)")
            continue
        killed = sum(n for s, n in counts.items() if s in _KILLED)
        rest = ", ".join(f"{s} {n}" for s, n in sorted(counts.items()) if s not in _KILLED)
        rate = f"{killed:4d}/{total:<4d} killed ({100 * killed / total:5.1f} %)"
        print(f"{module:50s} {rate}{'; ' + rest if rest else ''}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
