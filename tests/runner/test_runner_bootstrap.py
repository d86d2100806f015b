"""The runner's bootstrap intervals: ``metrics_ci`` on ok cells and the paired ``drop_ci`` of attack effects,
checked against the full evaluator on literally resampled frame lists; schema, tables and the off switch."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cell_builders import hand_cell
from eval_fixture_generator import load_generator

from robustbench3d.errors import RobustBenchError
from robustbench3d.eval.bootstrap import resample_weights
from robustbench3d.eval.kitti_eval import evaluate
from robustbench3d.kitti import Labels
from robustbench3d.kitti.labels import parse_labels
from robustbench3d.results import validate_summary
from robustbench3d.runner.config import RunConfig
from robustbench3d.runner.effect import attach_effects
from robustbench3d.runner.table import summary_table
from robustbench3d.seed_table import seed_table_text

SHA = "a" * 64
GEN = load_generator()


def _cell(attack: str, metrics: dict, fingerprint: str) -> dict:
    return hand_cell(attack, metrics, fingerprint, SHA)


@pytest.fixture
def run_dir(tmp_path: Path):
    ids, gt_lines, dt_lines = GEN.make_set(GEN.SetSpec(seed=301, frames=30, gt_per_frame=6.0, score_decimals=2))
    gt = [parse_labels("\n".join(gt_lines[i]), f"{i}.txt", scored=False) for i in ids]
    rng = np.random.default_rng(0)
    clean_rows = {i: dt_lines.get(i, []) for i in ids}
    attacked_rows = {i: [r for r in rows if rng.random() > 0.4] for i, rows in clean_rows.items()}
    cells = []
    for attack, rows, fp in (("none", clean_rows, "b" * 64), ("random-shape", attacked_rows, "c" * 64)):
        data = tmp_path / f"v+{attack}+detector" / "data"
        data.mkdir(parents=True)
        for i in ids:
            (data / f"{i}.txt").write_text("".join(r + "\n" for r in rows[i]))
        dets = [parse_labels("\n".join(rows[i]), f"{i}.txt", scored=True) for i in ids]
        cells.append(_cell(attack, evaluate(gt, dets, classes=("Car",)), fp))
    return tmp_path, cells, gt, ids


def _reference(gt: list[Labels], data: Path, ids: list[str], w: np.ndarray) -> float:
    dets = [parse_labels((data / f"{i}.txt").read_text(), f"{i}.txt", scored=True) for i in ids]
    frames = np.repeat(np.arange(len(ids)), w)
    return evaluate([gt[i] for i in frames], [dets[i] for i in frames])["Car"]["bev"]["R40"]["moderate"]


def test_cells_get_intervals_equal_to_the_literal_bootstrap(run_dir) -> None:
    cells_dir, cells, gt, ids = run_dir
    n, seed = 20, 4
    changed = attach_effects(cells, cells_dir, gt, ids, bootstrap=n, seed=seed)
    assert changed == [0, 1]
    validate_summary(cells)
    w = resample_weights(len(ids), n, seed)
    clean = np.array([_reference(gt, cells_dir / "v+none+detector" / "data", ids, w[r]) for r in range(n)])
    attacked = np.array([_reference(gt, cells_dir / "v+random-shape+detector" / "data", ids, w[r]) for r in range(n)])
    assert cells[0]["metrics_ci"]["Car"]["bev"]["R40"]["moderate"] == pytest.approx(
        list(np.percentile(clean, [2.5, 97.5])), abs=1e-9)
    assert cells[1]["metrics_ci"]["Car"]["bev"]["R40"]["moderate"] == pytest.approx(
        list(np.percentile(attacked, [2.5, 97.5])), abs=1e-9)
    drop = cells[1]["attack_effect"]["drop_ci"]
    assert drop["Car"]["bev"]["R40"]["moderate"] == pytest.approx(
        list(np.percentile(clean - attacked, [2.5, 97.5])), abs=1e-9)
    assert drop["meta"]["resamples"] == n and drop["meta"]["seed"] == seed and drop["meta"]["frames"] == len(ids)
    assert "attack_effect" not in cells[0]
    # Every AP of the metrics has an interval, lo <= hi.
    for m, by_recall in cells[0]["metrics"]["Car"].items():
        for r, by_diff in by_recall.items():
            for d in by_diff:
                lo, hi = cells[0]["metrics_ci"]["Car"][m][r][d]
                assert lo <= hi
    # Unchanged inputs: nothing to rewrite; a different resample count: recomputed.
    assert attach_effects(cells, cells_dir, gt, ids, bootstrap=n, seed=seed) == []
    assert attach_effects(cells, cells_dir, gt, ids, bootstrap=n + 1, seed=seed) == [0, 1]
    assert cells[0]["metrics_ci"]["meta"]["resamples"] == n + 1


def test_tables_print_the_intervals_and_zero_disables(run_dir) -> None:
    cells_dir, cells, gt, ids = run_dir
    attach_effects(cells, cells_dir, gt, ids, bootstrap=15, seed=0)
    lo, hi = cells[0]["metrics_ci"]["Car"]["bev"]["R40"]["moderate"]
    ap = cells[0]["metrics"]["Car"]["bev"]["R40"]["moderate"]
    table = summary_table(cells)
    assert f"{ap:6.2f} [{lo:.1f}, {hi:.1f}]" in table and "bootstrap interval" in table
    dlo, dhi = cells[1]["attack_effect"]["drop_ci"]["Car"]["bev"]["R40"]["moderate"]
    assert f"[{-dhi:.1f}, {-dlo:.1f}])" in table  # the AP change -drop: the interval flips
    assert f"[{lo:.1f}, {hi:.1f}]" in seed_table_text(cells)
    changed = attach_effects(cells, cells_dir, gt, ids, bootstrap=0)
    assert changed == [0, 1]
    assert "metrics_ci" not in cells[0] and "drop_ci" not in cells[1]["attack_effect"]
    validate_summary(cells)
    assert "[" not in summary_table(cells)


def test_schema_rejects_a_malformed_interval(run_dir) -> None:
    cells_dir, cells, gt, ids = run_dir
    attach_effects(cells, cells_dir, gt, ids, bootstrap=5, seed=0)
    cells[0]["metrics_ci"]["Car"]["bev"]["R40"]["moderate"] = [1.0]
    with pytest.raises(Exception, match="metrics_ci"):
        validate_summary(cells)


def test_run_config_refuses_negative_resamples(tmp_path: Path) -> None:
    assert RunConfig(("v",), ("none",), ("gt",), tmp_path).bootstrap == 1000
    with pytest.raises(RobustBenchError, match="--bootstrap"):
        RunConfig(("v",), ("none",), ("gt",), tmp_path, bootstrap=-1)
