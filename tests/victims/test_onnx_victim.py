"""ONNX victims end to end with seeded random weights (non-trivial BatchNorm statistics, a non-zero
T-Net head, a seg bias giving partial masks): per-stage export with both exporters, the manifest,
byte-determinism, onnxruntime-only inference, clear errors for bad directories, and parity at
three levels (stage tensors, boxes per frame, AP) on real KITTI frames and generated ones."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from torch import nn

from robustbench3d.cli import main
from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.fileio import sha256_file
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.victims import create_victim
from robustbench3d.victims.cascade import CascadeSettings, FPointNetCascade
from robustbench3d.victims.onnx.export import ExportOptions, describe_kwargs, export_cascade, legacy_exporter_available
from robustbench3d.victims.onnx.manifest import STAGES, read_manifest
from robustbench3d.victims.onnx.parity import Tolerances, box_parity, run_parity, tensor_parity
from robustbench3d.victims.onnx.runtime import OnnxCascade

torch.set_num_threads(1)
SEED = 3


def randomised_cascade(seed: int) -> FPointNetCascade:
    """The lite cascade with seeded random weights that exercise every stage."""
    cascade = FPointNetCascade.untrained("lite", "mini", seed=seed, settings=CascadeSettings(seed=seed))
    cascade.yolo.cfg = replace(cascade.yolo.cfg, max_detections=8)  # bounded proposals from a random detector
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in [*cascade.fpn.modules(), *cascade.yolo.net.modules()]:
            if isinstance(m, nn.modules.batchnorm._BatchNorm):
                m.running_mean.normal_(0, 0.2, generator=gen)
                m.running_var.uniform_(0.5, 2.0, generator=gen)
                m.weight.uniform_(0.5, 1.5, generator=gen)
                m.bias.normal_(0, 0.1, generator=gen)
        cascade.fpn.tnet.out.weight.normal_(0, 0.05, generator=gen)
        cascade.fpn.tnet.out.bias.normal_(0, 0.1, generator=gen)
        pts = torch.randn(4, cascade.num_points, 4, generator=gen) + torch.tensor([0.0, 1.0, 15.0, 0.0])
        logits = cascade.fpn.seg(pts, torch.eye(3)[:1].expand(4, 3))
        cascade.fpn.seg.classifier.bias[1] -= (logits[..., 1] - logits[..., 0]).median()  # partial masks
    return cascade


def load_victim(weights: Path, seed: int = SEED) -> FPointNetCascade:
    return create_victim("fpointnet-v1-lite", weights=str(weights), seed=seed)


def export(weights: Path, out: Path, exporter: str) -> None:
    export_cascade(load_victim(weights), out, ExportOptions(exporter),
                   source={"victim": "fpointnet-v1-lite", "kwargs": describe_kwargs({"weights": str(weights)})},
                   reproduce_command=f"robustbench3d export-onnx fpointnet-v1-lite --exporter {exporter}")


@pytest.fixture(scope="module")
def weights(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("weights") / "cascade.pt"
    randomised_cascade(SEED).save(path)
    return path


@pytest.fixture(scope="module", params=["dynamo", "legacy"])
def exported(request, weights, tmp_path_factory) -> tuple[str, Path]:
    if request.param == "legacy" and not legacy_exporter_available():
        pytest.skip("this torch has no legacy (TorchScript) ONNX exporter")
    out = tmp_path_factory.mktemp(f"onnx-{request.param}")
    export(weights, out, request.param)
    return request.param, out


@pytest.fixture(scope="module")
def base_dir(weights, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("onnx-base")
    export(weights, out, "legacy" if legacy_exporter_available() else "dynamo")  # the fastest exporter
    return out


@pytest.fixture(scope="module")
def frames(kitti_samples):
    ds = KittiDataset(kitti_samples, split=None)
    return [ds.frame(f) for f in ds.frame_ids]


@pytest.fixture(scope="module")
def synth(shared_split) -> Path:
    return shared_split(4, seed=0, val_fraction=0.5)


# ---- export and manifest -------------------------------------------------------------------
def test_manifest_layout(exported, weights):
    exporter, out = exported
    m = read_manifest(out)
    assert [s.name for s in m.stages] == list(STAGES)
    shapes = {s.name: ([t.shape for t in s.inputs], [t.shape for t in s.outputs]) for s in m.stages}
    assert shapes == {
        "detector_2d": ([(1, 3, 192, 640)], [(1, 18, 12, 40), (1, 18, 24, 80)]),
        "instance_segmentation": ([(4, 512, 4), (4, 3)], [(4, 512, 2)]),
        "center_regression": ([(1, 512, 3), (1, 3)], [(1, 3)]),
        "box_estimation": ([(1, 512, 3), (1, 3)], [(1, 59)]),
    }
    assert m.exporter["name"] == exporter and m.exporter["opset"] == 18 and m.exporter["torch"] == torch.__version__
    assert (m.exporter["onnxscript"] is not None) == (exporter == "dynamo")
    victim = load_victim(weights)
    assert m.config["fpointnet"] == json.loads(json.dumps(victim.fpn.cfg.to_dict()))
    assert m.config["yolo"]["max_detections"] == 8 and m.config["settings"]["seed"] == SEED
    assert m.source["kwargs"]["weights"] == {"file": "cascade.pt", "sha256": sha256_file(weights)}
    text = (out / "manifest.json").read_text()
    assert str(weights.parent) not in text and str(out) not in text  # no machine-specific paths
    for s in m.stages:
        assert sha256_file(out / s.file) == s.sha256
        model = onnx.load(out / s.file)
        assert {o.domain: o.version for o in model.opset_import}.get("", 18) == 18
        assert all(n.domain in ("", "ai.onnx") for n in model.graph.node)
        assert all(d.HasField("dim_value") for v in [*model.graph.input, *model.graph.output]
                   for d in v.type.tensor_type.shape.dim)
        assert not any(n.doc_string or len(n.metadata_props) for n in model.graph.node)  # no source paths


def test_export_is_byte_deterministic(exported, weights, tmp_path):
    exporter, out = exported
    export(weights, tmp_path, exporter)
    assert [(s.file, s.sha256) for s in read_manifest(tmp_path).stages] == \
        [(s.file, s.sha256) for s in read_manifest(out).stages]
    assert (tmp_path / "manifest.json").read_bytes() == (out / "manifest.json").read_bytes()


# ---- inference ---------------------------------------------------------------------------
def test_inference_imports_no_torch(exported, frames, kitti_samples, weights):
    _, out = exported
    code = (
        "import json, sys\n"
        "from robustbench3d.kitti.dataset import KittiDataset\n"
        "from robustbench3d.victims.onnx.runtime import OnnxCascade\n"
        f"ds = KittiDataset({str(kitti_samples)!r}, split=None)\n"
        "frames = [ds.frame(f) for f in ds.frame_ids]\n"
        f"victim = OnnxCascade({str(out)!r}, seed={SEED})\n"
        "rows = {p: [d.to_text(2) for d in victim.detect(frames, p)] for p in ('gt', 'detector')}\n"
        "print(json.dumps({'torch': 'torch' in sys.modules, 'rows': rows}))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                          env={"PATH": "", "OMP_NUM_THREADS": "1", "ROBUSTBENCH3D_NO_PLUGINS": "1"})
    result = json.loads(proc.stdout)
    assert result["torch"] is False
    victim = load_victim(weights)
    for source in ("gt", "detector"):
        ref = victim.detect(frames, source)
        got = [DetText(t) for t in result["rows"][source]]
        assert [g.geometry for g in got] == [DetText(r.to_text(2)).geometry for r in ref]
        assert sum(len(g.geometry) for g in got) > 0


class DetText:
    """Result-file text split into geometry lines and scores."""

    def __init__(self, text: str):
        lines = text.splitlines()
        self.geometry = [line.rsplit(" ", 1)[0] for line in lines]
        self.scores = [float(line.rsplit(" ", 1)[1]) for line in lines]


def test_padded_batches_do_not_change_a_frustums_outputs(base_dir):
    seg = OnnxCascade(base_dir).stages["instance_segmentation"]
    rng = np.random.default_rng(0)
    pts = rng.normal(0, 1, (6, 512, 4)).astype(np.float32)
    one_hot = np.eye(3, dtype=np.float32)[[0, 1, 2, 0, 1, 2]]
    full = seg.run(pts, one_hot)[0]
    assert full.shape == (6, 512, 2)  # 4 + 2 padded to 4
    for rows in ([0], [5, 1], [3, 2, 1]):
        assert np.array_equal(seg.run(pts[rows], one_hot[rows])[0], full[rows])


# ---- bad directories ---------------------------------------------------------------------
def _rewrite_manifest(directory: Path, edit) -> None:
    data = json.loads((directory / "manifest.json").read_text())
    edit(data)
    (directory / "manifest.json").write_text(json.dumps(data))


def _set_sha(data: dict, stage: str, path: Path) -> None:
    next(s for s in data["stages"] if s["name"] == stage)["sha256"] = sha256_file(path)


def test_bad_directories_get_clear_errors_naming_the_file(base_dir, tmp_path):
    def copy(name: str) -> Path:
        return Path(shutil.copytree(base_dir, tmp_path / name))

    with pytest.raises(DataFormatError, match="directory not found"):
        OnnxCascade(tmp_path / "nowhere")
    d = copy("no-manifest")
    (d / "manifest.json").unlink()
    with pytest.raises(DataFormatError, match=r"manifest\.json: manifest not found"):
        OnnxCascade(d)
    d = copy("bad-json")
    (d / "manifest.json").write_text("{")
    with pytest.raises(DataFormatError, match=r"manifest\.json: not valid JSON"):
        OnnxCascade(d)
    d = copy("missing-stage")
    _rewrite_manifest(d, lambda m: m.update(stages=[s for s in m["stages"] if s["name"] != "box_estimation"]))
    with pytest.raises(DataFormatError, match=r"manifest\.json: stage 'box_estimation' missing"):
        OnnxCascade(d)
    d = copy("missing-file")
    (d / "center_regression.onnx").unlink()
    with pytest.raises(DataFormatError, match=r"center_regression\.onnx: stage 'center_regression' file missing"):
        OnnxCascade(d)
    d = copy("hash")
    data = bytearray((d / "instance_segmentation.onnx").read_bytes())
    data[-1] ^= 0xFF
    (d / "instance_segmentation.onnx").write_bytes(bytes(data))
    with pytest.raises(DataFormatError, match=r"instance_segmentation\.onnx: sha256 [0-9a-f]{64} does not match"):
        OnnxCascade(d)
    d = copy("corrupt")
    (d / "box_estimation.onnx").write_bytes(b"\x08\x07not a protobuf" * 50)
    _rewrite_manifest(d, lambda m: _set_sha(m, "box_estimation", d / "box_estimation.onnx"))
    with pytest.raises(DataFormatError, match=r"box_estimation\.onnx: onnxruntime cannot load stage"):
        OnnxCascade(d)
    d = copy("swapped")  # a valid graph with the wrong interface under the stage's name
    shutil.copy(d / "center_regression.onnx", d / "box_estimation.onnx")
    _rewrite_manifest(d, lambda m: _set_sha(m, "box_estimation", d / "box_estimation.onnx"))
    with pytest.raises(DataFormatError, match=r"box_estimation\.onnx: stage 'box_estimation': graph outputs"):
        OnnxCascade(d)

    def batch_two(m: dict) -> None:  # consistent manifest, but the graph's batch is 4
        seg = next(s for s in m["stages"] if s["name"] == "instance_segmentation")
        for t in seg["inputs"] + seg["outputs"]:
            t["shape"][0] = 2
    d = copy("shapes")
    _rewrite_manifest(d, batch_two)
    with pytest.raises(DataFormatError, match=r"instance_segmentation\.onnx: .*graph inputs .* differ from"):
        OnnxCascade(d)
    d = copy("config")
    _rewrite_manifest(d, lambda m: m["config"]["fpointnet"].update(num_points=1024))
    with pytest.raises(DataFormatError, match=r"manifest\.json: stage 'instance_segmentation': inputs"):
        OnnxCascade(d)


def test_stage_file_names_are_bare_or_a_sibling_directorys():
    from robustbench3d.victims.onnx.manifest import is_stage_file_name

    for ok in ("a.onnx", "../lite-onnx/detector_2d.onnx"):
        assert is_stage_file_name(ok), ok
    for bad in ("a.pt", "sub/a.onnx", "../a.onnx", "../../x/a.onnx", "../x/../a.onnx", "../../a.onnx",
                "/abs/a.onnx", "../x/y/a.onnx", "./a.onnx", "../x/", "..\\x\\a.onnx", ".onnx/../a.onnx"):
        assert not is_stage_file_name(bad), bad


def test_export_shares_identical_graphs_with_a_sibling_directory(base_dir, weights, synth, tmp_path):
    """``--share``: stages byte-identical to the sibling's are referenced (``../SIBLING/NAME.onnx``),
    not written; the victim loads and detects as the sibling does; a changed shared file or a
    directory elsewhere is refused, naming it."""
    shutil.copytree(base_dir, tmp_path / "base")
    out = tmp_path / "twin"
    exporter = read_manifest(base_dir).exporter["name"]
    export_cascade(load_victim(weights), out, ExportOptions(exporter),
                   source={"victim": "fpointnet-v1-lite", "kwargs": {}}, reproduce_command="x",
                   share=tmp_path / "base")
    manifest = read_manifest(out)
    assert [s.file for s in manifest.stages] == [f"../base/{s.name}.onnx" for s in manifest.stages]
    assert sorted(p.name for p in out.iterdir()) == ["manifest.json"]
    ds = KittiDataset(synth, split=None)
    frames = [ds.frame(f) for f in ds.frame_ids[:2]]
    want = OnnxCascade(tmp_path / "base", seed=SEED).detect(frames, "gt")
    got = OnnxCascade(out, seed=SEED).detect(frames, "gt")
    assert [a.to_text() for a in want] == [b.to_text() for b in got] and any(len(a) for a in want)
    with pytest.raises(RobustBenchError, match="must be another ONNX victim directory beside"):
        export_cascade(load_victim(weights), tmp_path / "elsewhere" / "twin", ExportOptions(exporter),
                       source={}, reproduce_command="x", share=tmp_path / "base")
    assert not (tmp_path / "elsewhere").exists()
    with pytest.raises(RobustBenchError, match="must be another ONNX victim directory beside"):  # itself
        export_cascade(load_victim(weights), out, ExportOptions(exporter), source={}, reproduce_command="x",
                       share=out)
    assert read_manifest(out).stages == manifest.stages  # the refused export left the directory as it was
    data = bytearray((tmp_path / "base" / "box_estimation.onnx").read_bytes())
    data[-1] ^= 0xFF
    (tmp_path / "base" / "box_estimation.onnx").write_bytes(bytes(data))
    with pytest.raises(DataFormatError, match=r"base/box_estimation\.onnx: sha256 [0-9a-f]{64} does not match"):
        OnnxCascade(out)


# ---- parity ------------------------------------------------------------------------------
def test_stage_tensor_parity_and_input_sensitivity(exported, weights, frames):
    tol = Tolerances()
    tensors, sensitivity = tensor_parity(load_victim(weights), OnnxCascade(exported[1]), frames, tol)
    assert {t.stage for t in tensors} == set(STAGES) and len(tensors) == 5
    for t in tensors:
        assert t.ok and t.max_abs_diff <= 1e-4 and t.max_abs_ref > 1e-2, t
        assert 0.0 <= t.mismatch_fraction <= t.differing_fraction <= 1.0
    assert len(sensitivity) == 7  # image; points, one_hot; object_points, one_hot (x2)
    for s in sensitivity:
        assert s.ok and s.torch_change > 1e-4 and s.onnx_change > 1e-4, s  # non-vacuous with these weights


def test_a_graph_with_baked_constants_is_caught(base_dir, weights, frames, tmp_path):
    d = Path(shutil.copytree(base_dir, tmp_path / "baked"))
    h = onnx.helper
    value = np.random.default_rng(0).normal(size=(1, 59)).astype(np.float32)
    graph = h.make_graph(
        [h.make_node("Constant", [], ["box_output"], value=onnx.numpy_helper.from_array(value))], "baked",
        [h.make_tensor_value_info("object_points", onnx.TensorProto.FLOAT, [1, 512, 3]),
         h.make_tensor_value_info("one_hot", onnx.TensorProto.FLOAT, [1, 3])],
        [h.make_tensor_value_info("box_output", onnx.TensorProto.FLOAT, [1, 59])])
    onnx.save(h.make_model(graph, opset_imports=[h.make_opsetid("", 18)], ir_version=9), d / "box_estimation.onnx")
    _rewrite_manifest(d, lambda m: _set_sha(m, "box_estimation", d / "box_estimation.onnx"))
    tensors, sensitivity = tensor_parity(load_victim(weights), OnnxCascade(d), frames, Tolerances())
    box = [s for s in sensitivity if s.stage == "box_estimation"]
    assert box and all(not s.ok and s.onnx_change == 0.0 and s.torch_change > 1e-4 for s in box)
    assert [t.ok for t in tensors if t.stage == "box_estimation"] == [False]
    assert all(s.ok for s in sensitivity if s.stage != "box_estimation")


def test_boxes_per_frame_are_identical(exported, weights, frames):
    victim, onnx_victim = load_victim(weights), OnnxCascade(exported[1], seed=SEED)
    for source, min_rows in (("gt", 3), ("detector", 6)):
        a, b = victim.detect(frames, source), onnx_victim.detect(frames, source)
        result = box_parity(frames, source, a, b, Tolerances())
        assert result.ok and result.identical_frames == len(frames), result
        assert result.rows_torch == result.rows_onnx >= min_rows
    # the check is not vacuous: a different resampling seed changes the written rows
    other = OnnxCascade(exported[1], seed=SEED + 1).detect(frames, "gt")
    assert not box_parity(frames, "gt", victim.detect(frames, "gt"), other, Tolerances()).ok


def test_ap_parity_on_a_generated_val_split(exported, weights, synth):
    ds = KittiDataset(synth, split="val")
    frames = [ds.frame(f) for f in ds.frame_ids]
    report = run_parity(load_victim(weights), OnnxCascade(exported[1], seed=SEED), frames)
    assert report.ok, report.to_dict()
    assert [a.proposals for a in report.ap] == ["gt", "detector"]
    for a in report.ap:
        assert a.values >= 24 and a.max_abs_delta <= 0.01
    assert sum(b.rows_torch for b in report.boxes) > 0


def test_parity_command(base_dir, weights, synth, tmp_path, capsys):
    out = tmp_path / "report.json"
    rc = main(["parity", "fpointnet-v1-lite", "--onnx", str(base_dir), "--data", str(synth), "--max-frames", "1",
               "--victim-arg", f"weights={weights}", "--seed", str(SEED), "--json", str(out)])
    text = capsys.readouterr().out
    assert rc == 0, text
    report = json.loads(out.read_text())
    assert report["ok"] and {t["stage"] for t in report["tensors"]} == set(STAGES)
    assert "== boxes per frame" in text and text.rstrip().endswith("parity: PASS")
    other = tmp_path / "other.pt"
    randomised_cascade(SEED + 10).save(other)  # different weights than the export: parity must fail
    rc = main(["parity", "fpointnet-v1-lite", "--onnx", str(base_dir), "--data", str(synth), "--max-frames", "1",
               "--victim-arg", f"weights={other}", "--proposals", "gt"])
    assert rc == 1 and capsys.readouterr().out.rstrip().endswith("parity: FAIL")


def test_export_command_reproduces_the_hashes(exported, weights, tmp_path):
    """The CLI in a fresh process (another hash seed) writes the same bytes as the in-process export."""
    exporter, out = exported
    proc = subprocess.run([sys.executable, "-m", "robustbench3d", "export-onnx", "fpointnet-v1-lite", "--out",
                           str(tmp_path), "--exporter", exporter, "--victim-arg", f"weights={weights}",
                           "--victim-arg", f"seed={SEED}"], capture_output=True, text=True,
                          env={"PATH": "", "OMP_NUM_THREADS": "1", "PYTHONHASHSEED": "12345",
                               "ROBUSTBENCH3D_NO_PLUGINS": "1"})
    assert proc.returncode == 0, proc.stderr
    assert [s.sha256 for s in read_manifest(tmp_path).stages] == [s.sha256 for s in read_manifest(out).stages]
    assert hashlib.sha256((tmp_path / "detector_2d.onnx").read_bytes()).hexdigest()[:16] in proc.stdout
    assert read_manifest(tmp_path).reproduce["command"] == (
        f"robustbench3d export-onnx fpointnet-v1-lite --out DIR --exporter {exporter} --opset 18 --batch-2d 1 "
        f"--batch-seg 4 --victim-arg seed={SEED} --victim-arg weights=cascade.pt")


@pytest.mark.slow
def test_ap_parity_on_more_generated_frames(weights, tmp_path):
    """Slow: AP-level parity of both exporters on a 16-frame generated dataset (8 val frames)."""
    from robustbench3d.testing import synth_dataset

    synth_dataset(tmp_path / "data", 16, seed=1)
    ds = KittiDataset(tmp_path / "data", split="val")
    frames = [ds.frame(f) for f in ds.frame_ids]
    for exporter in ("dynamo", "legacy") if legacy_exporter_available() else ("dynamo",):
        export(weights, tmp_path / exporter, exporter)
        report = run_parity(load_victim(weights), OnnxCascade(tmp_path / exporter, seed=SEED), frames)
        assert report.ok, report.to_dict()
