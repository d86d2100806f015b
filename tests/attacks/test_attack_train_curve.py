"""``attack train``'s held-out curve (issue #33): frames it never trains on, evaluated every K steps as a
benchmark cell scores them (CSV + PNG), the best state written, the plateau stop, resume across an evaluation,
the written-once rule of the curve files and the ranges of the new options.

The dataset: six generated frames, all in the train split, so the curve holds out the last one (at most a fifth
of the split). References are computed independently: the split file read here, ``robustbench3d run`` on a split
of the held-out frame, the CSV read with pandas, the checkpoint's history read with torch.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from robustbench3d.attacks.train import UniversalTrainer
from robustbench3d.attacks.train_config import TrainConfig, TrainingError
from robustbench3d.attacks.train_run import checkpoint_path, data_identity, train_universal
from robustbench3d.cli import main
from robustbench3d.datasets import dataset_identity, load_ground_truth, resolve_dataset
from robustbench3d.testing import synth_dataset
from robustbench3d.victims.cascade import FPointNetCascade

FAST = {"batch_cars": 4, "occlusion": "none", "supersample": 1}
COLUMNS = ["step", "train_loss", "heldout_loss", "heldout_lidar", "heldout_image", "heldout_laplacian", "clean_ap",
           "attacked_ap", "relative_drop", "asr", "best"]

pytestmark = pytest.mark.usefixtures("cache")  # a fresh cache per test (conftest)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """Generated frames 0-5, all in the train split."""
    return synth_dataset(tmp_path_factory.mktemp("synth"), 6, seed=0, val_fraction=0.0)


@pytest.fixture(scope="module")
def split(dataset) -> list[str]:
    """The train split's frame ids, read from its file."""
    return (dataset / "ImageSets" / "train.txt").read_text().split()


@pytest.fixture(scope="module")
def victim(lite_victim) -> FPointNetCascade:
    return lite_victim  # the session's shared one (conftest): read only


def train(victim, dataset, out: Path, max_frames: int | None = None, log=None, **kw):
    resolved = resolve_dataset(dataset, "train", progress=False)
    gt = load_ground_truth(resolved, max_frames)
    config = TrainConfig(**{**FAST, **{k: v for k, v in kw.items() if k not in ("resume", "on_step", "force")}})
    return train_universal(victim, {"name": "fpointnet-v1-lite"}, resolved.kitti(), gt.frame_ids, gt.labels, config,
                           out, data_identity=data_identity(dataset_identity(resolved, gt), resolved.root),
                           resume=kw.get("resume", False), force=kw.get("force", False), progress=False,
                           on_step=kw.get("on_step"), log=log)


def curve_files(out: Path) -> tuple[Path, Path]:
    return out.with_name(out.stem + ".curve.csv"), out.with_name(out.stem + ".curve.png")


def as_class(victim, cls):
    other = object.__new__(cls)
    other.__dict__.update(victim.__dict__)
    return other


class Recording(FPointNetCascade):
    """The shipped victim, recording the frame of every segmentation call with and without gradients."""

    seen: dict[bool, set[str]]

    def frustum_logits(self, *args, **kwargs):
        self.seen[torch.is_grad_enabled()].add(kwargs["frame_id"])
        return super().frustum_logits(*args, **kwargs)


def test_held_out_frames_are_never_trained_on(victim, dataset, split, tmp_path):
    """The last frame of the split (a fifth of six frames, rounded down) is evaluated but never differentiated;
    every other frame is trained on (two 28-car batches visit all 55 cars of the first five frames). The last
    state equals that of a run without evaluation on the first five frames alone: the held-out frame changes
    nothing."""
    rec = as_class(victim, Recording)
    rec.seen = {True: set(), False: set()}
    kw = {"mode": "adv-shape", "steps": 2, "batch_cars": 28, "eval_every": 2, "eval_frames": 4}
    lines: list[str] = []
    made_by = train(rec, dataset, tmp_path / "h.ply", log=lines.append, **kw)
    assert rec.seen[True] == set(split[:5]) and split[5] not in rec.seen[True]
    assert split[5] in rec.seen[False]
    held = made_by["curve"]["held_out"]
    assert (held["frames"], held["first_frame"], held["last_frame"]) == (1, split[5], split[5])
    labels = (dataset / "training" / "label_2" / f"{split[5]}.txt").read_text().splitlines()
    assert held["cars"] == sum(line.startswith("Car ") for line in labels)
    assert any("the last 1 of the split's 6 frames (--eval-frames 4: at most a fifth" in ln for ln in lines)
    train(victim, dataset, tmp_path / "ref.ply", max_frames=5, **{**kw, "eval_every": 0})
    last, ref = (torch.load(checkpoint_path(tmp_path / n), weights_only=True) for n in ("h.ply", "ref.ply"))
    assert torch.equal(last["delta"], ref["delta"]) and last["step"] == ref["step"] == 2


