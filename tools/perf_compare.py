"""Performance regression check: run the ``bench`` suite (benchmarks/) and compare it with the stored baseline.

Every benchmark's CPU time is divided by that of a reference kernel timed in the same run: the kernel
(``benchmarks/conftest.py``) is timed right before and right after every benchmark (stored in the report
as ``extra_info.reference_s``) and the run's reference is the minimum over all of them, so the stored
values compare across machines of different speed, and a stretch of load during one timing of the
kernel (it moved by 20 % between runs when timed once) does not shift every value. The statistic is the minimum
over the rounds: other processes only ever add CPU time (cache and TLB pollution, context switches), so
the minimum is the most repeatable estimate of the code's own cost on a shared machine; medians of the
same runs moved by up to 30-50 % with the load (see the README).

A benchmark fails when its normalised value is more than ``--threshold`` (25 %) above the baseline's in
the full run AND again when only the failing benchmarks are rerun, in up to ``RERUN_PROCESSES`` fresh
pytest processes, each benchmark keeping its best value over them (a process's minimum moved by 20-30 %
between fresh processes on an idle machine: memory layout and thread start-up differ per process);
a slowdown that does not repeat is reported as noise. A benchmark of the baseline that did not run
(skipped, removed, renamed) also fails: re-record the baseline if that was intended.

    python tools/perf_compare.py                    # run the suite, compare, exit 1 on a repeated slowdown
    python tools/perf_compare.py --write-baseline   # run the suite, store benchmarks/baseline.json

On another CPU model than the baseline's the comparison is printed but not enforced (``--any-cpu`` enforces it):
the reference kernel evens out speed, not microarchitecture (numpy, oneDNN and Embree pick other SIMD kernels).

Exit status: 0 pass, 1 slowdown, missing benchmark or failing suite, 2 unusable baseline or arguments.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

REPO = Path(__file__).resolve().parents[1]
SUITE = "benchmarks"
BASELINE = REPO / SUITE / "baseline.json"
REFERENCE = "benchmarks/conftest.py::reference_kernel, min over 25 rounds before and after every benchmark"
TIMER = "time.process_time"
STATISTIC = "min"
#: Multiplies the fixed round counts of the heavy benchmarks (benchmarks/conftest.py's ``rounds`` fixture).
ROUNDS_SCALE_ENV = "ROBUSTBENCH3D_BENCH_ROUNDS_SCALE"
THRESHOLD = 0.25
#: Fresh pytest processes the suspects are rerun in at most (stopping once every one is within the threshold).
RERUN_PROCESSES = 3
FORMAT = 1


class BaselineError(Exception):
    """An unusable baseline or benchmark report (message names the file and field)."""


class Timing(NamedTuple):
    """One benchmark of a report: its pytest node id, its time and its reference kernel's (seconds)."""

    node_id: str
    seconds: float
    reference_s: float


def timings(report: dict[str, Any], source: str = "report", statistic: str = STATISTIC) -> dict[str, Timing]:
    """``name -> Timing`` of a pytest-benchmark JSON report (``statistic`` over the rounds)."""
    out: dict[str, Timing] = {}
    try:
        for b in report["benchmarks"]:
            name, seconds = b["name"], float(b["stats"][statistic])
            reference = b.get("extra_info", {}).get("reference_s")
            if not isinstance(reference, (int, float)) or isinstance(reference, bool) or not reference > 0:
                raise BaselineError(f"{source}: benchmarks.{name}.extra_info.reference_s: {reference!r} is not a "
                                    "positive time (is benchmarks/conftest.py's reference fixture in place?)")
            timer = b.get("options", {}).get("timer", "")
            if timer != TIMER.rsplit(".", 1)[-1]:
                raise BaselineError(f"{source}: benchmarks: {name!r} was timed with {timer!r}, not {TIMER}")
            if name in out:
                raise BaselineError(f"{source}: benchmarks: two benchmarks named {name!r}")
            out[name] = Timing(b["fullname"], seconds, float(reference))
    except (KeyError, TypeError, ValueError) as exc:
        raise BaselineError(f"{source}: benchmarks: not a pytest-benchmark report "
                            f"({type(exc).__name__}: {exc})") from None
    return out


def run_reference(timed: dict[str, Timing]) -> float:
    """The run's reference kernel time: the minimum over its timings beside every benchmark."""
    return min(t.reference_s for t in timed.values())


def normalise(timed: dict[str, Timing]) -> dict[str, float]:
    """Each benchmark's time divided by the run's reference kernel time."""
    if not timed:
        raise BaselineError("the benchmark report holds no benchmark")
    ref = run_reference(timed)
    return {name: t.seconds / ref for name, t in timed.items()}


def best_of(runs: list[dict[str, float]]) -> dict[str, float]:
    """Each benchmark's smallest normalised value over several runs (a benchmark missing from a run is
    taken from the others)."""
    best: dict[str, float] = {}
    for run in runs:
        for name, value in run.items():
            best[name] = min(value, best.get(name, value))
    return best


