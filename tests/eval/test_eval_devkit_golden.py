"""Agreement with the official KITTI devkit's printed AP on generated sets and on the real samples.

The golden numbers in ``fixtures/eval/devkit_golden.json`` were printed by the compiled official
devkit (see ``fixtures/eval/README.md``); this evaluator never produced them.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from eval_fixture_generator import load_generator

from robustbench3d.eval.kitti_eval import evaluate_dirs

FIXTURES = Path(__file__).parents[1] / "fixtures" / "eval"
GOLDEN = json.loads((FIXTURES / "devkit_golden.json").read_text())
TOLERANCE = 1e-3  # AP points; the devkit prints 6 decimals of a float32 sum
CLASSES = ("Car", "Pedestrian", "Cyclist")




GEN = load_generator()


def compare(ours: dict, devkit: dict) -> list[str]:
    """Differences between our result and the devkit's AP lines (empty: agreement)."""
    problems = []
    for cls in CLASSES:
        for metric in ("2d", "aos", "bev", "3d"):
            ref, got = devkit.get(cls, {}).get(metric), ours.get(cls, {}).get(metric)
            if ref is None:
                # The devkit prints nothing for a class without detections (we report AP 0) or for a
                # metric it skips (we skip it too).
                if got is not None and any(v != 0 for r in got.values() for v in r.values()):
                    problems.append(f"{cls} {metric}: devkit skipped it, we report {got}")
                continue
            if got is None:
                problems.append(f"{cls} {metric}: devkit reports it, we skipped it")
                continue
            for recall in ("R40", "R11"):
                for diff, value in ref[recall].items():
                    if abs(got[recall][diff] - value) > TOLERANCE:
                        problems.append(f"{cls} {metric} {recall} {diff}: devkit {value}, ours {got[recall][diff]}")
    return problems


@pytest.mark.parametrize("name", sorted(GOLDEN["sets"]))
def test_generated_set_matches_devkit(name: str, tmp_path: Path) -> None:
    ids, gt, dt = GEN.make_set(GEN.SETS[name])
    assert GEN.set_digest(ids, gt, dt) == GOLDEN["sets"][name]["digest"], (
        "the fixture generator's output changed; regenerate the golden file as fixtures/eval/README.md says")
    GEN.write_set(tmp_path, ids, gt, dt)
    ours = evaluate_dirs(tmp_path / "label_2", tmp_path / "results", tmp_path / "frames.txt", classes=CLASSES)
    devkit = GOLDEN["sets"][name]["devkit"]
    assert compare(ours, devkit) == []
    assert ("aos" not in {s["metric"] for s in ours["meta"]["skipped"]}) == devkit["compute_aos"]


def test_golden_sets_cover_the_rules() -> None:
    """The committed sets exercise what they claim: skips, several classes, few GT, extra files."""
    sets = GOLDEN["sets"]
    assert not sets["no_orientation_no_3d"]["devkit"]["compute_aos"]
    assert "bev" not in sets["no_orientation_no_3d"]["devkit"]["Pedestrian"]
    assert "2d" not in sets["no_orientation_no_3d"]["devkit"].get("Cyclist", {})
    assert {"Car", "Pedestrian", "Cyclist"} <= set(sets["multiclass"]["devkit"])
    values = [v for s in sets.values() for c in CLASSES for m in s["devkit"].get(c, {}).values()
              for r in m.values() for v in r.values()]
    assert min(values) < 50 < max(values)  # not all trivial


def test_real_samples_match_devkit(kitti_samples: Path, tmp_path: Path) -> None:
    real = GOLDEN["real_samples"]
    split = tmp_path / "val.txt"
    split.write_text("".join(f"{f}\n" for f in real["frames"]))
    ours = evaluate_dirs(kitti_samples / "training/label_2", kitti_samples / "results/pointgnn_car_val/data",
                         split, classes=("Car",))
    assert compare(ours, real["devkit"]) == []
