"""``run``'s terminal output: messages through the ``robustbench3d`` logger written with ``tqdm.write``
(never into a progress bar), ``-q``/``-v`` levels, and the result table folded to the terminal width by
``rich`` (every number kept) while a file or pipe gets the plain table.

Numbers are checked against ``summary.json`` read here with ``json``; stderr and stdout as captured.
"""

from __future__ import annotations

import io
import json
import logging
import re
import shutil
import sys
from collections import Counter
from functools import partial
from pathlib import Path

import pytest
import tqdm as tqdm_module

from robustbench3d.cli import main
from robustbench3d.logs import LineLog, cli_logging
from robustbench3d.runner.table import fold_table, summary_table
from robustbench3d.seed_table import seed_table_text

VICTIM = "fpointnet-v1-lite"
NUMBER = re.compile(r"[-+]?\d+\.\d+")


@pytest.fixture(scope="module")
def dataset(shared_split) -> Path:
    """Three generated frames, all in the val split."""
    return shared_split(3, seed=5, val_fraction=1.0)


def argv(dataset: Path, out: Path, *extra: str) -> list[str]:
    return ["run", "--victims", VICTIM, "--attacks", "none,benign-sphere", "--proposals", "gt", "--data", str(dataset),
            "--max-frames", "2", "--bootstrap", "20", "--out", str(out), "--jobs", "1", *extra]


@pytest.fixture(scope="module")
def finished(dataset, tmp_path_factory) -> Path:
    """A finished run (made with progress bars off, output discarded)."""
    import contextlib

    out = tmp_path_factory.mktemp("run") / "r"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert main(argv(dataset, out, "--no-progress")) == 0
    return out


def cells(out: Path) -> list[dict]:
    return json.loads((out / "summary.json").read_text())


def expected_numbers(summary: list[dict]) -> list[str]:
    """Every Car BEV/3D AP (two decimals) and interval bound (one decimal) of the summary, from its JSON."""
    found = []
    for cell in summary:
        for metric in ("bev", "3d"):
            for recall in ("R40", "R11"):
                for difficulty in ("easy", "moderate", "hard"):
                    found.append(f"{cell['metrics']['Car'][metric][recall][difficulty]:.2f}")
                    found += [f"{v:.1f}" for v in cell["metrics_ci"]["Car"][metric][recall][difficulty]]
    return found


# --- messages through tqdm.write -----------------------------------------------------------------------

def test_the_handler_writes_through_tqdm_write(monkeypatch):
    written = []
    monkeypatch.setattr(tqdm_module.tqdm, "write", classmethod(lambda cls, s, file=None, end="\n", nolock=False:
                                                              written.append((s, file))))
    stream = io.StringIO()
    with cli_logging(0, stream):
        logging.getLogger("robustbench3d.runner").info("a cell line")
        logging.getLogger("robustbench3d.runner").debug("a detail")  # below INFO: not written
    assert written == [("a cell line", stream)]
    assert stream.getvalue() == ""  # nothing written around tqdm


def test_a_line_clears_an_open_bar_and_never_joins_it():
    stream = io.StringIO()
    bar = tqdm_module.tqdm(total=4, file=stream, ncols=60, mininterval=0)
    bar.update(1)
    with cli_logging(0, stream):
        logging.getLogger("robustbench3d.runner").warning("[1/2] a cell: ok")
    bar.update(1)
    bar.close()
    text = stream.getvalue()
    before, line, after = text.partition("[1/2] a cell: ok")
    assert line and after.startswith("\n")  # the line ends its own row
    assert before.endswith("\r") and before.rsplit("\r", 2)[-2].strip() == ""  # the bar's row blanked first
    assert after.startswith("\n\r") and "2/4" in after  # and the bar redrawn below it


def test_cli_lines_go_through_tqdm_write(dataset, tmp_path, monkeypatch, capsys):
    written = []
    real = tqdm_module.tqdm.write

    def record(cls, s, file=None, end="\n", nolock=False):
        written.append(s)
        real(s, file=file, end=end, nolock=nolock)

    monkeypatch.setattr(tqdm_module.tqdm, "write", classmethod(record))
    assert main(argv(dataset, tmp_path / "r")) == 0
    assert any(s.startswith("[1/2] fpointnet-v1-lite / none / gt: ok") for s in written)
    assert any(s.startswith("frames: the first 2 of split val") for s in written)


