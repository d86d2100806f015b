"""Lazy generation of the embedded dataset: only the frames a run evaluates are generated, each with
the bytes of the same frame of a full generation; the frames record, resume after an interruption,
concurrent generations and the dataset identity of the evaluated frames."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from robustbench3d.datasets import (
    EMBEDDED,
    EmbeddedParams,
    dataset_identity,
    embedded_split,
    ensure_embedded,
    load_ground_truth,
    resolve_dataset,
)
from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.synth import writer
from robustbench3d.synth.writer import (
    FRAMES_RECORD,
    MANIFEST,
    generate_dataset,
    in_val,
    index_ranges,
    read_frames_record,
)

SEED = 1
FRAMES = 4
PARAMS = EmbeddedParams(frames=FRAMES, seed=SEED, val_fraction=0.5)
FILES = (("calib", "txt"), ("velodyne", "bin"), ("image_2", "png"), ("label_2", "txt"))


def frame_bytes(root: Path, index: int) -> dict[str, bytes]:
    return {sub: (root / "training" / sub / f"{index:06d}.{ext}").read_bytes() for sub, ext in FILES}


def labelled(root: Path) -> list[str]:
    return sorted(p.name for p in (root / "training" / "label_2").iterdir())


def temporaries(root: Path) -> list[Path]:
    return [p for p in root.rglob("*.tmp")]


def digest_by_hand(ids: list[str], texts: list[bytes]) -> str:
    """SplitDigest's documented layout, written out independently."""
    lines = [b"robustbench3d split digest v1\n", f"{len(ids)}\n".encode()]
    lines += [f"{i} {hashlib.sha256(t).hexdigest()}\n".encode() for i, t in zip(ids, texts, strict=True)]
    return hashlib.sha256(b"".join(lines)).hexdigest()


@pytest.fixture(scope="module")
def full(tmp_path_factory) -> Path:
    """Every frame of the small dataset, generated the ordinary (non-lazy) way."""
    root = tmp_path_factory.mktemp("full")
    generate_dataset(root, FRAMES, SEED, val_fraction=0.5, workers=1, progress=False)
    return root


def test_the_small_dataset_has_a_val_frame_after_frame_zero():
    # frame 0 is train and frame 3 the only val frame: a first-1 val slice needs frame 3 alone
    assert [i for i in range(FRAMES) if in_val(SEED, i, 0.5)] == [3]
    assert embedded_split(PARAMS, "val") == ["000003"]
    assert embedded_split(PARAMS, "train") == ["000000", "000001", "000002"]
    assert embedded_split(PARAMS, "test") is None
    val = embedded_split(EMBEDDED, "val")
    assert val is not None and len(val) == 1009 and val[:3] == ["000000", "000003", "000005"]


def test_lazy_frames_have_the_bytes_of_a_full_generation(full, tmp_path, monkeypatch):
    monkeypatch.setenv("ROBUSTBENCH3D_CACHE", str(tmp_path / "cache"))
    lines: list[str] = []
    ds = resolve_dataset(None, "val", embedded=PARAMS, lazy=True, max_frames=1, progress=False, log=lines.append)
    root = tmp_path / "cache" / "datasets" / "synth"
    assert ds.root == root.resolve() and labelled(root) == ["000003.txt"]  # the evaluated frame only
    assert lines and lines[0].startswith("generating 1 of the 1 frames needed")
    assert read_frames_record(root) == [3]
    # the split lists and the generator manifest are the full generation's, byte for byte
    for name in ("ImageSets/train.txt", "ImageSets/val.txt", "ImageSets/trainval.txt", MANIFEST):
        assert (root / name).read_bytes() == (full / name).read_bytes(), name
    assert frame_bytes(root, 3) == frame_bytes(full, 3)

    # a run that needs another frame generates that one and keeps the first untouched
    stamp = (root / "training" / "velodyne" / "000003.bin").stat().st_mtime_ns
    resolve_dataset(None, "train", embedded=PARAMS, lazy=True, max_frames=1, progress=False)
    assert labelled(root) == ["000000.txt", "000003.txt"]
    assert (root / "training" / "velodyne" / "000003.bin").stat().st_mtime_ns == stamp
    assert frame_bytes(root, 0) == frame_bytes(full, 0)
    record = json.loads((root / FRAMES_RECORD).read_text())
    assert record == {"generator": "robustbench3d.synth", "version": writer.GENERATOR_VERSION, "seed": SEED,
                      "count": 2, "frames": [[0, 0], [3, 3]]}

    # the whole dataset (what training asks for) completes the lazy directory to the full one
    ensure_embedded(root, PARAMS, progress=False)
    for i in range(FRAMES):
        assert frame_bytes(root, i) == frame_bytes(full, i)
    assert read_frames_record(root) == [0, 1, 2, 3] and not temporaries(root)


