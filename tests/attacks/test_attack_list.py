"""``attack list``: every attack a user can name, with the parameters its factory takes."""

from __future__ import annotations

import json
from pathlib import Path

from robustbench3d.cli import main
from robustbench3d.commands.attack_list import factory_parameters

MANIFEST = Path(__file__).resolve().parents[2] / "attacks" / "objects" / "manifest.json"


def test_factory_parameters_by_hand():
    def factory(path, *, seed=0, scale=0.1234567891, name="x", **extra):
        return None

    assert factory_parameters(factory) == ["path", "seed=0", "scale=0.123457", "name=x"]
    assert factory_parameters(len) == []  # a builtin without a readable signature: no parameters listed


def test_attack_list_json_names_the_controls_and_every_shipped_object(capsys):
    assert main(["attack", "list", "--json"]) == 0
    items = {r["name"]: r for r in json.loads(capsys.readouterr().out)}
    shipped = [o["name"] for o in json.loads(MANIFEST.read_text())["objects"]]
    assert len(shipped) >= 3
    for name in shipped:
        assert items[name]["origin"] == "shipped object" and items[name]["error"] is None
    assert {"none", "benign-sphere", "random-shape", "object-file"} <= set(items)
    assert items["object-file"]["parameters"][0] == "path"  # required: no default
    assert "seed=0" in items["random-shape"]["parameters"]
    assert items["none"]["parameters"] == []


def test_attack_list_table_filters_by_pattern(capsys):
    assert main(["attack", "list", "adv-*"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[:2] == ["name", "parameters"]
    assert sorted(line.split()[0] for line in lines[1:]) == sorted(
        o["name"] for o in json.loads(MANIFEST.read_text())["objects"] if o["name"].startswith("adv-"))
