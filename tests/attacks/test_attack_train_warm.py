"""``attack train`` start-up and fresh-cache costs (issue #34): the exact-occlusion scene depths are computed before
the first step (:func:`robustbench3d.attacks.depth_cache.warm_scene_depths`, resumable, in worker processes) so no
step rebuilds a scene, and the optimiser is a written-out Adam that does not import ``torch._dynamo``.

References are independent of the code under test: ``torch.optim.Adam`` itself; the depths of the scene rebuilt
from the generator (:func:`~robustbench3d.synth.scene_depth.dataset_scene_depth`) and the camera render with them;
a training with the warm-up switched off (the cache then fills during the steps, as before the warm-up existed);
the cache files read with numpy.
"""

from __future__ import annotations

import io
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import robustbench3d.attacks.train_run as train_run
import robustbench3d.synth.scene_depth as scene_depth
from robustbench3d.attacks import depth_cache
from robustbench3d.attacks.base import attack_rng, target_cars
from robustbench3d.attacks.depth_cache import synth_key
from robustbench3d.attacks.object import benign_sphere
from robustbench3d.attacks.roof import RoofObjectAttack
from robustbench3d.attacks.train import UniversalTrainer
from robustbench3d.attacks.train_config import TrainConfig
from robustbench3d.attacks.train_run import data_identity, train_universal
from robustbench3d.cli import main
from robustbench3d.datasets import dataset_identity, load_ground_truth, resolve_dataset
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.sensors.camera_render import render_camera
from robustbench3d.testing import synth_dataset

pytestmark = pytest.mark.usefixtures("cache")  # a fresh cache per test (conftest)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """Generated frames 0-4, all in the train split (the held-out curve keeps the last one)."""
    return synth_dataset(tmp_path_factory.mktemp("synth"), 5, seed=0, val_fraction=0.0)


@pytest.fixture(scope="module")
def victim(lite_victim):
    return lite_victim  # the session's shared one (conftest): read only


def _files(cache: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((cache / "scene_depth").glob("*/*.npz"))}


def _attack(dataset: Path) -> tuple[RoofObjectAttack, KittiDataset]:
    kitti = KittiDataset(dataset, split="train")
    attack = RoofObjectAttack(benign_sphere())
    attack.bind_dataset(kitti)
    return attack, kitti


def _rebuilds(monkeypatch) -> list[str]:
    """Count scene rebuilds (the frames rebuilt, in order)."""
    calls: list[str] = []
    rebuild = scene_depth.dataset_scene_depth

    def counted(root, frame_id):
        calls.append(frame_id)
        return rebuild(root, frame_id)

    monkeypatch.setattr(scene_depth, "dataset_scene_depth", counted)
    return calls


# ---- Adam ---------------------------------------------------------------------------------------------------


def _params() -> tuple[torch.Tensor, torch.Tensor]:
    """The trainer's parameters at their start: shape offsets 0 and the logits of the neutral grey."""
    delta = torch.zeros(162, 3, dtype=torch.float64, requires_grad=True)
    logit = torch.full((162, 3), math.log(128 / 127), dtype=torch.float64, requires_grad=True)
    return delta, logit


def _gradients(steps: int) -> list[list[torch.Tensor]]:
    """Gradients of very different sizes per step, some entries exactly 0 (a car-less step, an unused vertex)."""
    g = torch.Generator().manual_seed(7)
    out = []
    for k in range(steps):
        pair = [torch.randn(162, 3, dtype=torch.float64, generator=g) * 10.0 ** (k % 6 - 3) for _ in range(2)]
        pair[0][::5] = 0.0
        out.append(pair)
    return out


def _torch_step(opt: torch.optim.Adam, params, grads) -> None:
    for p, g in zip(params, grads, strict=True):
        p.grad = g.clone()
    opt.step()
    opt.zero_grad(set_to_none=True)


def _saved(state: dict) -> bytes:
    buf = io.BytesIO()
    torch.save(state, buf)
    return buf.getvalue()


