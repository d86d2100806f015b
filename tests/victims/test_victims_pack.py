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


def test_pack_sets_inference_options_of_the_detector(tmp_path: Path) -> None:
    import pytest

    from robustbench3d.errors import RobustBenchError
    from robustbench3d.victims.torchfile import network_sha256

    torch.set_num_threads(1)
    state = FPointNetCascade.untrained("lite", "mini", seed=3).state()
    torch.save(state["yolo"], tmp_path / "yolo.pt")
    torch.save(state["fpointnet"], tmp_path / "fpn.pt")
    base = ["victims", "pack", "--yolo", str(tmp_path / "yolo.pt"), "--fpointnet", str(tmp_path / "fpn.pt")]
    out = tmp_path / "tta.pt"
    assert main([*base, "--out", str(out), "--yolo-option", "flip_tta=true", "--yolo-option", "nms_threshold=0.5"]) == 0
    cfg = FPointNetCascade.load(out).yolo.cfg
    assert cfg.flip_tta and cfg.nms_threshold == 0.5 and not cfg.nms_merge
    assert network_sha256(FPointNetCascade.load(out).state()["yolo"]["state_dict"]) == network_sha256(
        state["yolo"]["state_dict"])  # the weights are untouched
    for bad, why in (("anchors=[]", "KEY one of"), ("flip_tta=1", "takes a bool"), ("nms_threshold=x", "not JSON"),
                     ("max_detections=2.5", "takes a int")):
        with pytest.raises(RobustBenchError, match=why):
            from robustbench3d.commands import victims_pack as pack_command

            pack_command.run(pack_command_args([*base, "--out", str(tmp_path / "x.pt"), "--yolo-option", bad]))
    assert not (tmp_path / "x.pt").exists()


def _summary(path: Path, weights_sha: str) -> None:
    """A minimal run summary: one clean detector cell that ran with ``weights_sha``."""
    import json

    ap = {rp: {"easy": 90.0, "moderate": 80.0, "hard": 70.0} for rp in ("R40", "R11")}
    cell = {"victim": "v", "attack": "none", "proposals": "detector", "status": "ok",
            "dataset": {"split": "val"}, "metrics": {"Car": {"2d": ap, "bev": ap, "3d": ap, "aos": ap}},
            "provenance": {"config": {"victim": {"weights_sha256": None, "weight_files": {"weights": weights_sha}}}}}
    other = {**cell, "victim": "another", "provenance": {"config": {"victim": {"weights_sha256": None,
                                                                               "weight_files": {}}}}}
    path.write_text(json.dumps([cell, other]), encoding="utf-8")


def test_pack_writes_a_manifest_entry_checked_against_the_run(tmp_path: Path, capsys) -> None:
    import json

    import pytest

    from robustbench3d.errors import RobustBenchError
    from robustbench3d.victims.shipped import shipped

    torch.set_num_threads(1)
    state = FPointNetCascade.untrained("lite", "mini", seed=3).state()
    torch.save(state["yolo"], tmp_path / "yolo.pt")
    torch.save(state["fpointnet"], tmp_path / "fpn.pt")
    script = tmp_path / "reproduce.sh"
    script.write_text("#!/bin/sh\n# comment\nrobustbench3d train yolo --seed 0\n\nrobustbench3d victims pack\n")
    out, manifest = tmp_path / "w.pt", tmp_path / "manifest.json"
    args = ["victims", "pack", "--yolo", str(tmp_path / "yolo.pt"), "--fpointnet", str(tmp_path / "fpn.pt"),
            "--out", str(out), "--manifest", str(manifest), "--victim", "v", "--reproduce", str(script)]
    assert main(args) == 0
    sha = hashlib.sha256(out.read_bytes()).hexdigest()
    entry = shipped("v", manifest)
    assert entry.sha256 == sha and entry.size_bytes == out.stat().st_size and entry.path == out
    assert entry.record["reproduce"]["commands"] == ["robustbench3d train yolo --seed 0", "robustbench3d victims pack"]
    assert entry.record["networks"]["fpointnet"]["config"]["name"] == "lite"
    # accuracy only from a run that used this very file
    _summary(tmp_path / "summary.json", sha)
    assert main([*args, "--summary", str(tmp_path / "summary.json")]) == 0
    record = json.loads(manifest.read_text())["weights"][0]
    assert record["accuracy"]["cells"]["detector"]["bev"]["R40"]["moderate"] == 80.0
    assert "aos" not in record["accuracy"]["cells"]["detector"]
    _summary(tmp_path / "other.json", "0" * 64)
    with pytest.raises(RobustBenchError, match="did not run with the packed weights"):
        from robustbench3d.commands import victims_pack as pack_command

        pack_command.run(pack_command_args([*args, "--summary", str(tmp_path / "other.json")]))


