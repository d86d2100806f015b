"""Where a result came from: code, environment, data and weights identities (for result files).

Nothing here imports torch or onnxruntime: library versions are read from installed metadata, and
torch's runtime flags are reported only when torch is already loaded (a torch victim ran).
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import os
import platform
import subprocess
import sys
from collections.abc import Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from robustbench3d import __version__
from robustbench3d.fileio import sha256_file

#: Libraries whose versions every result records (None when not installed).
LIBRARIES: tuple[str, ...] = ("numpy", "torch", "onnxruntime", "onnx", "pillow", "trimesh", "embreex")
#: First line hashed by :class:`SplitDigest`; bump if the hashed layout changes.
SPLIT_DIGEST_HEADER = b"robustbench3d split digest v1\n"


def utc_now() -> str:
    """Current UTC time, ISO 8601 with seconds (e.g. ``2026-01-31T12:00:00Z``)."""
    return datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


class SplitDigest:
    """sha256 identity of a split: its frame ids in order and the bytes of each frame's label file.

    Hashed layout (reproducible by hand): the header line :data:`SPLIT_DIGEST_HEADER`, then
    ``"<frame count>\\n"``, then per frame in split order ``"<frame id> <sha256 of the label file>\\n"``.
    """

    def __init__(self, frame_ids: Sequence[str]):
        self._ids = list(frame_ids)
        self._next = 0
        self._h = hashlib.sha256(SPLIT_DIGEST_HEADER)
        self._h.update(f"{len(self._ids)}\n".encode())

    def update(self, frame_id: str, label_bytes: bytes) -> None:
        """Add the next frame's label file (frames must come in split order)."""
        if self._next >= len(self._ids) or self._ids[self._next] != frame_id:
            expected = self._ids[self._next] if self._next < len(self._ids) else "no more frames"
            raise ValueError(f"SplitDigest: got frame {frame_id}, expected {expected}")
        self._h.update(f"{frame_id} {hashlib.sha256(label_bytes).hexdigest()}\n".encode())
        self._next += 1

    def hexdigest(self) -> str:
        if self._next != len(self._ids):
            raise ValueError(f"SplitDigest: {self._next} of {len(self._ids)} frames hashed")
        return self._h.hexdigest()


def reset_peak_rss() -> bool:
    """Reset this process's peak resident set size (Linux: write 5 to ``/proc/self/clear_refs``); False where
    that is not possible (then :func:`peak_rss_mb` reports the peak since the process started)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def peak_rss_mb() -> float | None:
    """Peak resident set size of this process since the last :func:`reset_peak_rss` (``VmHWM``), MB; None
    without ``/proc``."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def git_info(source_dir: str | Path | None = None) -> dict[str, Any]:
    """Commit and dirty flag of the git checkout the package runs from.

    ``source_dir`` defaults to the directory holding the ``robustbench3d`` package; it counts as a
    checkout only if it is the top level of a git work tree (an installed copy inside some other
    repository is not). Returns ``{"commit": None, "dirty": None}`` outside a checkout or without
    git. Read-only: ``--no-optional-locks`` keeps ``git status`` from touching the index.
    """
    root = Path(source_dir) if source_dir is not None else Path(__file__).resolve().parents[1]
    none: dict[str, Any] = {"commit": None, "dirty": None}

    def git(*args: str) -> str | None:
        try:
            proc = subprocess.run(["git", "--no-optional-locks", "-C", str(root), *args], capture_output=True,
                                  text=True, timeout=10, check=False)
        except (OSError, subprocess.TimeoutExpired):
            return None
        return proc.stdout.strip() if proc.returncode == 0 else None

    top = git("rev-parse", "--show-toplevel")
    if top is None or Path(top).resolve() != root.resolve():
        return none
    commit = git("rev-parse", "HEAD")
    status = git("status", "--porcelain")
    if commit is None:
        return none
    return {"commit": commit, "dirty": None if status is None else bool(status)}


def library_versions(names: Sequence[str] = LIBRARIES) -> dict[str, str | None]:
    """Installed versions (distribution metadata; nothing is imported), plus Python's."""
    out: dict[str, str | None] = {"python": platform.python_version()}
    for name in names:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    return out


def _cpu_model() -> str | None:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def platform_info() -> dict[str, Any]:
    """Operating system, machine and CPU."""
    return {"system": platform.system(), "release": platform.release(), "machine": platform.machine(),
            "python_implementation": platform.python_implementation(), "cpu": _cpu_model(),
            "cpu_count": os.cpu_count()}


def determinism_flags() -> dict[str, Any]:
    """Settings that affect bit-reproducibility; torch's only if torch is loaded."""
    flags: dict[str, Any] = {
        "PYTHONHASHSEED": os.environ.get("PYTHONHASHSEED"),
        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS"),
        "torch_loaded": "torch" in sys.modules,
    }
    torch = sys.modules.get("torch")
    if torch is not None:
        flags["torch_deterministic_algorithms"] = bool(torch.are_deterministic_algorithms_enabled())
        flags["torch_num_threads"] = int(torch.get_num_threads())
    return flags


def host_provenance(source_dir: str | Path | None = None) -> dict[str, Any]:
    """The parts of provenance that are the same for every cell of a run (collected once)."""
    return {"package": {"name": "robustbench3d", "version": __version__}, "git": git_info(source_dir),
            "platform": platform_info()}


def weight_files(kwargs: Mapping[str, Any]) -> dict[str, str]:
    """sha256 of every keyword argument that names an existing file (weights, ONNX graphs...)."""
    out = {}
    for key, value in sorted(kwargs.items()):
        if isinstance(value, str | os.PathLike) and Path(value).is_file():
            out[key] = sha256_file(value)
    return out


__all__ = [
    "LIBRARIES", "SPLIT_DIGEST_HEADER", "SplitDigest", "determinism_flags", "git_info", "host_provenance",
    "library_versions", "peak_rss_mb", "platform_info", "reset_peak_rss", "utc_now", "weight_files",
]