def test_written_out_adam_equals_torch_adam_bit_for_bit():
    """Twelve steps on the trainer's two parameter groups (shape lr 0.02, colour lr 0.2, the shipped rates): the
    parameters after every step, the optimiser state and the bytes torch.save writes of it are torch's."""
    from robustbench3d.attacks.train import Adam

    grads = _gradients(12)
    mine, ref = _params(), _params()
    ours = Adam([{"params": [mine[0]], "lr": 0.02}, {"params": [mine[1]], "lr": 0.2}])
    theirs = torch.optim.Adam([{"params": [ref[0]], "lr": 0.02}, {"params": [ref[1]], "lr": 0.2}])
    for k, g in enumerate(grads):
        ours.step(g)
        _torch_step(theirs, ref, g)
        for a, b in zip(mine, ref, strict=True):
            assert torch.equal(a, b), f"step {k}"
    assert not torch.equal(mine[1], _params()[1])  # the steps moved the parameters
    assert _saved(ours.state_dict()) == _saved(theirs.state_dict())


def test_written_out_adam_resumes_torch_adam_state_and_back():
    """A checkpoint written by torch.optim.Adam (every checkpoint before this class) continues bit for bit, and
    torch continues this class's state the same way."""
    from robustbench3d.attacks.train import Adam

    grads = _gradients(8)
    mine, ref = _params(), _params()
    theirs = torch.optim.Adam([{"params": [ref[1]], "lr": 0.2}])
    for g in grads[:4]:
        _torch_step(theirs, [ref[1]], [g[1]])
    with torch.no_grad():
        mine[1].copy_(ref[1])
    ours = Adam([{"params": [mine[1]], "lr": 0.2}])
    ours.load_state_dict(torch.load(io.BytesIO(_saved(theirs.state_dict())), weights_only=True))
    for g in grads[4:6]:
        ours.step([g[1]])
        _torch_step(theirs, [ref[1]], [g[1]])
    assert torch.equal(mine[1], ref[1])
    back = torch.optim.Adam([{"params": [ref[1]], "lr": 0.2}])
    back.load_state_dict(torch.load(io.BytesIO(_saved(ours.state_dict())), weights_only=True))
    for g in grads[6:]:
        ours.step([g[1]])
        _torch_step(back, [ref[1]], [g[1]])
    assert torch.equal(mine[1], ref[1])
    with pytest.raises(ValueError, match="parameter groups"):
        Adam([{"params": [mine[0]], "lr": 0.02}, {"params": [mine[1]], "lr": 0.2}]).load_state_dict(
            theirs.state_dict())


