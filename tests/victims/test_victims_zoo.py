"""The victim registry as shipped: in-tree entries, their metadata, the contract check, and
``robustbench3d victims list``."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from robustbench3d.cli import main
from robustbench3d.errors import RobustBenchError
from robustbench3d.victims import VICTIMS, create_victim
from robustbench3d.victims.base import (
    Detector,
    FrustumSegmentationOracle,
    ImageObjectnessOracle,
    check_victim,
)
from robustbench3d.victims.shipped import shipped
from robustbench3d.victims.spec import Capabilities, EntryInfo, VictimSpec


def test_in_tree_victims_are_registered_with_metadata():
    assert {"fpointnet-v1", "fpointnet-v1-lite"} <= set(VICTIMS.names())
    spec = VICTIMS.get("fpointnet-v1")
    assert isinstance(spec, VictimSpec)
    cap = spec.info.capabilities
    assert cap.modalities == ("camera", "lidar") and cap.backend == "torch" and cap.gradients and cap.deterministic
    for name in ("fpointnet-v1", "fpointnet-v1-lite"):  # both cascades ship weights (issue 17: the full one)
        assert VICTIMS.get(name).info.weights_sha256 == shipped(name).sha256


def test_listing_does_not_import_torch():
    code = ("import sys; from robustbench3d.victims import VICTIMS; "
            "[VICTIMS.get(n).info for n in VICTIMS.names('fpointnet*')]; print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"ROBUSTBENCH3D_NO_PLUGINS": "1", "PATH": ""})
    assert out.stdout.strip() == "False"


def test_factory_refuses_to_run_without_weights_unless_asked(tmp_path):
    with pytest.raises(RobustBenchError, match="no such cascade weights file"):
        create_victim("fpointnet-v1", weights=tmp_path / "missing.pt")
    victim = create_victim("fpointnet-v1-lite", allow_untrained=True)
    assert isinstance(victim, Detector)
    assert isinstance(victim, ImageObjectnessOracle) and isinstance(victim, FrustumSegmentationOracle)
    assert victim.num_points == 512


def test_check_victim_enforces_declared_capabilities():
    class LidarOnly:
        supported_proposals = ("detector",)

        def detect(self, frames, proposals="detector"):
            return []

    lidar = Capabilities(modalities=("lidar",), backend="other", gradients=False, deterministic=True)
    check_victim(LidarOnly(), lidar)
    with pytest.raises(TypeError, match="implements no oracle"):
        check_victim(LidarOnly(), Capabilities(("lidar",), "torch", gradients=True, deterministic=True))
    with pytest.raises(TypeError, match="does not implement Detector"):
        check_victim(object(), lidar)

    class BadProposals(LidarOnly):
        supported_proposals = ("magic",)

    with pytest.raises(TypeError, match="supported_proposals"):
        check_victim(BadProposals(), lidar)


def test_victims_list_cli(capsys):
    assert main(["victims", "list", "--json", "fpointnet*"]) == 0
    rows = json.loads(capsys.readouterr().out)
    by_name = {r["name"]: r for r in rows}
    assert {"fpointnet-v1", "fpointnet-v1-lite"} <= set(by_name) <= {"fpointnet-v1", "fpointnet-v1-lite",
                                                                     "fpointnet-v1-lite-onnx", "fpointnet-v1-onnx"}
    assert by_name["fpointnet-v1"]["capabilities"]["modalities"] == ["camera", "lidar"]
    assert by_name["fpointnet-v1"]["weights_sha256"] == shipped("fpointnet-v1").sha256
    assert by_name["fpointnet-v1"]["origin"] == "in-tree"
    assert main(["victims", "list"]) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[0].split()[:3] == ["name", "modalities", "backend"]
    assert any(line.startswith("fpointnet-v1-lite ") and "camera+lidar" in line for line in table)


def test_capabilities_and_info_validation():
    cap = Capabilities(modalities=("lidar", "camera"), backend="torch", gradients=True, deterministic=True)
    assert cap.modalities == ("camera", "lidar")  # canonical order
    for bad in ((), ("radar",), ("lidar", "lidar")):
        with pytest.raises(ValueError, match="modalities"):
            Capabilities(modalities=bad, backend="torch", gradients=False, deterministic=True)
    with pytest.raises(ValueError, match="backend"):
        Capabilities(modalities=("lidar",), backend="jax", gradients=False, deterministic=True)
    EntryInfo(cap, weights_sha256="0" * 64)
    for bad in ("0" * 63, "G" * 64, "A" * 64):
        with pytest.raises(ValueError, match="sha256"):
            EntryInfo(cap, weights_sha256=bad)
    assert json.loads(json.dumps(EntryInfo(cap).as_dict()))["capabilities"]["modalities"] == ["camera", "lidar"]