def test_library_callers_keep_their_print_fn(caplog):
    lines = []
    log = LineLog(logging.getLogger("robustbench3d.runner"), lines.append)
    with caplog.at_level(logging.DEBUG, logger="robustbench3d"):
        log("info")
        log.warning("warning")
        log.debug("detail")
    assert lines == ["info", "warning"]  # details only to the logger
    assert [r.getMessage() for r in caplog.records] == ["detail"]


# --- -q / -v ------------------------------------------------------------------------------------------

def test_quiet_shows_warnings_and_the_tables_only(dataset, tmp_path, capsys):
    out = tmp_path / "r"
    assert main(argv(dataset, out, "--no-progress")) == 0
    err = capsys.readouterr().err
    assert "[1/2] fpointnet-v1-lite / none / gt: ok" in err and "frames: the first 2" in err
    assert "fingerprint" not in err  # details need -v
    # a replaced cell is a warning: shown with -q; the per-cell lines and bars are not
    assert main(argv(dataset, out, "-q", "--force", "--max-frames", "1")) == 0  # the last --max-frames counts
    captured = capsys.readouterr()
    assert "replacing finished cell fpointnet-v1-lite+none+gt (--force)" in captured.err
    assert "[1/2]" not in captured.err and "frames:" not in captured.err and "frame/s" not in captured.err
    assert summary_table(cells(out)) in captured.out  # the result table as always


def test_verbose_adds_the_details(dataset, tmp_path, capsys):
    out = tmp_path / "r"
    assert main(argv(dataset, out, "--no-progress", "-v")) == 0
    err = capsys.readouterr().err
    for cell in cells(out):  # each cell's fingerprint, as recorded in its cell.json
        key = f"{cell['victim']} / {cell['attack']} / {cell['proposals']}"
        assert f"{key}: fingerprint {cell['provenance']['fingerprint'][:12]}" in err
    assert "[1/2] fpointnet-v1-lite / none / gt: ok" in err


def test_verbose_shows_each_shard(dataset, tmp_path, capsys):
    out = tmp_path / "r"
    assert main(argv(dataset, out, "--no-progress", "-v", "--jobs", "2")) == 0  # the last --jobs counts
    err = capsys.readouterr().err
    assert "shard 1/1 of fpointnet-v1-lite+none+gt: 2 frame(s), ok" in err
    with pytest.raises(SystemExit):  # -q and -v exclude each other
        main(argv(dataset, out, "-q", "-v"))


# --- the table --------------------------------------------------------------------------------------------

def test_a_file_or_pipe_gets_the_plain_table(finished, dataset, capsys):
    capsys.readouterr()
    assert main(argv(dataset, finished, "--no-progress")) == 0  # every cell reused
    printed = capsys.readouterr().out
    summary = cells(finished)
    assert printed.startswith(summary_table(summary) + "\n")
    assert seed_table_text(summary) in printed


def test_the_table_folds_to_a_narrow_width_keeping_every_number(finished):
    summary = cells(finished)
    plain = summary_table(summary)
    assert max(len(line) for line in plain.splitlines()) > 200  # today's table: far wider than a terminal
    folded = summary_table(summary, width=80)
    assert max(len(line) for line in folded.splitlines()) <= 80
    assert Counter(NUMBER.findall(folded)) == Counter(NUMBER.findall(plain))
    assert not Counter(expected_numbers(summary)) - Counter(NUMBER.findall(folded))
    assert folded.count("victim / attack / proposals") > 1  # column groups moved to blocks below
    wide = summary_table(summary, width=400)
    assert wide.count("victim / attack / proposals") == 1  # a wide terminal: one table
    assert Counter(NUMBER.findall(wide)) == Counter(NUMBER.findall(plain))


def test_the_seed_table_folds_too(finished):
    summary = cells(finished)
    from robustbench3d.runner.table import fit_lines

    plain = seed_table_text(summary)
    folded = fit_lines(seed_table_text(summary, table=partial(fold_table, width=72, key=2)), 72)
    assert max(len(line) for line in folded.splitlines()) <= 72
    assert Counter(NUMBER.findall(folded)) == Counter(NUMBER.findall(plain))


def test_a_terminal_gets_the_folded_table(finished, dataset, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "90")
    assert shutil.get_terminal_size().columns == 90
    capsys.readouterr()
    monkeypatch.setattr(sys.stdout, "isatty", lambda: True)
    assert main(argv(dataset, finished, "--no-progress", "-q")) == 0
    printed = capsys.readouterr().out
    assert max(len(line) for line in printed.splitlines()) <= 90
    assert not Counter(expected_numbers(cells(finished))) - Counter(NUMBER.findall(printed))
