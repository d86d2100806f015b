"""The speed and memory benchmarks ``robustbench3d bench`` runs (:data:`BENCHMARKS`) and their table.

Targets are checked here, in benchmarks, never as wall-clock asserts in unit tests. Each
benchmark is a function ``run(quick: bool) -> list[dict]`` returning table rows; rows may carry a
``target`` and a ``met`` column. Benchmarks are registered lazily by "module:function".
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass

from robustbench3d.texttable import format_table

BENCHMARKS: dict[str, str] = {
    "cli": "robustbench3d.bench:cli_startup",
    "eval": "robustbench3d.eval.bench:run",
    "synth": "robustbench3d.synth.bench:run",
    "onnx": "robustbench3d.victims.onnx.bench:run",
    "victim": "robustbench3d.victims.bench:run",
    "fpn-train": "robustbench3d.victims.fpointnet.bench_train:run",
    "objectness": "robustbench3d.victims.yolo.bench_objectness:run",
    "attack": "robustbench3d.attacks.bench:run",
    "lidar": "robustbench3d.sensors.bench:run",
    "bootstrap": "robustbench3d.eval.bench_bootstrap:run",
}


@dataclass(frozen=True)
class Measured:
    """Result of :func:`run_timed_subprocess`: wall seconds, peak RSS (MB) and CPU seconds (user + system, the
    child and its own children) of the child."""

    seconds: float
    peak_rss_mb: float
    stdout: str
    cpu_seconds: float = 0.0


def run_timed_subprocess(argv: list[str], env: dict[str, str] | None = None) -> Measured:
    """Run a command to completion; measure its wall time (start-up included) and peak RSS.

    Peak RSS is read from ``getrusage(RUSAGE_CHILDREN)``, which holds the maximum over all waited
    children, so the command is run through a fresh ``python -c`` wrapper that reports its own child.
    """
    wrapper = (
        "import json,resource,subprocess,sys,time;"
        "t=time.perf_counter();p=subprocess.run(sys.argv[1:],capture_output=True,text=True);"
        "dt=time.perf_counter()-t;"
        "u=resource.getrusage(resource.RUSAGE_CHILDREN);r=u.ru_maxrss/1024;"
        "print(json.dumps({'s':dt,'rss':r,'cpu':u.ru_utime+u.ru_stime,'rc':p.returncode,'out':p.stdout,"
        "'err':p.stderr}))"
    )
    proc = subprocess.run([sys.executable, "-c", wrapper, *argv], capture_output=True, text=True,
                          env={**os.environ, **(env or {})}, check=True)
    info = json.loads(proc.stdout)
    if info["rc"] != 0:
        raise RuntimeError(f"benchmarked command failed ({info['rc']}): {' '.join(argv)}\n{info['err']}")
    return Measured(info["s"], info["rss"], info["out"], info["cpu"])


def dict_table(rows: list[dict]) -> str:
    """Plain-text table of dict rows (columns in first-seen order; floats to 4 significant digits)."""
    cols: list[str] = []
    for r in rows:
        cols.extend(k for k in r if k not in cols)

    def fmt(v: object) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        if isinstance(v, bool):
            return "yes" if v else "NO"
        return "" if v is None else str(v)

    return format_table(cols, [[fmt(r.get(c)) for c in cols] for r in rows])


def cli_startup(quick: bool) -> list[dict]:
    """Wall time of ``robustbench3d --help`` in a fresh interpreter (median of 5; 3 when quick)."""
    import statistics

    runs = [run_timed_subprocess([sys.executable, "-m", "robustbench3d", "--help"]) for _ in range(3 if quick else 5)]
    median = statistics.median(r.seconds for r in runs)
    return [{"case": "robustbench3d --help", "seconds_median": median, "peak_rss_mb": max(r.peak_rss_mb for r in runs),
             "target": "< 0.5 s", "met": median < 0.5}]
