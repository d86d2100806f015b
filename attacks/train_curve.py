"""The held-out curve of ``attack train``: the loss, relative drop and attack success rate of the object on
cars it never trains on, every ``eval_every`` steps, the best state kept and the plateau stop.

**Held-out frames.** The last ``held_out`` frames of the training split (after ``--max-frames``, in split
order): ``eval_frames`` of them, but at most a fifth of the split (:meth:`TrainConfig.held_out
<robustbench3d.attacks.train_config.TrainConfig.held_out>`; none with ``eval_every`` 0 or a split under five
frames). They are cut off before the trainer is built (:func:`split_held_out`), so the batch sampler never
sees them; the val split, which the benchmark scores, is never used.

**An evaluation** at step ``s`` (after ``s`` optimisation steps; at 0, every ``eval_every`` steps and at the
last step) records one row (:data:`CSV_COLUMNS`):

* ``train_loss``: the mean total training loss of the steps since the previous evaluation (empty at step 0);
* ``heldout_loss`` and its terms: the training loss of the current object on every target car of the held-out
  frames, no gradient, EOT draws fixed per frame
  (:meth:`~robustbench3d.attacks.train.UniversalTrainer.heldout_losses`);
* ``clean_ap``, ``attacked_ap``, ``relative_drop``, ``asr``: the victim's ``detect`` on the held-out frames
  clean (computed once per run) and attacked exactly as a benchmark cell attacks them (the roof-object attack
  with the current object and its default settings, the frame's target cars, ``attack_rng(seed, frame)``;
  detections rounded to result-file precision), with the proposals of :func:`eval_proposals`; Car BEV AP
  R40 moderate (percent) of the evaluator, the relative drop (a fraction, empty where the clean AP is 0) and
  the attack success rate (empty without a Car matched clean) as a benchmark run's attack effect defines
  them (:func:`robustbench3d.metrics.drop_tables`, :func:`robustbench3d.metrics.success_rate`);
* ``best``: 1 where the row's held-out loss is below every earlier row's (the best state so far), else 0.

**The best state** is the one of lowest held-out loss (:data:`CRITERION`): the loss is what the optimiser
lowers, a mean over every held-out car and deterministic, so it moves smoothly from one evaluation to the
next, while an AP drop on a few hundred held-out cars moves in steps of whole cars and picking its maximum
would mostly pick noise. The object file is the best state; the checkpoint keeps the last one (``--resume``).

**The plateau stop** (:func:`plateau`): at an evaluation at step ``s``, when the best held-out loss up to
``s`` is less than ``plateau_tol`` (relative) below the best up to step ``s - plateau_window``, training
stops and says so. The rows of the regular evaluations (steps ``0, K, 2K, ...``) are kept in the checkpoint;
the row of a last step that is not a multiple of ``K`` is not (a run resumed with more steps does not have
it, as an uninterrupted one would not), so ``--resume`` gives the bytes of an uninterrupted run.

**Files** next to ``OBJ.ply``: ``OBJ.curve.csv`` (one row per evaluation, header :data:`CSV_COLUMNS`, floats
in their shortest exact form, empty cells for values that do not apply) and ``OBJ.curve.png`` (matplotlib,
Agg: the losses, then the relative drop and ASR, against the step, the best step marked), both written
atomically whenever a checkpoint is, so they always hold a prefix of the rows the checkpoint holds.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from robustbench3d.attacks.train_config import TrainConfig
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.kitti.labels import Labels
from robustbench3d.metrics import HEADLINE

CSV_COLUMNS: tuple[str, ...] = ("step", "train_loss", "heldout_loss", "heldout_lidar", "heldout_image",
                                "heldout_laplacian", "clean_ap", "attacked_ap", "relative_drop", "asr", "best")
CRITERION = "lowest held-out loss"
#: The AP of the curve (class, metric, recall sampling, difficulty): the headline AP every summary reads.
AP_OF = HEADLINE


def curve_paths(out: str | Path) -> tuple[Path, Path]:
    """(``NAME.curve.csv``, ``NAME.curve.png``) beside object file ``out``."""
    out = Path(out)
    return out.with_name(out.stem + ".curve.csv"), out.with_name(out.stem + ".curve.png")


def split_held_out(frame_ids: list[str], labels: list[Labels], held_out: int
                   ) -> tuple[list[str], list[Labels], list[str], list[Labels]]:
    """(training frame ids, their labels, held-out frame ids, their labels): the last ``held_out`` frames are
    held out."""
    cut = len(frame_ids) - held_out
    return frame_ids[:cut], labels[:cut], frame_ids[cut:], labels[cut:]


def eval_proposals(config: TrainConfig, victim: Any = None) -> str:
    """The proposal source the curve scores with: the victim's own 2D detector when the mode has an image
    term (the texture works through that detector; with ground-truth boxes it could not show), else the 2D
    boxes the LiDAR loss trained on (``lidar_boxes``); ``"detector"`` for a ``victim`` without frustum oracles
    (it finds its own objects, :func:`~robustbench3d.victims.base.has_frustum_oracles`)."""
    from robustbench3d.victims.base import has_frustum_oracles

    if victim is not None and not has_frustum_oracles(victim):
        return "detector"
    return "detector" if config.kind.image else config.lidar_boxes


class HeldOut:
    """The held-out frames of a run and the victim's detections on them (clean ones computed once).

    Args:
        victim: the white-box victim; kitti: the dataset; frame_ids, labels: the held-out frames and their
        ground truth; source: proposal source (:func:`eval_proposals`); seed: the attack generators' seed
        (``attack_rng(seed, frame)``, as a benchmark run with ``--seed seed``).
    """

    def __init__(self, victim: Any, kitti: KittiDataset, frame_ids: list[str], labels: list[Labels], source: str,
                 seed: int) -> None:
        from robustbench3d.attacks.base import target_cars

        self.victim, self.kitti, self.frame_ids, self.labels = victim, kitti, frame_ids, labels
        self.source, self.seed = source, seed
        self.cars = sum(len(target_cars(lab)) for lab in labels)
        self._clean: tuple[list[Labels], dict[str, Any]] | None = None

    def describe(self) -> dict[str, Any]:
        """The sidecar's record of the held-out frames."""
        return {"rule": "the last frames of the training split, never drawn for training",
                "frames": len(self.frame_ids), "first_frame": self.frame_ids[0], "last_frame": self.frame_ids[-1],
                "cars": self.cars, "proposals": self.source, "seed": self.seed}

    def _detect(self, frame: Any, gt: Labels, record: Any) -> Labels:
        """The victim's detections of one frame as a benchmark cell scores them (result-file precision)."""
        from robustbench3d.kitti.labels import RESULT_PRECISION, parse_labels
        from robustbench3d.victims.base import victim_inputs

        # a frustum protocol gets the record of the object's placement
        bare, given = victim_inputs([frame], [gt], self.source, objects=None if record is None else [record])
        det = self.victim.detect(bare, given)[0]
        return parse_labels(det.to_text(RESULT_PRECISION), f"{frame.frame_id}.txt", scored=True)

    def _recorded(self) -> bool:
        return self.source not in ("detector", "gt")

    def clean(self) -> tuple[list[Labels], dict[str, Any]]:
        """Clean detections of every held-out frame and their evaluation (computed on the first call)."""
        if self._clean is None:
            from robustbench3d.attacks.base import target_cars
            from robustbench3d.eval.kitti_eval import evaluate

            dets = []
            for fid, gt in zip(self.frame_ids, self.labels, strict=True):
                frame = self.kitti.lazy_frame(fid, gt)
                record = None
                if self._recorded():
                    from robustbench3d.attacks.record import nominal_record

                    record = nominal_record(frame, target_cars(gt))
                dets.append(self._detect(frame, gt, record))
            self._clean = dets, evaluate(self.labels, dets, classes=(AP_OF[0],), metrics=(AP_OF[1],))
        return self._clean

    def attack(self, obj: Any) -> Any:
        """The roof-object attack of ``obj`` as a benchmark cell builds it (its default settings), bound to the
        dataset."""
        from robustbench3d.attacks.roof import RoofObjectAttack

        attack = RoofObjectAttack(obj)
        attack.bind_dataset(self.kitti)
        return attack

    def depth_jobs(self, obj: Any) -> list[Any]:
        """The exact-occlusion cache files (:class:`~robustbench3d.attacks.depth_cache.DepthJob`) that
        attacking the held-out frames with ``obj`` (or an object of the same bounds) reads."""
        from robustbench3d.attacks.depth_cache import attack_depth_jobs

        return attack_depth_jobs(self.attack(obj), self.kitti, self.frame_ids, self.labels)

    def attacked(self, obj: Any) -> list[Labels]:
        """Detections of every held-out frame attacked with ``obj`` as a benchmark cell attacks it."""
        from robustbench3d.attacks.base import attack_rng, target_cars

        attack = self.attack(obj)
        dets = []
        for fid, gt in zip(self.frame_ids, self.labels, strict=True):
            clean = self.kitti.lazy_frame(fid, gt)
            rng = attack_rng(self.seed, fid)
            if self._recorded():
                frame, record = attack.apply_recorded(clean, target_cars(gt), rng)
            else:
                frame, record = attack.apply(clean, target_cars(gt), rng), None
            dets.append(self._detect(frame, gt, record))
        return dets

    def effect(self, obj: Any) -> dict[str, float | None]:
        """Clean and attacked AP (:data:`AP_OF`, percent), relative drop and attack success rate of ``obj``."""
        from robustbench3d.eval.kitti_eval import evaluate
        from robustbench3d.results import APResult, drop_tables, success_rate

        clean_dets, clean_metrics = self.clean()
        dets = self.attacked(obj)
        cls, metric, recall, difficulty = AP_OF
        clean, attacked = APResult(clean_metrics), APResult(evaluate(self.labels, dets, classes=(cls,),
                                                                     metrics=(metric,)))
        ap, _, relative = drop_tables(clean, attacked)
        if metric not in clean.metrics(cls):  # the evaluator skipped the class (no Car in the frames)
            return {"clean_ap": None, "attacked_ap": None, "relative_drop": None, "asr": None}
        rate = success_rate(self.labels, clean_dets, dets, clean.iou(cls, metric))["rate"]
        return {"clean_ap": ap[cls][metric][recall][difficulty],
                "attacked_ap": attacked.ap(cls, metric, recall, difficulty),
                "relative_drop": relative[cls][metric][recall][difficulty], "asr": rate}