def pack_command_args(argv: list[str]):
    import argparse

    from robustbench3d.commands import victims_pack as pack_command

    parser = argparse.ArgumentParser()
    pack_command.add_arguments(parser)
    return parser.parse_args(argv[2:])


def test_pack_records_the_run_a_fine_tuned_network_started_from(tmp_path: Path) -> None:
    import json

    from robustbench3d.fileio import sha256_file
    from robustbench3d.victims.shipped import shipped
    from robustbench3d.victims.training import CHECKPOINT, LOG

    torch.set_num_threads(1)
    state = FPointNetCascade.untrained("lite", "mini", seed=3).state()

    def trainer_dir(name: str, task: dict, val: float) -> Path:
        d = tmp_path / name
        d.mkdir()
        torch.save(FPointNetCascade.untrained("lite", "mini", seed=round(val * 10)).state()["yolo"], d / "model.pt")
        torch.save({"run_config": {"task": task, "loop": {}}, "state": {"step": 7}}, d / CHECKPOINT)
        (d / LOG).write_text(json.dumps({"epoch": 1, "val_ap70": val}) + "\n")
        return d / "model.pt"

    torch.save(state["fpointnet"], tmp_path / "fpn.pt")
    base = trainer_dir("base", {"epochs": 80}, 0.5)
    tuned = trainer_dir("tuned", {"epochs": 30, "init": str(base), "init_sha256": sha256_file(base)}, 0.6)
    manifest = tmp_path / "manifest.json"
    pack = ["victims", "pack", "--fpointnet", str(tmp_path / "fpn.pt"), "--manifest", str(manifest)]
    assert main([*pack, "--yolo", str(tuned), "--out", str(tmp_path / "a.pt"), "--victim", "a"]) == 0
    chain = shipped("a", manifest).record["training"]["yolo"]
    assert chain["last_validation"] == {"val_ap70": 0.6} and chain["run_config"]["task"]["epochs"] == 30
    assert chain["init"]["sha256"] == sha256_file(base) and chain["init"]["run_config"]["task"] == {"epochs": 80}
    assert chain["init"]["last_validation"] == {"val_ap70": 0.5}
    # a run started from a packed file: its record comes from the manifest entry of that file
    packed = tmp_path / "a.pt"
    again = trainer_dir("again", {"epochs": 5, "init": str(packed), "init_sha256": sha256_file(packed)}, 0.7)
    assert main([*pack, "--yolo", str(again), "--out", str(tmp_path / "b.pt"), "--victim", "b"]) == 0
    second = shipped("b", manifest).record["training"]["yolo"]
    assert second["run_config"]["task"]["epochs"] == 5
    assert second["init"]["recorded_in"]["victim"] == "a" and second["init"]["run_config"]["task"]["epochs"] == 30
    assert second["init"]["init"]["run_config"]["task"] == {"epochs": 80}
    # the same network from another container (the packed cascade file) keeps its record
    assert main([*pack, "--yolo", str(tmp_path / "b.pt"), "--out", str(tmp_path / "c.pt"), "--victim", "c"]) == 0
    third = shipped("c", manifest).record
    assert third["training"]["yolo"]["run_config"]["task"]["epochs"] == 5
    b_yolo = shipped("b", manifest).record["networks"]["yolo"]
    assert third["networks"]["yolo"]["state_sha256"] == b_yolo["state_sha256"]
    # repacking an entry's own file into that entry keeps its record without pointing at itself
    before = shipped("a", manifest).record["training"]["yolo"]
    assert main([*pack, "--yolo", str(packed), "--out", str(tmp_path / "a2.pt"), "--victim", "a"]) == 0
    assert shipped("a", manifest).record["training"]["yolo"] == before and "recorded_in" not in before


