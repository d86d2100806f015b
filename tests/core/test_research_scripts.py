"""The research scripts (``research/``): each imports (from its file, without running its main) against today's
package, ``--help`` of those with argparse exits 0, shell scripts parse (``bash -n``); the one substitution of
product code left (``train_iou_loss.box_gradients``) takes effect, and its loss is used through the image-loss
table by name."""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import torch

RESEARCH = Path(__file__).resolve().parents[2] / "research"
PY_SCRIPTS = sorted(RESEARCH.glob("*.py"))
SH_SCRIPTS = sorted(RESEARCH.glob("*.sh"))


def import_script(path: Path) -> ModuleType:
    """``path`` imported as a module named after its stem (so ``if __name__ == "__main__"`` stays false), with
    its folder first on ``sys.path`` as when Python runs it (a script may import its siblings); the module and
    the siblings it imported are removed from ``sys.modules`` afterwards."""
    before = set(sys.modules)
    sys.path.insert(0, str(path.parent))
    try:
        spec = importlib.util.spec_from_file_location(f"research_{path.stem}", path)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(path.parent))
        for name in set(sys.modules) - before:
            if getattr(sys.modules[name], "__file__", None) and Path(sys.modules[name].__file__).parent == path.parent:
                del sys.modules[name]


def test_the_research_folder_holds_the_scripts():
    names = {p.name for p in PY_SCRIPTS + SH_SCRIPTS}
    assert {"frustum_share.py", "paired_vs_control.py", "shape_bound.py", "texture_bound.py",
            "train_iou_loss.py", "train_sweep.sh"} <= names
    assert (RESEARCH / "README.md").is_file()
    readme = (RESEARCH / "README.md").read_text(encoding="utf-8")
    missing = sorted(n for n in names if f"`{n}`" not in readme)
    assert not missing, f"research/README.md says nothing of {missing}"


@pytest.mark.parametrize("path", PY_SCRIPTS, ids=lambda p: p.name)
def test_script_imports_and_help_exits_0(path: Path):
    from robustbench3d.attacks.losses import IMAGE_LOSSES

    losses = list(IMAGE_LOSSES)
    module = import_script(path)
    assert losses == list(IMAGE_LOSSES), "importing a research script changed the image-loss table"
    assert callable(getattr(module, "main", None)), f"{path.name}: no main()"
    if hasattr(module, "argparse"):  # an argparse script: its --help runs every import and builds the parser
        out = subprocess.run([sys.executable, str(path), "--help"], capture_output=True, text=True, timeout=120,
                             cwd=RESEARCH.parent)
        assert out.returncode == 0, out.stderr
        assert "usage:" in out.stdout


