"""Reference accuracy of the shipped cascade on the first frames of the embedded dataset.

Used by ``tests/victims/test_shipped_accuracy.py``; run as a script it (re)measures the references the
tests compare with and writes ``tests/fixtures/shipped_accuracy.json``::

    OMP_NUM_THREADS=1 python tests/helpers/accuracy_reference.py fast  # frames 0..35 (19 val), GT, 10 seeds (~1 min)
    OMP_NUM_THREADS=1 python tests/helpers/accuracy_reference.py slow  # frames 0..159 (85 val), both, 5 seeds (~10 min)

Frames 0..N-1 are generated with the embedded dataset's parameters (frame i and its split are pure
functions of (seed, i), so their val frames are val frames of the embedded dataset, never trained
on) and ``robustbench3d run`` scores ``fpointnet-v1-lite`` on their val split once per run seed
(the case's seeds; the seed draws the per-frustum resampling and object-point gather). The file keeps
every seed's AP, their mean and sample standard deviation; a test runs seed 0 and accepts
``|AP - mean| <= K_SIGMA · std`` (see :func:`tolerance`). Re-record only for an intended change
of the victim's results, and say so in the commit.
"""

from __future__ import annotations

import json
import statistics
import sys
from pathlib import Path
from typing import Any

from robustbench3d.cli import main as cli_main
from robustbench3d.datasets import EMBEDDED
from robustbench3d.kitti.splits import write_split
from robustbench3d.results import CellResult, read_summary
from robustbench3d.synth.frame import generate_frame
from robustbench3d.synth.writer import frame_complete, frame_id, in_val, write_frame

VICTIM = "fpointnet-v1-lite"
REFERENCE = Path(__file__).resolve().parents[1] / "fixtures" / "shipped_accuracy.json"
#: Per case: frames 0..N-1 considered (only their val frames, about half, are generated), proposal
#: sources, and the run seeds the spread is measured over.
CASES: dict[str, tuple[int, tuple[str, ...], tuple[int, ...]]] = {
    "fast": (36, ("gt",), tuple(range(10))),
    "slow": (160, ("detector", "gt"), tuple(range(5))),
}
#: Metrics compared: (metric, recall points, difficulty).
METRICS = (("3d", "R40", "moderate"), ("bev", "R40", "moderate"), ("3d", "R40", "hard"), ("bev", "R40", "hard"))
#: Allowed deviation from the mean, in standard deviations across seeds.
K_SIGMA = 3.0


def metric_key(metric: str, recall: str, difficulty: str) -> str:
    return f"{metric}/{recall}/{difficulty}"


def generate(data: Path, frames: int) -> None:
    """The val frames among frames 0..frames-1 of the embedded dataset (its seed and val fraction)
    in ``data`` (KITTI layout, ``ImageSets/val.txt``); the train frames are not generated."""
    val = [i for i in range(frames) if in_val(EMBEDDED.seed, i, EMBEDDED.val_fraction)]
    for i in val:
        if not frame_complete(data, i):
            write_frame(data, i, generate_frame(EMBEDDED.seed, i))
    write_split(data / "ImageSets" / "val.txt", [frame_id(i) for i in val])


def run_ap(data: Path, out: Path, proposals: tuple[str, ...], seed: int) -> dict[str, dict[str, float]]:
    """``robustbench3d run`` of the shipped cascade: {proposals: {metric key: AP %}}."""
    code = cli_main(["run", "--victims", VICTIM, "--attacks", "none", "--proposals", ",".join(proposals),
                     "--data", str(data), "--out", str(out), "--seed", str(seed), "--workers", "1", "--no-progress"])
    if code != 0:
        raise RuntimeError(f"robustbench3d run exited {code}")
    result: dict[str, dict[str, float]] = {}
    for cell in map(CellResult, read_summary(out / "summary.json")):
        result[cell.proposals] = {metric_key(*m): float(cell.ap("Car", *m)) for m in METRICS}
    return result


def tolerance(entry: dict[str, Any]) -> float:
    """Allowed |AP - mean| of one reference entry: K_SIGMA standard deviations across seeds."""
    return K_SIGMA * float(entry["std"])


def record(case: str, work: Path) -> dict[str, Any]:
    """Measure one case over its seeds (frames generated under ``work``)."""
    frames, proposals, seeds = CASES[case]
    data = work / "data"
    generate(data, frames)
    runs = [run_ap(data, work / f"run{seed}", proposals, seed) for seed in seeds]
    refs: dict[str, dict[str, Any]] = {}
    for source in proposals:
        refs[source] = {}
        for m in METRICS:
            key = metric_key(*m)
            values = [r[source][key] for r in runs]
            refs[source][key] = {"per_seed": values, "mean": statistics.fmean(values),
                                 "std": statistics.stdev(values)}
    return {"frames": frames, "val_frames": len((data / "ImageSets" / "val.txt").read_text().split()),
            "seeds": list(seeds), "proposals": refs}


def main(argv: list[str]) -> int:
    import tempfile

    from robustbench3d.victims.shipped import shipped

    cases = argv or list(CASES)
    doc = json.loads(REFERENCE.read_text(encoding="utf-8")) if REFERENCE.is_file() else {}
    weights = shipped(VICTIM)
    assert weights is not None
    doc.update({"victim": VICTIM, "weights_sha256": weights.sha256, "k_sigma": K_SIGMA})
    for case in cases:
        with tempfile.TemporaryDirectory() as tmp:
            doc[case] = {"command": f"OMP_NUM_THREADS=1 python tests/helpers/accuracy_reference.py {case}",
                         **record(case, Path(tmp))}
    REFERENCE.parent.mkdir(parents=True, exist_ok=True)
    REFERENCE.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