def test_curve_rows_are_what_a_benchmark_run_of_the_written_object_measures(victim, dataset, split, tmp_path):
    """adv-texture, evaluations at 0, 2 and the last step 3: the CSV (read with pandas) has the documented
    columns; OBJ.ply is the state of lowest held-out loss; ``robustbench3d run`` of OBJ.ply on a split of the
    held-out frame gives that row's clean and attacked AP, relative drop and ASR; train_loss is the mean of the
    checkpoint's step losses since the previous evaluation; at step 0 (the grey sphere, no EOT) the held-out
    loss is the step loss of a trainer whose only frame is the held-out one, with a batch of all its cars; the
    PNG is a PNG."""
    out = tmp_path / "tex.ply"
    made_by = train(victim, dataset, out, mode="adv-texture", steps=3, lr_color=1.0, eval_every=2, eval_frames=1)
    csv_path, png_path = curve_files(out)
    df = pd.read_csv(csv_path)
    assert list(df.columns) == COLUMNS and df["step"].tolist() == [0, 2, 3]
    assert df["heldout_lidar"].isna().all() and df["heldout_laplacian"].isna().all()
    assert np.allclose(df["heldout_loss"], df["heldout_image"]) and np.isnan(df["train_loss"][0])
    best = df.loc[df["heldout_loss"].idxmin()]
    assert made_by["object_step"] == best["step"] == made_by["curve"]["best_step"]
    assert df["best"].tolist() == [int(v < df["heldout_loss"][:i].min()) if i else 1
                                   for i, v in enumerate(df["heldout_loss"])]
    hist = torch.load(checkpoint_path(out), weights_only=True)["history"]
    for prev, step in ((0, 2), (2, 3)):
        row = df[df["step"] == step].iloc[0]
        assert row["train_loss"] == pytest.approx(np.mean([h["total"] for h in hist[prev:step]]), rel=1e-12)
    assert png_path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert made_by["stopped"]["reason"] == "steps" and made_by["steps"] == 3
    # the held-out loss at step 0
    resolved = resolve_dataset(dataset, "train", progress=False)
    gt = load_ground_truth(resolved)
    cars = made_by["curve"]["held_out"]["cars"]
    alone = UniversalTrainer(victim, resolved.kitti(), gt.frame_ids[5:], gt.labels[5:],
                             TrainConfig(**{**FAST, "mode": "adv-texture", "batch_cars": cars}))
    assert df["heldout_loss"][0] == pytest.approx(alone.compute_step(0).losses["total"], rel=1e-9)
    # the benchmark's own numbers for the written object on the held-out frame (seed 0 = the training seed)
    (dataset / "ImageSets" / "heldout.txt").write_text(split[5] + "\n")
    shutil.copyfile(out, tmp_path / "curve-object.ply")
    shutil.copyfile(out.with_suffix(".json"), tmp_path / "curve-object.json")
    code = main(["run", "--victims", "fpointnet-v1-lite", "--attacks", f"none,{tmp_path / 'curve-object.ply'}",
                 "--proposals", "detector", "--data", str(dataset), "--split", "heldout", "--out",
                 str(tmp_path / "run"), "--no-progress"])
    assert code == 0
    cells = {c["attack"]: c for c in json.loads((tmp_path / "run" / "summary.json").read_text())}
    clean, attacked = cells["none"], cells["curve-object"]
    assert best["clean_ap"] == pytest.approx(clean["metrics"]["Car"]["bev"]["R40"]["moderate"], rel=1e-12)
    assert best["attacked_ap"] == pytest.approx(attacked["metrics"]["Car"]["bev"]["R40"]["moderate"], rel=1e-12)
    effect = attacked["attack_effect"]
    assert best["relative_drop"] == pytest.approx(effect["relative_drop"]["Car"]["bev"]["R40"]["moderate"], abs=1e-12)
    assert best["asr"] == pytest.approx(effect["success"]["rate"], abs=1e-12)


