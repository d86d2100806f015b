"""``victims pack`` joins the trainers' outputs into one cascade file whose printed hash is the file's."""

from __future__ import annotations

import hashlib
from pathlib import Path

import torch

from robustbench3d.cli import main
from robustbench3d.victims.cascade import FPointNetCascade


def test_pack_round_trip(tmp_path: Path, capsys) -> None:
    torch.set_num_threads(1)
    source = FPointNetCascade.untrained("lite", "mini", seed=3)
    state = source.state()
    torch.save(state["yolo"], tmp_path / "yolo.pt")
    torch.save(state["fpointnet"], tmp_path / "fpn.pt")
    out = tmp_path / "cascade.pt"
    assert main(["victims", "pack", "--yolo", str(tmp_path / "yolo.pt"), "--fpointnet", str(tmp_path / "fpn.pt"),
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out.split()[0]
    assert printed == hashlib.sha256(out.read_bytes()).hexdigest()
    loaded = FPointNetCascade.load(out, sha256=printed)
    for part in ("yolo", "fpointnet"):
        want, got = state[part]["state_dict"], loaded.state()[part]["state_dict"]
        assert want.keys() == got.keys()
        assert all(torch.equal(want[k], got[k]) for k in want)
