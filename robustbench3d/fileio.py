"""File access shared by every command.

Atomic writes (a reader never sees a half-written file, a crash leaves no partial output); reading
a data file, where any OS error becomes a :class:`DataFormatError` naming the file; and the
up-front checks of output paths (``--out``, ``--json``) that fail before any work is done; and the
entry update of the shipped-file manifests (weights, objects).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
import threading
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import IO, Any

from robustbench3d.errors import DataFormatError, RobustBenchError

#: The problem reported for a user-supplied text file that starts with a UTF-8 byte-order mark.
BOM_PROBLEM = "file starts with a UTF-8 byte-order mark; save it without BOM"

_UMASK_LOCK = threading.Lock()


def current_umask() -> int:
    """The process's file-creation mask (read by setting it and restoring it at once, under a lock)."""
    with _UMASK_LOCK:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def new_file_mode() -> int:
    """The permission bits an ``open(path, "w")`` would give a new file: ``0o666`` less the umask."""
    return 0o666 & ~current_umask()


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "w") -> Iterator[IO]:
    """Open a temporary file next to ``path``; on success fsync and rename it over ``path``.

    The file gets the permission bits a plain ``open`` would give it (``0o666`` less the umask;
    ``mkstemp`` alone makes ``0o600``, unreadable to colleagues and web servers). On an exception the
    temporary file is removed and ``path`` is left as it was.
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_open supports modes 'w' and 'wb', not {mode!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, new_file_mode())
        with os.fdopen(fd, mode, **({"encoding": "utf-8", "newline": "\n"} if mode == "w" else {})) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_open(path, "wb") as f:
        f.write(data)


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write UTF-8 ``text`` to ``path`` atomically (newlines written as ``\\n``)."""
    with atomic_open(path, "w") as f:
        f.write(text)


def read_user_text(path: str | Path) -> str:
    """UTF-8 text of a file the user supplies (labels, calib, splits, manifests, registrations).

    Newlines are read as ``\n``. A missing file raises :class:`FileNotFoundError` (callers word
    it). Bytes that are not UTF-8, and a leading UTF-8 byte-order mark, raise
    :class:`~robustbench3d.errors.DataFormatError` naming the file: the BOM is refused rather than
    skipped, so every reader (including ones that parse raw bytes) accepts exactly the same files.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise DataFormatError(path, f"not UTF-8 text ({exc.reason})") from None
    if text.startswith("\ufeff"):
        raise DataFormatError(path, BOM_PROBLEM, line=1)
    return text


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


@contextlib.contextmanager
def data_file_errors(path: str | Path, missing: str = "file not found") -> Iterator[None]:
    """Turn an OS error while reading the data file ``path`` (missing, a directory, a symlink loop,
    no permission...) into :class:`DataFormatError` naming it; ``missing`` words a missing file."""
    try:
        yield
    except FileNotFoundError:
        raise DataFormatError(path, missing) from None
    except IsADirectoryError:
        raise DataFormatError(path, "is a directory, expected a file") from None
    except OSError as exc:
        raise DataFormatError(path, f"cannot read ({exc.strerror or exc})") from None


def read_data_bytes(path: str | Path, missing: str = "file not found") -> bytes:
    """The bytes of a data file (errors as :func:`data_file_errors`)."""
    with data_file_errors(path, missing):
        return Path(path).read_bytes()


def read_data_text(path: str | Path, missing: str = "file not found") -> str:
    """The text of a data file as :func:`read_user_text` reads it (errors as :func:`data_file_errors`)."""
    with data_file_errors(path, missing):
        return read_user_text(path)


def _writable_ancestor(path: Path, flag: str) -> Path:
    """The nearest existing ancestor of ``path``, checked to be a directory we can create files in."""
    anc = path.parent
    while not anc.exists() and anc != anc.parent:
        if anc.is_symlink():
            raise RobustBenchError(f"{flag} {path}: {anc} is a broken symbolic link")
        anc = anc.parent
    if not anc.is_dir():
        raise RobustBenchError(f"{flag} {path}: {anc} is not a directory")
    _probe_writable(anc, path, flag)
    return anc


def _probe_writable(directory: Path, path: Path, flag: str) -> None:
    """Create and remove a temporary file in ``directory`` (permission bits do not bind root)."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=".rb3d-write-check.", dir=directory)
    except OSError as exc:
        raise RobustBenchError(f"{flag} {path}: cannot create files in {directory} ({exc.strerror or exc})") from None
    os.close(fd)
    os.unlink(tmp)


