"""``robustbench3d eval`` and directory loading: table, JSON layout, frame-set rules, clear errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from robustbench3d.cli import main
from robustbench3d.errors import DataFormatError
from robustbench3d.eval.kitti_eval import evaluate_dirs
from robustbench3d.eval.loading import _slow_table, read_table

CAR = "Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59"
VAN = "Van 0.00 1 1.50 10.00 150.00 120.00 230.00 2.10 1.90 5.00 -12.00 1.80 15.00 1.00"
DONTCARE = "DontCare -1 -1 -10 700.00 160.00 760.00 200.00 -1 -1 -1 -1000 -1000 -1000 -10"


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def make_dirs(root: Path, frames: int = 3) -> tuple[Path, Path]:
    for i in range(frames):
        write(root / "gt" / f"{i:06d}.txt", f"{CAR}\n{VAN}\n{DONTCARE}\n")
        if i != 1:  # frame 000001 has no result file: no detections
            write(root / "pred" / f"{i:06d}.txt", f"{CAR} 0.9\n")
    return root / "gt", root / "pred"


def test_table_and_json_layout(tmp_path: Path, capsys) -> None:
    gt, pred = make_dirs(tmp_path)
    out = tmp_path / "res" / "ap.json"
    assert main(["eval", "--gt", str(gt), "--pred", str(pred), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    for label in ("Car 2D AP@0.70 R40", "Car 2D AP@0.70 R11", "Car AOS@0.70 R40", "Car BEV AP@0.70 R40",
                  "Car 3D AP@0.70 R11"):
        assert label in text
    assert "easy" in text and "moderate" in text and "hard" in text
    result = json.loads(out.read_text())
    assert set(result) == {"Car", "meta"}
    assert set(result["Car"]) == {"2d", "aos", "bev", "3d"}
    for by_recall in result["Car"].values():
        assert set(by_recall) == {"R11", "R40"}
        for aps in by_recall.values():
            assert set(aps) == {"easy", "moderate", "hard"}
            assert all(0.0 <= v <= 100.0 for v in aps.values())
    meta = result["meta"]
    assert meta["frames"] == 3 and meta["frames_without_results"] == 1
    assert meta["gt_objects"] == {"Car": 3, "Van": 3, "DontCare": 3}
    assert meta["detections"] == {"Car": 2}
    assert meta["min_overlap"]["Car"] == {"2d": 0.7, "aos": 0.7, "bev": 0.7, "3d": 0.7}
    assert meta["difficulty"]["min_height_px"] == [40, 25, 25]
    assert meta["difficulty"]["max_truncation"] == [0.15, 0.3, 0.5]
    assert len(meta["recall_points"]["R40"]) == 40 and meta["recall_points"]["R11"][-1] == 1.0
    assert meta["version"] and meta["ap_unit"] == "percent"
    # Car is 26.79 px high: moderate/hard only, 3 counted, 2 found -> 2 thresholds -> R40 = 1/40.
    assert result["Car"]["2d"]["R40"] == pytest.approx({"easy": 0.0, "moderate": 2.5, "hard": 2.5})
    assert not list(out.parent.glob(".*tmp"))  # written atomically, no temp file left


def test_missing_result_file_equals_empty_file(tmp_path: Path) -> None:
    gt, pred = make_dirs(tmp_path)
    a = evaluate_dirs(gt, pred)
    write(pred / "000001.txt", "")
    b = evaluate_dirs(gt, pred)
    assert a["Car"] == b["Car"] and b["meta"]["frames_without_results"] == 0


def test_result_files_outside_the_frame_set_are_ignored_and_reported(tmp_path: Path, capsys) -> None:
    gt, pred = make_dirs(tmp_path)
    write(pred / "000777.txt", f"{CAR} 0.99\n")
    split = write(tmp_path / "val.txt", "000000\n000002\n")
    result = evaluate_dirs(gt, pred, split)
    assert result["meta"]["frames"] == 2
    assert result["meta"]["ignored_result_files"] == {"count": 1, "examples": ["000777"]}
    assert main(["eval", "--gt", str(gt), "--pred", str(pred)]) == 0
    assert "not in the frame set and were ignored (e.g. 000777.txt)" in capsys.readouterr().out



def test_directory_meta_classes_metrics_and_ignored_examples(tmp_path: Path) -> None:
    """The directories and split are recorded as given; classes and metrics reach the evaluation (Pedestrian
    asked for although only cars are detected; BEV alone); at most 10 ignored result files are named."""
    gt, pred = make_dirs(tmp_path)
    for i in range(11):
        write(pred / f"{100 + i:06d}.txt", f"{CAR} 0.5\n")
    result = evaluate_dirs(gt, pred, classes=("Pedestrian",), metrics=("bev",))
    meta = result["meta"]
    assert meta["gt_dir"] == str(gt) and meta["pred_dir"] == str(pred) and meta["split"] is None
    assert meta["classes"] == ["Pedestrian"] and meta["metrics"] == ["bev"] and set(result) == {"Pedestrian", "meta"}
    assert set(result["Pedestrian"]) == {"bev"}
    assert meta["ignored_result_files"] == {"count": 11, "examples": [f"{100 + i:06d}" for i in range(10)]}
    split = write(tmp_path / "val.txt", "000000\n000002\n")
    meta = evaluate_dirs(gt, pred, split)["meta"]
    assert meta["split"] == str(split) and meta["classes"] == ["Car"] and meta["metrics"] == ["2d", "aos", "bev", "3d"]


def test_devkit_result_layout_with_data_subdirectory(tmp_path: Path) -> None:
    gt, pred = make_dirs(tmp_path)
    pred.rename(tmp_path / "data")
    (tmp_path / "sha").mkdir()
    (tmp_path / "data").rename(tmp_path / "sha" / "data")
    result = evaluate_dirs(gt, tmp_path / "sha")
    assert result["meta"]["pred_dir"].endswith("data") and result["meta"]["detections"] == {"Car": 2}
    # result files next to a data/ subdirectory: the files are the results
    gt2, pred2 = make_dirs(tmp_path / "two")
    (pred2 / "data").mkdir()
    assert evaluate_dirs(gt2, pred2)["meta"]["pred_dir"] == str(pred2)


@pytest.mark.parametrize(("setup", "message"), [
    ("no_gt_dir", "ground-truth label directory not found"),
    ("no_pred_dir", "result directory not found"),
    ("empty_gt", "no label files"),
    ("split_without_gt", "000009.txt: ground-truth label file not found (frame listed in"),
    ("bad_split", "val.txt:2: field 'frame_id'"),
    ("bad_result", "000002.txt:1: field 'y': expected a number, got 'abc'"),
    ("short_gt_line", "000000.txt:2: expected 15 columns, got 14"),
    ("unknown_type", "000000.txt:1: field 'type': unknown object type 'Bus'"),
    ("nan_score", "000000.txt:1: field 'score': expected a finite number"),
])
def test_bad_input_names_file_line_and_field(tmp_path: Path, capsys, setup: str, message: str) -> None:
    gt, pred = make_dirs(tmp_path)
    args = ["eval", "--gt", str(gt), "--pred", str(pred)]
    if setup == "no_gt_dir":
        args[2] = str(tmp_path / "nope")
    elif setup == "no_pred_dir":
        args[4] = str(tmp_path / "nope")
    elif setup == "empty_gt":
        (tmp_path / "empty").mkdir()
        args[2] = str(tmp_path / "empty")
    elif setup == "split_without_gt":
        args += ["--split", str(write(tmp_path / "val.txt", "000000\n000009\n"))]
    elif setup == "bad_split":
        args += ["--split", str(write(tmp_path / "val.txt", "000000\nframe1\n"))]
    elif setup == "bad_result":
        write(pred / "000002.txt", CAR.replace("1.71", "abc") + " 0.5\n")
    elif setup == "short_gt_line":
        write(gt / "000000.txt", CAR + "\n" + CAR.rsplit(" ", 1)[0] + "\n")
    elif setup == "unknown_type":
        write(gt / "000000.txt", CAR.replace("Car", "Bus") + "\n")
    elif setup == "nan_score":
        write(pred / "000000.txt", CAR + " nan\n")
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("robustbench3d: error:") and message in err, err


def test_bad_class_or_metric_option(tmp_path: Path, capsys) -> None:
    gt, pred = make_dirs(tmp_path)
    assert main(["eval", "--gt", str(gt), "--pred", str(pred), "--classes", "Car,Bus"]) == 2
    assert "unknown class 'Bus'" in capsys.readouterr().err
    assert main(["eval", "--gt", str(gt), "--pred", str(pred), "--metrics", "bev,map"]) == 2
    assert "unknown metric 'map'" in capsys.readouterr().err
    assert main(["eval", "--gt", str(gt), "--pred", str(pred), "--metrics", "bev", "--classes", "car"]) == 0
    assert "Car BEV AP@0.70 R40" in capsys.readouterr().out



def test_valid_files_take_the_fast_path_and_equal_the_data_layer(tmp_path: Path, monkeypatch) -> None:
    """Valid ground truth (15 columns) and results (16), with a blank last line and frames without a file,
    are read without the slow per-file reader, into the values written; the slow reader gives the same."""
    import robustbench3d.eval.loading as loading

    gt_file = write(tmp_path / "gt.txt", f"{CAR}\n{VAN}\n{DONTCARE}\n{VAN.replace(' 1 1.50', ' 3 1.50')}\n\n")
    res_file = write(tmp_path / "res.txt", f"{CAR} 0.9\n")
    cases = (([gt_file, None], False), ([None, res_file, None], True))
    slow = [_slow_table(paths, scored) for paths, scored in cases]

    def refuse(paths, scored):
        raise AssertionError("valid files went to the slow path")

    monkeypatch.setattr(loading, "_slow_table", refuse)
    gt, res = (read_table(paths, scored) for paths, scored in cases)
    assert gt.n_frames == 2 and gt.frame.tolist() == [0, 0, 0, 0] and gt.score is None
    assert gt.bbox[:2].tolist() == [[587.01, 173.33, 614.12, 200.12], [10.0, 150.0, 120.0, 230.0]]
    assert gt.occluded.tolist() == [0, 1, -1, 3] and gt.box3d[1].tolist() == [2.1, 1.9, 5.0, -12.0, 1.8, 15.0, 1.0]
    assert res.n_frames == 3 and res.frame.tolist() == [1] and res.score.tolist() == [0.9]
    for fast, ref in ((gt, slow[0]), (res, slow[1])):
        assert fast.n_frames == ref.n_frames
        for field in ("frame", "type", "truncated", "occluded", "alpha", "bbox", "box3d", "score"):
            a, b = getattr(fast, field), getattr(ref, field)
            assert (a is None and b is None) or (a.dtype == b.dtype and np.array_equal(a, b)), field


def test_non_utf8_files_get_the_precise_error(tmp_path: Path) -> None:
    bad = tmp_path / "000000.txt"
    bad.write_bytes(CAR.encode() + b" 0.9\xff\n")
    for scored in (True, False):
        with pytest.raises(DataFormatError, match=r"000000\.txt: not UTF-8 text"):
            read_table([bad], scored)



def test_frame_set_errors_exactly_and_other_entries_ignored(tmp_path: Path) -> None:
    from robustbench3d.eval.loading import frame_ids, load_dirs

    gt, pred = make_dirs(tmp_path)
    (gt / "sub.txt").mkdir()  # a directory named like a label file, and a file of another kind: not frames
    write(gt / "notes.md", "not a label file\n")
    write(pred / "notes.md", "not a result file\n")
    loaded = load_dirs(gt, pred)
    assert loaded.frame_ids == ["000000", "000001", "000002"] and loaded.ignored_result_files == []
    cases = [
        (lambda: frame_ids(gt / "000000.txt"), f"{gt / '000000.txt'}: ground-truth label path is not a directory"),
        (lambda: load_dirs(gt, pred / "000000.txt"), f"{pred / '000000.txt'}: result path is not a directory"),
        (lambda: frame_ids(gt, tmp_path / "none.txt"), f"{tmp_path / 'none.txt'}: split file not found"),
        (lambda: frame_ids(gt, write(tmp_path / "empty.txt", "")),
         f"{tmp_path / 'empty.txt'}: split file lists no frames"),
        (lambda: frame_ids(gt / "sub.txt"), f"{gt / 'sub.txt'}: no label files (*.txt) in the ground-truth directory"),
    ]
    for call, message in cases:
        with pytest.raises(DataFormatError) as err:
            call()
        assert str(err.value) == message


def test_fast_path_rejections_get_the_strict_readers_error(tmp_path: Path) -> None:
    """Rows the fast path must not accept, each alone in a file: occlusion 4 or -2, an impossible GT value,
    and a result file whose lines have 15 and 17 columns (32 tokens, two rows' worth): read as results."""
    occ = CAR.split()
    for value in ("4", "-2"):
        p = write(tmp_path / f"occ{value}.txt", " ".join([*occ[:2], value, *occ[3:]]) + "\n")
        with pytest.raises(DataFormatError, match="field 'occluded'"):
            read_table([p], scored=False)
        r = write(tmp_path / f"res{value}.txt", " ".join([*occ[:2], value, *occ[3:]]) + " 0.5\n")
        with pytest.raises(DataFormatError, match="field 'occluded'"):
            read_table([r], scored=True)
    p = write(tmp_path / "trunc.txt", CAR.replace("Car 0.00", "Car 1.50") + "\n")
    with pytest.raises(DataFormatError, match="field 'truncated'"):
        read_table([p], scored=False)
    p = write(tmp_path / "mixed.txt", f"{CAR}\n{CAR} 0.9 0.8\n")
    with pytest.raises(DataFormatError) as err:
        read_table([p], scored=True)
    assert str(err.value) == f"{p}:1: expected 16 columns, got 15"


def test_fast_reader_equals_the_data_layer(kitti_samples: Path, tmp_path: Path) -> None:
    res = kitti_samples / "results/pointgnn_car_val/data"  # trailing spaces, blank last line, empty file
    labels = sorted((kitti_samples / "training/label_2").glob("*.txt"))
    odd = write(tmp_path / "odd.txt", "Car 0 0 0 1 2 3 4 1 1 1 0 0 9 0\r\n   \n\tVan 0.5 3 1 1 2 3 44 1 1 1 0 0 9 0\n")
    for paths, scored in ((labels, False), ([*sorted(res.glob("*.txt")), None], True), ([odd, None], False)):
        fast, slow = read_table(paths, scored), _slow_table(paths, scored)
        for field in ("frame", "type", "truncated", "occluded", "alpha", "bbox", "box3d", "score"):
            a, b = getattr(fast, field), getattr(slow, field)
            assert (a is None and b is None) or np.array_equal(a, b), field
    assert read_table([odd], False).type.tolist() == [0, 1]


def test_bad_files_fall_back_to_precise_errors(tmp_path: Path) -> None:
    p = write(tmp_path / "x.txt", f"{CAR}\n{CAR} 0.1 extra\n")
    with pytest.raises(DataFormatError, match=r"x.txt:2: expected 15 columns, got 17"):
        read_table([p], scored=False)
    p = write(tmp_path / "y.txt", CAR.replace(" 0 -1.58", " 1.5 -1.58") + "\n")
    with pytest.raises(DataFormatError, match=r"y.txt:1: field 'occluded'"):
        read_table([p], scored=False)



def test_eval_options_by_hand() -> None:
    import argparse

    from robustbench3d.commands.eval import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    options = {a.option_strings[0]: (a.required, a.metavar, a.default, a.help)
               for a in parser._actions if a.option_strings[0] != "-h"}
    assert options == {
        "--gt": (True, "DIR", None, "ground-truth label directory (label_2)"),
        "--pred": (True, "DIR", None, "result directory (16-column files; a frame without a file has no detections)"),
        "--split": (False, "FILE", None, "frame ids to evaluate (default: every GT label file)"),
        "--classes": (False, "LIST", None, "comma-separated subset of Car,Pedestrian,Cyclist (default: every class "
                                            "with a detection, as the devkit; Car if none)"),
        "--metrics": (False, "LIST", "2d,aos,bev,3d", "comma-separated subset of 2d,aos,bev,3d (default: all)"),
        "--json": (False, "PATH", None, "also write the result as JSON (atomically)"),
    }



def test_cli_passes_classes_and_metrics_and_names_the_json_option(tmp_path: Path, capsys) -> None:
    gt, pred = make_dirs(tmp_path)
    assert main(["eval", "--gt", str(gt), "--pred", str(pred), "--classes", " pedestrian, ,", "--metrics", "3d"]) == 0
    out = capsys.readouterr().out
    assert "Pedestrian 3D AP@0.50 R40" in out and "Car" not in out and "BEV" not in out and "2D" not in out
    assert main(["eval", "--gt", str(gt), "--pred", str(pred), "--json", str(tmp_path)]) == 2
    assert f"--json {tmp_path}: is a directory; expected a file name" in capsys.readouterr().err



def test_package_loads_the_evaluator_lazily_by_name() -> None:
    import robustbench3d.eval as package
    from robustbench3d.eval import kitti_eval

    assert package.evaluate is kitti_eval.evaluate and package.evaluate_dirs is kitti_eval.evaluate_dirs
    with pytest.raises(AttributeError, match=r"^module 'robustbench3d\.eval' has no attribute 'ap'$"):
        _ = package.ap


def test_cli_module_imports_no_numpy() -> None:
    code = "import sys, robustbench3d.commands.eval; print('numpy' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_ap_table_and_json_text_by_hand(tmp_path: Path) -> None:
    from robustbench3d.eval.report import ap_table, write_json

    result = {
        "meta": {"classes": ["Car", "Cyclist"], "min_overlap": {"Car": {"3d": 0.7}}, "evaluator": "robustbench3d",
                 "version": "1.0", "frames": 3,
                 "skipped": [{"class": "Cyclist", "metric": "3d", "reason": "no detections"}],
                 "notes": ["first", "second"]},
        "Car": {"3d": {"R40": {"easy": 88.5, "moderate": 7.25, "hard": 100.0},
                       "R11": {"easy": 1000 / 11, "moderate": 100 / 11, "hard": 0.0}}},
    }   # no "Cyclist" entry: its metric was skipped
    assert ap_table(result).split("\n") == [
        "KITTI AP in % (robustbench3d 1.0, devkit semantics), 3 frames",
        " " * 20 + " easy  moderate    hard",                     # column widths 18, 5, 8, 6
        "Car 3D AP@0.70 R40  88.50      7.25  100.00",
        "Car 3D AP@0.70 R11  90.91      9.09    0.00",
        "skipped: Cyclist 3d: no detections",
        "note: first",
        "note: second",
    ]
    del result["meta"]["skipped"], result["meta"]["notes"]
    assert ap_table(result).count("\n") == 3
    write_json(tmp_path / "r.json", {"a": [1, 2]})
    assert (tmp_path / "r.json").read_text() == '{\n  "a": [\n    1,\n    2\n  ]\n}\n'
