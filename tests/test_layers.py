"""The package layout and the import direction.

* The hand-kept ``packages`` list of ``pyproject.toml`` names exactly the folders with an
  ``__init__.py`` under the ``package-dir`` sources (``robustbench3d/``, ``eval/``, ``victims/``,
  ``attacks/``), and the installed package resolves to those folders.
* ``lint-imports`` keeps the ``[tool.importlinter]`` contracts (README "Architecture") on the
  installed layout, and reports an upward import when one is added.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the dev extra installs tomli
    import tomli as tomllib
pytest.importorskip("importlinter", reason="import-linter is in the dev extra")

REPO = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("lint_imports", REPO / "tools" / "lint_imports.py")
assert _spec is not None and _spec.loader is not None
lint_imports = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(lint_imports)


def setuptools_table() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]


def packages_on_disk(package_dir: dict[str, str], base: Path = REPO) -> set[str]:
    """Every folder with an ``__init__.py`` under the mapped source folders, named as installed."""
    found = set()
    for name, directory in package_dir.items():
        root = base / directory
        for init in root.rglob("__init__.py"):
            found.add(".".join([name, *init.parent.relative_to(root).parts]))
    return found


def test_packages_list_names_every_package_folder():
    table = setuptools_table()
    listed = table["packages"]
    assert len(listed) == len(set(listed)), "a package is listed twice"
    on_disk = packages_on_disk(table["package-dir"])
    missing, stale = sorted(on_disk - set(listed)), sorted(set(listed) - on_disk)
    assert not missing, f"folders with __init__.py not in [tool.setuptools] packages (not installed): {missing}"
    assert not stale, f"listed in [tool.setuptools] packages but no folder with __init__.py: {stale}"


def test_the_guard_finds_nested_packages_under_their_installed_names(tmp_path):
    for folder in ("core/sub/deep", "core/data", "plug"):
        (tmp_path / folder).mkdir(parents=True)
    for init in ("core", "core/sub", "core/sub/deep", "plug"):
        (tmp_path / init / "__init__.py").write_text("")
    found = packages_on_disk({"top": "core", "top.plug": "plug"}, tmp_path)
    assert found == {"top", "top.sub", "top.sub.deep", "top.plug"}  # core/data has no __init__.py


def test_package_dir_mapping_is_what_is_installed():
    table = setuptools_table()
    mapping = table["package-dir"]
    assert {"robustbench3d", "robustbench3d.eval", "robustbench3d.victims", "robustbench3d.attacks"} <= set(mapping)
    for name in table["packages"]:
        top = max((m for m in mapping if name == m or name.startswith(m + ".")), key=len)
        folder = (REPO / mapping[top]).joinpath(*name[len(top):].split(".")[1:])
        spec = importlib.util.find_spec(name)
        assert spec is not None and spec.origin is not None, name
        assert Path(spec.origin).resolve() == (folder / "__init__.py").resolve(), name


def test_import_contracts_are_kept():
    proc = lint_imports.run()
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "0 broken" in proc.stdout
    analyzed = int(proc.stdout.split("Analyzed ")[1].split(" files")[0])
    assert analyzed > 100  # eval/, victims/ and attacks/ were seen in the installed layout


def _append_import(root: Path, module: str, imported: str) -> None:
    """Replace the staged link of ``module`` (dotted name) by a copy that also imports ``imported``."""
    path = root.joinpath(*module.split(".")).with_suffix(".py")
    text = path.read_text(encoding="utf-8")
    path.unlink()
    path.write_text(f"{text}\nimport {imported}  # noqa\n", encoding="utf-8")


@pytest.mark.parametrize(("module", "imported"), [
    ("robustbench3d.texttable", "robustbench3d.runner.config"),  # a foundation importing the runner
    ("robustbench3d.eval.rules", "robustbench3d.victims.base"),  # the evaluator importing a layer above
    ("robustbench3d.eval.rules", "robustbench3d.synth.writer"),  # synth and eval are independent
    ("robustbench3d.victims.zoo", "robustbench3d.attacks.base"),  # victims never import attacks
    ("robustbench3d.results", "robustbench3d.datasets"),  # datasets, results, testing are independent
])
def test_an_import_against_the_direction_breaks_the_contract(module, imported):
    proc = lint_imports.run(edit=lambda root: _append_import(root, module, imported))
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "1 broken" in proc.stdout and f"{module} -> {imported}" in proc.stdout, proc.stdout
