"""``robustbench3d check`` (robustbench3d.gate): baselines written and read back, hand-made runs whose AP or AP
drop moved by a known amount, every way a run can differ from its baseline, and bad input (exit 2)."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest
from cell_builders import hand_provenance, write_run

from robustbench3d.cli import main
from robustbench3d.errors import DataFormatError
from robustbench3d.gate import FORMAT, baseline_from_run, compare, read_baseline, read_run

SHA = "ab" * 32
DIFFS = ("easy", "moderate", "hard")
EVALUATION = {"evaluator": "robustbench3d.eval", "classes": ["Car"]}  # the cells' configured evaluation


def by_diff(values: tuple[float, float, float]) -> dict[str, float]:
    return dict(zip(DIFFS, values, strict=True))


def metrics(bev: tuple, d3: tuple) -> dict:
    return {"Car": {m: {"R40": by_diff(v), "R11": by_diff(v)} for m, v in (("bev", bev), ("3d", d3))},
            "meta": {"evaluator": "robustbench3d.eval", "version": "1", "ap_unit": "percent", "frames": 10,
                     "classes": ["Car"], "metrics": ["bev", "3d"], "min_overlap": {"Car": {"bev": 0.7, "3d": 0.7}}}}


def cell(attack: str, proposals: str, bev: tuple | None, d3: tuple | None = None, status: str = "ok",
         drop: tuple[float, float] | None = None) -> dict:
    """A schema-valid cell of victim "v"; ``drop``: (BEV, 3D) moderate drops of an attacked cell."""
    c = {
        "schema_version": 1, "victim": "v", "attack": attack, "proposals": proposals, "status": status,
        "reason": None if status == "ok" else "it failed",
        "dataset": {"root": "/data", "split": "val", "frames": 10, "split_frames": 10, "sha256": SHA,
                    "embedded": None, "manifest": None},
        "metrics": metrics(bev, d3 or bev) if status == "ok" else None,
        "provenance": hand_provenance("v", attack, proposals, SHA, weights_sha256=SHA, evaluation=EVALUATION),
    }
    if drop is not None:
        def table(values: tuple[float, float]) -> dict:
            return {"Car": {m: {r: {"easy": 0.0, "moderate": v, "hard": 0.0} for r in ("R40", "R11")}
                            for m, v in zip(("bev", "3d"), values, strict=True)}}

        c["attack_effect"] = {
            "clean_cell": f"v+none+{proposals}", "clean_fingerprint": SHA, "clean": table((0.0, 0.0)),
            "drop": table(drop), "relative_drop": table((0.0, 0.0)),
            "success": {"class": "Car", "metric": "bev", "iou": 0.7, "difficulty": "moderate", "score_threshold": 0.5,
                        "clean_matched": 4, "attacked_missed": 1, "rate": 0.25}}
    return c


def summary() -> list[dict]:
    """Clean 80/64/50 (3D 70/52/40), an attacked cell with drops 16 (BEV) and 12 (3D), a skipped cell."""
    return [cell("none", "detector", (80.0, 64.0, 50.0), (70.0, 52.0, 40.0)),
            cell("adv", "detector", (60.0, 48.0, 40.0), (58.0, 40.0, 30.0), drop=(16.0, 12.0)),
            cell("none", "gt", None, status="skipped")]


@pytest.fixture
def base(tmp_path: Path) -> Path:
    """The baseline of :func:`summary`, written through the command."""
    run = write_run(tmp_path / "base_run", summary())
    assert main(["check", str(run), "--write-baseline", str(tmp_path / "baseline.json")]) == 0
    return tmp_path / "baseline.json"


def check(run: Path, baseline: Path, *extra: str) -> int:
    return main(["check", str(run), "--baseline", str(baseline), *extra])


def test_baseline_records_the_summary_numbers_exactly(base):
    data = read_baseline(base)
    assert (data["format"], data["version"]) == (FORMAT, 1)
    assert data["dataset"] == {"split": "val", "frames": 10, "split_frames": 10, "sha256": SHA, "embedded": None,
                               "root": "/data"}
    assert data["protocol"]["seed"] == 0 and data["protocol"]["min_overlap"] == {"bev": 0.7, "3d": 0.7}
    clean, adv, skipped = data["cells"]
    assert clean["ap"] == {"bev": by_diff((80.0, 64.0, 50.0)), "3d": by_diff((70.0, 52.0, 40.0))}
    assert clean["drop_moderate"] is None
    assert adv["drop_moderate"] == {"bev": 16.0, "3d": 12.0}
    assert (skipped["status"], skipped["ap"], skipped["drop_moderate"]) == ("skipped", None, None)


def test_untouched_run_passes(base, tmp_path, capsys):
    run = write_run(tmp_path / "same", summary())
    assert check(run, base) == 0
    out = capsys.readouterr().out
    # 2 ok cells x 6 AP + 1 attacked cell x 2 drops = 14 values, 3 cells (the skipped one by status)
    assert "check passed" in out and "3 cell(s), 14 value(s) compared" in out


def test_lowered_ap_fails_with_a_diff_row(base, tmp_path, capsys):
    cells = summary()
    cells[0]["metrics"]["Car"]["bev"]["R40"]["moderate"] = 62.5  # 64 -> 62.5: -1.5 > 1.0
    assert check(write_run(tmp_path / "low", cells), base) == 1
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("v+none+detector"))
    assert row.split() == ["v+none+detector", "BEV", "AP", "moderate", "64.00", "62.50", "-1.50", "1.00", "regression"]
    assert "check FAILED" in out and "1 regression(s), 0 improvement(s)" in out


def test_tolerance_boundary_is_inclusive(base, tmp_path):
    cells = summary()
    cells[0]["metrics"]["Car"]["3d"]["R40"]["hard"] = 39.5  # exactly 0.5 below
    run = write_run(tmp_path / "edge", cells)
    assert check(run, base, "--tol-ap", "0.5") == 0
    assert check(run, base, "--tol-ap", "0.25") == 1


def test_drop_moves_regression_and_improvement(base, tmp_path, capsys):
    cells = summary()
    cells[1]["attack_effect"]["drop"]["Car"]["bev"]["R40"]["moderate"] = 19.0  # larger drop: worse
    cells[1]["attack_effect"]["drop"]["Car"]["3d"]["R40"]["moderate"] = 10.0  # smaller drop: better
    run = write_run(tmp_path / "drop", cells)
    assert check(run, base, "--tol-drop", "1.5") == 1
    lines = capsys.readouterr().out.splitlines()
    assert next(x for x in lines if "BEV drop" in x).split()[-5:] == ["16.00", "19.00", "+3.00", "1.50", "regression"]
    assert next(x for x in lines if "3D drop" in x).split()[-5:] == ["12.00", "10.00", "-2.00", "1.50", "improvement"]
    # the drops' own tolerance: 3.0 covers both moves
    assert check(run, base, "--tol-drop", "3") == 0


def test_improvement_fails_unless_allowed(base, tmp_path, capsys):
    cells = summary()
    cells[0]["metrics"]["Car"]["bev"]["R40"]["easy"] = 85.0
    run = write_run(tmp_path / "better", cells)
    assert check(run, base) == 1
    assert "the baseline is stale" in capsys.readouterr().out
    assert check(run, base, "--allow-improvements") == 0
    out = capsys.readouterr().out
    assert "improvement (allowed)" in out and "except 1 allowed improvement(s)" in out


def test_missing_extra_and_changed_cells_fail(base, tmp_path, capsys):
    cells = summary()
    extra = cell("other", "detector", (1.0, 1.0, 1.0), drop=(0.0, 0.0))
    run = write_run(tmp_path / "shape", [cells[0], cells[2], extra])
    assert check(run, base) == 1
    out = capsys.readouterr().out
    assert "problem: cell v+adv+detector is in the baseline but not in the run" in out
    assert "problem: cell v+other+detector is in the run but not in the baseline" in out
    failed = summary()
    failed[1] = cell("adv", "detector", None, status="error")
    assert check(write_run(tmp_path / "err", failed), base) == 1
    assert "problem: cell v+adv+detector is error (baseline: ok): it failed" in capsys.readouterr().out


def test_other_dataset_or_protocol_fails_other_root_does_not(base, tmp_path, capsys):
    moved = summary()
    for c in moved:
        c["dataset"]["root"] = "/elsewhere"
    assert check(write_run(tmp_path / "root", moved), base) == 0
    assert "note: dataset root /elsewhere (baseline: /data)" in capsys.readouterr().out
    other = summary()
    for c in other:
        c["dataset"]["sha256"] = "cd" * 32
        c["dataset"]["frames"] = 9
    assert check(write_run(tmp_path / "data", other), base) == 1
    out = capsys.readouterr().out
    assert "is not comparable with" in out and ": another dataset\n" in out
    assert "  dataset frames: baseline 10, run 9\n" in out
    assert f"  dataset sha256: baseline {'ab' * 8}..., run {'cd' * 8}...\n" in out
    seeded = summary()
    for c in seeded:
        c["provenance"]["seed"] = 3
    assert check(write_run(tmp_path / "seed", seeded), base) == 1
    out = capsys.readouterr().out
    assert ": another evaluation protocol\n" in out and "  protocol seed: baseline 0, run 3\n" in out


def test_compare_counts_match_a_brute_force_over_the_values(base, tmp_path):
    """Every (cell, value) pair moved by a distinct amount: exactly those past tolerance are reported."""
    cells = summary()
    shifts = {}
    k = 0
    for i in (0, 1):
        for m in ("bev", "3d"):
            for d in DIFFS:
                k += 1
                delta = 0.25 * k * (-1) ** k  # 0.25 .. 3.0 alternating signs
                cells[i]["metrics"]["Car"][m]["R40"][d] += delta
                shifts[(i, m, d)] = delta
    path = write_run(tmp_path / "many", cells) / "summary.json"
    for tol in (0.0, 0.5, 1.3, 2.9, 3.0):
        report = compare(read_baseline(base), read_run(path.parent)[1], path, tol_ap=tol, tol_drop=100.0)
        assert len(report.moves) == sum(abs(s) > tol for s in shifts.values())
        for move in report.moves:
            assert abs(move.delta) > tol
            assert move.verdict == ("improvement" if move.delta > 0 else "regression")


def test_bad_input_exits_2_naming_file_and_field(base, tmp_path, capsys):
    assert check(tmp_path / "nowhere", base) == 2
    assert "nowhere: run directory not found" in capsys.readouterr().err
    run = write_run(tmp_path / "ok", summary())
    assert check(run, tmp_path / "missing.json") == 2
    assert "missing.json: file not found" in capsys.readouterr().err
    data = json.loads(base.read_text())
    for mutate, field in [(lambda d: d.update(format="x"), "$.format"),
                          (lambda d: d.update(version=2), "$.version"),
                          (lambda d: d["cells"][0]["ap"]["bev"].update(easy="80"), "$.cells[0].ap.bev.easy"),
                          (lambda d: d["cells"][1].pop("drop_moderate"), "$.cells[1].drop_moderate"),
                          (lambda d: d["dataset"].pop("sha256"), "$.dataset.sha256"),
                          (lambda d: d["cells"].append(copy.deepcopy(d["cells"][0])), "$.cells[3]")]:
        broken = copy.deepcopy(data)
        mutate(broken)
        path = tmp_path / "broken.json"
        path.write_text(json.dumps(broken))
        assert check(run, path) == 2
        err = capsys.readouterr().err
        assert f"broken.json: field '{field}'" in err, err
    (run / "summary.json").write_text('[{"victim": 1}]')
    assert check(run, base) == 2
    assert "summary.json: field '$[0]'" in capsys.readouterr().err
    with pytest.raises(DataFormatError, match="not valid JSON"):
        (tmp_path / "bad.json").write_text("{")
        read_baseline(tmp_path / "bad.json")


def test_negative_tolerance_is_a_usage_error(base, tmp_path):
    with pytest.raises(SystemExit) as exc:
        check(write_run(tmp_path / "r", summary()), base, "--tol-ap", "-1")
    assert exc.value.code == 2


def test_baseline_of_a_run_with_failed_cells_is_refused(tmp_path, capsys):
    cells = summary()
    cells[1] = cell("adv", "detector", None, status="error")
    run = write_run(tmp_path / "failed", cells)
    assert main(["check", str(run), "--write-baseline", str(tmp_path / "b.json")]) == 2
    assert "v+adv+detector failed; a baseline records finished cells only" in capsys.readouterr().err
    assert not (tmp_path / "b.json").exists()


def test_baseline_from_run_accepts_the_summary_file_itself(tmp_path):
    run = write_run(tmp_path / "r", summary())
    assert baseline_from_run(run / "summary.json")["cells"] == baseline_from_run(run)["cells"]
