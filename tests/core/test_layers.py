"""The package layout and the import direction.

* The hand-kept ``packages`` list of ``pyproject.toml`` names exactly the folders with an
  ``__init__.py`` under the ``package-dir`` sources (``robustbench3d/``, ``eval/``, ``victims/``,
  ``attacks/``), and the installed package resolves to those folders.
* ``lint-imports`` keeps the ``[tool.importlinter]`` contracts (README "Architecture") on the
  installed layout, and reports an upward import when one is added.
* The ``acyclic`` contract reports an import cycle when one is added: inside the runner (an import of
  ``grid`` inside a function or under ``TYPE_CHECKING``, as ``parallel`` and ``flags`` had), inside another
  package, or between two modules of one layer that the ``layers`` contract lets import each other.
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

REPO = Path(__file__).resolve().parents[2]
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


def contract_ids() -> list[str]:
    return [c["id"] for c in tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
            ["tool"]["importlinter"]["contracts"]]


def test_import_contracts_are_kept():
    ids = contract_ids()
    assert {"layers", "acyclic"} <= set(ids)
    proc = lint_imports.run()
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert f"Contracts: {len(ids)} kept, 0 broken." in proc.stdout, proc.stdout
    analyzed = int(proc.stdout.split("Analyzed ")[1].split(" files")[0])
    assert analyzed > 100  # eval/, victims/ and attacks/ were seen in the installed layout


def _append_code(root: Path, module: str, code: str) -> None:
    """Replace the staged link of ``module`` (dotted name) by a copy ending with ``code``. A linked folder on
    the way (a subpackage such as ``runner/`` is staged as one link) first becomes a folder of links, so
    the repository's file is never written."""
    folder = root
    for part in module.split(".")[:-1]:
        folder = folder / part
        if folder.is_symlink():
            source = folder.resolve()
            folder.unlink()
            folder.mkdir()
            for entry in sorted(source.iterdir()):
                (folder / entry.name).symlink_to(entry, target_is_directory=entry.is_dir())
    path = folder / f"{module.split('.')[-1]}.py"
    text = path.read_text(encoding="utf-8")
    path.unlink()
    path.write_text(f"{text}\n{code}", encoding="utf-8")


def _append_import(root: Path, module: str, imported: str) -> None:
    """Replace the staged link of ``module`` (dotted name) by a copy that also imports ``imported``."""
    _append_code(root, module, f"import {imported}  # noqa\n")


@pytest.mark.parametrize(("module", "imported"), [
    ("robustbench3d.texttable", "robustbench3d.runner.config"),  # a foundation importing the runner
    ("robustbench3d.eval.rules", "robustbench3d.victims.base"),  # the evaluator importing a layer above
    ("robustbench3d.eval.rules", "robustbench3d.synth.writer"),  # synth and eval are independent
    ("robustbench3d.victims.zoo", "robustbench3d.attacks.base"),  # victims never import attacks
    ("robustbench3d.results", "robustbench3d.datasets"),  # datasets, results, testing are independent
])
def test_an_import_against_the_direction_breaks_the_contract(module, imported):
    # an upward import often closes a cycle too: the layers contract alone here
    proc = lint_imports.run(["--contract", "layers"], edit=lambda root: _append_import(root, module, imported))
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "1 broken" in proc.stdout and f"{module} -> {imported}" in proc.stdout, proc.stdout


LAZY_GRID = "def _lazy():\n    from robustbench3d.runner import grid  # noqa\n"
TYPING_GRID = "import typing\nif typing.TYPE_CHECKING:\n    from robustbench3d.runner.grid import RunReport  # noqa\n"


