"""Are two run directories the same results? Exit 0 when every file is byte-identical, the JSON files
(``summary.json``, each ``cell.json``) after setting aside what describes the computation rather than its
results: wall and CPU time, peak memory, start and end times, worker names, the output directory and the
code's git state (``provenance.{seconds,cpu_seconds,peak_rss_mb,started,finished,executor.workers,run.out,
git}``). Used to show that a speed-up changed no result:

    python tools/same_results.py runs/before runs/after
    python tools/same_results.py --across-executors RUN_LOCAL RUN_RAY

``--across-executors`` also sets aside the executor record and whether torch was loaded in the parent
(``provenance.executor``, ``provenance.determinism.torch_loaded``): the same results computed by local worker
processes and by a Ray cluster (docs/executors.md).

Prints each difference (file, and for JSON the key path) and exits 1 if there is one, 2 on bad arguments.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

#: Provenance keys that describe how a result was computed, not what it is.
RUNTIME_KEYS = ("seconds", "cpu_seconds", "peak_rss_mb", "started", "finished", "git")
RUNTIME_PATHS = (("executor", "workers"), ("run", "out"))
#: What else differs between executors (``--across-executors``).
EXECUTOR_KEYS = ("executor",)
EXECUTOR_PATHS = (("determinism", "torch_loaded"),)


def _results_only(data: Any, across_executors: bool = False) -> Any:
    """``data`` with the runtime keys removed from every ``provenance`` mapping in it."""
    if isinstance(data, list):
        return [_results_only(v, across_executors) for v in data]
    if not isinstance(data, dict):
        return data
    out = {k: _results_only(v, across_executors) for k, v in data.items()}
    prov = out.get("provenance")
    if isinstance(prov, dict):
        keys = RUNTIME_KEYS + (EXECUTOR_KEYS if across_executors else ())
        paths = RUNTIME_PATHS + (EXECUTOR_PATHS if across_executors else ())
        prov = {k: v for k, v in prov.items() if k not in keys}
        for outer, inner in paths:
            if isinstance(prov.get(outer), dict):
                prov[outer] = {k: v for k, v in prov[outer].items() if k != inner}
        out["provenance"] = prov
    return out


def _json_differences(a: Any, b: Any, where: str) -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for k in sorted(set(a) | set(b), key=str)
                for d in (_json_differences(a.get(k), b.get(k), f"{where}/{k}") if k in a and k in b
                          else [f"{where}/{k}: only in {'the first' if k in a else 'the second'}"])]
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (u, v) in enumerate(zip(a, b, strict=True)) for d in _json_differences(u, v, f"{where}[{i}]")]
    return [] if a == b and type(a) is type(b) else [f"{where}: {str(a)[:60]} != {str(b)[:60]}"]


def differences(first: Path, second: Path, across_executors: bool = False) -> list[str]:
    """Every difference between the run directories ``first`` and ``second`` (empty: the same results)."""
    files_a = {p.relative_to(first) for p in first.rglob("*") if p.is_file()}
    files_b = {p.relative_to(second) for p in second.rglob("*") if p.is_file()}
    out = [f"{p}: only in {first if p in files_a else second}" for p in sorted(files_a ^ files_b)]
    for rel in sorted(files_a & files_b):
        a, b = (first / rel).read_bytes(), (second / rel).read_bytes()
        if a == b:
            continue
        if rel.suffix == ".json":
            out += [f"{rel}{d}" for d in _json_differences(_results_only(json.loads(a), across_executors),
                                                            _results_only(json.loads(b), across_executors), "")]
        else:
            out.append(f"{rel}: bytes differ")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("first", type=Path)
    parser.add_argument("second", type=Path)
    parser.add_argument("--across-executors", action="store_true",
                        help="also set aside the executor record and provenance.determinism.torch_loaded")
    args = parser.parse_args(argv)
    for d in (args.first, args.second):
        if not d.is_dir():
            parser.error(f"{d}: not a directory")
    found = differences(args.first, args.second, args.across_executors)
    for line in found:
        print(line)
    print(f"{'different' if found else 'the same results'}: {args.first} vs {args.second}")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
