"""The written-once rule for ``report --out DIR``.

``report`` writes ``DIR/report_manifest.json`` naming every file it wrote there. It writes into a new or
empty ``DIR``, or into one holding such a manifest, an earlier report: the refresh rule, a report replaces
the files its earlier report wrote (and removes those the new one no longer writes) and prints one line
saying so; other entries are kept. Any other non-empty ``DIR`` (a run directory, a folder of the user's)
is refused unless ``--force``, and so is a file the new report would write that the manifest does not
list; under ``--force`` each such file replaced is named in one line. Refusals come before any file is
written. ``DIR`` may be inside a run directory (``--out RUN/report``).

Standard library only.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from robustbench3d.errors import RobustBenchError

MANIFEST = "report_manifest.json"
WRITTEN_BY = "robustbench3d report"
#: The only names a report writes (its pages and ``figures/*.png``): a manifest listing anything else
#: is not a report's, so a forged one cannot make report replace or remove other files.
_OWN_NAME = re.compile(r"(leaderboard\.(html|md)|figures/[A-Za-z0-9._-]+\.png)")


@dataclass(frozen=True)
class OutDir:
    """``--out DIR`` checked up front: ``earlier`` the files an earlier report there wrote (relative paths)."""

    path: Path
    earlier: tuple[str, ...]
    force: bool
    foreign: bool  # not empty and not an earlier report's (allowed by --force)


def _read_manifest(path: Path) -> tuple[str, ...]:
    """The files a manifest lists; :class:`RobustBenchError` naming what is wrong with it."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise RobustBenchError(f"cannot be read as JSON ({exc})") from None
    files = doc.get("files") if isinstance(doc, dict) else None
    if not isinstance(doc, dict) or doc.get("written_by") != WRITTEN_BY or not isinstance(files, list):
        raise RobustBenchError(f"does not say written_by {WRITTEN_BY!r} with a list of files")
    bad = next((f for f in files if not isinstance(f, str) or not _OWN_NAME.fullmatch(f)), None)
    if bad is not None:
        raise RobustBenchError(f"lists {bad!r}, not a file report writes")
    return tuple(files)


def check_out_dir(path: str | Path, force: bool) -> OutDir:
    """Check ``--out`` before any work: writable, and new, empty or an earlier report's (else ``force``)."""
    from robustbench3d.fileio import check_output_dir

    out = check_output_dir(path, "--out")
    if not out.exists() or not any(out.iterdir()):
        return OutDir(out, (), force, False)
    manifest = out / MANIFEST
    why = f"holds no {MANIFEST}"
    if manifest.is_file() and not manifest.is_symlink():
        try:
            return OutDir(out, _read_manifest(manifest), force, False)
        except RobustBenchError as exc:
            why = f"its {MANIFEST} {exc}"
    if not force:
        raise RobustBenchError(f"--out {out}: is not empty and not an earlier report ({why}); choose a new or empty "
                               "directory, or pass --force to write into it (nothing was written)")
    return OutDir(out, (), force, True)


def plan_writes(out: OutDir, files: Sequence[str]) -> list[str]:
    """Check the files about to be written (relative paths) and return the lines to print; raises before
    anything is written when one exists that no earlier report here wrote and ``--force`` is not given."""
    from robustbench3d.fileio import check_output_file, replacing_note

    targets = [out.path / f for f in files]
    for target in [*targets, out.path / MANIFEST]:
        check_output_file(target, "--out")  # not a directory, a broken link or a special file
    theirs = [t for f, t in zip(files, targets, strict=True) if f not in out.earlier and t.exists()]
    if theirs and not out.force:
        more = f" (and {len(theirs) - 1} more)" if len(theirs) > 1 else ""
        raise RobustBenchError(f"--out {out.path}: {theirs[0]}{more} exists and was not written by an earlier report "
                               "here; pass --force to replace it (nothing was written)")
    lines = [note for t in theirs if (note := replacing_note(t))]
    kept = _other_entries(out.path, {*files, *out.earlier}) if out.path.is_dir() else 0
    if out.earlier:
        gone = [f for f in out.earlier if f not in files and (out.path / f).is_file()]
        lines.append(f"replacing the report written earlier in {out.path} ({len(out.earlier)} files listed in "
                     f"{MANIFEST}; {len(gone)} no longer written, removed; {_entries(kept)} kept)")
    elif out.foreign:
        lines.append(f"writing into {out.path}, which is not an earlier report's (--force): {len(theirs)} file(s) "
                     f"replaced, {_entries(kept)} kept")
    return lines


def _entries(n: int) -> str:
    return f"{n} other entr{'y' if n == 1 else 'ies'}"


def _other_entries(root: Path, own: set[str]) -> int:
    """Entries of ``root`` (top level and ``figures/``) that are not the report's files."""
    entries = [p for p in root.iterdir() if p.name not in (MANIFEST, "figures")]
    figures = root / "figures"
    if figures.is_dir() and not figures.is_symlink():
        entries += list(figures.iterdir())
    elif figures.exists() or figures.is_symlink():
        entries.append(figures)
    return sum(p.relative_to(root).as_posix() not in own for p in entries)


def write_report(out: OutDir, contents: dict[str, bytes]) -> None:
    """Write ``contents`` (relative path -> bytes) atomically; the manifest first names them together with
    the earlier report's files (an interrupted write leaves every file of either listed), then the earlier
    files no longer written are removed and the manifest names exactly the new ones."""
    from robustbench3d import __version__
    from robustbench3d.fileio import atomic_write_bytes, atomic_write_text

    def manifest(files: Sequence[str]) -> None:
        doc: dict[str, Any] = {"written_by": WRITTEN_BY, "version": __version__, "files": sorted(files)}
        atomic_write_text(out.path / MANIFEST, json.dumps(doc, indent=1) + "\n")

    manifest({*out.earlier, *contents})
    for rel, data in contents.items():
        atomic_write_bytes(out.path / rel, data)
    for rel in out.earlier:
        target = out.path / rel
        if rel not in contents and target.is_file() and not target.is_symlink():
            target.unlink()
    manifest(list(contents))