@pytest.mark.parametrize("path", SH_SCRIPTS, ids=lambda p: p.name)
def test_shell_script_parses(path: Path):
    out = subprocess.run(["bash", "-n", str(path)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr


def test_a_script_importing_a_vanished_name_fails_the_import(tmp_path):
    """The check above catches a research script left behind by a rename in the package: a copy of
    ``texture_bound.py`` importing a name the package lacks, or a sibling's name that is gone, does not import."""
    for script, old, new in [("texture_bound.py", "neg_log_one_minus_product", "neg_log_one_minus_product_gone"),
                             ("train_iou_loss.py", "box_gradients", "box_gradients_gone")]:
        copy = tmp_path / script.removesuffix(".py")
        copy.mkdir()
        for p in PY_SCRIPTS:
            shutil.copy(p, copy / p.name)
        target = copy / ("texture_bound.py" if script == "train_iou_loss.py" else script)
        source = (copy / script).read_text(encoding="utf-8")
        assert old in source
        (copy / script).write_text(source.replace(old, new), encoding="utf-8")
        import_script(copy / "frustum_share.py")  # an untouched copy imports
        with pytest.raises(ImportError, match=old):
            import_script(target)


@pytest.fixture(scope="module")
def iou_script() -> ModuleType:
    return import_script(RESEARCH / "train_iou_loss.py")


@pytest.fixture(scope="module")
def victim(lite_victim):
    return lite_victim  # the session's shared one (conftest): read only


@pytest.fixture(scope="module")
def synth(shared_split) -> Path:
    """Generated frames 0-3; train: 1 and 2."""
    return shared_split(4, seed=0, val_fraction=0.5)


def test_box_gradients_keeps_the_candidate_ious_differentiable(iou_script, victim, synth):
    """Inside ``box_gradients()`` the victim's candidates carry the IoU's gradient w.r.t. the image (the loss
    ``iou`` needs it; the substitution must reach the function the detector calls), with the same candidates and
    IoU values as outside it, where IoUs are detached (the oracle's contract) and the loss refuses them."""
    import robustbench3d.victims.yolo.detector as detector
    from robustbench3d.attacks.base import target_cars
    from robustbench3d.datasets import load_ground_truth, resolve_dataset

    dataset = resolve_dataset(synth, "train", progress=False)
    frame = dataset.kitti().frame(load_ground_truth(dataset).frame_ids[0])
    image = torch.from_numpy(frame.image.astype(np.float32) / 255.0).permute(2, 0, 1)[None].requires_grad_()
    boxes = [target_cars(frame.labels).bbox[:3]]
    plain = victim.objectness(image, boxes, iou_threshold=0.5)
    assert not plain.iou.requires_grad and bool((plain.iou >= 0.5).any())
    with pytest.raises(RuntimeError, match="detached"):
        iou_script.iou_weighted_losses(plain, 2)
    original = detector.candidates_for_targets
    with iou_script.box_gradients():
        assert detector.candidates_for_targets is not original
        graded = victim.objectness(image, boxes, iou_threshold=0.5)
    assert detector.candidates_for_targets is original
    assert graded.iou.requires_grad
    assert torch.equal(graded.iou.detach(), plain.iou) and torch.equal(graded.target_index, plain.target_index)
    assert torch.equal(graded.objectness_logit.detach(), plain.objectness_logit)
    (grad,) = torch.autograd.grad(graded.iou.sum(), image)
    assert bool(grad.abs().sum() > 0)


def test_iou_loss_hand_values(iou_script):
    """``-log(1 - o c IoU)`` summed per target over its candidates of IoU >= 0.5 of the image (``use_class=False``:
    ``-log(1 - o IoU)``)."""
    from robustbench3d.victims.base import ObjectnessCandidates

    def sigmoid(x: float) -> float:
        return 1.0 / (1.0 + np.exp(-x))

    c = ObjectnessCandidates(
        objectness_logit=torch.tensor([0.0, 2.0, -1.0, 5.0, 1.0]), class_logit=torch.tensor([1.0, 0.0, 3.0, 5.0, 0.0]),
        boxes=torch.zeros(5, 4), iou=torch.tensor([0.6, 0.2, 0.9, 0.9, 0.5]),
        image_index=torch.tensor([0, 0, 0, 1, 0]), target_index=torch.tensor([0, 0, 1, 0, 0]))
    t0 = -np.log(1 - sigmoid(0) * sigmoid(1) * 0.6) - np.log(1 - sigmoid(1) * sigmoid(0) * 0.5)
    t1 = -np.log(1 - sigmoid(-1) * sigmoid(3) * 0.9)
    got = iou_script.iou_weighted_losses(c, 3).numpy()
    np.testing.assert_allclose(got, [t0, t1, 0.0], rtol=1e-6)
    no_class = iou_script.iou_weighted_losses(c, 3, use_class=False).numpy()
    np.testing.assert_allclose(no_class, [-np.log(1 - sigmoid(0) * 0.6) - np.log(1 - sigmoid(1) * 0.5),
                                          -np.log(1 - sigmoid(-1) * 0.9), 0.0], rtol=1e-6)


def test_train_iou_loss_trains_with_the_loss_by_name(tmp_path, synth, cache):
    """The script registers ``iou`` in the image-loss table for its own process and trains with it by name: the
    object file records ``image_loss: iou``; ``--image-loss`` is refused (the script fixes the loss)."""
    import json

    script = str(RESEARCH / "train_iou_loss.py")
    common = ["adv-texture", "--victim", "fpointnet-v1-lite", "--data", str(synth), "--steps", "1", "--batch-cars",
              "2", "--occlusion", "none", "--eval-every", "0", "--no-progress", "--workers", "1"]
    out = subprocess.run([sys.executable, script, *common, "--out", str(tmp_path / "o.ply")], capture_output=True,
                         text=True, timeout=300, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    sidecar = json.loads((tmp_path / "o.json").read_text(encoding="utf-8"))
    assert sidecar["made_by"]["config"]["image_loss"] == "iou"
    refused = subprocess.run([sys.executable, script, *common, "--out", str(tmp_path / "p.ply"), "--image-loss",
                              "sum"], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert refused.returncode == 2 and "--image-loss" in refused.stderr
    assert not (tmp_path / "p.ply").exists()