def _plateau_steps(df: pd.DataFrame, window: int, tol: float) -> int | None:
    """The first evaluation step at which the best loss so far is less than tol below the best up to
    step - window (the documented rule), from the CSV alone."""
    for step in df["step"]:
        now = df[df["step"] <= step]["heldout_loss"].min()
        earlier = df[df["step"] <= step - window]["heldout_loss"]
        if len(earlier) and earlier.min() - now < tol * abs(earlier.min()):
            return int(step)
    return None


def test_plateau_stop_and_its_resume(victim, dataset, tmp_path):
    """Shape steps of 1e-6 leave the held-out loss flat: with the default tolerance (0.4 %), evaluations every
    step and a window of 2 steps, training stops at step 2 (the first evaluation with one 2 steps before it),
    says so in one line and records it; a run interrupted before that stop and resumed gives the same bytes;
    resumed again with the same settings it stops at once, with --plateau-tol 0 it trains on."""
    kw = {"mode": "adv-shape", "steps": 20, "batch_cars": 2, "lr_shape": 1e-6, "eval_every": 1, "eval_frames": 1,
          "plateau_window": 2}
    lines: list[str] = []
    made_by = train(victim, dataset, tmp_path / "full.ply", log=lines.append, **kw)
    df = pd.read_csv(curve_files(tmp_path / "full.ply")[0])
    assert _plateau_steps(df, 2, 0.004) == 2 and df["step"].tolist() == [0, 1, 2] and made_by["steps"] == 2
    assert made_by["stopped"]["reason"] == "plateau" and made_by["stopped"]["step"] == 2
    said = [ln for ln in lines if "stopping on a plateau" in ln]
    assert len(said) == 1 and said[0].startswith("step 2: the best held-out loss") and "over 2 steps" in said[0]
    assert said[0] == made_by["stopped"]["line"]

    class Stop(Exception):
        pass

    def interrupt(trainer):
        if trainer.step == 1:
            raise Stop

    with pytest.raises(Stop):
        train(victim, dataset, tmp_path / "part.ply", **kw, on_step=interrupt, checkpoint_every=1)
    train(victim, dataset, tmp_path / "part.ply", **kw, resume=True)
    for a, b in zip(_outputs(tmp_path / "full.ply"), _outputs(tmp_path / "part.ply"), strict=True):
        assert a.read_bytes() == b.read_bytes(), a.name
    lines.clear()
    again = train(victim, dataset, tmp_path / "full.ply", **kw, resume=True, log=lines.append)
    assert again["steps"] == 2 and any("stopping on a plateau" in ln for ln in lines)
    on = train(victim, dataset, tmp_path / "full.ply", **{**kw, "plateau_tol": 0.0, "steps": 3}, resume=True)
    assert on["steps"] == 3 and on["stopped"]["reason"] == "steps"
    assert pd.read_csv(curve_files(tmp_path / "full.ply")[0])["step"].tolist() == [0, 1, 2, 3]


def _outputs(out: Path) -> list[Path]:
    return [out, *curve_files(out)]


def test_resume_across_an_evaluation_gives_the_bytes_of_an_uninterrupted_run(victim, dataset, tmp_path):
    """Evaluations every 2 steps, checkpoints every 3. A finished 3-step run (with its extra evaluation of its last
    step) continued to 6 steps and interrupted after the evaluation of step 4 (its last checkpoint: step 3), then
    resumed again, gives the bytes of an uninterrupted 6-step run: the evaluation of step 4 is done again and
    the extra one of step 3 is not kept."""

    class Stop(Exception):
        pass

    def interrupt(trainer):
        if trainer.step == 5:
            raise Stop

    kw = {"mode": "adv-shape", "steps": 6, "batch_cars": 2, "eval_every": 2, "eval_frames": 1,
          "checkpoint_every": 3, "eot": ("jitter",), "plateau_tol": 0.0}
    full = train(victim, dataset, tmp_path / "full.ply", **kw)
    train(victim, dataset, tmp_path / "part.ply", **{**kw, "steps": 3})
    assert pd.read_csv(curve_files(tmp_path / "part.ply")[0])["step"].tolist() == [0, 2, 3]
    with pytest.raises(Stop):
        train(victim, dataset, tmp_path / "part.ply", **kw, on_step=interrupt, resume=True)
    assert torch.load(checkpoint_path(tmp_path / "part.ply"), weights_only=True)["step"] == 3
    resumed = train(victim, dataset, tmp_path / "part.ply", **kw, resume=True)
    for a, b in zip(_outputs(tmp_path / "full.ply"), _outputs(tmp_path / "part.ply"), strict=True):
        assert a.read_bytes() == b.read_bytes(), a.name
    assert pd.read_csv(curve_files(tmp_path / "part.ply")[0])["step"].tolist() == [0, 2, 4, 6]
    assert resumed["curve"]["files"] == {"csv": "part.curve.csv", "png": "part.curve.png"}
    for d in (full, resumed):
        d.pop("wall_time_s")
        d["curve"].pop("eval_time_s")
        d["curve"].pop("files")
    assert resumed == full


