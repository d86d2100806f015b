"""Regression pin: the generated files stay byte-identical across refactors of the generator.

The digests below were produced by GENERATOR_VERSION 1 as committed before the performance work on
the synth pipeline (frames 0 and 3 of seed 0, one per recording day, i.e. image size); they equal the
files of the seed-0 dataset made with that code. A change that alters them must bump
``GENERATOR_VERSION`` (and these digests) instead of silently changing existing datasets.
"""

from __future__ import annotations

import pytest

from robustbench3d.fileio import sha256_file
from robustbench3d.synth.frame import generate_frame
from robustbench3d.synth.writer import GENERATOR_VERSION, write_frame

V1_SHA256 = {
    0: {  # recording day of KITTI frame 000000, 1224x370
        "calib/000000.txt": "29b89ca9fa49b2cad778bf73910ff7210c7998badae39796cf29666081992d7f",
        "velodyne/000000.bin": "e19976c0081df3edac310d461d3bac9550923f66fd969a586e73813f8be53b58",
        "image_2/000000.png": "333fbd978e20c4106bb2f6d20f77f0466d0e30836135cee9be8c9cfaa7f30ee8",
        "label_2/000000.txt": "0737b853a7c552d44e11410ef365b344f21248ff12fff46a6da1b1a7aed1911e",
    },
    3: {  # 2011_09_26, 1242x375
        "calib/000003.txt": "5813c05a89e33e67244891c62e153e0a572692d42365b8665e38cc242c7d4918",
        "velodyne/000003.bin": "5cefc39445e10223e248bfb3e4ad0eeb994bd0550b211ce9c2d3ac3965dd54d4",
        "image_2/000003.png": "9f2f57728659a295360aadb6c4646d1c55bde56cb3cab71df1d74f7cdde185e4",
        "label_2/000003.txt": "a05c7e7b817018f35c8ccc57378962539c546b663277f4dd3f795e8ecf05072c",
    },
}


@pytest.mark.skipif(GENERATOR_VERSION != 1, reason="the pinned digests are those of generator version 1")
@pytest.mark.parametrize("index", sorted(V1_SHA256))
def test_frames_are_byte_identical_to_generator_version_1(index, tmp_path):
    write_frame(tmp_path, index, generate_frame(0, index))
    got = {name: sha256_file(tmp_path / "training" / name) for name in V1_SHA256[index]}
    assert got == V1_SHA256[index]
