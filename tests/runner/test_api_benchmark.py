"""``robustbench3d.benchmark``: one call from a model object, registered nowhere, to a results table --
the same numbers as ``robustbench3d run`` gives the registered victim, read back from its CSV file."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest

import robustbench3d
from robustbench3d.cli import main
from robustbench3d.errors import RobustBenchError
from robustbench3d.testing import synth_dataset
from robustbench3d.victims import VICTIMS

LITE = "fpointnet-v1-lite"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return synth_dataset(tmp_path_factory.mktemp("synth"), 3, seed=11, val_fraction=1.0)


class Wrapped:
    """A user's model: the lite cascade behind an object the harness has never seen."""

    def __init__(self) -> None:
        self.inner = VICTIMS.get(LITE).create()
        self.supported_proposals = self.inner.supported_proposals

    def detect(self, frames, proposals="detector"):
        return self.inner.detect(frames, proposals)


def cli_rows(dataset: Path, out: Path) -> list[dict[str, str]]:
    assert main(["run", "--victims", LITE, "--attacks", "none,benign-sphere", "--proposals", "gt", "--data",
                 str(dataset), "--out", str(out), "--no-progress", "--jobs", "1", "--bootstrap", "50"]) == 0
    with open(out / "results.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_benchmark_of_an_unregistered_object_equals_the_cli_run_of_the_registered_victim(dataset, tmp_path):
    reference = cli_rows(dataset, tmp_path / "cli")
    df = robustbench3d.benchmark(Wrapped(), attacks=("benign-sphere",), frames=None, proposals=("gt",),
                                 name="my-model", data=dataset, bootstrap=50)
    assert "my-model" not in VICTIMS  # registered for the call only
    assert len(df) == len(reference) > 0
    assert set(df["victim"]) == {"my-model"} and set(df["attack"]) == {"none", "benign-sphere"}
    key = ("attack", "proposals", "class", "metric", "recall_points", "difficulty")
    got = {tuple(str(r[k]) for k in key): r for r in df.to_dict("records")}
    for ref in reference:
        row = got[tuple(ref[k] for k in key)]
        for col in ("ap", "clean_ap", "ap_drop", "relative_drop", "attack_success_rate"):
            want = float(ref[col]) if ref[col] != "" else math.nan
            assert (math.isnan(want) and math.isnan(row[col])) or row[col] == want, col


def test_benchmark_by_name_keeps_the_run_directory_when_asked(dataset, tmp_path):
    df = robustbench3d.benchmark(LITE, attacks=("none",), frames=2, proposals=("gt",), data=dataset,
                                 out=tmp_path / "kept", bootstrap=50)
    assert set(df["victim"]) == {LITE} and set(df["attack"]) == {"none"}
    assert (tmp_path / "kept" / "summary.json").is_file() and (tmp_path / "kept" / "results.csv").is_file()


def test_benchmark_refuses_what_is_not_a_detector_and_a_taken_name(dataset):
    with pytest.raises(RobustBenchError, match="not a detector"):
        robustbench3d.benchmark(object(), data=dataset)
    with pytest.raises(RobustBenchError, match="already registered"):
        robustbench3d.benchmark(Wrapped(), name=LITE, data=dataset)
