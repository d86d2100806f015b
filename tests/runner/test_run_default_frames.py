"""``run``'s frames: a first-N slice of the embedded val split by default, ``--full`` for the whole
split, ``--max-frames`` for another slice; the line printed at the start says which."""

from __future__ import annotations

import pytest

from robustbench3d.cli import main
from robustbench3d.commands.run import frames_line
from robustbench3d.datasets import EMBEDDED
from robustbench3d.errors import RobustBenchError
from robustbench3d.runner.config import DEFAULT_VAL_FRAMES, default_max_frames
from robustbench3d.synth.writer import in_val


def test_the_default_is_a_slice_of_the_embedded_val_split_only():
    assert default_max_frames(None, False, None, "val") == DEFAULT_VAL_FRAMES
    assert default_max_frames(None, True, None, "val") is None  # --full
    assert default_max_frames(40, False, None, "val") == 40
    assert default_max_frames(None, False, "/data/kitti", "val") is None  # a --data dataset: the whole split
    assert default_max_frames(None, False, None, "train") is None
    with pytest.raises(RobustBenchError, match="--full and --max-frames exclude each other"):
        default_max_frames(5, True, None, "val")


def test_the_printed_line_names_the_frames_and_the_full_count():
    val = [i for i in range(EMBEDDED.frames) if in_val(EMBEDDED.seed, i, EMBEDDED.val_fraction)]  # by hand
    n = len(val)
    last = f"{val[DEFAULT_VAL_FRAMES - 1]:06d}"
    def line(requested, full, data, split="val"):  # as run prints it: the run's max_frames, then the flags
        return frames_line(default_max_frames(requested, full, data, split), requested, full, data, split)

    assert line(None, False, None) == (
        f"frames: the first {DEFAULT_VAL_FRAMES} of the {n} frames of the embedded val split, 000000..{last} "
        f"(the quick default, runner.config.DEFAULT_VAL_FRAMES); --full runs all {n}")
    assert line(None, True, None) == f"frames: all {n} frames of the embedded val split (--full)"
    assert line(3, False, None) == (f"frames: the first 3 of the {n} frames of the embedded val "
                                    f"split, 000000..{val[2]:06d} (--max-frames); --full runs all {n}")
    assert line(5000, False, None) == f"frames: all {n} frames of the embedded val split"
    assert line(None, False, "/d") == "frames: every frame of split val of /d"
    assert line(7, False, "/d") == "frames: the first 7 of split val of /d (--max-frames)"
    # the line describes the max_frames it is given (it no longer recomputes it)
    assert frames_line(4, None, False, None, "val") == (
        f"frames: the first 4 of the {n} frames of the embedded val split, 000000..{val[3]:06d} "
        f"(the quick default, runner.config.DEFAULT_VAL_FRAMES); --full runs all {n}")


def test_full_with_max_frames_is_refused_with_exit_2(tmp_path, capsys):
    assert main(["run", "--victims", "fpointnet-v1-lite", "--full", "--max-frames", "3", "--out",
                 str(tmp_path / "run"), "--no-progress"]) == 2
    assert "--full and --max-frames exclude each other" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()