def check_output_file(path: str | Path, flag: str, *, force: bool = True) -> Path:
    """Check, before any work, that ``path`` can be written as a file (given as option ``flag``).

    It must not be a directory, a dangling symbolic link or (unless ``force``) an existing file: the
    written-once rule, a command never replaces a file it did not create unless ``--force`` says so
    (see :func:`replacing_note`). Its existing ancestors must be directories and the nearest one
    writable (missing directories are created at write time). Raises :class:`RobustBenchError`.
    """
    path = Path(path)
    if path.is_symlink() and not path.exists():
        raise RobustBenchError(f"{flag} {path}: is a broken symbolic link (to {os.readlink(path)})")
    if path.is_dir():
        raise RobustBenchError(f"{flag} {path}: is a directory; expected a file name")
    if path.exists() and not path.is_file():
        raise RobustBenchError(f"{flag} {path}: exists and is not a regular file")
    if path.exists() and not force:
        raise RobustBenchError(f"{flag} {path}: exists; pass --force to replace it (nothing was written)")
    _writable_ancestor(path, flag)
    return path


def replacing_note(path: str | Path) -> str | None:
    """The line a command prints before replacing an existing ``path`` under ``--force``, else None."""
    path = Path(path)
    return f"replacing {path} (--force)" if path.exists() else None


def check_output_dir(path: str | Path, flag: str) -> Path:
    """Check, before any work, that ``path`` is, or can be created as, a writable directory.

    Raises :class:`RobustBenchError` for an existing non-directory, an ancestor that is not a
    directory, or a directory we cannot create files in.
    """
    path = Path(path)
    if path.is_symlink() and not path.exists():
        raise RobustBenchError(f"{flag} {path}: is a broken symbolic link (to {os.readlink(path)})")
    if path.exists():
        if not path.is_dir():
            raise RobustBenchError(f"{flag} {path}: exists and is not a directory")
        _probe_writable(path, path, flag)
    else:
        _writable_ancestor(path, flag)
    return path


def remove_created_dir(path: str | Path, scaffolding: tuple[str, ...] = (".lock",)) -> bool:
    """Undo a failed command's output directory when it holds no output: remove ``path`` if it
    contains only empty directories and files named in ``scaffolding``. True if removed."""
    path = Path(path)
    if not path.is_dir() or path.is_symlink():
        return False
    entries = sorted(path.rglob("*"), key=lambda p: len(p.parts), reverse=True)
    if any(p.is_symlink() or (not p.is_dir() and p.name not in scaffolding) for p in entries):
        return False
    for p in entries:  # deepest first
        if p.is_dir():
            p.rmdir()
        else:
            p.unlink()
    path.rmdir()
    return True


def upsert_json_entry(path: str | Path, data: dict[str, Any], list_key: str, id_key: str, entry: Mapping[str, Any],
                      check: Callable[[dict[str, Any]], object] | None = None) -> dict[str, Any]:
    """Replace the entry of ``data[list_key]`` whose ``id_key`` equals ``entry``'s (or add ``entry``), sort
    that list by ``id_key``, call ``check(data)`` (it raises on a bad result: nothing is written), then
    write ``data`` to ``path`` atomically (indented JSON, sorted keys, final newline); returns ``data``.
    ``data`` is the file's current content, read and checked by the caller (a shipped-file manifest)."""
    ident = entry[id_key]
    kept = [e for e in data[list_key] if e[id_key] != ident]
    data[list_key] = sorted([*kept, dict(entry)], key=lambda e: e[id_key])
    if check is not None:
        check(data)
    atomic_write_text(path, json.dumps(data, indent=2, sort_keys=True) + "\n")
    return data
