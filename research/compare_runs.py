"""Compare two ``robustbench3d run`` output directories (docs/executors.md).

    python research/compare_runs.py RUN_A RUN_B

Prints whether the result files (``cells/*/data/*``) are identical byte for byte, whether the
``summary.json`` cells are equal except the timing and host fields of their provenance, and whether
``results.csv`` is identical; exits 0 when all three hold, 1 otherwise (naming what differs).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

#: Provenance fields that may differ between executors and machines (timings, hosts, processes).
TIMING_FIELDS = ("started", "finished", "seconds", "cpu_seconds", "peak_rss_mb", "executor")


def comparable_summary(run: Path) -> list[dict[str, Any]]:
    """The run's summary cells without timing/host fields, its output path and whether torch was loaded."""
    cells = json.loads((run / "summary.json").read_text(encoding="utf-8"))
    for cell in cells:
        prov = cell["provenance"]
        for key in TIMING_FIELDS:
            prov.pop(key, None)
        prov["run"].pop("out", None)
        prov["determinism"].pop("torch_loaded", None)
    return cells


def result_files(run: Path) -> dict[str, bytes]:
    return {str(p.relative_to(run)): p.read_bytes() for p in sorted(run.glob("cells/*/data/*"))}


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    a, b = (Path(x) for x in argv)
    fa, fb = result_files(a), result_files(b)
    sa, sb = comparable_summary(a), comparable_summary(b)
    csv = (a / "results.csv").read_bytes() == (b / "results.csv").read_bytes()
    print(f"result files: {len(fa)} vs {len(fb)}, identical: {fa == fb}")
    print(f"summary cells: {len(sa)} vs {len(sb)}, equal except timing/host fields: {sa == sb}")
    print(f"results.csv identical: {csv}")
    for name in sorted(set(fa) ^ set(fb)):
        print(f"  only in one run: {name}")
    for name in sorted(n for n in set(fa) & set(fb) if fa[n] != fb[n]):
        print(f"  differs: {name}")
    for x, y in zip(sa, sb, strict=False):
        for key in sorted(set(x) | set(y)):
            if x.get(key) != y.get(key):
                print(f"  cell {x['victim']}/{x['attack']}/{x['proposals']}: '{key}' differs")
    return 0 if fa == fb and sa == sb and csv else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
