"""Check the import direction declared in ``pyproject.toml`` (``[tool.importlinter]``) with
import-linter's ``lint-imports``.

import-linter's graph builder (grimp) finds a package's modules by walking the package's
directory, but ``eval/``, ``victims/`` and ``attacks/`` join ``robustbench3d`` only through the
``package-dir`` mapping of ``[tool.setuptools]`` (they are ``robustbench3d.eval``, ``.victims`` and
``.attacks`` once installed). This script stages that installed layout as symbolic links in a
temporary directory, with a link to the repository's ``pyproject.toml``, and runs ``lint-imports``
there; the exit status is lint-imports' (0: every contract kept). Extra arguments go to it::

    python tools/lint_imports.py [--verbose]
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the dev extra installs tomli
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]
PYPROJECT = REPO / "pyproject.toml"
_SKIP = {"__pycache__"}


def package_dirs(pyproject: Path = PYPROJECT) -> dict[str, Path]:
    """Installed package name -> its source directory (``[tool.setuptools] package-dir``)."""
    table = tomllib.loads(pyproject.read_text(encoding="utf-8"))["tool"]["setuptools"]["package-dir"]
    return {name: (pyproject.parent / directory).resolve() for name, directory in table.items()}


def stage(dest: Path, pyproject: Path = PYPROJECT) -> Path:
    """Build the installed layout of every mapped package under ``dest`` (a directory per package,
    holding a link to each entry of its source directory), link ``pyproject.toml`` beside it and
    return ``dest``."""
    (dest / "pyproject.toml").symlink_to(pyproject.resolve())
    mapped = package_dirs(pyproject)
    for name in sorted(mapped, key=lambda n: n.count(".")):  # parents before the packages inside them
        target = dest.joinpath(*name.split("."))
        target.mkdir(parents=True, exist_ok=True)
        for entry in sorted(mapped[name].iterdir()):
            if entry.name in _SKIP or f"{name}.{entry.name}" in mapped:
                continue
            (target / entry.name).symlink_to(entry, target_is_directory=entry.is_dir())
    return dest


def lint_imports_executable() -> str:
    """The ``lint-imports`` script of this interpreter's environment (else the first on PATH)."""
    path = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])
    found = shutil.which("lint-imports", path=path)
    if found is None:
        raise SystemExit("lint-imports not found: install the dev extra (pip install -c constraints.txt -e '.[dev]')")
    return found


def run(args: list[str] | None = None, pyproject: Path = PYPROJECT,
        edit: Callable[[Path], None] | None = None) -> subprocess.CompletedProcess[str]:
    """Run ``lint-imports`` on the staged layout (after ``edit(root)``, if given); output captured."""
    with tempfile.TemporaryDirectory(prefix="rb3d-layout-") as tmp:
        root = stage(Path(tmp), pyproject)
        if edit is not None:
            edit(root)
        return subprocess.run([lint_imports_executable(), "--no-cache", "--no-logo", *(args or [])],
                              cwd=root, capture_output=True, text=True, check=False)


def main(argv: list[str] | None = None) -> int:
    proc = run(list(sys.argv[1:] if argv is None else argv))
    sys.stdout.write(proc.stdout)
    sys.stderr.write(proc.stderr)
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())