def make_row(step: int, train_loss: float | None, losses: dict[str, float], effect: dict[str, float | None],
             rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The curve row of an evaluation (module doc); ``rows``: the rows before it (for ``best``)."""
    loss = losses["total"]
    best = all(loss < r["heldout_loss"] for r in rows)
    return {"step": step, "train_loss": train_loss, "heldout_loss": loss,
            "heldout_lidar": losses.get("lidar"), "heldout_image": losses.get("image"),
            "heldout_laplacian": losses.get("laplacian"), **effect, "best": int(best)}


def best_of(rows: Sequence[dict[str, Any]]) -> dict[str, Any] | None:
    """The row of the best state (lowest held-out loss, the earliest of equal ones), None without rows."""
    best = None
    for row in rows:
        if best is None or row["heldout_loss"] < best["heldout_loss"]:
            best = row
    return best


def plateau(rows: Sequence[dict[str, Any]], window: int, tol: float) -> str | None:
    """Why training stops at the last row's step ``s`` (module doc), or None: the best held-out loss up to
    ``s`` is less than ``tol`` (relative) below the best of the rows at steps up to ``s - window`` (None
    while there is no such row)."""
    if not rows:
        return None
    step = rows[-1]["step"]
    earlier = [r for r in rows if r["step"] <= step - window]
    if not earlier:
        return None
    ref, now = best_of(earlier), best_of(rows)
    assert ref is not None and now is not None
    gain = ref["heldout_loss"] - now["heldout_loss"]
    if gain >= tol * abs(ref["heldout_loss"]):
        return None
    share = gain / abs(ref["heldout_loss"]) if ref["heldout_loss"] else 0.0
    return (f"step {step}: the best held-out loss {now['heldout_loss']:.6g} (step {now['step']}) is {share:.2%} "
            f"below {ref['heldout_loss']:.6g}, the best up to step {step - window} (step {ref['step']}): "
            f"less than {tol:.2%} over {window} steps, stopping on a plateau")


def _cell(value: Any) -> str:
    if value is None:
        return ""
    return repr(float(value)) if isinstance(value, float) else str(value)


def csv_text(rows: Sequence[dict[str, Any]]) -> str:
    """The text of ``OBJ.curve.csv`` (module doc)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for row in rows:
        writer.writerow([_cell(row[c]) for c in CSV_COLUMNS])
    return buf.getvalue()


def read_csv_rows(path: Path) -> list[list[str]] | None:
    """The cells of a curve file's rows (header first), None if it is not one (no such header)."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None
    rows = list(csv.reader(io.StringIO(text)))
    return rows if rows and tuple(rows[0]) == CSV_COLUMNS else None


def figure_png(rows: Sequence[dict[str, Any]], title: str) -> bytes:
    """``OBJ.curve.png``: (top) the training loss (running mean) and the held-out loss, (bottom) the held-out
    relative drop and ASR in percent, against the step; the best step marked in both."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    best = best_of(rows)
    steps = [r["step"] for r in rows]
    fig, (ax, bx) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    train = [(r["step"], r["train_loss"]) for r in rows if r["train_loss"] is not None]
    if train:
        ax.plot(*zip(*train, strict=True), "o-", ms=3, color="0.55", label="training loss (mean since last)")
    ax.plot(steps, [r["heldout_loss"] for r in rows], "o-", ms=3, color="#4c78a8", label="held-out loss")
    for name, colour, label in (("relative_drop", "#f58518", "relative drop, BEV R40 moderate"),
                                ("asr", "#54a24b", "attack success rate")):
        pts = [(r["step"], 100.0 * r[name]) for r in rows if r[name] is not None]
        if pts:
            bx.plot(*zip(*pts, strict=True), "o-", ms=3, color=colour, label=label)
    if best is not None:
        for axis in (ax, bx):
            axis.axvline(best["step"], color="#e45756", ls="--", lw=1)
        ax.plot([best["step"]], [best["heldout_loss"]], "*", ms=12, color="#e45756",
                label=f"best (step {best['step']})")
    ax.set_ylabel("loss")
    ax.set_title(title, fontsize=9)
    bx.set_ylabel("held-out, %")
    bx.set_xlabel("step")
    for axis in (ax, bx):
        axis.grid(alpha=0.3)
        axis.legend(fontsize=7)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight", metadata={"Software": None})
    plt.close(fig)
    return buf.getvalue()


def write_curve(out: str | Path, rows: Sequence[dict[str, Any]], title: str) -> None:
    """Write ``OBJ.curve.csv`` and ``OBJ.curve.png`` of object file ``out`` atomically."""
    from robustbench3d.fileio import atomic_write_bytes, atomic_write_text

    csv_path, png_path = curve_paths(out)
    atomic_write_text(csv_path, csv_text(rows))
    atomic_write_bytes(png_path, figure_png(rows, title))