def test_identity_of_the_same_frames_is_the_same_lazily_or_fully_generated(full, tmp_path, monkeypatch):
    monkeypatch.setenv("ROBUSTBENCH3D_CACHE", str(tmp_path / "cache"))
    lazy = resolve_dataset(None, "train", embedded=PARAMS, lazy=True, max_frames=2, progress=False)
    assert labelled(lazy.root) == ["000000.txt", "000001.txt"]
    a = dataset_identity(lazy, load_ground_truth(lazy, 2))
    whole = resolve_dataset(full, "train")
    b = dataset_identity(whole, load_ground_truth(whole, 2))
    labels = [(full / "training" / "label_2" / f"00000{i}.txt").read_bytes() for i in (0, 1)]
    assert a["sha256"] == b["sha256"] == digest_by_hand(["000000", "000001"], labels)
    keys = ("split", "frames", "split_frames", "first_frame", "last_frame", "manifest")
    assert {k: a[k] for k in keys} == {k: b[k] for k in keys}
    assert (a["frames"], a["split_frames"], a["last_frame"]) == (2, 3, "000001")
    assert a["manifest"] == {"generator": "robustbench3d.synth", "version": writer.GENERATOR_VERSION, "seed": SEED}
    assert a["embedded"] == PARAMS.as_dict()
    # the whole split of the full dataset: the digest of every frame of it
    c = dataset_identity(whole, load_ground_truth(whole))
    all_labels = [(full / "training" / "label_2" / f"00000{i}.txt").read_bytes() for i in (0, 1, 2)]
    assert c["sha256"] == digest_by_hand(["000000", "000001", "000002"], all_labels) != a["sha256"]


def test_an_interrupted_generation_resumes_to_the_same_bytes(full, tmp_path, monkeypatch):
    root = tmp_path / "part"
    real = writer.write_image
    calls = []

    def dies_on_second_image(*args, **kwargs):
        calls.append(args[0])
        if len(calls) == 2:
            raise KeyboardInterrupt  # the process is stopped between the scan and the image of frame 1
        return real(*args, **kwargs)

    monkeypatch.setattr(writer, "write_image", dies_on_second_image)
    with pytest.raises(KeyboardInterrupt):
        generate_dataset(root, FRAMES, SEED, only=[0, 1, 3], workers=1, progress=False)
    monkeypatch.setattr(writer, "write_image", real)
    assert labelled(root) == ["000000.txt"] and (root / "training" / "velodyne" / "000001.bin").is_file()
    assert read_frames_record(root) == [0] and not (root / "ImageSets").exists()
    stale = root / "training" / "image_2" / ".000001.png.x1y2.tmp"
    stale.write_bytes(b"half an image")  # what a kill during the atomic write leaves
    kept = (root / "training" / "velodyne" / "000000.bin").stat().st_mtime_ns

    report = generate_dataset(root, FRAMES, SEED, only=[0, 1, 3], workers=1, progress=False)
    assert (report.frames, report.generated, report.skipped) == (3, 2, 1)
    assert labelled(root) == ["000000.txt", "000001.txt", "000003.txt"]
    assert (root / "training" / "velodyne" / "000000.bin").stat().st_mtime_ns == kept
    for i in (0, 1, 3):
        assert frame_bytes(root, i) == frame_bytes(full, i)
    assert read_frames_record(root) == [0, 1, 3] and not temporaries(root)
    assert (root / "ImageSets" / "val.txt").read_bytes() == (full / "ImageSets" / "val.txt").read_bytes()


