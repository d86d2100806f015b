"""Surface materials as the two sensors see them: ids stored per mesh face and their sensor properties.

A face's appearance is its material id (:class:`Mat`) plus a linear-RGB albedo in [0, 1] (stored
per face by the generator). The material decides how the LiDAR sees the face (reflectivity, chance
of a return at all, whether the reflectivity follows the albedo's brightness: :data:`TINTED`) and
how the camera shades it (specular strength). The generator's palettes and textures are in
:mod:`robustbench3d.synth.materials` and :mod:`robustbench3d.synth.camera`.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np


class Mat(IntEnum):
    """Material ids stored per face (uint8)."""

    GROUND = 0  # terrain: asphalt / grass / lane paint decided per point from the road layout
    SIDEWALK = 1
    CURB = 2
    PAINT = 3  # vehicle body paint
    GLASS = 4
    TYRE = 5
    RIM = 6
    HEADLIGHT = 7
    TAILLIGHT = 8
    TRIM = 9  # dark plastic: bumpers, grille, underbody
    FACADE = 10
    WINDOW = 11  # building windows
    WALL = 12
    FOLIAGE = 13
    BARK = 14
    METAL = 15  # poles, bicycle frames
    SIGN = 16  # retro-reflective sign faces
    CLOTH = 17
    SKIN = 18
    ROOF = 19  # building roofs


@dataclass(frozen=True)
class Material:
    """Sensor-relevant properties of a material.

    Attributes:
        reflectivity: LiDAR reflectance at normal incidence and short range, in [0, 1).
        return_prob: probability that a LiDAR pulse hitting it produces a return at all
            (glass and tyres swallow many pulses).
        specular: strength of the camera's sky reflection / sun highlight, 0 for matte.
    """

    reflectivity: float
    return_prob: float
    specular: float


MATERIALS: dict[Mat, Material] = {
    Mat.GROUND: Material(0.30, 1.0, 0.0),
    Mat.SIDEWALK: Material(0.34, 1.0, 0.0),
    Mat.CURB: Material(0.38, 1.0, 0.0),
    Mat.PAINT: Material(0.42, 0.97, 0.35),
    Mat.GLASS: Material(0.08, 0.75, 0.9),
    Mat.TYRE: Material(0.05, 0.8, 0.0),
    Mat.RIM: Material(0.45, 1.0, 0.3),
    Mat.HEADLIGHT: Material(0.8, 1.0, 0.6),
    Mat.TAILLIGHT: Material(0.8, 1.0, 0.4),
    Mat.TRIM: Material(0.12, 0.95, 0.05),
    Mat.FACADE: Material(0.40, 1.0, 0.0),
    Mat.WINDOW: Material(0.10, 0.7, 0.7),
    Mat.WALL: Material(0.38, 1.0, 0.0),
    Mat.FOLIAGE: Material(0.42, 0.95, 0.0),
    Mat.BARK: Material(0.30, 1.0, 0.0),
    Mat.METAL: Material(0.40, 1.0, 0.3),
    Mat.SIGN: Material(0.97, 1.0, 0.2),
    Mat.CLOTH: Material(0.30, 1.0, 0.0),
    Mat.SKIN: Material(0.35, 1.0, 0.0),
    Mat.ROOF: Material(0.30, 1.0, 0.0),
}

#: Per-material arrays indexed by material id.
REFLECTIVITY = np.array([MATERIALS[m].reflectivity for m in Mat], dtype=np.float32)
RETURN_PROB = np.array([MATERIALS[m].return_prob for m in Mat], dtype=np.float32)
SPECULAR = np.array([MATERIALS[m].specular for m in Mat], dtype=np.float32)
#: (len(Mat),) bool: materials whose LiDAR reflectivity scales with the albedo's brightness
#: (:func:`robustbench3d.sensors.lidar_model.material_reflectivity`).
TINTED = np.isin(np.arange(len(Mat)), [Mat.PAINT, Mat.FACADE, Mat.WALL, Mat.CLOTH])
