"""The paired 95 % bootstrap interval of AP(control cell) - AP(attacked cell) over the same frames of one run.

    python research/paired_vs_control.py RUN_DIR CONTROL_CELL ATTACKED_CELL

(cell directory names, e.g. ``fpointnet-v1-lite+benign-sphere+gt-object``). Prints Car BEV R40 easy / moderate /
hard of both cells and the interval of their paired difference (percentage points; 1000 resamples, seed 0): an
interval excluding 0 says the attacked object costs more than the control on these frames.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from robustbench3d.datasets import load_ground_truth, resolve_dataset
from robustbench3d.eval.bootstrap import FrameBootstrap, drop_intervals
from robustbench3d.kitti.labels import read_labels


def main(argv: list[str]) -> int:
    run, control, attacked = Path(argv[0]), argv[1], argv[2]
    cell = json.loads((run / "cells" / control / "cell.json").read_text())
    frames = cell["dataset"]["frames"]
    dataset = resolve_dataset(cell["dataset"]["root"], cell["dataset"]["split"], lazy=True, max_frames=frames)
    gt = load_ground_truth(dataset, frames)

    def prep(name: str) -> FrameBootstrap:
        dets = [read_labels(run / "cells" / name / "data" / f"{fid}.txt", scored=True) for fid in gt.frame_ids]
        return FrameBootstrap(gt.labels, dets)

    a, b = prep(control), prep(attacked)
    table = drop_intervals(a, b)
    for name, p in ((control, a), (attacked, b)):
        ap = p.full["Car"]["bev"]["R40"]
        print(f"{name}: BEV R40 {ap['easy']:.2f} / {ap['moderate']:.2f} / {ap['hard']:.2f}")
    ci = table["Car"]["bev"]["R40"]
    print(f"paired AP({control}) - AP({attacked}), 95 %: " + ", ".join(f"{d} [{ci[d][0]:.2f}, {ci[d][1]:.2f}]"
                                                                       for d in ("easy", "moderate", "hard")))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