def test_training_start_up_does_not_import_torch_dynamo(dataset, tmp_path):
    """Building the trainer, a step's update, a checkpoint and a resume from it leave ``torch._dynamo`` (about a
    second of CPU to import) unimported; a fresh interpreter, since the test session may have imported it."""
    code = f"""
import sys
import torch
from robustbench3d.attacks.train import StepResult, UniversalTrainer
from robustbench3d.attacks.train_config import TrainConfig
from robustbench3d.kitti.dataset import KittiDataset
kitti = KittiDataset({str(dataset)!r}, split="train")
ids = kitti.frame_ids
trainer = UniversalTrainer(None, kitti, ids, [kitti.labels(f) for f in ids],
                           TrainConfig(mode="adv-object", steps=2, occlusion="none"))
grads = [torch.ones_like(p) for p in trainer.params]
trainer.apply_step(StepResult({{"total": 1.0}}, 1, 0, 0, 0, grads))
identity = {{"config": trainer.config.identity()}}
trainer.save_checkpoint(Path({str(tmp_path / "c.pt")!r}), identity)
trainer.load_checkpoint(Path({str(tmp_path / "c.pt")!r}), identity)
print("dynamo" if "torch._dynamo" in sys.modules else "no dynamo", trainer.step)
"""
    run = subprocess.run([sys.executable, "-c", "from pathlib import Path" + code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["no", "dynamo", "1"]


# ---- the warm-up --------------------------------------------------------------------------------------------


def test_warmed_depths_equal_the_rebuilt_scene_and_no_scene_is_rebuilt_after(dataset, cache, monkeypatch):
    """Warmed in two worker processes: the cached depths are the rebuilt scene's wherever they are finite, an
    object on every target car renders exactly as with the rebuilt scene, and attacking the frames afterwards
    rebuilds no scene."""
    from robustbench3d.attacks.depth_cache import attack_depth_jobs, warm_scene_depths

    attack, kitti = _attack(dataset)
    jobs = attack_depth_jobs(attack, kitti, kitti.frame_ids)
    assert len(jobs) >= 2
    monkeypatch.setattr(depth_cache, "FRAMES_PER_WORKER", 1)  # two processes for a few frames
    report = warm_scene_depths(dataset.resolve(), synth_key(dataset), jobs, workers=2)
    assert (report.computed, report.kept, report.workers) == (len(jobs), 0, 2)
    assert len(_files(cache)) == len(jobs)
    finite_values = 0
    for job in jobs:
        exact = scene_depth.dataset_scene_depth(dataset, job.frame_id)
        with np.load(job.path(synth_key(dataset), cache)) as z:
            boxes = z["boxes"]
            assert len(boxes) > 0
            for i, (u0, v0, u1, v1) in enumerate(boxes):
                off = (np.arange(3) + 0.5) / 3 - 0.5  # the renderer's 3 x 3 samples per pixel
                u = np.repeat((np.arange(u0, u1)[:, None] + off).reshape(1, -1), (v1 - v0) * 3, axis=0)
                v = np.repeat((np.arange(v0, v1)[:, None] + off).reshape(-1, 1), (u1 - u0) * 3, axis=1)
                ref = exact.depth(u.ravel(), v.ravel()).reshape(u.shape)
                got = z[f"depth_{i}"]
                finite = np.isfinite(got)  # +inf: beyond any object on the roof (checked by the renders below)
                assert np.array_equal(got[finite], ref[finite])
                finite_values += int(finite.sum())
    assert finite_values > 1000
    calls = _rebuilds(monkeypatch)
    for job in jobs:
        frame = kitti.frame(job.frame_id)
        targets = target_cars(frame.labels)
        attacked = attack.apply(frame, targets, attack_rng(0, job.frame_id))
        placed = attack.place(targets, attack_rng(0, job.frame_id))
        assert calls == []  # the attack read the warmed file
        meshes = [(v, attack.obj.faces, attack.obj.colors) for v, _ in placed]
        ref = render_camera(frame.image, frame.calib, meshes, supersample=attack.supersample,
                            scene_depth=scene_depth.dataset_scene_depth(dataset, job.frame_id)).image
        calls.clear()
        assert np.array_equal(attacked.image, ref)


def test_warm_up_resumes_keeping_readable_files(dataset, cache, monkeypatch, capsys):
    """Interrupted after its first frame, the warm-up leaves that frame's file whole; run again it keeps every
    readable file byte for byte, computes only the rest, replaces a damaged file and says so in one line."""
    from robustbench3d.attacks.depth_cache import attack_depth_jobs, warm_scene_depths

    attack, kitti = _attack(dataset)
    jobs = attack_depth_jobs(attack, kitti, kitti.frame_ids)
    key, root = synth_key(dataset), dataset.resolve()
    write = depth_cache.cached_scene_depth
    done: list[str] = []

    def interrupted(*args, **kwargs):
        if done:
            raise KeyboardInterrupt
        done.append(args[2])
        return write(*args, **kwargs)

    monkeypatch.setattr(depth_cache, "cached_scene_depth", interrupted)
    with pytest.raises(KeyboardInterrupt):
        warm_scene_depths(root, key, jobs, workers=1)
    monkeypatch.setattr(depth_cache, "cached_scene_depth", write)
    first = _files(cache)
    (name, data), = first.items()
    assert name.startswith(done[0])
    lines: list[str] = []
    calls = _rebuilds(monkeypatch)
    report = warm_scene_depths(root, key, jobs, workers=1, log=lines.append)
    assert (report.kept, report.computed, report.replaced) == (1, len(jobs) - 1, 0)
    assert sorted(calls) == sorted(j.frame_id for j in jobs if j.frame_id != done[0])
    after = _files(cache)
    assert after[name] == data and len(after) == len(jobs)
    assert f"{len(jobs) - 1} in this process" in lines[0] and "1 cached (kept)" in lines[0]
    # a damaged file (cut short) is replaced and the line says so; the others are kept
    damaged = jobs[-1].path(key, cache)
    damaged.write_bytes(damaged.read_bytes()[:100])
    calls.clear()
    lines.clear()
    report = warm_scene_depths(root, key, jobs, workers=1, log=lines.append)
    assert (report.kept, report.computed, report.replaced) == (len(jobs) - 1, 1, 1) and calls == [jobs[-1].frame_id]
    assert "replacing 1 unreadable or other-version file(s)" in lines[0]
    with np.load(damaged) as z:
        assert len(z["boxes"]) == len([f for f in z.files if f.startswith("depth_")])
    # all present: nothing to say, nothing rebuilt
    calls.clear()
    lines.clear()
    assert warm_scene_depths(root, key, jobs, workers=1, log=lines.append).computed == 0
    assert lines == [] and calls == []


def test_step_frames_are_the_frames_of_the_steps_cars(dataset):
    kitti = KittiDataset(dataset, split="train")
    ids = kitti.frame_ids
    trainer = UniversalTrainer(None, kitti, ids, [kitti.labels(f) for f in ids],
                               TrainConfig(mode="adv-texture", steps=9, batch_cars=3, seed=4))
    for start, stop in ((0, 1), (2, 5), (0, 40), (7, 7)):
        want: list[str] = []
        for step in range(start, stop):
            for fi, _ in trainer.batch(step):
                if ids[fi] not in want:
                    want.append(ids[fi])
        assert trainer.step_frames(start, stop) == want


def _train(victim, dataset: Path, out: Path, **kw) -> dict:
    resolved = resolve_dataset(dataset, "train", progress=False)
    gt = load_ground_truth(resolved)
    config = TrainConfig(mode="adv-texture", steps=3, batch_cars=4, eval_every=2, supersample=1, image_loss="sum",
                         lr_color=0.2)
    return train_universal(victim, {"name": "fpointnet-v1-lite"}, resolved.kitti(), gt.frame_ids, gt.labels, config,
                           out, data_identity=data_identity(dataset_identity(resolved, gt), resolved.root),
                           progress=False, **kw)


def test_training_after_the_warm_up_rebuilds_no_scene_and_writes_the_same_object(victim, dataset, tmp_path, cache,
                                                                                 monkeypatch):
    """adv-texture under exact occlusion with the held-out curve (the steps' crops at supersample 1, the
    benchmark-cell attack of the held-out frame at 3): after the warm-up no step and no evaluation rebuilds a
    scene, and the object, curve and sidecar are those of the same training without the warm-up."""
    original = scene_depth.dataset_scene_depth
    calls = _rebuilds(monkeypatch)
    warm, warmed = train_run.warm_depths, []

    def then_no_rebuild(*args, **kwargs):
        report = warm(*args, **kwargs)
        warmed.append((report, list(calls)))
        monkeypatch.setattr(scene_depth, "dataset_scene_depth", lambda *a: pytest.fail("scene rebuilt after warm-up"))
        return report

    monkeypatch.setattr(train_run, "warm_depths", then_no_rebuild)
    lines: list[str] = []
    made = _train(victim, dataset, tmp_path / "warm.ply", log=lines.append)
    (report, rebuilt), = warmed
    assert report.computed == len(rebuilt) > 0 and report.kept == 0
    names = [p.name for p in (cache / "scene_depth").glob("*/*.npz")]
    assert any("_s1_" in n for n in names) and any("_s3_" in n for n in names)
    assert any(line.startswith("exact occlusion: the scene depths of") for line in lines)

    monkeypatch.setattr(train_run, "warm_depths", lambda *a, **k: None)  # as before the warm-up existed
    monkeypatch.setattr(scene_depth, "dataset_scene_depth", original)
    monkeypatch.setenv("ROBUSTBENCH3D_CACHE", str(tmp_path / "other-cache"))
    plain = _train(victim, dataset, tmp_path / "plain.ply")
    assert (tmp_path / "warm.ply").read_bytes() == (tmp_path / "plain.ply").read_bytes()
    assert (tmp_path / "warm.curve.csv").read_bytes() == (tmp_path / "plain.curve.csv").read_bytes()
    strip = ("wall_time_s", "curve")
    assert {k: v for k, v in made.items() if k not in strip} == {k: v for k, v in plain.items() if k not in strip}
    assert json.dumps(made["curve"]["best"]) == json.dumps(plain["curve"]["best"])


def test_cli_refuses_workers_out_of_range_before_any_work(dataset, tmp_path, capsys):
    out = tmp_path / "o.ply"
    code = main(["attack", "train", "adv-texture", "--victim", "fpointnet-v1-lite", "--data", str(dataset),
                 "--out", str(out), "--steps", "1", "--workers", "0", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "--workers must be an integer in 1..1024 (worker processes), got 0" in err
    assert list(tmp_path.iterdir()) == []
