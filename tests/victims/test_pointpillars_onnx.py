"""The PointPillars ONNX twin: export -> onnxruntime parity with the torch victim on real (synthetic) frames
(output maps within 1e-4, the same detections within stated tolerances), the directory registered like the
cascade twins (lidar-only ONNX capabilities, cascade-only arguments refused with one line), a graph file that
does not match its manifest refused, a scan with more pillars than the graph holds refused, the export
command, the parity command (numbers within tolerance, exit 1 beyond it, a wrong --onnx directory refused in one
line before any work), and (once they ship) the shipped twin pinned to the shipped weights, reproduced and at
parity."""

from __future__ import annotations

import hashlib
import json
import re
import shlex
from dataclasses import replace

import numpy as np
import pytest
import torch

from robustbench3d.cli import main
from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.kitti import KittiDataset
from robustbench3d.testing import synth_dataset
from robustbench3d.victims import VICTIMS, create_victim
from robustbench3d.victims.onnx.options import ExportOptions
from robustbench3d.victims.onnx.pointpillars import PointPillarsOnnx
from robustbench3d.victims.onnx.pointpillars_export import export_pointpillars, parity
from robustbench3d.victims.onnx.registration import SHIPPED_POINTPILLARS, victim_spec
from robustbench3d.victims.pointpillars.config import PointPillarsConfig
from robustbench3d.victims.pointpillars.detector import PointPillarsDetector
from robustbench3d.victims.pointpillars.glue import crop_scan, run_scan
from robustbench3d.victims.pointpillars.model import build_model
from robustbench3d.victims.pointpillars.pillars import pillarise
from robustbench3d.victims.shipped import shipped, weights_dir

pytest.importorskip("onnxruntime")
torch.set_num_threads(1)
TINY = PointPillarsConfig(pillar_channels=8, block_channels=(8, 8, 8), block_layers=(1, 1, 1), up_channels=8,
                          head_channels=8)


@pytest.fixture(scope="module")
def synth_root(tmp_path_factory):
    return synth_dataset(tmp_path_factory.mktemp("ppo"), 2, seed=7, val_fraction=1.0)


@pytest.fixture(scope="module")
def setup(tmp_path_factory, synth_root):
    ds = KittiDataset(synth_root, split="val")
    frames = [ds.frame(f) for f in ds.frame_ids]
    victim = PointPillarsDetector(build_model(TINY, 2).eval())
    out = tmp_path_factory.mktemp("onnx") / "pp-twin"
    export_pointpillars(victim, out, ExportOptions("dynamo"), max_pillars=4000)
    return victim, frames, out


def test_parity_with_torch(setup):
    victim, frames, out = setup
    twin = PointPillarsOnnx(out)
    rep = parity(victim, twin, frames, [f.labels for f in frames])
    assert rep.max_output_diff <= 1e-4 and rep.same_counts
    assert rep.max_score_diff <= 1e-5 and rep.max_location_diff <= 1e-3
    assert rep.max_dimension_diff <= 1e-3 and rep.max_rotation_diff <= 1e-3
    assert rep.ap_torch == pytest.approx(rep.ap_onnx, abs=1e-9)


def test_padding_changes_nothing(setup):
    """The same scan through the graph and the unpadded torch network: identical peaks."""
    victim, frames, out = setup
    twin = PointPillarsOnnx(out)
    feats, coords, mask = pillarise(crop_scan(frames[0].scan, frames[0].calib, frames[0].image_size, TINY.grid),
                                    TINY.grid)
    a, b = victim.network(feats, coords, mask), twin.network(feats, coords, mask)
    assert len(feats) < twin.max_pillars and np.abs(a - b).max() <= 1e-4


def test_registered_like_the_cascade_twins(setup):
    _, frames, out = setup
    spec = victim_spec(out)
    assert spec.info.capabilities.modalities == ("lidar",) and spec.info.capabilities.backend == "onnx"
    twin = spec.create(threads=1)
    assert isinstance(twin, PointPillarsOnnx)
    assert len(twin.detect([replace(frames[0], labels=None)])[0]) > 0
    assert isinstance(spec.create(seed=1), PointPillarsOnnx)  # the runner passes its seed to every victim
    with pytest.raises(RobustBenchError) as err:
        spec.create(gather="topk")
    assert "'gather' is for F-PN cascades" in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(RobustBenchError, match="'threads'"):
        spec.create(threads=0)


def test_changed_graph_refused(setup, tmp_path):
    _, _, out = setup
    copy = tmp_path / "copy"
    copy.mkdir()
    (copy / "manifest.json").write_text((out / "manifest.json").read_text())
    data = bytearray((out / "pointpillars.onnx").read_bytes())
    data[-1] ^= 1
    (copy / "pointpillars.onnx").write_bytes(bytes(data))
    with pytest.raises(DataFormatError, match="sha256 does not match"):
        PointPillarsOnnx(copy)
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["format"] = "something/1"
    (copy / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DataFormatError, match="field 'format'"):
        PointPillarsOnnx(copy)


