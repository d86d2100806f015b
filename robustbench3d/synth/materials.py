"""Surface materials of the procedural scenes and their colour palettes.

Every mesh face carries a material id (:class:`Mat`) and a linear-RGB albedo in [0, 1]. The
material decides how the LiDAR sees the face (reflectivity, chance of a return at all) and how
the camera shades it (specular strength, texture); the ids and their sensor properties live in
:mod:`robustbench3d.sensors.materials` (re-exported here). Colours are linear RGB; the camera applies
the sRGB transfer curve at the end.

The palettes deliberately overlap: white, silver, grey, black, red and blue occur on cars as well
as on vans, buildings, walls, clothes and signs, so that a detector cannot find cars by colour.
"""

from __future__ import annotations

import numpy as np

from robustbench3d.sensors.materials import (  # noqa: F401  (re-exported for the generator's modules)
    MATERIALS,
    REFLECTIVITY,
    RETURN_PROB,
    SPECULAR,
    Mat,
    Material,
)


def srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    """sRGB values in [0, 1] to linear RGB (the standard piecewise curve)."""
    c = np.asarray(rgb, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _palette(hexes: list[tuple[str, float]]) -> tuple[np.ndarray, np.ndarray]:
    cols = np.array([[int(h[i:i + 2], 16) / 255 for i in (0, 2, 4)] for h, _ in hexes])
    w = np.array([p for _, p in hexes], dtype=np.float64)
    return srgb_to_linear(cols), w / w.sum()


# (sRGB hex, weight). Car paints roughly follow the colour shares of European cars of the 2010s.
CAR_PAINT = _palette([
    ("c8cbcd", 14), ("9a9fa3", 12), ("6b7075", 9), ("2b2d30", 8), ("141517", 10), ("eeeeea", 12),
    ("d9d6cc", 4), ("8e1b1b", 5), ("b52b25", 4), ("1f3b6e", 6), ("3d5f8f", 4), ("15253f", 4),
    ("284d36", 2), ("6e6a4e", 2), ("b9a27a", 2), ("d8b13a", 1), ("c46a24", 1), ("5a3b2a", 1),
])
VAN_PAINT = _palette([("f0f0ec", 30), ("c8cbcd", 12), ("8a9096", 8), ("1e2f55", 6), ("b52b25", 4),
                      ("d8c23a", 3), ("202224", 6), ("dcd8c8", 5)])
FACADE = _palette([
    ("e8dcc2", 8), ("f2efe6", 8), ("c9c4ba", 6), ("a8a39a", 5), ("d7b98a", 5), ("b5644a", 5),
    ("c98f74", 4), ("8d5a44", 3), ("9aa6ad", 4), ("6f777d", 3), ("e3d27c", 2), ("b8c7b0", 2),
    ("3e4042", 2), ("eeeeea", 3),
])
WALL = _palette([("9c9a94", 8), ("bdbab2", 6), ("7a7873", 5), ("a45a44", 4), ("e4e1d8", 4),
                 ("5c5a56", 3), ("8a7a62", 2), ("2f3a44", 1)])
CLOTH = _palette([
    ("1c1d22", 10), ("2e3b55", 8), ("4a5d7e", 6), ("7a7d82", 5), ("d9d9d4", 4), ("8e1f22", 3),
    ("c0392b", 2), ("3f5e3a", 2), ("b89f77", 3), ("5b3a29", 3), ("e0b53a", 1), ("6d3c79", 1),
])
SKIN = _palette([("e9c3a6", 4), ("d1a07d", 4), ("a8755a", 2), ("6b4431", 1)])
FOLIAGE = _palette([("3f5a2a", 5), ("4e6b30", 5), ("2e4522", 4), ("5f7a3a", 3), ("6d7042", 2),
                    ("7a6a3a", 1)])
TRIM = srgb_to_linear(np.array([0.09, 0.09, 0.10]))
TYRE = srgb_to_linear(np.array([0.06, 0.06, 0.065]))
RIM = srgb_to_linear(np.array([0.55, 0.56, 0.58]))
GLASS = srgb_to_linear(np.array([0.10, 0.12, 0.14]))
HEADLIGHT = srgb_to_linear(np.array([0.85, 0.86, 0.85]))
TAILLIGHT = srgb_to_linear(np.array([0.60, 0.05, 0.05]))
METAL = srgb_to_linear(np.array([0.45, 0.46, 0.47]))
BARK = srgb_to_linear(np.array([0.28, 0.22, 0.17]))
SIDEWALK = srgb_to_linear(np.array([0.58, 0.57, 0.55]))
CURB = srgb_to_linear(np.array([0.66, 0.65, 0.63]))
WINDOW = srgb_to_linear(np.array([0.16, 0.19, 0.22]))
SIGN_COLORS = srgb_to_linear(np.array([[0.85, 0.85, 0.85], [0.75, 0.1, 0.1], [0.1, 0.25, 0.65],
                                       [0.9, 0.75, 0.1]]))


def pick(rng: np.random.Generator, palette: tuple[np.ndarray, np.ndarray], jitter: float = 0.06) -> np.ndarray:
    """One colour from a palette with multiplicative brightness/hue jitter (linear RGB, float64)."""
    cols, w = palette
    c = cols[rng.choice(len(cols), p=w)]
    c = c * (1.0 + jitter * rng.standard_normal(3)) * (1.0 + jitter * rng.standard_normal())
    return np.clip(c, 0.005, 0.95)
