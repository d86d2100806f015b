"""No file a user supplies is unpickled. Every command that reads weights, a training checkpoint or
the files a manifest entry follows reads torch files as data only: a crafted pickle (whose
unpickling runs code that creates a marker file), a raw pickle, or a file that is not a torch
archive at all is refused with one line naming the file, exit status 2 and no traceback."""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path

import pytest
import torch

from robustbench3d.cli import main
from robustbench3d.errors import DataFormatError
from robustbench3d.fileio import sha256_file
from robustbench3d.testing import box_car_dataset
from robustbench3d.victims.cascade import FPointNetCascade
from robustbench3d.victims.torchfile import load_torch_data
from robustbench3d.victims.training import CHECKPOINT, read_checkpoint
from robustbench3d.victims.yolo.detector import YoloDetector

torch.set_num_threads(1)


class Payload:
    """Unpickling this object runs arbitrary code: here, code that creates ``marker``."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (exec, (f"open({str(self.marker)!r}, 'w').close()",))


def evil_file(path: Path, marker: Path, kind: str, layout: str = "model") -> Path:
    """A malicious file: ``torch`` (a torch.save archive shaped like a ``model`` / ``checkpoint``
    / ``cascade`` file, the payload in place of data) or ``raw`` (a plain pickle of the payload)."""
    if kind == "raw":
        path.write_bytes(pickle.dumps(Payload(marker)))
        return path
    evil = Payload(marker)
    payload = {"model": {"config": {"layout": "mini"}, "state_dict": evil},
               "checkpoint": {"model": {}, "optimizer": {}, "state": evil, "run_config": {}},
               "cascade": {"format": "robustbench3d.fpointnet_cascade/1", "yolo": evil, "fpointnet": evil}}[layout]
    torch.save(payload, path)
    return path


def not_torch_file(path: Path, kind: str) -> Path:
    """A file that is not a torch archive."""
    if kind == "random":
        path.write_bytes(bytes(range(256)) * 3)
    elif kind == "text":
        path.write_text("these are not weights\n")
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "zip":
        with zipfile.ZipFile(path, "w") as z:
            z.writestr("weights/readme.txt", "a zip archive, but not one torch.save wrote")
    elif kind == "pickle":
        path.write_bytes(pickle.dumps({"config": {}, "state_dict": {}}))
    return path


NOT_TORCH = {"random": "not the zip archive that torch.save writes", "text": "not the zip archive that torch.save",
             "empty": "empty file", "zip": "without the data.pkl record",
             "pickle": "raw pickle, which is never unpickled"}


def assert_refused(capsys, rc: int, path: Path, marker: Path | None, why: str) -> str:
    """Exit 2 with one error line naming ``path`` and ``why``; no traceback; no marker file."""
    out, err = capsys.readouterr()
    if marker is not None:
        assert not marker.exists(), "the file was unpickled: its code ran"
    assert "Traceback" not in out + err
    errors = [ln for ln in err.splitlines() if ln.startswith("robustbench3d: error:")]
    assert len(errors) == 1, err
    assert errors[0].startswith(f"robustbench3d: error: {path}: ") and why in errors[0], errors[0]
    assert rc == 2, err
    return errors[0]


@pytest.fixture
def marker(tmp_path) -> Path:
    return tmp_path / "PWNED"


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory) -> Path:
    return box_car_dataset(tmp_path_factory.mktemp("tiny_kitti"))


@pytest.fixture(scope="module")
def parts(tmp_path_factory) -> dict[str, Path]:
    """Legitimate ``model.pt`` files of both networks and a cascade file of them."""
    d = tmp_path_factory.mktemp("parts")
    cascade = FPointNetCascade.untrained("lite", "mini", seed=3)
    for name, part in cascade.state().items():
        if name != "format":
            torch.save(part, d / f"{name}.pt")
    cascade.save(d / "cascade.pt")
    return {"yolo": d / "yolo.pt", "fpointnet": d / "fpointnet.pt", "cascade": d / "cascade.pt"}


@pytest.fixture(scope="module")
def run_data(tmp_path_factory) -> Path:
    from robustbench3d.synth.writer import generate_dataset

    root = tmp_path_factory.mktemp("synth")
    generate_dataset(root, 1, seed=5, val_fraction=1.0, workers=1, progress=False)
    return root


def test_the_payload_runs_when_unpickled(tmp_path, marker):
    """The malicious files are live: a plain unpickler (or weights_only=False) runs their code."""
    pickle.loads(pickle.dumps(Payload(marker)))
    assert marker.exists()
    marker.unlink()
    torch.load(evil_file(tmp_path / "evil.pt", marker, "torch"), weights_only=False)
    assert marker.exists()


@pytest.mark.parametrize("kind", ["torch", "raw"])
def test_loader_refuses_a_malicious_file_without_running_it(tmp_path, marker, kind):
    path = evil_file(tmp_path / "evil.pt", marker, kind)
    why = "refusing to unpickle it" if kind == "torch" else "raw pickle, which is never unpickled"
    for load in (lambda: load_torch_data(path, "weights file"), lambda: FPointNetCascade.load(path),
                 lambda: FPointNetCascade.from_parts(path, path), lambda: YoloDetector.load(path),
                 lambda: read_checkpoint(path)):
        with pytest.raises(DataFormatError, match=why) as info:
            load()
        assert str(info.value).startswith(f"{path}: ") and "\n" not in str(info.value)
    assert not marker.exists()


def test_loader_reads_data_only_files(parts):
    """Legitimate files (tensors and plain containers) still load, bit for bit."""
    want = torch.load(parts["cascade"], weights_only=True)
    got = load_torch_data(parts["cascade"], "cascade weights file")
    assert got["format"] == want["format"] and got["yolo"]["config"] == want["yolo"]["config"]
    sd = want["fpointnet"]["state_dict"]
    assert all(torch.equal(sd[k], got["fpointnet"]["state_dict"][k]) for k in sd)
    net = YoloDetector.load(parts["yolo"]).net.state_dict()
    assert all(torch.equal(net[k], want["yolo"]["state_dict"][k]) for k in net)


@pytest.mark.parametrize("trainer", ["yolo", "fpointnet"])
@pytest.mark.parametrize("kind", ["torch", "raw"])
def test_train_resume_refuses_a_malicious_checkpoint(tiny_data, tmp_path, marker, trainer, kind, capsys):
    out = tmp_path / "out"
    out.mkdir()
    ckpt = evil_file(out / CHECKPOINT, marker, kind, layout="checkpoint")
    argv = ["train", trainer, "--data", str(tiny_data), "--out", str(out), "--epochs", "1", "--batch-size", "2",
            "--no-progress", "--threads", "1", "--resume"]
    if trainer == "fpointnet":
        argv += ["--model", "lite", "--augment-x", "1"]
    why = "refusing to unpickle it" if kind == "torch" else "raw pickle"
    line = assert_refused(capsys, main(argv), ckpt, marker, why)
    assert not (out / "model.pt").exists()
    if kind == "raw":
        assert "training checkpoint" in line


def test_train_resume_refuses_a_file_that_is_not_a_checkpoint(tiny_data, tmp_path, parts, capsys):
    """A data-only torch file of another kind (a model.pt copied to last.pt) is refused with a hint."""
    out = tmp_path / "out"
    out.mkdir()
    (out / CHECKPOINT).write_bytes(parts["fpointnet"].read_bytes())
    argv = ["train", "fpointnet", "--data", str(tiny_data), "--out", str(out), "--epochs", "1", "--model", "lite",
            "--batch-size", "2", "--augment-x", "1", "--no-progress", "--threads", "1", "--resume"]
    line = assert_refused(capsys, main(argv), out / CHECKPOINT, None, "not a training checkpoint")
    assert "delete it (or use another --out)" in line


@pytest.mark.parametrize("kind", ["torch", "raw"])
def test_train_yolo_init_refuses_a_malicious_file(tiny_data, tmp_path, marker, kind, capsys):
    init = evil_file(tmp_path / "init.pt", marker, kind)
    argv = ["train", "yolo", "--data", str(tiny_data), "--out", str(tmp_path / "out"), "--epochs", "1",
            "--no-progress", "--threads", "1", "--init", str(init)]
    assert_refused(capsys, main(argv), init, marker, "refusing to unpickle" if kind == "torch" else "raw pickle")


@pytest.mark.parametrize("kind", sorted(NOT_TORCH))
def test_train_yolo_init_refuses_a_file_that_is_not_torch(tiny_data, tmp_path, kind, capsys):
    init = not_torch_file(tmp_path / "init.pt", kind)
    argv = ["train", "yolo", "--data", str(tiny_data), "--out", str(tmp_path / "out"), "--epochs", "1",
            "--no-progress", "--threads", "1", "--init", str(init)]
    assert_refused(capsys, main(argv), init, None, NOT_TORCH[kind])


@pytest.mark.parametrize("network", ["yolo", "fpointnet"])
@pytest.mark.parametrize("kind", ["torch", "raw", "cascade"])
def test_pack_refuses_malicious_weights(parts, tmp_path, marker, network, kind, capsys):
    evil = evil_file(tmp_path / "evil.pt", marker, "raw" if kind == "raw" else "torch",
                     layout="cascade" if kind == "cascade" else "model")
    sources = {**{n: str(parts[n]) for n in ("yolo", "fpointnet")}, network: str(evil)}
    out = tmp_path / "packed.pt"
    argv = ["victims", "pack", "--yolo", sources["yolo"], "--fpointnet", sources["fpointnet"], "--out", str(out)]
    assert_refused(capsys, main(argv), evil, marker, "raw pickle" if kind == "raw" else "refusing to unpickle")
    assert not out.exists()


@pytest.mark.parametrize("kind", sorted(NOT_TORCH))
def test_pack_refuses_weights_that_are_not_torch(parts, tmp_path, kind, capsys):
    bad = not_torch_file(tmp_path / "bad.pt", kind)
    argv = ["victims", "pack", "--yolo", str(bad), "--fpointnet", str(parts["fpointnet"]),
            "--out", str(tmp_path / "packed.pt")]
    assert_refused(capsys, main(argv), bad, None, NOT_TORCH[kind])


def test_pack_refuses_weights_that_do_not_fit_their_configuration(parts, tmp_path, capsys):
    state = torch.load(parts["yolo"], weights_only=True)
    state["state_dict"].pop(sorted(state["state_dict"])[0])
    torch.save(state, tmp_path / "short.pt")
    argv = ["victims", "pack", "--yolo", str(tmp_path / "short.pt"), "--fpointnet", str(parts["fpointnet"]),
            "--out", str(tmp_path / "packed.pt")]
    assert_refused(capsys, main(argv), tmp_path / "short.pt", None, "the yolo weights do not fit its configuration")


def _trainer_dir(root: Path, parts: dict[str, Path], task: dict) -> Path:
    """A trainer output directory: a legitimate model.pt and a data-only last.pt with ``task``."""
    root.mkdir()
    (root / "model.pt").write_bytes(parts["yolo"].read_bytes())
    torch.save({"run_config": {"task": task, "loop": {}}, "state": {"step": 3}}, root / CHECKPOINT)
    return root / "model.pt"


@pytest.mark.parametrize("kind", ["torch", "raw"])
def test_pack_manifest_refuses_a_malicious_checkpoint_beside_the_weights(parts, tmp_path, marker, kind, capsys):
    model = _trainer_dir(tmp_path / "yolo", parts, {"epochs": 1})
    ckpt = evil_file(model.parent / CHECKPOINT, marker, kind, layout="checkpoint")
    manifest, out = tmp_path / "manifest.json", tmp_path / "packed.pt"
    argv = ["victims", "pack", "--yolo", str(model), "--fpointnet", str(parts["fpointnet"]), "--out", str(out),
            "--manifest", str(manifest), "--victim", "v"]
    assert_refused(capsys, main(argv), ckpt, marker, "refusing to unpickle" if kind == "torch" else "raw pickle")
    assert not out.exists() and not manifest.exists()


@pytest.mark.parametrize("kind", ["torch", "raw"])
def test_pack_manifest_refuses_a_malicious_init_it_follows(parts, tmp_path, marker, kind, capsys):
    """The checkpoint of a fine-tuning run names its ``init`` file: pack follows it, as data only."""
    init = evil_file(tmp_path / "init.pt", marker, kind)
    model = _trainer_dir(tmp_path / "tuned", parts, {"init": str(init), "init_sha256": sha256_file(init)})
    manifest = tmp_path / "manifest.json"
    argv = ["victims", "pack", "--yolo", str(model), "--fpointnet", str(parts["fpointnet"]),
            "--out", str(tmp_path / "packed.pt"), "--manifest", str(manifest), "--victim", "v"]
    assert_refused(capsys, main(argv), init, marker, "refusing to unpickle" if kind == "torch" else "raw pickle")
    assert not manifest.exists()


def test_pack_manifest_refuses_a_checkpoint_that_is_not_plain_data(parts, tmp_path, capsys):
    """A data-only last.pt whose run configuration holds a tensor cannot become a JSON record."""
    model = _trainer_dir(tmp_path / "yolo", parts, {"epochs": 1})
    torch.save({"run_config": {"task": torch.zeros(2)}, "state": {"step": 3}}, model.parent / CHECKPOINT)
    manifest = tmp_path / "manifest.json"
    argv = ["victims", "pack", "--yolo", str(model), "--fpointnet", str(parts["fpointnet"]),
            "--out", str(tmp_path / "packed.pt"), "--manifest", str(manifest), "--victim", "v"]
    assert_refused(capsys, main(argv), model.parent / CHECKPOINT, None, "field 'run_config': not plain JSON-like")
    assert not manifest.exists()


def test_pack_manifest_refuses_a_pickled_manifest(parts, tmp_path, marker, capsys):
    manifest = evil_file(tmp_path / "manifest.json", marker, "raw")
    argv = ["victims", "pack", "--yolo", str(parts["yolo"]), "--fpointnet", str(parts["fpointnet"]),
            "--out", str(tmp_path / "packed.pt"), "--manifest", str(manifest), "--victim", "v"]
    assert_refused(capsys, main(argv), manifest, marker, "not valid JSON")


def test_pack_manifest_records_a_data_only_checkpoint(parts, tmp_path, capsys):
    """The training record still comes from last.pt (now read as data only)."""
    from robustbench3d.victims.shipped import shipped

    model = _trainer_dir(tmp_path / "yolo", parts, {"epochs": 4})
    manifest = tmp_path / "manifest.json"
    assert main(["victims", "pack", "--yolo", str(model), "--fpointnet", str(parts["fpointnet"]),
                 "--out", str(tmp_path / "packed.pt"), "--manifest", str(manifest), "--victim", "v"]) == 0
    record = shipped("v", manifest).record["training"]["yolo"]
    assert record["run_config"] == {"task": {"epochs": 4}, "loop": {}} and record["steps"] == 3


def _run_argv(run_data: Path, out: Path, *victim_args: str) -> list[str]:
    args = [a for pair in victim_args for a in ("--victim-arg", f"fpointnet-v1-lite:{pair}")]
    return ["run", "--victims", "fpointnet-v1-lite", "--proposals", "gt", "--data", str(run_data), "--out", str(out),
            "--no-progress", *args]


@pytest.mark.parametrize("arg", ["weights", "yolo_weights", "fpointnet_weights"])
@pytest.mark.parametrize("kind", ["torch", "raw"])
def test_run_refuses_malicious_victim_weights(run_data, parts, tmp_path, marker, arg, kind, capsys):
    evil = evil_file(tmp_path / "evil.pt", marker, "raw" if kind == "raw" else "torch",
                     layout="cascade" if arg == "weights" else "model")
    other = {"yolo_weights": f"fpointnet_weights={parts['fpointnet']}",
             "fpointnet_weights": f"yolo_weights={parts['yolo']}"}.get(arg)
    argv = _run_argv(run_data, tmp_path / "run", f"{arg}={evil}", *([other] if other else []))
    assert_refused(capsys, main(argv), evil, marker, "refusing to unpickle" if kind == "torch" else "raw pickle")


@pytest.mark.parametrize("kind", sorted(NOT_TORCH))
def test_run_refuses_victim_weights_that_are_not_torch(run_data, tmp_path, kind, capsys):
    bad = not_torch_file(tmp_path / "bad.pt", kind)
    assert_refused(capsys, main(_run_argv(run_data, tmp_path / "run", f"weights={bad}")), bad, None,
                       NOT_TORCH[kind])


@pytest.mark.parametrize("command", ["export-onnx", "parity"])
def test_onnx_commands_refuse_malicious_victim_weights(run_data, tmp_path, marker, command, capsys):
    evil = evil_file(tmp_path / "evil.pt", marker, "torch", layout="cascade")
    extra = ["--out", str(tmp_path / "onnx")] if command == "export-onnx" else ["--data", str(run_data)]
    argv = [command, "fpointnet-v1-lite", "--victim-arg", f"weights={evil}", "--exporter", "legacy", *extra]
    assert_refused(capsys, main(argv), evil, marker, "refusing to unpickle")
    assert not (tmp_path / "onnx").exists()


def test_checkpoints_the_trainer_writes_hold_data_only(tiny_data, tmp_path):
    """last.pt loads with the data-only loader and holds only tensors and plain containers."""
    from robustbench3d.victims.fpointnet.training import FPointNetTrainConfig
    from robustbench3d.victims.fpointnet.training import train as train_fpn
    from robustbench3d.victims.training import LoopOptions

    train_fpn(tiny_data, tmp_path, FPointNetTrainConfig(model="lite", augment_x=1),
              LoopOptions(epochs=1, batch_size=2, max_steps=1, progress=False))
    ckpt = read_checkpoint(tmp_path / CHECKPOINT, resumable=True)

    def plain(x) -> bool:
        if isinstance(x, dict):
            return all(isinstance(k, str | int) and plain(v) for k, v in x.items())
        if isinstance(x, list | tuple):
            return all(plain(v) for v in x)
        return x is None or isinstance(x, bool | int | float | str | torch.Tensor)

    assert plain(ckpt) and ckpt["state"]["step"] == 1 and ckpt["model"] and ckpt["optimizer"]["state"]
    assert zipfile.is_zipfile(tmp_path / CHECKPOINT)