def test_too_many_pillars_refused(setup):
    _, _, out = setup
    twin = PointPillarsOnnx(out)
    m = TINY.grid.max_points
    n = twin.max_pillars + 1
    with pytest.raises(RobustBenchError, match="more than the graph's max_pillars"):
        twin.network(np.zeros((n, m, 9), np.float32), np.zeros((n, 2), np.int64), np.zeros((n, m), bool))


def test_export_command_writes_a_loadable_twin(setup, tmp_path, capsys):
    """`victims export-onnx pointpillars --victim-arg weights=FILE`: the graph of those weights, a manifest
    naming the weights file by sha256 and the command that rebuilds it; the twin detects as the torch victim."""
    victim, frames, _ = setup
    weights = tmp_path / "tiny.pt"
    torch.save({"config": TINY.to_dict(), "state_dict": victim.model.state_dict()}, weights)
    out = tmp_path / "cli-twin"
    argv = ["victims", "export-onnx", "pointpillars", "--out", str(out), "--exporter", "dynamo",
            "--victim-arg", f"weights={weights}"]
    assert main(argv) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["source"]["kwargs"]["weights"]["sha256"] == hashlib.sha256(weights.read_bytes()).hexdigest()
    assert manifest["reproduce"]["command"].startswith("robustbench3d export-onnx pointpillars --out DIR")
    twin = PointPillarsOnnx(out)
    a, b = victim.detect(frames[:1])[0], twin.detect(frames[:1])[0]
    assert len(a) == len(b) and np.abs(a.score - b.score).max() <= 1e-5
    assert main([*argv, "--share", str(tmp_path / "x")]) == 2
    assert "--share: a PointPillars export is one graph" in capsys.readouterr().err


@pytest.mark.skipif(shipped("pointpillars") is None or "pointpillars-onnx" not in VICTIMS.names(),
                    reason="no shipped pointpillars weights and twin")
def test_shipped_twin_is_pinned_reproduced_and_at_parity(setup, tmp_path):
    _, frames, _ = setup
    onnx_dir = weights_dir() / SHIPPED_POINTPILLARS["pointpillars-onnx"]
    manifest = json.loads((onnx_dir / "manifest.json").read_text())
    assert VICTIMS.get("pointpillars-onnx").info.weights_sha256 == hashlib.sha256(
        (onnx_dir / "manifest.json").read_bytes()).hexdigest()
    assert VICTIMS.get("pointpillars-onnx").info.capabilities.modalities == ("lidar",)
    assert manifest["source"] == {"victim": "pointpillars", "kwargs": {},
                                  "weights_sha256": shipped("pointpillars").sha256}
    graph = onnx_dir / manifest["graph"]["file"]
    assert hashlib.sha256(graph.read_bytes()).hexdigest() == manifest["graph"]["sha256"]
    victim, twin = create_victim("pointpillars"), create_victim("pointpillars-onnx")
    rep = parity(victim, twin, frames, [f.labels for f in frames])
    assert rep.max_output_diff <= 1e-4 and rep.same_counts and rep.max_score_diff <= 1e-5
    assert rep.ap_torch == pytest.approx(rep.ap_onnx, abs=1e-9)
    import onnx
    import onnxscript

    ex = manifest["exporter"]
    here = {"torch": torch.__version__, "onnx": onnx.__version__, "onnxscript": onnxscript.__version__}
    if any(ex[k] != v for k, v in here.items() if ex.get(k) is not None):
        pytest.skip(f"exporter versions {here} differ from the recorded {ex}")
    argv = shlex.split(manifest["reproduce"]["command"].replace("DIR", str(tmp_path / "again")))
    assert main(argv[1:]) == 0
    again = json.loads((tmp_path / "again" / "manifest.json").read_text())
    assert again["graph"]["sha256"] == manifest["graph"]["sha256"]


def printed(text: str, check: str) -> str:
    """The value column of row ``check`` of the parity table in ``text``."""
    match = re.search(rf"^{re.escape(check)}\s+(\S+)\s", text, re.M)
    assert match, f"no row {check!r} in:\n{text}"
    return match.group(1)


def save_weights(path, model) -> str:
    torch.save({"config": TINY.to_dict(), "state_dict": model.state_dict()}, path)
    return str(path)


@pytest.mark.skipif(shipped("pointpillars") is None or "pointpillars-onnx" not in VICTIMS.names(),
                    reason="no shipped pointpillars weights and twin")
