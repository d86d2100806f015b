"""Where generated data and caches live.

``$ROBUSTBENCH3D_CACHE`` if set, else ``~/.cache/robustbench3d``. Generated datasets go under
``<cache>/datasets/<name>``; nothing large is written inside the repository.
"""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir() -> Path:
    """Root of robustbench3d's caches (not created here)."""
    env = os.environ.get("ROBUSTBENCH3D_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "robustbench3d"


def dataset_dir(name: str) -> Path:
    """Directory of a generated dataset in the cache."""
    return cache_dir() / "datasets" / name
