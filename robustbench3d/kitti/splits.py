"""Split lists (``ImageSets/{train,val,test}.txt``): one frame id per line."""

from __future__ import annotations

import re
from pathlib import Path

from robustbench3d.errors import DataFormatError
from robustbench3d.fileio import atomic_write_text, read_data_text

_ID = re.compile(r"^\d{6}$")


def read_split(path: str | Path) -> list[str]:
    """Frame ids (6-digit strings) in file order; the final newline is optional."""
    path = Path(path)
    ids: list[str] = []
    seen: set[str] = set()
    text = read_data_text(path)
    for lineno, raw in enumerate(text.split("\n"), start=1):
        tok = raw.strip()
        if not tok:
            continue
        if not _ID.match(tok):
            raise DataFormatError(path, f"expected a 6-digit frame id, got {tok!r}", lineno, "frame_id")
        if tok in seen:
            raise DataFormatError(path, f"frame id {tok} listed twice", lineno, "frame_id")
        seen.add(tok)
        ids.append(tok)
    return ids


def write_split(path: str | Path, ids: list[str]) -> None:
    for i in ids:
        if not _ID.match(i):
            raise ValueError(f"frame id must be 6 digits, got {i!r}")
    atomic_write_text(path, "".join(f"{i}\n" for i in ids))
