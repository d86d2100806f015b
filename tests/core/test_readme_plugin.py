"""The README's plugin recipe and Python API snippet are real code: the recipe's block runs as a module, its
``SPEC`` passes the registry's contract check, and ``benchmark`` scores the detector on a tiny split."""

from __future__ import annotations

import re
import types
from pathlib import Path

from robustbench3d.results import CSV_COLUMNS
from robustbench3d.testing import synth_dataset
from robustbench3d.victims.spec import VictimSpec

README = Path(__file__).resolve().parents[2] / "README.md"


def section_code(heading: str, lang: str = "python") -> str:
    """The first ``lang`` code block after ``heading`` in the README."""
    text = README.read_text(encoding="utf-8")
    start = text.index(f"\n{heading}\n")
    match = re.compile(rf"```{lang}\n(.*?)```", re.S).search(text, start)
    assert match is not None, heading
    return match.group(1)


def test_the_plugin_recipe_runs_and_its_victim_is_scored(tmp_path):
    import robustbench3d

    module = types.ModuleType("my_victim")
    exec(compile(section_code("### Writing a victim plugin"), "README:my_victim", "exec"), module.__dict__)
    assert isinstance(module.SPEC, VictimSpec)
    victim = module.SPEC.create()  # the registry's contract check (check_victim) passes
    data = synth_dataset(tmp_path / "synth", 2, seed=4, val_fraction=1.0)
    df = robustbench3d.benchmark(victim, attacks=("none",), frames=None, data=data, bootstrap=20)
    bev = df[(df["metric"] == "bev") & (df["recall_points"] == 40)]
    assert set(bev["difficulty"]) == {"easy", "moderate", "hard"} and (bev["ap"] == 0.0).all()  # detects nothing
    toml = section_code("### Writing a victim plugin", "toml")
    assert '[project.entry-points."robustbench3d.victims"]' in toml and '"my_victim:SPEC"' in toml


def test_the_python_api_snippet_names_real_columns():
    code = section_code("## Python API")
    assert "robustbench3d.benchmark(" in code
    for column in re.findall(r'"(\w+)"', code.split("print(", 1)[1]):
        assert column in CSV_COLUMNS, column
    for column in re.findall(r"(\w+) ==", code):
        assert column in CSV_COLUMNS, column