@pytest.mark.parametrize(("module", "code", "package", "pairs"), [
    # grid imports parallel and flags at module level: a way back, however hidden, closes a cycle
    ("robustbench3d.runner.parallel", LAZY_GRID, "robustbench3d.runner", {".parallel -> .grid", ".grid -> .parallel"}),
    ("robustbench3d.runner.flags", TYPING_GRID, "robustbench3d.runner", {".flags -> .grid", ".grid -> .flags"}),
    # kitti_eval imports rules
    ("robustbench3d.eval.rules", "def _lazy():\n    from robustbench3d.eval import kitti_eval  # noqa\n",
     "robustbench3d.eval", {".rules -> .kitti_eval", ".kitti_eval -> .rules"}),
    # fileio imports errors; the layers contract lets the foundations import each other, this one not in a circle
    ("robustbench3d.errors", "def _lazy():\n    import robustbench3d.fileio  # noqa\n",
     "robustbench3d", {".errors -> .fileio", ".fileio -> .errors"}),
])
def test_an_import_cycle_breaks_the_acyclic_contract(module, code, package, pairs):
    source = importlib.util.find_spec(module).origin
    before = Path(source).read_bytes()
    proc = lint_imports.run(["--contract", "acyclic"], edit=lambda root: _append_code(root, module, code))
    assert Path(source).read_bytes() == before, f"{source} was written"  # only the staged copy changed
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "Contracts: 0 kept, 1 broken." in proc.stdout, proc.stdout
    cycles = [line for line in proc.stdout.splitlines() if line.startswith("No cycles are allowed in ")]
    assert cycles == [f"No cycles are allowed in {package}."], proc.stdout
    assert any(f"- {pair} (1 import)" in proc.stdout for pair in pairs), proc.stdout


def test_the_acyclic_contract_lists_no_known_cycle():
    """The cycles once listed as ignored imports ({victims.base, victims.spec}, {victims.onnx.export,
    victims.onnx.export_command}, {attacks.base, attacks.record}) are gone, so the contract ignores nothing."""
    contracts = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["importlinter"]
    acyclic = next(c for c in contracts["contracts"] if c["id"] == "acyclic")
    assert acyclic.get("ignore_imports", []) == []


LAZY = "def _lazy():\n    {}  # noqa\n"
TYPING = "import typing\nif typing.TYPE_CHECKING:\n    {}  # noqa\n"


@pytest.mark.parametrize(("module", "code", "backend"), [
    # the object-file resolver once took sanitise_name from the ONNX victim code
    ("robustbench3d.attacks.zoo", LAZY.format("from robustbench3d.victims.onnx.registration import sanitise_name"),
     "robustbench3d.victims.onnx"),
    ("robustbench3d.attacks.record", TYPING.format("import robustbench3d.victims.cascade"),
     "robustbench3d.victims.cascade"),
    ("robustbench3d.attacks.roof", LAZY.format("from robustbench3d.victims.fpointnet import frustum"),
     "robustbench3d.victims.fpointnet"),
    ("robustbench3d.attacks.placement", LAZY.format("import robustbench3d.victims.zoo"),  # zoo builds the cascades
     "robustbench3d.victims.cascade"),
])
def test_an_attack_importing_a_victim_backend_breaks_the_contract(module, code, backend):
    proc = lint_imports.run(["--contract", "attacks-know-no-backend"],
                            edit=lambda root: _append_code(root, module, code))
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "Contracts: 0 kept, 1 broken." in proc.stdout, proc.stdout
    assert f"robustbench3d.attacks is not allowed to import {backend}" in proc.stdout, proc.stdout


def test_attacks_may_import_the_victim_contract():
    code = ("def _lazy():\n    from robustbench3d.victims import VICTIMS  # noqa\n"
            "    from robustbench3d.victims.base import check_victim  # noqa\n"
            "    import robustbench3d.victims.spec  # noqa\n")
    proc = lint_imports.run(["--contract", "attacks-know-no-backend"],
                            edit=lambda root: _append_code(root, "robustbench3d.attacks.zoo", code))
    assert proc.returncode == 0 and "Contracts: 1 kept, 0 broken." in proc.stdout, proc.stdout + proc.stderr


def _readme_layers() -> list[str]:
    """The first column of README "Architecture"'s layer table, as written in the contract."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    table = text[text.index("| layer | what lives there |"):].split("\n\n", 1)[0].splitlines()[2:]
    return [row.split(" | ", 1)[0].strip("| ").replace("\\|", "|").replace("`", "") for row in table]


def test_the_readme_architecture_table_is_the_layers_contract() -> None:
    data = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    (layers,) = [c["layers"] for c in data["tool"]["importlinter"]["contracts"] if c["id"] == "layers"]
    assert _readme_layers() == layers
