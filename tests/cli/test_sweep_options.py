"""``robustbench3d sweep``: its options refused up front (one line naming the option and its range), the grid's
points and names, each point's training settings, and the README's "smallest object" sentence, by hand cases."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

from robustbench3d.cli import main
from robustbench3d.errors import RobustBenchError
from robustbench3d.sweep.analysis import smallest_sentence
from robustbench3d.sweep.grid import Point, benign_name, parse_levels, parse_radii, points
from robustbench3d.sweep.train import train_config

BASE = ["sweep", "--victim", "fpointnet-v1-lite", "--mode", "adv-texture", "--no-progress"]


@pytest.mark.parametrize(("extra", "words"), [
    (["--levels", "5"], ["--levels", "2, 3, 4"]),
    (["--levels", "1"], ["--levels", "2, 3, 4"]),
    (["--levels", "2,2"], ["--levels", "twice"]),
    (["--levels", ""], ["--levels", "comma-separated"]),
    (["--radii", "0.1"], ["--radii", "0.2..0.6"]),
    (["--radii", "0.7"], ["--radii", "0.2..0.6"]),
    (["--radii", "0.255"], ["--radii", "centimetres"]),
    (["--radii", "nan"], ["--radii", "0.2..0.6"]),
    (["--radii", "0.4,0.40"], ["--radii", "twice"]),
    (["--radii", "big"], ["--radii", "0.2..0.6"]),
    (["--seed", "-1"], ["--seed"]),
    (["--bootstrap", "5"], ["--bootstrap"]),
    (["--workers", "0"], ["--workers"]),
    (["--max-frames", "0"], ["--max-frames"]),
    (["--train-max-frames", "0"], ["--train-max-frames"]),
    (["--proposals", "lidar"], ["--proposals", "lidar"]),
    (["--proposals", "gt,gt"], ["--proposals"]),
    (["--steps", "0"], ["steps", "(--steps)"]),
    (["--plateau-tol", "2"], ["plateau_tol", "(--plateau-tol)"]),
    (["--eval-frames", "0"], ["eval_frames", "(--eval-frames)"]),
    (["--address", "localhost:1"], ["--address", "--executor ray"]),
])
def test_bad_options_are_refused_in_one_line_before_any_work(tmp_path, capsys, extra, words):
    out = tmp_path / "sweep"
    assert main([*BASE, "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("robustbench3d: error:") and "\n" not in err
    for w in words:
        assert w in err
    assert not out.exists()


def test_a_non_sweep_directory_is_refused_unless_force(tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("mine", encoding="utf-8")
    assert main([*BASE, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "not a sweep directory" in err and "--force" in err
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_points_are_the_grid_plus_the_seed_point_named_by_their_parameters():
    assert parse_levels("4,2") == (2, 4)
    assert parse_radii("0.6, 0.2") == (0.2, 0.6)
    pts = points("adv-texture", (3, 4), (0.2, 0.6))
    assert [p.name for p in pts] == ["adv-texture-l2-r0.40", "adv-texture-l3-r0.20", "adv-texture-l3-r0.60",
                                     "adv-texture-l4-r0.20", "adv-texture-l4-r0.60"]
    assert [p.seed_point for p in pts] == [True, False, False, False, False]
    assert [p.vertex_colours for p in pts] == [162, 642, 642, 2562, 2562]  # 10 * 4**level + 2
    assert pts[1].file == "objects/adv-texture-l3-r0.20.ply"
    assert len(points("adv-shape", (2, 4), (0.2, 0.4, 0.6))) == 6  # the seed's point is one of them
    assert benign_name(0.4) == "benign-sphere" and benign_name(0.2) == "benign-sphere-r0.20"
    with pytest.raises(RobustBenchError, match="--mode"):
        points("adv-paint", (2,), (0.4,))


def test_each_point_trains_with_the_shipped_recipe_but_its_family():
    manifest = json.loads((Path(__file__).resolve().parents[2] / "attacks/objects/manifest.json").read_text(
        encoding="utf-8"))
    shipped = next(o for o in manifest["objects"] if o["name"] == "adv-texture")["training"]["config"]
    cfg = train_config(Point(4, 0.6, "adv-texture"), {"steps": None, "eval_frames": 10})
    assert (cfg.level, cfg.radius, cfg.mode) == (4, 0.6, "adv-texture")
    for field in ("lr_color", "batch_cars", "image_loss", "steps"):  # the recipe, not TrainConfig's defaults
        assert getattr(cfg, field) == shipped[field]
    assert cfg.eval_frames == 10 and cfg.eval_every > 0  # with the held-out curve: trained to its plateau


def _row(name, level, radius, proposals, rel, ci=(0.1, 0.2)):
    return {"victim": "v", "proposals": proposals, "attack": name, "kind": "object", "name": name, "level": level,
            "radius": radius, "vertex_colours": 10 * 4 ** level + 2, "relative_drop": rel,
            "relative_drop_ci": list(ci)}


DOC = {"config": {"mode": "adv-texture"}, "dataset": {"frames": 1009, "split": "val"}, "scores": [
    _row("a-l2-r0.20", 2, 0.2, "detector", 0.30), _row("a-l4-r0.20", 4, 0.2, "detector", 0.55, (0.5, 0.6)),
    _row("a-l2-r0.40", 2, 0.4, "detector", 0.52), _row("a-l2-r0.60", 2, 0.6, "detector", 0.70),
    _row("a-l2-r0.20", 2, 0.2, "gt", 0.01), _row("a-l4-r0.20", 4, 0.2, "gt", None),
    _row("a-l2-r0.40", 2, 0.4, "gt", 0.05, (0.02, 0.08)), _row("a-l2-r0.60", 2, 0.6, "gt", 0.03),
    {**_row("benign-sphere", 2, 0.4, "detector", 0.9), "kind": "benign"},
]}


def test_the_smallest_object_sentence_by_hand():
    text = smallest_sentence(DOC, "v")
    # detector: at r 0.20 the level-4 object reaches 55 % (the level-2 one 30 %): smallest radius first
    assert "with detector proposals the smallest that takes ≥ 50 % of moderate BEV AP is radius 0.20 m with 2562 " \
           "vertex colours (a-l4-r0.20): 55.0 % (95 % CI 50.0–60.0 %)" in text
    # gt: none reaches 50 %; the largest measured drop is named (the None one is not measured)
    assert "with gt proposals none does (largest: a-l2-r0.40, 5.0 % (95 % CI 2.0–8.0 %))" in text
    assert text.startswith("v: of the 4 adv-texture objects swept (radius 0.20–0.60 m, 162–2562 vertex colours, "
                           "1009 frames of val)")
    assert "benign" not in text  # controls are not candidates


def test_the_smallest_object_prefers_fewer_colours_at_the_same_radius():
    doc = copy.deepcopy(DOC)
    doc["scores"][0]["relative_drop"] = 0.5  # exactly half counts
    assert "radius 0.20 m with 162 vertex colours (a-l2-r0.20): 50.0 %" in smallest_sentence(doc, "v")
    with pytest.raises(RobustBenchError, match="no object"):
        smallest_sentence(doc, "other")
