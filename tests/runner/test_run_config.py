"""Run files: ``run --print-config`` writes a run's configuration as TOML (the keys of its provenance),
``run --config FILE`` replays it (byte-identical result files), ``run --config-from RUN_DIR`` takes it from
a finished run; command-line options override the file; a bad file is refused in one line naming the file,
the line and the key, before anything is written.

The run files are read back here with ``tomllib`` and compared with the provenance read from
``summary.json`` with ``json``; result files are compared byte by byte.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from robustbench3d.cli import main
from robustbench3d.runner import RunConfig

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

VICTIM = "fpointnet-v1-lite"
BASE = ["--victims", VICTIM, "--attacks", "none,benign-sphere", "--proposals", "gt", "--max-frames", "2",
        "--bootstrap", "20", "--seed", "3"]
QUIET = ["--jobs", "1", "--no-progress"]


@pytest.fixture(scope="module")
def dataset(shared_split) -> Path:
    """Three generated frames, all in the val split."""
    return shared_split(3, seed=5, val_fraction=1.0)


def print_config(capsys, *argv: str) -> str:
    capsys.readouterr()
    assert main(["run", *argv, "--print-config"]) == 0
    return capsys.readouterr().out


def result_files(out: Path) -> dict[str, bytes]:
    """results.csv, seed_table.md and every cell's result files, by path."""
    files = [out / "results.csv", out / "seed_table.md", *sorted(out.glob("cells/*/data/*"))]
    return {str(p.relative_to(out)): p.read_bytes() for p in files}


@pytest.fixture(scope="module")
def original(dataset, tmp_path_factory) -> tuple[Path, str]:
    """A run made from the command line, and the run file --print-config printed for it first."""
    import contextlib
    import io

    root = tmp_path_factory.mktemp("original")
    out = root / "a"
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        assert main(["run", *BASE, "--data", str(dataset), "--out", str(out), *QUIET, "--print-config"]) == 0
    assert not out.exists()  # --print-config runs nothing
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["run", *BASE, "--data", str(dataset), "--out", str(out), *QUIET]) == 0
    return out, text.getvalue()


def test_run_keys_are_the_provenance_keys(original):
    out, text = original
    from robustbench3d.runner.runfile import RUN_KEYS

    config = RunConfig(victims=("v",), attacks=("none",), proposals=("gt",), out=Path("x"))
    assert list(RUN_KEYS) == list(config.as_dict())
    recorded = json.loads((out / "summary.json").read_text())[0]["provenance"]["run"]
    assert tomllib.loads(text) == recorded  # data and max_frames are set here: no null to spell


def test_print_config_then_config_replays_byte_identical_results(original, tmp_path, capsys):
    out, text = original
    run_file = tmp_path / "run.toml"
    run_file.write_text(text)
    replay = tmp_path / "b"
    assert main(["run", "--config", str(run_file), "--out", str(replay), *QUIET]) == 0
    first, second = result_files(out), result_files(replay)
    assert len(first) == 2 + 2 * 2  # results.csv, seed_table.md, 2 cells x 2 frames
    assert first == second


def test_config_from_a_finished_run_gives_its_run_file(original, capsys):
    out, text = original
    assert tomllib.loads(print_config(capsys, "--config-from", str(out))) == tomllib.loads(text)


def test_command_line_options_override_the_file(dataset, tmp_path, capsys):
    run_file = tmp_path / "run.toml"
    run_file.write_text(f'victims = ["{VICTIM}"]\nattacks = ["none", "benign-sphere"]\nout = "{tmp_path / "x"}"\n'
                        f'data = "{dataset}"\nseed = 1\nbatch_size = 2\nmax_frames = 3\n'
                        '[attack_args.benign-sphere]\nradius = 0.3\ncolor = "red"\n')
    got = tomllib.loads(print_config(capsys, "--config", str(run_file), "--seed", "5", "--max-frames", "1",
                                     "--attack-arg", "benign-sphere:color=blue"))
    assert got["seed"] == 5 and got["max_frames"] == 1  # given: the command line's
    assert got["batch_size"] == 2 and got["victims"] == [VICTIM]  # not given: the file's
    assert got["attack_args"] == {"benign-sphere": {"radius": 0.3, "color": "blue"}}  # key by key
    assert got["proposals"] == ["detector"] and got["bootstrap"] == 1000  # in neither: run's defaults
    assert tomllib.loads(print_config(capsys, "--config", str(run_file), "--full"))["max_frames"] == "all"
    assert not (tmp_path / "x").exists()


