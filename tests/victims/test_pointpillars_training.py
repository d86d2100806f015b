"""PointPillars training: a run stopped and resumed equals the uninterrupted run (weights and log), a few
steps on one frame reduce the loss, and the command refuses bad options with one line before writing."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from robustbench3d.cli import main
from robustbench3d.testing import synth_dataset
from robustbench3d.victims.pointpillars.config import PointPillarsConfig
from robustbench3d.victims.pointpillars.pillars import PillarGrid
from robustbench3d.victims.pointpillars.training import (
    PointPillarsTask,
    PointPillarsTrainConfig,
    load_frames,
    train,
)
from robustbench3d.victims.torchfile import load_torch_data
from robustbench3d.victims.training import LoopOptions

torch.set_num_threads(1)
TINY = PointPillarsConfig(grid=PillarGrid(pillar_size=0.64), pillar_channels=8, block_channels=(8, 8, 8),
                          block_layers=(1, 1, 1), up_channels=8, head_channels=8)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return synth_dataset(tmp_path_factory.mktemp("ppdata"), 4, seed=5, val_fraction=0.25)


def test_resume_equals_uninterrupted(data, tmp_path):
    tcfg = PointPillarsTrainConfig(warmup_steps=2)
    opts = LoopOptions(epochs=3, batch_size=2, seed=4, progress=False)
    full = tmp_path / "full"
    train(data, full, TINY, tcfg, opts, val_limit=1)
    part = tmp_path / "part"
    state = train(data, part, TINY, tcfg, LoopOptions(**{**opts.__dict__, "max_steps": 2}), val_limit=1)
    assert not state["finished"] and not (part / "model.pt").exists()
    train(data, part, TINY, tcfg, opts, resume=True, val_limit=1)
    a, b = (load_torch_data(d / "model.pt", "model")["state_dict"] for d in (full, part))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert (full / "log.jsonl").read_text() == (part / "log.jsonl").read_text()
    assert "val_bev_r40_moderate" in (full / "log.jsonl").read_text()


def test_steps_reduce_the_loss(data):
    _, frames = load_frames(data, "train", TINY, 1)
    task = PointPillarsTask(frames, None, TINY, PointPillarsTrainConfig(warmup_steps=1, flip=False, rotation=0.0,
                                                                        scaling=0.0), 0, 40)
    idx = np.array([0, 0])
    rng = np.random.default_rng(0)
    first = task.loss(idx, rng, torch.Generator())[0].item()
    for step in range(40):
        task.schedule(0, step, 0)
        loss, _ = task.loss(idx, rng, torch.Generator())
        task.optimizer.zero_grad()
        loss.backward()
        task.optimizer.step()
    task.model.eval()
    assert task.loss(idx, rng, torch.Generator())[0].item() < 0.7 * first


@pytest.mark.parametrize(("option", "value", "message"), [
    ("--val-limit", "-1", "--val-limit -1: expected 0..10000"),
    ("--pillar-size", "2", "--pillar-size 2.0: expected 0.16..0.64"),
    ("--lr", "5", "--lr 5.0: expected 1e-06..0.1"),
    ("--batch-size", "1", "--batch-size 1: expected 2..256"),
])
def test_cli_refuses_bad_options(data, tmp_path, capsys, option, value, message):
    out = tmp_path / "out"
    assert main(["victims", "train-pointpillars", "--data", str(data), "--out", str(out), option, value]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1 and not out.exists()


def test_cli_refuses_an_earlier_run_without_resume(data, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "last.pt").write_bytes(b"x")
    assert main(["victims", "train-pointpillars", "--data", str(data), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "pass --resume" in err and len(err.splitlines()) == 1 and (out / "last.pt").read_bytes() == b"x"
