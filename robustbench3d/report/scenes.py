"""Scene figures in the manner of the seed paper's Fig. 3: one frame clean (left) and attacked (right), each
as ``robustbench3d show`` draws it (:func:`robustbench3d.draw.render`: the camera image with projected 3D boxes
above a bird's-eye view of the scan) — ground truth in its class colours, the cell's detections in red —
and in the attacked bird's-eye view the object's LiDAR returns in yellow. The attacked frame is rebuilt
exactly as the cell attacked it (:func:`robustbench3d.attacks.apply.attacked_frame`: same attack, seed and placement);
the detections are the clean and attacked cells' KITTI result files ``RUN/cells/<cell>/data/<frame>.txt``,
drawn from the score threshold the attack success rate uses (the F1-optimal one on the clean cell).

Frames are chosen where the attack hurt most: the most ground-truth Cars matched by a clean detection
(BEV IoU >= 0.7 at that threshold) and by no attacked one; ties by more Cars, then by frame id.
Before drawing, the label files of the frames the cell evaluated (the first ``frames`` of its split) are
hashed as the runner hashed them and must give the cell's dataset sha256, and the attack rebuilt from its
name must describe itself as the cell recorded, or no figure is made (the reason is returned instead).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from robustbench3d.eval.rules import TARGET_CLASS
from robustbench3d.report.data import RunCell
from robustbench3d.results import CellResult

BEV_RANGE = 50.0


@dataclass(frozen=True)
class Scene:
    """A drawn scene (PNG) or the reason none could be drawn."""

    cell: RunCell
    frame: str | None
    png: bytes | None
    caption: str


def _result(path: Path, threshold: float) -> Any:
    from robustbench3d.kitti import read_labels
    from robustbench3d.kitti.labels import Labels

    if not path.exists():
        return Labels.empty(with_score=True)
    dets = read_labels(path, scored=True).of_types([TARGET_CLASS])
    return dets.select(dets.score >= threshold)


def _boxes(labels: Any) -> Any:
    import numpy as np

    return np.concatenate([labels.dimensions, labels.location, labels.rotation_y[:, None]], axis=1)


def _matched(gt: Any, dets: Any) -> Any:
    """(G,) bool: GT Car with a detection of BEV IoU >= 0.7."""
    import numpy as np

    from robustbench3d.eval.iou import bev_iou

    if len(gt) == 0 or len(dets) == 0:
        return np.zeros(len(gt), bool)
    return (bev_iou(_boxes(gt), _boxes(dets)) >= 0.7).any(axis=1)


class SceneSource:
    """The frames a section's cells evaluated, checked once against the cells' dataset sha256.

    The identity is the runner's own (:func:`robustbench3d.datasets.load_ground_truth`): the first
    ``dataset["frames"]`` ids of the split and their label files, so a ``--max-frames`` run of a larger,
    partly generated dataset is checked on exactly the frames it evaluated and needs no other file.
    ``problem`` says why no figure can be drawn (dataset absent, a label file missing or changed).
    """

    def __init__(self, dataset: Mapping[str, Any]):
        from robustbench3d.datasets import ResolvedDataset, load_ground_truth
        from robustbench3d.errors import RobustBenchError

        self.problem: str | None = None
        self.kitti = None
        self.gt: dict[str, Any] = {}
        self.frames: list[str] = []
        root = Path(dataset["root"])
        if not (root / "training").is_dir():
            self.problem = f"dataset {root} is not on this machine"
            return
        resolved = ResolvedDataset(root=root, split=dataset["split"], embedded=None, manifest=None)
        try:
            truth = load_ground_truth(resolved, int(dataset["frames"]))
        except RobustBenchError as exc:  # split file or an evaluated frame's label file missing or unreadable
            self.problem = f"dataset {root} split {dataset['split']} cannot be read as the run read it ({exc})"
            return
        if truth.sha256 != dataset["sha256"]:
            self.problem = (f"dataset {root} split {dataset['split']} has changed since the run (labels sha256 of "
                            f"the {len(truth.frame_ids)} evaluated frames)")
            return
        self.kitti = resolved.kitti()
        self.frames = truth.frame_ids
        self.gt = dict(zip(truth.frame_ids, truth.labels, strict=True))


def worst_frames(source: SceneSource, attacked_dir: Path, clean_dir: Path, threshold: float, count: int) -> list[str]:
    """The ``count`` frames with the most Cars found clean and lost attacked (see the module doc)."""
    scored = []
    for fid in source.frames:
        gt = source.gt[fid].of_types([TARGET_CLASS])
        if len(gt) == 0:
            continue
        clean = _matched(gt, _result(clean_dir / f"{fid}.txt", threshold))
        attacked = _matched(gt, _result(attacked_dir / f"{fid}.txt", threshold))
        scored.append((-int((clean & ~attacked).sum()), -len(gt), fid))
    return [fid for *_, fid in sorted(scored)[:count]]


def scene(source: SceneSource, rc: RunCell, frame: str | None = None) -> Scene:
    """The scene figure of attacked cell ``rc`` on ``frame`` (default: its worst frame)."""
    import numpy as np

    from robustbench3d.attacks import resolve_attack
    from robustbench3d.attacks.apply import attacked_frame
    from robustbench3d.draw import render
    from robustbench3d.report.figures import _pyplot, png_bytes

    cell = CellResult(rc.cell)
    effect = cell.effect or {}
    if source.kitti is None:
        return Scene(rc, frame, None, f"{rc.name}: no scene figure: {source.problem}")
    clean_dir = rc.run / "cells" / (cell.clean_cell or "") / "data"
    att_dir = rc.run / "cells" / rc.name / "data"
    if not effect or not clean_dir.is_dir() or not att_dir.is_dir():
        return Scene(rc, frame, None, f"{rc.name}: no scene figure: the result files of the cell or of its clean "
                                      f"cell are not in {rc.run / 'cells'}")
    try:
        _, attack = resolve_attack(cell.attack)
        described = json.loads(json.dumps(attack.describe()))
    except Exception as exc:  # an object file of another machine, a plugin that is not installed
        return Scene(rc, frame, None, f"{rc.name}: no scene figure: attack {cell.attack!r} cannot be rebuilt "
                                      f"here ({exc})")
    if described != cell.config["attack"]["object"]:
        return Scene(rc, frame, None, f"{rc.name}: no scene figure: attack {cell.attack!r} here is not the "
                                      "object the cell evaluated (its description differs)")
    threshold = float(effect["success"]["score_threshold"])  # the attack success rate's record
    if frame is None:
        found = worst_frames(source, att_dir, clean_dir, threshold, 1)
        if not found:
            return Scene(rc, None, None, f"{rc.name}: no scene figure: no frame with Cars")
        frame = found[0]
    clean = source.kitti.frame(frame)
    attacked, added = attacked_frame(source.kitti, clean, cell.attack, int(cell.config["seed"]))
    clean_dets = _result(clean_dir / f"{frame}.txt", threshold)
    att_dets = _result(att_dir / f"{frame}.txt", threshold)
    gt = source.gt[frame].of_types([TARGET_CLASS])
    lost = int((_matched(gt, clean_dets) & ~_matched(gt, att_dets)).sum())
    panels = [render(clean, clean_dets, BEV_RANGE), render(attacked, att_dets, BEV_RANGE, highlight=added)]

    plt = _pyplot()
    from matplotlib.patches import Patch

    fig, axes = plt.subplots(1, 2, figsize=(16, 16 / 2 * panels[0].shape[0] / panels[0].shape[1] + 0.9))
    titles = [f"clean ({cell.clean_cell}): {len(clean_dets)} detections",
              f"attacked ({rc.name}): {len(att_dets)} detections, {len(added)} object LiDAR returns"]
    for ax, pic, title in zip(axes, panels, titles, strict=True):
        ax.imshow(np.asarray(pic), interpolation="antialiased")
        ax.set_title(title, fontsize=10)
        ax.set_axis_off()
    fig.legend(handles=[Patch(color="#00ff00", label="ground-truth Car"),
                        Patch(color="#ff7800", label="other ground truth (Van, Truck, …; show's colours)"),
                        Patch(color="#ff0000", label=f"detection (score ≥ {threshold:.3f})"),
                        Patch(color="#ffff00", label="attack object's LiDAR returns (BEV)")],
               loc="lower center", ncols=4, fontsize=9, frameon=False)
    fig.subplots_adjust(left=0.01, right=0.99, top=0.95, bottom=0.05, wspace=0.02)
    png = png_bytes(fig, dpi=110)
    caption = (f"{rc.name}, frame {frame}: {len(gt)} ground-truth Cars, {lost} found clean and lost under the "
               f"attack (BEV IoU ≥ 0.7, score ≥ {threshold:.3f}); bird's-eye view {BEV_RANGE:.0f} m ahead")
    return Scene(rc, frame, png, caption)
