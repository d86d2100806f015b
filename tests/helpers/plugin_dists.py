"""Fake installed distributions for the plugin tests: entry points that the registries discover once the
directory holding them is on ``sys.path`` (or ``PYTHONPATH`` of a child process)."""

from __future__ import annotations

from pathlib import Path


def write_dist(root: Path, dist: str, version: str, entry_points: dict[str, str]) -> None:
    """A minimal installed distribution with ``robustbench3d.victims`` entry points under ``root``."""
    meta = root / f"{dist.replace('-', '_')}-{version}.dist-info"
    meta.mkdir(parents=True)
    (meta / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: {version}\n")
    lines = ["[robustbench3d.victims]"] + [f"{k} = {v}" for k, v in entry_points.items()]
    (meta / "entry_points.txt").write_text("\n".join(lines) + "\n")