def _argv(out: Path, data: Path, *extra: str) -> list[str]:
    return ["attack", "train", "adv-shape", "--victim", "fpointnet-v1-lite", "--data", str(data), "--out", str(out),
            "--steps", "1", "--batch-cars", "2", "--eval-every", "1", "--eval-frames", "1", "--occlusion", "none",
            "--no-progress", *extra]


def _one_error(capsys, argv: list[str], watch: Path, *words: str) -> None:
    before = {p: p.read_bytes() for p in watch.iterdir() if p.is_file()}
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("robustbench3d: error: ")]
    assert len(lines) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in lines[0], lines[0]
    assert {p: p.read_bytes() for p in watch.iterdir() if p.is_file()} == before


def test_curve_files_are_written_once(dataset, tmp_path, capsys):
    """An existing curve file is refused up front (before the dataset is read) unless --force, which says what
    it replaces; --resume replaces the curve of the training it continues and says so, and refuses a CSV that
    is not that training's."""
    out = tmp_path / "o.ply"
    csv_path, png_path = curve_files(out)
    csv_path.write_text("someone's notes\n")
    _one_error(capsys, _argv(out, tmp_path / "no-data"), tmp_path, "o.curve.csv", "--force")
    csv_path.unlink()
    png_path.write_bytes(b"someone's picture")
    _one_error(capsys, _argv(out, tmp_path / "no-data"), tmp_path, "o.curve.png", "--force")
    assert main(_argv(out, dataset, "--force")) == 0
    printed = capsys.readouterr().out
    assert f"replacing {png_path} (--force)" in printed and "held out for the curve: the last 1" in printed
    assert pd.read_csv(csv_path)["step"].tolist() == [0, 1]
    assert main(_argv(out, dataset, "--resume", "--steps", "2")) == 0
    printed = capsys.readouterr().out
    assert "replacing o.curve.csv and o.curve.png, the curve of the training o.train.pt continues (--resume)" \
        in printed
    assert pd.read_csv(csv_path)["step"].tolist() == [0, 1, 2]
    rows = csv_path.read_text().splitlines()
    csv_path.write_text("\n".join([rows[0], rows[1].replace(rows[1].split(",")[2], "0.5", 1), *rows[2:]]) + "\n")
    _one_error(capsys, _argv(out, dataset, "--resume", "--steps", "3"), tmp_path, "o.curve.csv",
               "is not the curve of the training", "--force")


@pytest.mark.parametrize(("option", "value", "field", "span"), [
    ("--eval-every", "-1", "'eval_every' (--eval-every)", "[0, 1000000]"),
    ("--eval-frames", "0", "'eval_frames' (--eval-frames)", "[1, 10000]"),
    ("--eval-frames", "10001", "'eval_frames' (--eval-frames)", "[1, 10000]"),
    ("--plateau-window", "0", "'plateau_window' (--plateau-window)", "[1, 1000000]"),
    ("--plateau-tol", "nan", "'plateau_tol' (--plateau-tol)", "[0, 1]"),
    ("--plateau-tol", "1.5", "'plateau_tol' (--plateau-tol)", "[0, 1]")])
def test_curve_options_out_of_range_are_refused_up_front(tmp_path, capsys, option, value, field, span):
    _one_error(capsys, _argv(tmp_path / "o.ply", tmp_path / "no-data", option, value), tmp_path, field, span)


