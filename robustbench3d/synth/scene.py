"""A procedural scene: calibration, road, lighting and objects, all meshes in the velodyne frame.

Labelled objects (Car, Van, Truck, Pedestrian, Cyclist) carry their KITTI box: dimensions
(h, w, l), bottom-centre location in rect and rotation_y, already rounded to the 0.01 precision
of the label files; the mesh is placed with exactly these rounded values, so the written label
is the true box of the mesh. The mesh fills the box tightly (see
:mod:`robustbench3d.synth.vehicles`).

Frames: velodyne (x forward, y left, z up) for all meshes; rect (x right, y down, z forward) for
the KITTI box fields.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from robustbench3d.geometry import roty, wrap_angle
from robustbench3d.kitti.calib import Calibration
from robustbench3d.sensors.camera_model import Lighting  # defined with the shading model; re-exported here
from robustbench3d.synth import materials as mt
from robustbench3d.synth.calibs import CameraDay
from robustbench3d.synth.materials import Mat
from robustbench3d.synth.mesh import Mesh, merge
from robustbench3d.synth.road import Road, Side

LABELLED_KINDS = ("Car", "Van", "Truck", "Pedestrian", "Cyclist")

# object-local (x forward, y left, z up) -> rect-local (x, y down, z): x_r = x, y_r = -z, z_r = y
_LOCAL_TO_RECT_LOCAL = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


@dataclass(frozen=True, eq=False)
class SceneObject:
    """One object of the scene.

    Attributes:
        kind: a KITTI type of :data:`LABELLED_KINDS`, or a clutter kind ('ground', 'sidewalk',
            'building', 'wall', 'pole', 'tree', 'bush').
        mesh: triangles in the velodyne frame.
        dimensions: (3,) h, w, l in m (labelled kinds only).
        location: (3,) bottom centre in rect, m (labelled kinds only).
        rotation_y: yaw about rect y, rad, in [-pi, pi] (labelled kinds only).
    """

    kind: str
    mesh: Mesh
    dimensions: np.ndarray | None = None
    location: np.ndarray | None = None
    rotation_y: float | None = None

    @property
    def labelled(self) -> bool:
        return self.kind in LABELLED_KINDS


@dataclass(frozen=True, eq=False)
class Scene:
    """Everything needed to render both sensors and to write the labels of one frame."""

    day: CameraDay
    road: Road
    lighting: Lighting
    objects: list[SceneObject] = field(default_factory=list)

    @property
    def calib(self) -> Calibration:
        return self.day.calib

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.day.image_size

    def labelled_indices(self) -> list[int]:
        return [i for i, o in enumerate(self.objects) if o.labelled]


def quantize(x: np.ndarray | float) -> np.ndarray:
    """Round to the label files' precision (values are written with ``%.2f``)."""
    return np.round(np.asarray(x, dtype=np.float64), 2)


def kitti_pose(calib: Calibration, base_velo: np.ndarray, yaw_velo: float) -> tuple[np.ndarray, float]:
    """KITTI (location, rotation_y) of an object standing at ``base_velo`` heading ``yaw_velo``.

    Args:
        base_velo: (3,) bottom centre in the velodyne frame, m.
        yaw_velo: heading in the velodyne frame (rad from +x towards +y).
    Returns:
        location (3,) in rect and rotation_y, both rounded to 0.01.
    """
    loc = calib.velo_to_rect_points(np.asarray(base_velo, np.float64)[None])[0]
    fwd = calib.velo_to_rect[:3, :3] @ np.array([np.cos(yaw_velo), np.sin(yaw_velo), 0.0])
    ry = float(wrap_angle(np.arctan2(-fwd[2], fwd[0])))
    ry = float(np.clip(np.round(ry, 2), -3.14, 3.14))
    return quantize(loc), ry


