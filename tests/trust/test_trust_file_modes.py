"""Output files get the permission bits the umask says (0o666 less the umask), as ``open`` would give
them: a shared result or report directory is readable by colleagues and web servers. Before, the atomic
writer's ``mkstemp`` left every file at 0o600 whatever the umask."""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from robustbench3d.fileio import atomic_write_bytes, atomic_write_text, current_umask, new_file_mode
from robustbench3d.runner import RunConfig, run_benchmark
from robustbench3d.testing import synth_dataset


@contextmanager
def umask(mask: int) -> Iterator[None]:
    old = os.umask(mask)
    try:
        yield
    finally:
        os.umask(old)


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.mark.parametrize("mask", [0o022, 0o027, 0o077, 0o002])
def test_atomic_writes_take_the_umask(tmp_path, mask):
    with umask(mask):
        assert current_umask() == mask and new_file_mode() == 0o666 & ~mask
        atomic_write_text(tmp_path / "a.txt", "x")
        atomic_write_bytes(tmp_path / "sub" / "b.bin", b"x")
        with open(tmp_path / "reference.txt", "w") as f:  # what a plain open gives, the reference
            f.write("x")
    want = mode(tmp_path / "reference.txt")
    assert want == 0o666 & ~mask
    assert mode(tmp_path / "a.txt") == want and mode(tmp_path / "sub" / "b.bin") == want


def test_a_replaced_file_gets_the_umask_too(tmp_path):
    target = tmp_path / "a.txt"
    target.write_text("old")
    target.chmod(0o600)
    with umask(0o022):
        atomic_write_text(target, "new")
    assert target.read_text() == "new" and mode(target) == 0o644


def test_every_file_of_a_run_is_readable_by_the_group_and_others_under_umask_022(tmp_path):
    data = synth_dataset(tmp_path / "synth", 2, seed=3, val_fraction=1.0)
    out = tmp_path / "run"
    with umask(0o022):
        run_benchmark(RunConfig(victims=("fpointnet-v1-lite",), attacks=("none",), proposals=("gt",), out=out,
                                data=data, progress=False), lambda _: None)
    files = [p for p in out.rglob("*") if p.is_file()]
    assert any(p.name == "results.csv" for p in files) and any(p.name == "summary.json" for p in files)
    assert {(p.relative_to(out).as_posix(), mode(p)) for p in files if mode(p) != 0o644} == set()