def test_no_curve_without_evaluation_or_frames_to_hold_out(victim, dataset, tmp_path):
    """--eval-every 0: every frame trains, no curve files, the sidecar says so; a split of four frames has no
    fifth to hold out."""
    lines: list[str] = []
    made_by = train(victim, dataset, tmp_path / "n.ply", log=lines.append, mode="adv-shape", steps=1, eval_every=0)
    assert made_by["curve"] is None and made_by["object_step"] == 1 and made_by["stopped"]["reason"] == "steps"
    assert not any(p.exists() for p in curve_files(tmp_path / "n.ply"))
    assert "no held-out curve (--eval-every 0): training on every frame of the split" in lines
    lines.clear()
    made_by = train(victim, dataset, tmp_path / "f.ply", max_frames=4, log=lines.append, mode="adv-shape", steps=1)
    assert made_by["curve"] is None and any("a split of 4 frame(s) leaves no frame to hold out" in ln for ln in lines)
    with pytest.raises(TrainingError, match=r"field 'plateau_tol' \(--plateau-tol\)"):
        TrainConfig(mode="adv-shape", plateau_tol=-0.1)


def test_cli_defaults_are_the_config_defaults():
    """attack_train.py keeps its module level to the standard library, so its option defaults are literals:
    they must be TrainConfig's."""
    import argparse
    from dataclasses import asdict

    from robustbench3d.commands.attack_train import add_arguments, config_from_args

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    parsed = config_from_args(parser.parse_args(["adv-texture", "--victim", "v", "--out", "o.ply"]))
    assert asdict(parsed) == asdict(TrainConfig(mode="adv-texture"))
    assert (parsed.eval_every, parsed.eval_frames, parsed.plateau_window, parsed.plateau_tol) == (25, 5, 60, 0.004)


def test_a_checkpoint_from_before_the_curve_resumes_without_evaluation(victim, dataset, tmp_path):
    """A checkpoint whose identity predates the curve's fields (no eval_every, eval_frames) is a training on every
    frame without evaluation: --eval-every 0 continues it, the default (a held-out frame) is another training."""
    kw = {"mode": "adv-shape", "steps": 1, "batch_cars": 2, "eval_every": 0}
    train(victim, dataset, tmp_path / "old.ply", **kw)
    ckpt = checkpoint_path(tmp_path / "old.ply")
    state = torch.load(ckpt, weights_only=True)
    for name in ("eval_every", "eval_frames"):
        del state["identity"]["config"][name]
    torch.save(state, ckpt)
    made_by = train(victim, dataset, tmp_path / "old.ply", **{**kw, "steps": 2}, resume=True)
    assert made_by["steps"] == 2 and made_by["curve"] is None
    with pytest.raises(TrainingError, match=r"another training \(config.eval_every, config.eval_frames differ\)"):
        train(victim, dataset, tmp_path / "old.ply", **{**kw, "steps": 3, "eval_every": 25}, resume=True)


class Worsening(FPointNetCascade):
    """The shipped victim whose objectness logits grow by 1 with every call made without gradients: the
    held-out loss rises from one evaluation to the next whatever the object does, so the best state is step 0's."""

    calls = 0

    def objectness(self, *args, **kwargs):
        from dataclasses import replace

        out = super().objectness(*args, **kwargs)
        if torch.is_grad_enabled():
            return out
        self.calls += 1
        return replace(out, objectness_logit=out.objectness_logit + float(self.calls))


def test_the_object_file_is_the_best_state_and_the_checkpoint_the_last(victim, dataset, tmp_path):
    """With the held-out loss rising at every evaluation the best state is the start, the undeformed grey sphere:
    OBJ.ply holds it (the template's vertices, neutral grey), the sidecar says so, and the checkpoint keeps the
    trained colours for --resume."""
    from robustbench3d.attacks.object import NEUTRAL_GREY, template_vertices
    from robustbench3d.attacks.objectfile import read_object_file

    out = tmp_path / "w.ply"
    made_by = train(as_class(victim, Worsening), dataset, out, mode="adv-texture", steps=2, lr_color=0.5,
                    eval_every=1, eval_frames=1)
    df = pd.read_csv(curve_files(out)[0])
    assert df["step"].tolist() == [0, 1, 2] and df["best"].tolist() == [1, 0, 0]
    assert df["heldout_loss"].is_monotonic_increasing
    assert made_by["object_step"] == made_by["curve"]["best_step"] == 0 and made_by["steps"] == 2
    obj = read_object_file(out).obj
    np.testing.assert_array_equal(obj.vertices(), template_vertices())
    assert np.all(obj.colors == np.round(NEUTRAL_GREY * 255) / 255)
    last = torch.sigmoid(torch.load(checkpoint_path(out), weights_only=True)["colour_logit"])
    assert (last - NEUTRAL_GREY).abs().max() > 0.1  # two steps of 0.5 on the logits