def test_max_frames_all_and_missing(tmp_path, capsys):
    run_file = tmp_path / "run.toml"
    run_file.write_text(f'victims = ["{VICTIM}"]\nout = "{tmp_path / "x"}"\nmax_frames = "all"\n')
    assert tomllib.loads(print_config(capsys, "--config", str(run_file)))["max_frames"] == "all"
    run_file.write_text(f'victims = ["{VICTIM}"]\nout = "{tmp_path / "x"}"\n')  # the embedded val split
    from robustbench3d.runner.config import DEFAULT_VAL_FRAMES

    got = tomllib.loads(print_config(capsys, "--config", str(run_file)))
    assert got["max_frames"] == DEFAULT_VAL_FRAMES and "data" not in got


@pytest.mark.parametrize(("text", "line", "words"), [
    ('victims = ["a"]\nout = "x"\nseed = [\n', 3, ["not valid TOML", "end of document"]),
    ('victims = ["a"]\nseed = 1x\nout = "x"\n', 2, ["not valid TOML", "column"]),
    ('victims = ["a"]\nout = "x"\n\njobs = 4\n', 4, ["field 'jobs'", "unknown key", "--jobs"]),
    ('victims = "a"\nout = "x"\n', 1, ["field 'victims'", "list of names"]),
    ('victims = ["a"]\nout = "x"\nseed = -1\n', 3, ["field 'seed'", "0..4294967295"]),
    ('victims = ["a"]\nout = "x"\nbootstrap = 5\n', 3, ["field 'bootstrap'", "10..100000"]),
    ('victims = ["a"]\nout = "x"\nmax_frames = "most"\n', 3, ["field 'max_frames'", '"all"']),
    ('victims = ["a"]\nout = "x"\nclasses = ["Truck"]\n', 3, ["field 'classes'", "Car"]),
    ('victims = ["a"]\nout = "x"\n[victim_args]\na = 1\n', 3, ["field 'victim_args'", "tables"]),
])
def test_a_bad_run_file_is_refused_in_one_line(tmp_path, capsys, text, line, words):
    run_file = tmp_path / "bad.toml"
    run_file.write_text(text)
    capsys.readouterr()
    assert main(["run", "--config", str(run_file), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"robustbench3d: error: {run_file}:{line}: ")
    assert all(w in err[0] for w in words), err[0]
    assert not (tmp_path / "out").exists()


def test_a_missing_run_file_and_missing_settings_are_refused(tmp_path, capsys):
    assert main(["run", "--config", str(tmp_path / "none.toml"), "--out", str(tmp_path / "o")]) == 2
    assert f"{tmp_path / 'none.toml'}: file not found" in capsys.readouterr().err
    assert main(["run", "--out", str(tmp_path / "o")]) == 2
    assert "--victims is required" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse: --config and --config-from exclude each other
        main(["run", "--config", str(tmp_path / "a.toml"), "--config-from", str(tmp_path)])
    assert not (tmp_path / "o").exists()


def test_a_null_factory_argument_cannot_be_printed(tmp_path, capsys):
    assert main(["run", "--victims", VICTIM, "--out", str(tmp_path / "o"), "--victim-arg", f"{VICTIM}:weights=null",
                 "--print-config"]) == 2
    assert "victim_args.fpointnet-v1-lite.weights is null" in capsys.readouterr().err


def test_config_from_picks_the_run_whose_grid_covers_every_cell(original, tmp_path, capsys):
    out, _ = original
    summary = json.loads((out / "summary.json").read_text())
    narrow = {**summary[0]["provenance"]["run"], "attacks": ["benign-sphere"], "seed": 9}  # misses the clean cell
    summary[1]["provenance"] = {**summary[1]["provenance"], "run": narrow, "finished": "2999-01-01T00:00:00Z"}
    copy = tmp_path / "copy"
    copy.mkdir()
    (copy / "summary.json").write_text(json.dumps(summary))
    assert tomllib.loads(print_config(capsys, "--config-from", str(copy)))["seed"] == 3  # the covering one
    summary[0]["provenance"] = {**summary[0]["provenance"], "run": narrow}
    (copy / "summary.json").write_text(json.dumps(summary))
    assert main(["run", "--config-from", str(copy), "--print-config"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{copy / 'summary.json'}: no recorded run configuration" in err[0]
