"""Rendering the attack object into both sensors, forward + backward (the cases of ``robustbench3d bench attack``).

A level-2 icosphere (r = 0.40 m, 162 vertices): on a car roof 10 m ahead in a generated scan (seed 0,
frame 0) for the LiDAR; 10 m ahead of camera 2 of KITTI 2011_09_26 over a random photo for the camera
crop (3 x 3 samples per pixel, float64 geometry).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

pytestmark = pytest.mark.bench


@pytest.fixture(scope="module")
def sphere() -> tuple[np.ndarray, np.ndarray]:
    from robustbench3d.attacks.object import RADIUS
    from robustbench3d.sensors.mesh import icosphere

    return icosphere(2, RADIUS)


def test_lidar_object_fwd_bwd(benchmark: Any, sphere: tuple[np.ndarray, np.ndarray]) -> None:
    """:func:`render_lidar_torch` of the object on the roof, loss = sum of squared hit points, and its gradient."""
    import torch

    from robustbench3d.attacks.bench import ROOF_Z_M
    from robustbench3d.attacks.object import RADIUS
    from robustbench3d.sensors.lidar_render import prepare_scan, render_lidar_torch
    from robustbench3d.synth.frame import frame_generators
    from robustbench3d.synth.layout import sample_scene
    from robustbench3d.synth.lidar import simulate_scan
    from robustbench3d.synth.raytrace import SceneGeometry

    scene_rng, lidar_rng, _ = frame_generators(0, 0)
    scene = sample_scene(scene_rng)
    prep = prepare_scan(simulate_scan(scene, SceneGeometry(scene), lidar_rng)[0])
    v0, faces = sphere
    verts = torch.tensor(v0 + np.array([10.0, 0.3, ROOF_Z_M + RADIUS]), requires_grad=True)

    def fwd_bwd() -> int:
        pts, _ = render_lidar_torch(prep, [(verts, faces, None)])
        verts.grad = None
        pts.pow(2).sum().backward()
        return len(pts)

    hits = benchmark(fwd_bwd)
    assert hits > 0 and verts.grad is not None and bool(torch.isfinite(verts.grad).all())


def test_camera_crop_fwd_bwd(benchmark: Any, sphere: tuple[np.ndarray, np.ndarray]) -> None:
    """:func:`render_camera_crop_torch` of the object, loss = sum of the crop, gradients w.r.t. vertices and colours."""
    import torch

    from robustbench3d.sensors.camera_render import render_camera_crop_torch
    from robustbench3d.synth.calibs import DAY_0926

    calib = DAY_0926.calib
    w, h = DAY_0926.image_size
    rng = np.random.default_rng(0)
    v0, faces = sphere
    verts = torch.tensor(v0 + np.array([0.5, 0.0, 10.0]), dtype=torch.float64, requires_grad=True)
    colors = torch.tensor(rng.random((len(v0), 3)), dtype=torch.float64, requires_grad=True)
    photo = torch.tensor(rng.random((h, w, 3)), dtype=torch.float32)

    def fwd_bwd() -> float:
        crop = render_camera_crop_torch(photo, calib, [(verts, faces, colors)], supersample=3)
        verts.grad = colors.grad = None
        loss = crop.values.sum()
        loss.backward()
        return float(loss.detach())

    total = benchmark(fwd_bwd)
    assert total > 0 and colors.grad is not None and float(colors.grad.abs().sum()) > 0
