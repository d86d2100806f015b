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

``sample`` draws a seeded uniform sample of one module's mutants (for a module too large to run
whole on two cores); ``report --only FILE`` then gives the sample's kill rate with its 95 % interval.
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


def _verdicts(dest: Path = STAGE) -> dict[str, dict[str, int | None]]:
    """Per mutated module: mutant name -> mutmut exit code (None: not run), from ``dest/mutants/**/*.py.meta``."""
    out: dict[str, dict[str, int | None]] = {}
    for meta in sorted((dest / "mutants").rglob("*.py.meta")):
        codes = json.loads(meta.read_text(encoding="utf-8")).get("exit_code_by_key", {})
        if codes:
            out[str(meta.relative_to(dest / "mutants"))[: -len(".py.meta")].replace("/", ".")] = codes
    return out


def report(dest: Path = STAGE, only: set[str] | None = None) -> dict[str, Counter[str]]:
    """Per mutated module: counts of mutmut statuses (of the mutants named in ``only``, if given)."""
    from mutmut.__main__ import status_by_exit_code

    out: dict[str, Counter[str]] = {}
    for module, codes in _verdicts(dest).items():
        kept = [c for name, c in codes.items() if only is None or name in only]
        if kept:
            out[module] = Counter(status_by_exit_code[c] for c in kept)
    return out


def sample(module: str, size: int, seed: int, dest: Path = STAGE, unchecked: bool = False) -> list[str]:
    """``size`` mutant names of ``module`` drawn uniformly without replacement (``numpy.random.default_rng(seed)``
    over the sorted names), sorted: a module too large to run whole is estimated from them. ``unchecked``: only
    from the mutants not run yet (a stratum beside those already run, whose verdicts are exact)."""
    import numpy as np

    names = sorted(n for n, code in _verdicts(dest).get(module, {}).items() if code is None or not unchecked)
    if not names:
        raise SystemExit(f"{module}: no mutants in {dest / 'mutants'} (stage, then `mutmut run` once generates them)")
    pick = np.random.default_rng(seed).choice(len(names), size=min(size, len(names)), replace=False)
    return sorted(names[i] for i in pick)


def wilson(killed: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a kill rate ``killed / n`` (0 to 1)."""
    if n == 0:
        return 0.0, 1.0
    p, z2 = killed / n, z * z
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = z * (p * (1 - p) / n + z2 / (4 * n * n)) ** 0.5 / (1 + z2 / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("command", choices=("stage", "report", "sample"))
    parser.add_argument("--dest", type=Path, default=STAGE, help=f"staging directory (default {STAGE})")
    parser.add_argument("--module", help="sample: the module (e.g. robustbench3d.sensors.camera_render)")
    parser.add_argument("--size", type=int, default=300, help="sample: how many mutants (default 300)")
    parser.add_argument("--seed", type=int, default=0, help="sample: seed of the draw (default 0)")
    parser.add_argument("--unchecked", action="store_true", help="sample: only from the mutants not run yet")
    parser.add_argument("--only", type=Path, metavar="FILE",
                        help="report: count only the mutants named in FILE (one per line, e.g. a sample), with the "
                             "kill rate's 95 %% Wilson interval")
    args = parser.parse_args(argv)
    if args.command == "stage":
        print(stage(args.dest))
        return 0
    if args.command == "sample":
        if not args.module:
            parser.error("sample needs --module")
        print("\n".join(sample(args.module, args.size, args.seed, args.dest, args.unchecked)))
        return 0
    only = set(args.only.read_text(encoding="utf-8").split()) if args.only else None
    for module, counts in report(args.dest, only).items():
        total = sum(counts.values())
        if counts["not checked"] == total:
            print(f"{module:50s} not run ({total} mutants)")
            continue
        killed = sum(n for s, n in counts.items() if s in _KILLED)
        rest = ", ".join(f"{s} {n}" for s, n in sorted(counts.items()) if s not in _KILLED)
        rate = f"{killed:4d}/{total:<4d} killed ({100 * killed / total:5.1f} %)"
        if only is not None:
            lo, hi = wilson(killed, total)
            rate += f" [95 % CI {100 * lo:.1f}-{100 * hi:.1f} %]"
        print(f"{module:50s} {rate}{'; ' + rest if rest else ''}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
