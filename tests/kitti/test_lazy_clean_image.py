"""A cell reads each clean image only when the victim or the attack reads it (:meth:`KittiDataset.lazy_frame`):
the same pixels as an eager read, no decoding for a victim given ground-truth boxes, and a file that
cannot be decoded is still bad input (the run exits 2), not a failed attack."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robustbench3d.attacks import create_attack
from robustbench3d.datasets import GroundTruth
from robustbench3d.errors import DataFormatError
from robustbench3d.kitti import dataset as kitti_dataset
from robustbench3d.kitti.dataset import EncodedImage, FileImageFrame, KittiDataset
from robustbench3d.kitti.image import read_image_size, write_image
from robustbench3d.kitti.labels import Labels
from robustbench3d.runner.cell import CellInputs, run_cell
from robustbench3d.testing import IMAGE_SIZE, SIMPLE_CALIB, write_kitti_frame
from robustbench3d.victims.base import victim_inputs

LABEL = "Car 0.00 0 -1.58 559.52 190.40 611.52 239.22 1.52 1.64 3.80 -0.89 2.12 24.24 -1.62\n"


@pytest.fixture
def kitti(tmp_path) -> KittiDataset:
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, size=(IMAGE_SIZE[1], IMAGE_SIZE[0], 3), dtype=np.uint8)
    scan = np.array([[10.0, 0.0, -1.0, 0.5], [20.0, 1.0, -1.5, 0.2]], dtype=np.float32)
    for fid in ("000000", "000001"):
        write_kitti_frame(tmp_path, fid, scan=scan, labels=LABEL, image=image, calib=SIMPLE_CALIB)
    (tmp_path / "ImageSets").mkdir()
    (tmp_path / "ImageSets" / "val.txt").write_text("000000\n000001\n")
    return KittiDataset(tmp_path, split="val")


def count_decodes(monkeypatch) -> list[str]:
    calls: list[str] = []
    real = kitti_dataset.decode_image

    def counting(data, path):
        calls.append(str(path))
        return real(data, path)

    monkeypatch.setattr(kitti_dataset, "decode_image", counting)
    return calls


def test_lazy_frame_has_the_eager_frame_and_decodes_once_on_first_read(kitti, monkeypatch):
    eager = kitti.frame("000000")
    calls = count_decodes(monkeypatch)
    frame = kitti.lazy_frame("000000", eager.labels)
    assert isinstance(frame, FileImageFrame) and calls == []
    # a victim reaches nothing but the frame's data through it: the decoder holds the file's bytes (no
    # path; tests/trust/test_trust_integrity.py walks everything reachable), the other fields hold no string but the id
    assert isinstance(frame.make_image, EncodedImage)
    assert frame.make_image.data == kitti.path("image", "000000").read_bytes()
    assert not any(isinstance(v, str | Path) for v in vars(frame.make_image).values())
    assert [v for v in vars(frame).values() if isinstance(v, str | Path)] == ["000000"]
    assert frame.image_size == IMAGE_SIZE == read_image_size(kitti.path("image", "000000")) and calls == []
    np.testing.assert_array_equal(frame.scan, eager.scan)
    np.testing.assert_array_equal(frame.calib.P2, eager.calib.P2)
    (bare,), _ = victim_inputs([frame], [eager.labels], "detector")  # the victim's copy shares the decode
    assert bare.labels is None and calls == []
    np.testing.assert_array_equal(bare.image, eager.image)
    np.testing.assert_array_equal(frame.image, eager.image)
    assert len(calls) == 1


def test_an_undecodable_image_is_bad_input_when_read(kitti):
    path = kitti.path("image", "000001")
    data = path.read_bytes()
    path.write_bytes(data[:60])  # the header survives, the pixels do not
    frame = kitti.lazy_frame("000001", None)
    assert frame.image_size == IMAGE_SIZE
    with pytest.raises(DataFormatError, match=r"image_2/000001\.png: unreadable image"):
        frame.image  # noqa: B018 - the access decodes
    path.write_bytes(b"not a png")
    with pytest.raises(DataFormatError, match=r"image_2/000001\.png: unreadable image"):
        kitti.lazy_frame("000001", None)
    path.unlink()
    with pytest.raises(DataFormatError, match=r"image_2/000001\.png: file not found"):
        kitti.lazy_frame("000001", None)


def test_an_image_that_does_not_fit_its_calibration_is_refused_before_decoding(kitti, monkeypatch):
    write_image(kitti.path("image", "000001"), np.zeros((40, 60, 3), np.uint8))
    calls = count_decodes(monkeypatch)
    with pytest.raises(DataFormatError, match=r"000001\.png"):
        kitti.lazy_frame("000001", None)
    assert calls == []


class ReadsImages:
    """TEST ONLY: one empty detection list per frame, after reading each frame's image."""

    supported_proposals = ("detector", "gt")

    def __init__(self) -> None:
        self.read = 0

    def detect(self, frames, proposals="detector"):
        for f in frames:
            if proposals == "detector":
                assert f.image.shape == (IMAGE_SIZE[1], IMAGE_SIZE[0], 3)
                self.read += 1
        return [Labels.empty(with_score=True) for _ in frames]


def _inputs(kitti: KittiDataset) -> CellInputs:
    from robustbench3d.kitti.labels import parse_labels

    labels = [parse_labels(LABEL, "label", scored=False)] * 2
    gt = GroundTruth(frame_ids=["000000", "000001"], labels=labels, split_frames=2, sha256="0" * 64)
    return CellInputs(kitti=kitti, gt=gt, seed=0, batch_size=2, classes=("Car",), progress=False)


def test_a_gt_cell_decodes_no_image_and_a_detector_cell_each_once(kitti, tmp_path, monkeypatch):
    calls = count_decodes(monkeypatch)
    victim = ReadsImages()
    run_cell(victim, "reads", create_attack("none"), "none", "gt", _inputs(kitti), tmp_path / "gt")
    assert calls == [] and victim.read == 0
    run_cell(victim, "reads", create_attack("none"), "none", "detector", _inputs(kitti), tmp_path / "det")
    assert victim.read == 2 and [p.rsplit("/", 1)[-1] for p in calls] == ["000000.png", "000001.png"]


def test_an_undecodable_image_read_by_the_victim_stops_the_run_as_bad_input(kitti, tmp_path):
    path = kitti.path("image", "000001")
    path.write_bytes(path.read_bytes()[:60])
    with pytest.raises(DataFormatError, match=r"image_2/000001\.png: unreadable image"):
        run_cell(ReadsImages(), "reads", create_attack("none"), "none", "detector", _inputs(kitti), tmp_path / "c")