def slower(ratios: dict[str, float], baseline: dict[str, float], threshold: float = THRESHOLD) -> dict[str, float]:
    """``name -> relative change`` of the benchmarks more than ``threshold`` above their baseline value."""
    return {n: ratios[n] / baseline[n] - 1.0 for n in ratios
            if n in baseline and ratios[n] / baseline[n] - 1.0 > threshold}


@dataclass
class Verdict:
    """Outcome of one comparison: ``first``/``second`` hold the relative changes of the first and of the
    rerun (only the benchmarks rerun), ``failed`` the slowdowns seen in both."""

    first: dict[str, float]
    second: dict[str, float] = field(default_factory=dict)
    failed: list[str] = field(default_factory=list)
    noise: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    new: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.failed and not self.missing


def decide(baseline: dict[str, float], first: dict[str, float], second: dict[str, float] | None,
           threshold: float = THRESHOLD) -> Verdict:
    """Compare normalised values with the baseline: a slowdown over ``threshold`` in ``first`` fails only if
    ``second`` (the rerun of those benchmarks, or None when nothing was rerun) shows it again."""
    change = {n: first[n] / baseline[n] - 1.0 for n in first if n in baseline}
    verdict = Verdict(first=change, missing=sorted(set(baseline) - set(first)), new=sorted(set(first) - set(baseline)))
    suspects = slower(first, baseline, threshold)
    if not suspects:
        return verdict
    second = second or {}
    verdict.second = {n: second[n] / baseline[n] - 1.0 for n in suspects if n in second}
    for n in sorted(suspects):
        if n not in second or second[n] / baseline[n] - 1.0 > threshold:  # not rerun: cannot clear it
            verdict.failed.append(n)
        else:
            verdict.noise.append(n)
    return verdict


def read_baseline(path: Path) -> dict[str, Any]:
    """The stored baseline, checked: ``format``, ``timer``, ``statistic``, ``reference`` and positive ``ratios``."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise BaselineError(f"{path}: no baseline; record one with --write-baseline") from None
    except json.JSONDecodeError as exc:
        raise BaselineError(f"{path}: not JSON ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise BaselineError(f"{path}: format: expected {FORMAT}")
    for key, want in (("timer", TIMER), ("statistic", STATISTIC), ("reference", REFERENCE)):
        if data.get(key) != want:
            raise BaselineError(f"{path}: {key}: {data.get(key)!r}, this comparer uses {want!r} (re-record it)")
    ratios = data.get("ratios")
    if not isinstance(ratios, dict) or not ratios:
        raise BaselineError(f"{path}: ratios: missing or empty")
    for name, value in ratios.items():
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not value > 0:
            raise BaselineError(f"{path}: ratios.{name}: {value!r} is not a positive number")
    return data


def baseline_record(report: dict[str, Any], source: str = "report") -> dict[str, Any]:
    """The baseline JSON of a full run: normalised ratios, plus the raw times (and medians) and the machine."""
    timed = timings(report, source)
    medians = {n: t.seconds for n, t in timings(report, source, "median").items()}
    cpu = report.get("machine_info", {}).get("cpu", {})
    return {
        "format": FORMAT,
        "timer": TIMER,
        "statistic": STATISTIC,
        "reference": REFERENCE,
        "threshold": THRESHOLD,
        "recorded": report.get("datetime") or datetime.datetime.now(datetime.timezone.utc).isoformat(),
        "machine": {"cpu": cpu.get("brand_raw"), "cores": cpu.get("count"),
                    "python": report.get("machine_info", {}).get("python_version")},
        "commit": report.get("commit_info", {}).get("id"),
        "seconds": {n: timed[n].seconds for n in sorted(timed)},
        "medians_s": dict(sorted(medians.items())),
        "reference_s": run_reference(timed),
        "reference_s_beside": {n: timed[n].reference_s for n in sorted(timed)},
        "ratios": dict(sorted(normalise(timed).items())),
    }


def run_suite(out: Path, node_ids: list[str] | None = None) -> dict[str, Any]:
    """Run the ``bench`` suite (or only ``node_ids``, with more rounds) on one thread; the JSON report."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    targets = [SUITE] if node_ids is None else sorted(node_ids)
    cmd = [sys.executable, "-m", "pytest", *targets, "-m", "bench", "-q", "-p", "no:cacheprovider",
           f"--benchmark-timer={TIMER}", f"--benchmark-json={out}"]
    if node_ids is not None:  # the second try measures more carefully: three times the rounds
        cmd += ["--benchmark-max-time=3", "--benchmark-min-rounds=15"]
        env[ROUNDS_SCALE_ENV] = "3"
    print("+", " ".join(cmd[2:]), flush=True)
    rc = subprocess.run(cmd, cwd=REPO, env=env).returncode
    if rc != 0:
        raise SystemExit(f"perf_compare: the benchmark suite failed (pytest exit {rc})")
    return json.loads(out.read_text(encoding="utf-8"))