def test_pack_shares_the_2d_stage_with_a_file_of_the_same_directory(tmp_path: Path, capsys) -> None:
    """``--yolo-shared``: the file refers to the --yolo file for the 2D weights (no copy), loads to the
    same networks, and refuses a shared file whose weights changed, a path and another directory."""
    import pytest

    from robustbench3d.errors import DataFormatError, RobustBenchError
    from robustbench3d.victims.torchfile import load_network_part, load_torch_data, network_sha256

    torch.set_num_threads(1)
    lite, full = FPointNetCascade.untrained("lite", "mini", seed=3), FPointNetCascade.untrained("lite", "mini", seed=5)
    lite.save(tmp_path / "lite.pt")
    torch.save(full.state()["fpointnet"], tmp_path / "fpn.pt")
    out = tmp_path / "full.pt"
    assert main(["victims", "pack", "--yolo", str(tmp_path / "lite.pt"), "--fpointnet", str(tmp_path / "fpn.pt"),
                 "--out", str(out), "--yolo-shared"]) == 0
    stored = load_torch_data(out, "cascade")
    assert "state_dict" not in stored["yolo"] and stored["yolo"]["shared"]["file"] == "lite.pt"
    copy = tmp_path / "copy.pt"
    assert main(["victims", "pack", "--yolo", str(tmp_path / "lite.pt"), "--fpointnet", str(tmp_path / "fpn.pt"),
                 "--out", str(copy)]) == 0
    yolo_bytes = sum(t.numel() * t.element_size() for t in lite.state()["yolo"]["state_dict"].values())
    assert copy.stat().st_size - out.stat().st_size > 0.95 * yolo_bytes  # no copy of the 2D weights
    loaded = FPointNetCascade.load(out).state()
    for part, want in (("yolo", lite.state()["yolo"]), ("fpointnet", full.state()["fpointnet"])):
        assert network_sha256(loaded[part]["state_dict"]) == network_sha256(want["state_dict"])
        assert loaded[part]["config"] == want["config"]
    assert network_sha256(load_network_part(out, "yolo")["state_dict"]) == network_sha256(
        lite.state()["yolo"]["state_dict"])  # also when the file is given as one part

    FPointNetCascade.untrained("lite", "mini", seed=4).save(tmp_path / "lite.pt")  # the shared weights change
    moved = r"full\.pt: field 'yolo\.shared\.state_sha256': the yolo weights in .*lite\.pt hash to "
    with pytest.raises(DataFormatError, match=moved):
        FPointNetCascade.load(out)
    (tmp_path / "lite.pt").unlink()
    with pytest.raises(DataFormatError, match=r"lite\.pt.*no such yolo"):
        FPointNetCascade.load(out)
    for bad in ("../lite.pt", "sub/lite.pt", ".."):
        state = {**stored, "yolo": {**stored["yolo"], "shared": {**stored["yolo"]["shared"], "file": bad}}}
        torch.save(state, tmp_path / "bad.pt")
        with pytest.raises(DataFormatError, match="bare name in the same directory"):
            FPointNetCascade.load(tmp_path / "bad.pt")
    torch.save({**stored, "yolo": {"config": {}, "shared": "lite.pt"}}, tmp_path / "bad.pt")
    with pytest.raises(DataFormatError, match="needs a 'config' dict"):
        FPointNetCascade.load(tmp_path / "bad.pt")
    (tmp_path / "other").mkdir()
    lite.save(tmp_path / "lite.pt")
    with pytest.raises(RobustBenchError, match="must be in the directory"):
        lite.save(tmp_path / "other" / "x.pt", share_yolo=tmp_path / "lite.pt")
    with pytest.raises(RobustBenchError, match="not this cascade's"):
        full.save(tmp_path / "x.pt", share_yolo=tmp_path / "lite.pt")
    assert not (tmp_path / "x.pt").exists()
    capsys.readouterr()
