"""Provenance: the split/label digest, git identity, library versions without importing torch,
weight-file hashes."""

from __future__ import annotations

import hashlib
import re
import subprocess
import sys
from pathlib import Path

import pytest

from robustbench3d.datasets import dataset_identity, load_ground_truth, resolve_dataset
from robustbench3d.errors import DataFormatError
from robustbench3d.provenance import SplitDigest, git_info, library_versions, weight_files

REPO = Path(__file__).resolve().parents[2]
LABELS = {
    "000003": "Car 0.00 0 -1.58 559.52 190.40 611.52 239.22 1.52 1.64 3.80 -0.89 2.12 24.24 -1.62\n",
    "000007": "",  # a frame without objects
    "000009": ("Van 0.00 2 2.11 68.12 167.46 216.28 242.87 2.22 1.97 4.60 -14.58 2.06 22.76 1.54\n"
               "DontCare -1 -1 -10 10.00 180.00 40.00 200.00 -1 -1 -1 -1000 -1000 -1000 -10\n"),
}


def labels_only_dataset(root: Path, split: list[str] | None = None) -> Path:
    (root / "training" / "label_2").mkdir(parents=True)
    for fid, text in LABELS.items():
        (root / "training" / "label_2" / f"{fid}.txt").write_text(text)
    (root / "ImageSets").mkdir()
    (root / "ImageSets" / "val.txt").write_text("".join(f"{i}\n" for i in (split or list(LABELS))))
    return root


def digest_by_hand(ids: list[str], texts: list[str]) -> str:
    """The documented layout of SplitDigest, written out independently."""
    lines = [b"robustbench3d split digest v1\n", f"{len(ids)}\n".encode()]
    lines += [f"{i} {hashlib.sha256(t.encode()).hexdigest()}\n".encode() for i, t in zip(ids, texts, strict=True)]
    return hashlib.sha256(b"".join(lines)).hexdigest()


def identity(root: Path, max_frames: int | None = None) -> dict:
    ds = resolve_dataset(root, "val")
    return dataset_identity(ds, load_ground_truth(ds, max_frames))


def test_split_digest_follows_the_documented_layout(tmp_path):
    root = labels_only_dataset(tmp_path / "ds")
    ident = identity(root)
    assert ident["sha256"] == digest_by_hand(list(LABELS), list(LABELS.values()))
    assert (ident["frames"], ident["split_frames"], ident["split"]) == (3, 3, "val")
    assert ident["root"] == str(root.resolve()) and ident["embedded"] is None


def test_digest_changes_when_a_label_file_changes_and_comes_back_when_restored(tmp_path):
    root = labels_only_dataset(tmp_path / "ds")
    before = identity(root)["sha256"]
    label = root / "training" / "label_2" / "000003.txt"
    original = label.read_text()
    label.write_text(original.replace("24.24", "24.25"))
    assert identity(root)["sha256"] != before
    label.write_text(original)
    assert identity(root)["sha256"] == before


def test_digest_covers_split_order_and_the_evaluated_frames(tmp_path):
    a = identity(labels_only_dataset(tmp_path / "a"))
    b = identity(labels_only_dataset(tmp_path / "b", split=["000009", "000003", "000007"]))
    assert a["sha256"] != b["sha256"]
    # --max-frames: the identity covers the evaluated frames (ids in order, label files), not the rest of
    # the split, which a lazily generated dataset need not hold
    root = tmp_path / "a"
    short = identity(root, max_frames=1)
    assert short["sha256"] == digest_by_hand(["000003"], [LABELS["000003"]])
    assert (short["frames"], short["split_frames"], short["last_frame"]) == (1, 3, "000003")
    (root / "training" / "label_2" / "000009.txt").unlink()
    assert identity(root, max_frames=1)["sha256"] == short["sha256"]
    (root / "training" / "label_2" / "000003.txt").write_text(LABELS["000003"].replace("24.24", "24.25"))
    assert identity(root, max_frames=1)["sha256"] != short["sha256"]


def test_missing_or_malformed_label_file_names_the_file(tmp_path):
    root = labels_only_dataset(tmp_path / "ds")
    (root / "training" / "label_2" / "000007.txt").unlink()
    with pytest.raises(DataFormatError, match=r"label_2/000007\.txt: ground-truth label file not found"):
        identity(root)
    (root / "training" / "label_2" / "000007.txt").write_text("Car 0.0 0\n")
    with pytest.raises(DataFormatError, match=r"label_2/000007\.txt:1: expected 15 columns, got 3"):
        identity(root)


def test_split_digest_rejects_frames_out_of_order():
    digest = SplitDigest(["000001", "000002"])
    with pytest.raises(ValueError, match="got frame 000002, expected 000001"):
        digest.update("000002", b"")
    digest.update("000001", b"")
    with pytest.raises(ValueError, match="1 of 2 frames hashed"):
        digest.hexdigest()


def test_git_info_in_the_checkout_and_outside(tmp_path):
    assert git_info(tmp_path) == {"commit": None, "dirty": None}
    if not (REPO / ".git").exists():
        pytest.skip("not running from a git checkout")
    info = git_info(REPO)
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    assert re.fullmatch(r"[0-9a-f]{40}", info["commit"]) and info["commit"] == head
    assert isinstance(info["dirty"], bool)
    # A sub-directory of the checkout is not the package's checkout root.
    assert git_info(REPO / "tests") == {"commit": None, "dirty": None}


def test_versions_and_provenance_do_not_import_torch():
    code = ("import sys; from robustbench3d.provenance import determinism_flags, host_provenance, library_versions;"
            "host_provenance(); v = library_versions(); f = determinism_flags();"
            "print('torch' in sys.modules, f['torch_loaded'], v['python'] == '%d.%d.%d' % sys.version_info[:3])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "False", "True"]
    versions = library_versions()
    assert {"python", "numpy", "torch", "onnxruntime"} <= set(versions)
    import numpy

    assert versions["numpy"] == numpy.__version__


def test_weight_files_hash_existing_file_arguments_only(tmp_path):
    weights = tmp_path / "cascade.pt"
    weights.write_bytes(b"\x00weights\x01")
    files = weight_files({"weights": str(weights), "seed": 3, "gather": "random", "missing": str(tmp_path / "no.pt"),
                          "yolo_weights": weights})
    expected = hashlib.sha256(b"\x00weights\x01").hexdigest()
    assert files == {"weights": expected, "yolo_weights": expected}


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/clear_refs is Linux")
def test_peak_rss_resets_and_sees_a_200_mb_allocation():
    """After a reset the peak is near the current RSS; touching 200 MB raises it by about 200 MB, and the next
    reset (the array freed) brings it back down."""
    import numpy as np

    from robustbench3d.provenance import peak_rss_mb, reset_peak_rss

    assert reset_peak_rss()
    base = peak_rss_mb()
    block = np.ones(25_000_000)  # 200 MB, every page touched
    high = peak_rss_mb()
    del block
    assert reset_peak_rss()
    low = peak_rss_mb()
    assert 180 < high - base < 260
    assert low < high - 150