def place_labelled(kind: str, local_mesh: Mesh, dims_hwl: np.ndarray, location: np.ndarray, rotation_y: float,
                   calib: Calibration) -> SceneObject:
    """Put an object-local mesh (exactly filling its (l, w, h) box) at a KITTI pose.

    The mesh goes object-local -> rect (R_y(rotation_y), + location) -> velodyne.
    """
    rect = local_mesh.vertices @ (roty(rotation_y)[0] @ _LOCAL_TO_RECT_LOCAL).T + location
    velo = calib.rect_to_velo_points(rect)
    mesh = Mesh(velo, local_mesh.faces, local_mesh.material, local_mesh.color)
    return SceneObject(kind, mesh, np.asarray(dims_hwl, np.float64), np.asarray(location, np.float64),
                       float(rotation_y))


def place_static(kind: str, local_mesh: Mesh, base_velo: np.ndarray, yaw_velo: float) -> SceneObject:
    """Put a clutter mesh (object-local, z up) at ``base_velo`` with heading ``yaw_velo`` (velodyne)."""
    c, s = np.cos(yaw_velo), np.sin(yaw_velo)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return SceneObject(kind, local_mesh.transformed(rot, base_velo))


def ground_mesh(road: Road, x_range: tuple[float, float] = (-110.0, 170.0),
                y_range: tuple[float, float] = (-120.0, 120.0), cell: float = 6.0) -> Mesh:
    """Terrain grid z = g(x, y) in the velodyne frame (material GROUND, textured when rendered)."""
    xs = np.arange(x_range[0], x_range[1] + cell / 2, cell)
    ys = np.arange(y_range[0], y_range[1] + cell / 2, cell)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    verts = np.column_stack([gx.ravel(), gy.ravel(), road.ground_z(gx, gy).ravel()])
    nx, ny = len(xs), len(ys)
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    n = len(faces)
    return Mesh(verts, faces, np.full(n, Mat.GROUND, np.uint8), np.ones((n, 3), np.float32))


def sidewalk_mesh(road: Road, side: Side, s_range: tuple[float, float], step: float = 4.0) -> Mesh | None:
    """Raised sidewalk strip (kerb face, top, outer face) along one side, cut at the cross street."""
    s_all = np.arange(s_range[0], s_range[1] + step / 2, step)
    parts = []
    keep = ~road.in_cross_street(s_all, 0.0)
    # split into runs of consecutive kept stations
    runs: list[list[float]] = []
    for s_val, k in zip(s_all, keep, strict=True):
        if k:
            if not runs or runs[-1][-1] != s_val - step:
                runs.append([])
            runs[-1].append(float(s_val))
    for run in runs:
        if len(run) < 2:
            continue
        s = np.array(run)
        d_in = side.sign * road.curb_d(side)
        d_out = side.sign * road.sidewalk_outer_d(side)
        x_in, y_in, _ = road.to_velo(s, np.full_like(s, d_in))
        x_out, y_out, _ = road.to_velo(s, np.full_like(s, d_out))
        g_in = road.ground_z(x_in, y_in)
        g_out = road.ground_z(x_out, y_out)
        h = road.curb_height
        ring = np.stack([
            np.column_stack([x_in, y_in, g_in - 0.05]), np.column_stack([x_in, y_in, g_in + h]),
            np.column_stack([x_out, y_out, g_out + h]), np.column_stack([x_out, y_out, g_out - 0.05]),
        ], axis=1)  # (M, 4, 3)
        m = len(s)
        idx = np.arange(m * 4).reshape(m, 4)
        faces, mats = [], []
        for j, mat in ((0, Mat.CURB), (1, Mat.SIDEWALK), (2, Mat.CURB)):
            a, b = idx[:-1, j], idx[:-1, j + 1]
            c, d = idx[1:, j], idx[1:, j + 1]
            faces += [np.stack([a, b, d], 1), np.stack([a, d, c], 1)]
            mats += [np.full(2 * (m - 1), mat, np.uint8)]
        f = np.concatenate(faces)
        mat_arr = np.concatenate(mats)
        col = np.where((mat_arr == Mat.CURB)[:, None], mt.CURB, mt.SIDEWALK).astype(np.float32)
        parts.append(Mesh(ring.reshape(-1, 3), f, mat_arr, col))
    return merge(parts) if parts else None