def report_table(baseline: dict[str, float], first: dict[str, float], verdict: Verdict, threshold: float) -> str:
    """Plain-text table: baseline ratio, this run's, change, the rerun's change and the verdict."""
    lines = [f"{'benchmark':42} {'baseline':>9} {'now':>9} {'change':>8} {'rerun':>8}  verdict"]
    for n in sorted(set(baseline) | set(first)):
        b, now = baseline.get(n), first.get(n)
        change = verdict.first.get(n)
        rerun = verdict.second.get(n)
        status = ("SLOWER (repeated)" if n in verdict.failed else "noise (not repeated)" if n in verdict.noise
                  else "MISSING" if n in verdict.missing else "new (not in baseline)" if n in verdict.new
                  else "faster" if change is not None and change < -threshold else "ok")
        lines.append(f"{n:42} {'' if b is None else f'{b:9.3f}':>9} {'' if now is None else f'{now:9.3f}':>9} "
                     f"{'' if change is None else f'{change:+8.1%}':>8} {'' if rerun is None else f'{rerun:+8.1%}':>8}"
                     f"  {status}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline", type=Path, default=BASELINE, help="baseline JSON (default: %(default)s)")
    parser.add_argument("--write-baseline", action="store_true", help="run the suite and store it as the baseline")
    parser.add_argument("--threshold", type=float, default=THRESHOLD, help="allowed slowdown (default: 0.25)")
    parser.add_argument("--out", type=Path, help="keep the pytest-benchmark JSON reports in this directory")
    parser.add_argument("--any-cpu", action="store_true",
                        help="enforce the threshold on another CPU model than the baseline's (default: report only)")
    args = parser.parse_args(argv)
    if not args.threshold > 0:
        parser.error("--threshold must be positive")
    try:
        base = None if args.write_baseline else read_baseline(args.baseline)
        with tempfile.TemporaryDirectory(prefix="rb3d-perf-") as tmp:
            out = args.out or Path(tmp)
            out.mkdir(parents=True, exist_ok=True)
            report = run_suite(out / "run1.json")
            if args.write_baseline:
                record = baseline_record(report, str(out / "run1.json"))
                args.baseline.write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
                print(f"baseline written to {args.baseline}: {len(record['ratios'])} benchmarks, reference kernel "
                      f"{record['reference_s'] * 1e3:.2f} ms")
                return 0
            assert base is not None
            timed = timings(report, str(out / "run1.json"))
            first = normalise(timed)
            suspects = slower(first, base["ratios"], args.threshold)
            second = None
            if suspects:
                print(f"over {args.threshold:.0%} slower, rerunning: {', '.join(sorted(suspects))}", flush=True)
                reruns: list[dict[str, float]] = []
                for k in range(RERUN_PROCESSES):
                    path = out / f"run{k + 2}.json"
                    reruns.append(normalise(timings(run_suite(path, [timed[n].node_id for n in suspects]),
                                                    str(path))))
                    second = best_of(reruns)
                    if all(n in second and second[n] / base["ratios"][n] - 1.0 <= args.threshold for n in suspects):
                        break
    except BaselineError as exc:
        print(f"perf_compare: {exc}", file=sys.stderr)
        return 2
    verdict = decide(base["ratios"], first, second, args.threshold)
    print(report_table(base["ratios"], first, verdict, args.threshold))
    here = report.get("machine_info", {}).get("cpu", {}).get("brand_raw")
    there = (base.get("machine") or {}).get("cpu")
    if here != there and not args.any_cpu and verdict.failed and not verdict.missing:
        # the reference kernel evens out speed, not microarchitecture: numpy, oneDNN and Embree pick other SIMD
        # kernels on another CPU model, which moves the ratios by more than the threshold
        print(f"perf_compare: NOT ENFORCED: the baseline was recorded on {there!r}, this is {here!r} "
              f"(record one here with --write-baseline, or pass --any-cpu to enforce)")
        return 0
    if verdict.failed:
        print(f"FAIL: over {args.threshold:.0%} slower than the baseline twice: {', '.join(verdict.failed)}")
    if verdict.missing:
        print(f"FAIL: in the baseline but not measured: {', '.join(verdict.missing)} "
              "(re-record with --write-baseline if intended)")
    if verdict.ok:
        print(f"perf_compare: OK ({len(verdict.first)} benchmarks within {args.threshold:.0%} of the baseline"
              + (f"; {len(verdict.noise)} slowdown(s) did not repeat" if verdict.noise else "") + ")")
    return 0 if verdict.ok else 1


if __name__ == "__main__":
    sys.exit(main())