def test_a_frame_finished_by_a_killed_run_is_recorded_by_the_next(full, tmp_path):
    root = tmp_path / "killed"
    generate_dataset(root, FRAMES, SEED, only=[0], workers=1, progress=False)
    (root / FRAMES_RECORD).unlink()  # the record was not rewritten before the kill
    report = generate_dataset(root, FRAMES, SEED, only=[0, 3], workers=1, progress=False)
    assert (report.generated, report.skipped) == (1, 1) and read_frames_record(root) == [0, 3]


def test_concurrent_generations_write_each_frame_once_and_whole(full, tmp_path):
    root = tmp_path / "shared"
    code = ("import sys; from robustbench3d.synth.writer import generate_dataset; "
            f"r = generate_dataset(sys.argv[1], {FRAMES}, {SEED}, only=[3], workers=1, progress=False); "
            "print(r.generated)")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    procs = [subprocess.Popen([sys.executable, "-c", code, str(root)], stdout=subprocess.PIPE, text=True, env=env)
             for _ in range(2)]
    outs = [p.communicate(timeout=300)[0].strip() for p in procs]
    assert [p.returncode for p in procs] == [0, 0]
    assert sorted(outs) == ["0", "1"]  # one generated the frame, the other waited and found it done
    assert labelled(root) == ["000003.txt"] and frame_bytes(root, 3) == frame_bytes(full, 3)
    assert read_frames_record(root) == [3] and not temporaries(root)


def test_index_ranges_and_a_malformed_record(tmp_path):
    assert index_ranges([]) == []
    assert index_ranges([5, 0, 1, 2, 2, 7, 8]) == [[0, 2], [5, 5], [7, 8]]
    assert read_frames_record(tmp_path) is None
    (tmp_path / FRAMES_RECORD).write_text('{"frames": [[3, 1]]}')
    with pytest.raises(DataFormatError, match=r"synth_frames\.json: field 'frames': expected a list of inclusive"):
        read_frames_record(tmp_path)
    (tmp_path / FRAMES_RECORD).write_text("{")
    with pytest.raises(DataFormatError, match=r"synth_frames\.json: not valid JSON"):
        read_frames_record(tmp_path)


def test_bad_lazy_requests_name_the_problem_and_generate_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv("ROBUSTBENCH3D_CACHE", str(tmp_path / "cache"))
    with pytest.raises(DataFormatError, match=r"ImageSets/test\.txt: split file not found \(available splits: train"):
        resolve_dataset(None, "test", embedded=PARAMS, lazy=True, progress=False)
    with pytest.raises(RobustBenchError, match="--max-frames must be at least 1, got 0"):
        resolve_dataset(None, "val", embedded=PARAMS, lazy=True, max_frames=0, progress=False)
    with pytest.raises(RobustBenchError, match=r"frame index 4 is outside the dataset's frames 0\.\.3"):
        generate_dataset(tmp_path / "x", FRAMES, SEED, only=[4], progress=False)
    assert not (tmp_path / "cache").exists()


@pytest.mark.slow
def test_lazy_frames_match_the_full_embedded_dataset_in_the_home_cache(tmp_path, monkeypatch):
    """Frame 0 and the first val frames of the real embedded dataset, lazily generated into a fresh
    cache, against the full generation in ``~/.cache`` (where present: made on this CPU family)."""
    home = Path.home() / ".cache" / "robustbench3d" / "datasets" / "synth"
    if not all((home / "training" / "label_2" / f"{i:06d}.txt").is_file() for i in (0, 3, 5)):
        pytest.skip(f"no full embedded dataset in {home}")
    monkeypatch.setenv("ROBUSTBENCH3D_CACHE", str(tmp_path / "cache"))
    ds = resolve_dataset(None, "val", lazy=True, max_frames=3, workers=2, progress=False)
    assert labelled(ds.root) == ["000000.txt", "000003.txt", "000005.txt"]
    for i in (0, 3, 5):
        assert frame_bytes(ds.root, i) == frame_bytes(home, i)
    for name in ("ImageSets/val.txt", MANIFEST):
        assert (ds.root / name).read_bytes() == (home / name).read_bytes()
    home_ds = resolve_dataset(home, "val")
    assert (dataset_identity(ds, load_ground_truth(ds, 3))["sha256"]
            == dataset_identity(home_ds, load_ground_truth(home_ds, 3))["sha256"])