def test_parity_command_on_the_shipped_twin(setup, synth_root, tmp_path, capsys):
    """`victims parity pointpillars --onnx victims/weights/pointpillars-onnx`: every number within its tolerance,
    PASS, exit 0; the map difference and the detection counts are those measured here on the same frames."""
    _, frames, _ = setup
    onnx_dir = weights_dir() / SHIPPED_POINTPILLARS["pointpillars-onnx"]
    report = tmp_path / "parity.json"
    assert main(["victims", "parity", "pointpillars", "--onnx", str(onnx_dir), "--data", str(synth_root),
                 "--max-frames", "2", "--json", str(report)]) == 0
    text = capsys.readouterr().out
    victim, twin = create_victim("pointpillars"), create_victim("pointpillars-onnx")
    maps = max(float(np.abs(victim.output(f.scan, f.calib, f.image_size)
                            - run_scan(twin.network, crop_scan(f.scan, f.calib, f.image_size, twin.cfg.grid),
                                       twin.cfg)).max()) for f in frames)
    assert maps <= 1e-4
    assert float(printed(text, "output maps max |Δ| (9 channels)")) == pytest.approx(maps, rel=1e-3)
    counts = [(len(a), len(b)) for a, b in zip(victim.detect(frames), twin.detect(frames), strict=True)]
    assert all(a == b for a, b in counts) and sum(a for a, _ in counts) > 0
    assert printed(text, "detections per frame equal") == "yes"
    assert float(printed(text, "score max |Δ|")) <= 1e-5
    for row in ("location max |Δ| (m)", "dimensions max |Δ| (m)", "rotation_y max |Δ| (rad)"):
        assert float(printed(text, row)) <= 1e-3
    aps = re.search(r"^Car BEV AP R40 moderate: torch (\S+), onnx (\S+)$", text, re.M)
    assert aps and aps.group(1) == aps.group(2)
    assert text.rstrip().endswith("parity: PASS")
    data = json.loads(report.read_text())
    assert data["ok"] and data["parity"]["frames"] == 2
    assert data["parity"]["max_output_diff"] == pytest.approx(maps, rel=1e-6)


def test_parity_command_exports_a_twin_and_fails_beyond_the_tolerance(setup, synth_root, tmp_path, capsys):
    """Without --onnx the victim is exported to a temporary twin (PASS, exit 0); a twin of other weights differs
    beyond the tolerance: FAIL, exit 1."""
    victim, _, out = setup
    same = save_weights(tmp_path / "same.pt", victim.model)
    argv = ["victims", "parity", "pointpillars", "--data", str(synth_root), "--max-frames", "1"]
    assert main([*argv, "--victim-arg", f"weights={same}"]) == 0
    text = capsys.readouterr().out
    assert "(torch) vs a temporary dynamo export (onnxruntime) on 1 frames" in text
    assert float(printed(text, "output maps max |Δ| (9 channels)")) <= 1e-4 and text.rstrip().endswith("PASS")
    other = save_weights(tmp_path / "other.pt", build_model(TINY, 3).eval())
    assert main([*argv, "--onnx", str(out), "--victim-arg", f"weights={other}"]) == 1
    text = capsys.readouterr().out
    assert float(printed(text, "output maps max |Δ| (9 channels)")) > 1e-4
    assert re.search(r"^output maps max \|Δ\| \(9 channels\)\s+\S+\s+<= 0.0001\s+NO$", text, re.M)
    assert text.rstrip().endswith("parity: FAIL")


def test_parity_command_refuses_a_wrong_onnx_directory_in_one_line(setup, tmp_path, capsys, monkeypatch):
    """A directory that is not a PointPillars twin (a cascade export, none, a changed graph), --proposals gt, and
    the twin given to a cascade: one error line, exit 2, before a victim is built or a dataset read."""
    _, _, out = setup

    def forbidden(*args, **kwargs):
        raise AssertionError("parity started work before checking its arguments")

    monkeypatch.setattr("robustbench3d.victims.onnx.torch_source.create_cascade", forbidden)
    monkeypatch.setattr("robustbench3d.datasets.resolve_dataset", forbidden)
    cascade = tmp_path / "cascade"
    cascade.mkdir()
    (cascade / "manifest.json").write_text(json.dumps({"format": "robustbench3d.onnx_cascade/1"}))
    changed = tmp_path / "changed"
    changed.mkdir()
    (changed / "manifest.json").write_text((out / "manifest.json").read_text())
    (changed / "pointpillars.onnx").write_bytes((out / "pointpillars.onnx").read_bytes() + b"\0")
    cases = [
        (["pointpillars", "--onnx", str(cascade)],
         f"{cascade / 'manifest.json'}: holds an F-PN cascade's stages, not a PointPillars graph"),
        (["pointpillars", "--onnx", str(tmp_path / "none")], f"{tmp_path / 'none'}: ONNX victim directory not found"),
        (["pointpillars", "--onnx", str(tmp_path)], f"{tmp_path / 'manifest.json'}: manifest not found"),
        (["pointpillars", "--onnx", str(changed)], f"{changed / 'pointpillars.onnx'}: sha256 does not match"),
        (["pointpillars", "--onnx", str(out), "--proposals", "gt,detector"],
         "--proposals: victim pointpillars finds its own objects; only detector is compared"),
        (["fpointnet-v1-lite", "--onnx", str(out)],
         f"{out / 'manifest.json'}: holds a PointPillars graph, not an F-PN cascade's stages"),
    ]
    for argv, message in cases:
        assert main(["victims", "parity", *argv]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"robustbench3d: error: {message}") and len(err.strip().splitlines()) == 1, err
