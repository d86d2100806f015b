"""Placing the roof object on a target car (KITTI rect frame: x right, y down, z forward; metres, radians).

Rule ``roof-centre`` (:data:`PLACEMENT_RULE`): the roof centre of a car is its label's bottom-centre
location raised by its height, ``location - (0, h, 0)``. An object-frame vertex ``v0 + dv``
(:mod:`robustbench3d.attacks.object`: x along the car, y down) goes to

    v_rect = R_y(ry + jitter.yaw) (v0 + dv) + roof_centre + R_y(ry) (jitter.forward, 0, jitter.lateral) - (0, y_low, 0)

with ``R_y`` the KITTI yaw (:func:`robustbench3d.geometry.roty`) and ``y_low`` the largest object-frame
y of the (deformed) vertices: a yaw leaves y unchanged, so the object's lowest point touches the
roof plane ``y = location_y - h`` and its centre sits ``y_low`` above the roof centre. Expectation
over transformation (EOT) draws the jitter per car from the frame's generator (:func:`sample_jitter`).
Numpy or torch vertices (torch stays differentiable; the lowest point passes the gradient to the
lowest vertex).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from robustbench3d.geometry import roty
from robustbench3d.kitti.calib import Calibration
from robustbench3d.kitti.labels import Labels

if TYPE_CHECKING:
    import torch

PLACEMENT_RULE = "roof-centre"
#: Default EOT jitter half ranges: +-5 cm in position along and across the car, +-5 degrees in yaw.
POSITION_JITTER_M = 0.05
YAW_JITTER_RAD = math.radians(5.0)


@dataclass(frozen=True)
class Car:
    """A target car: bottom-centre ``location`` (3,) in rect (m), ``dimensions`` (h, w, l) (m),
    ``rotation_y`` (rad)."""

    location: tuple[float, float, float]
    dimensions: tuple[float, float, float]
    rotation_y: float

    @classmethod
    def from_labels(cls, labels: Labels, index: int) -> Car:
        loc, dim = labels.location[index], labels.dimensions[index]
        return cls(location=(float(loc[0]), float(loc[1]), float(loc[2])),
                   dimensions=(float(dim[0]), float(dim[1]), float(dim[2])),
                   rotation_y=float(labels.rotation_y[index]))

    @property
    def roof_centre(self) -> np.ndarray:
        """(3,) rect point at the centre of the top face of the car's box."""
        x, y, z = self.location
        return np.array([x, y - self.dimensions[0], z])


def cars_of(labels: Labels) -> list[Car]:
    """Every row of ``labels`` as a :class:`Car`."""
    return [Car.from_labels(labels, k) for k in range(len(labels))]


@dataclass(frozen=True)
class Placement:
    """EOT jitter of one placement: ``forward`` / ``lateral`` offsets (m) along the car's length
    (local x) and width (local z), and ``yaw`` (rad) added to the car's rotation_y."""

    forward: float = 0.0
    lateral: float = 0.0
    yaw: float = 0.0


@dataclass(frozen=True)
class Pose:
    """Where an object was put: ``centre`` (3,) rect (the object-frame origin), ``yaw`` (rad, about
    rect y), ``rotation`` (3, 3) object -> rect, and the car's ``roof_centre`` (3,)."""

    centre: np.ndarray
    yaw: float
    rotation: np.ndarray
    roof_centre: np.ndarray


def sample_jitter(rng: np.random.Generator, position_range: float = POSITION_JITTER_M,
                  yaw_range: float = YAW_JITTER_RAD) -> Placement:
    """A jitter uniform in ``[-position_range, position_range]`` m (forward, then lateral) and
    ``[-yaw_range, yaw_range]`` rad, drawn from ``rng`` (three draws)."""
    forward, lateral = rng.uniform(-position_range, position_range, 2)
    yaw = rng.uniform(-yaw_range, yaw_range)
    return Placement(forward=float(forward), lateral=float(lateral), yaw=float(yaw))


def place_on_roof(obj_vertices: np.ndarray | torch.Tensor, car: Car,
                  jitter: Placement | None = None) -> tuple[np.ndarray | torch.Tensor, Pose]:
    """Object-frame vertices (V, 3) resting on ``car``'s roof (module doc): (rect vertices (V, 3),
    same type as the input, float64 for numpy; the :class:`Pose`)."""
    j = jitter or Placement()
    yaw = car.rotation_y + j.yaw
    rotation = roty(yaw)[0]
    offset = roty(car.rotation_y)[0] @ np.array([j.forward, 0.0, j.lateral])
    base = car.roof_centre + offset
    if isinstance(obj_vertices, np.ndarray):
        v = np.asarray(obj_vertices, dtype=np.float64)
        y_low = float(v[:, 1].max())
        centre = base - np.array([0.0, y_low, 0.0])
        return v @ rotation.T + centre, Pose(centre=centre, yaw=yaw, rotation=rotation, roof_centre=car.roof_centre)
    import torch

    v = obj_vertices
    lift = torch.zeros(3, dtype=v.dtype)
    lift[1] = v[:, 1].max()
    centre_t = torch.tensor(base, dtype=v.dtype) - lift
    placed = v @ torch.tensor(rotation.T, dtype=v.dtype) + centre_t
    pose = Pose(centre=centre_t.detach().cpu().numpy().astype(np.float64), yaw=yaw, rotation=rotation,
                roof_centre=car.roof_centre)
    return placed, pose


def rect_to_velo(vertices: np.ndarray | torch.Tensor, calib: Calibration) -> np.ndarray | torch.Tensor:
    """Rect-frame vertices (V, 3) in the velodyne frame (numpy via the Calibration, torch with the
    same matrix, differentiable)."""
    if isinstance(vertices, np.ndarray):
        return calib.rect_to_velo_points(vertices)
    import torch

    m = torch.tensor(calib.rect_to_velo, dtype=vertices.dtype)
    return vertices @ m[:3, :3].T + m[:3, 3]
