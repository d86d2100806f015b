"""The command layer: one module per command, named after it; old spellings kept as hidden aliases."""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path

import pytest

from robustbench3d.cli import ALIASES, COMMANDS, build_parser

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[2]
COMMANDS_DIR = REPO / "robustbench3d" / "commands"


def test_each_command_is_one_module_named_after_it() -> None:
    """The files in commands/ are exactly the table's commands, "group sub-name" spelled group_sub_name.py."""
    files = sorted(p.stem for p in COMMANDS_DIR.glob("*.py") if p.stem != "__init__")
    expected = sorted(name.replace(" ", "_").replace("-", "_") for name in COMMANDS)
    assert files == expected
    for name in COMMANDS:
        module = importlib.import_module("robustbench3d.commands." + name.replace(" ", "_").replace("-", "_"))
        assert callable(module.add_arguments) and callable(module.run), name


def _help(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit):
        build_parser().parse_args([*argv, "--help"])
    return capsys.readouterr().out


def test_aliases_are_hidden_from_help(capsys: pytest.CaptureFixture[str]) -> None:
    top = _help([], capsys)
    listed = {line.split()[0] for line in top.split("positional arguments:")[1].split("options:")[0].splitlines()[2:]
              if line.startswith("    ") and not line.startswith("     ")}
    assert listed == {name.split()[0] for name in COMMANDS}  # no "train", "export-onnx", "parity"
    victims = _help(["victims"], capsys)
    for sub in ("train-yolo", "train-fpointnet", "pack", "export-onnx", "parity"):
        assert f"    {sub}" in victims, sub


@pytest.mark.parametrize(("old", "new", "module"), [
    (["train", "yolo", "--data", "D", "--out", "O", "--epochs", "3"],
     ["victims", "train-yolo", "--data", "D", "--out", "O", "--epochs", "3"], "victims_train_yolo"),
    (["train", "fpointnet", "--data", "D", "--out", "O"], ["victims", "train-fpointnet", "--data", "D", "--out", "O"],
     "victims_train_fpointnet"),
    (["export-onnx", "V", "--out", "O", "--exporter", "legacy"],
     ["victims", "export-onnx", "V", "--out", "O", "--exporter", "legacy"], "victims_export_onnx"),
    (["parity", "V", "--max-frames", "2"], ["victims", "parity", "V", "--max-frames", "2"], "victims_parity"),
])
def test_an_old_spelling_parses_to_the_new_command(old: list[str], new: list[str], module: str) -> None:
    def settings(ns: argparse.Namespace) -> dict[str, object]:
        return {k: v for k, v in vars(ns).items() if k not in ("command", "subcommand")}

    a, b = build_parser().parse_args(old), build_parser().parse_args(new)
    assert settings(a) == settings(b)
    assert a._module == b._module == f"robustbench3d.commands.{module}"
    assert " ".join(new[:2]) in ALIASES.values()


def test_the_import_contract_has_one_command_layer_and_commands_are_independent() -> None:
    config = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    contracts = config["tool"]["importlinter"]["contracts"]
    (layers,) = [c["layers"] for c in contracts if c["id"] == "layers"]
    commands = {"robustbench3d.commands." + p.stem for p in COMMANDS_DIR.glob("*.py") if p.stem != "__init__"}
    named = {m.strip() for layer in layers for m in layer.replace(":", "|").split("|")}
    assert [layer for layer in layers if "commands" in layer] == ["commands"]
    assert not named & {c.removeprefix("robustbench3d.") for c in commands}
    (independent,) = [c for c in contracts if c["id"] == "commands-independent"]
    assert independent["type"] == "independence" and independent["modules"] == ["robustbench3d.commands.*"]
