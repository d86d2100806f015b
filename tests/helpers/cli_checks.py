"""A refused command, checked the one way the trust tests check it: exit status 2, one ``robustbench3d: error:``
line naming what is wrong, no traceback, and nothing under a watched directory written, replaced or left behind."""

from __future__ import annotations

from pathlib import Path

from robustbench3d.cli import main


def snapshot(root: Path) -> dict[str, bytes | None]:
    """Every path under ``root`` (hidden ones too) with its bytes (None for directories and links)."""
    return {str(p.relative_to(root)): None if p.is_dir() or p.is_symlink() else p.read_bytes()
            for p in sorted(root.rglob("*"))}


def fails_cleanly(watch: Path, capsys, argv: list[str], *names: str) -> str:
    """Run the CLI on ``argv``; assert exit 2, one error line naming every ``names``, no traceback and ``watch``
    unchanged; return the line."""
    before = snapshot(watch)
    rc = main(argv)
    captured = capsys.readouterr()
    assert rc == 2, captured.err
    lines = [ln for ln in captured.err.splitlines() if ln.startswith("robustbench3d: error: ")]
    assert len(lines) == 1, captured.err
    assert "Traceback" not in captured.err + captured.out
    for name in names:
        assert name in lines[0], lines[0]
    assert snapshot(watch) == before, "the refused command changed files or left files behind"
    return lines[0]
