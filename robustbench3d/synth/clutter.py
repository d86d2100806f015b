"""Unlabelled scene clutter: poles and signs, walls, buildings, trees and bushes.

Frame: object-local, x along the street (the facade / wall runs along x), y towards the road
side away from the street, z up, origin on the ground; metres.
"""

from __future__ import annotations

import numpy as np

from robustbench3d.synth import materials as mt
from robustbench3d.synth.materials import Mat
from robustbench3d.synth.mesh import Mesh, beam, box, ellipsoid, merge, prism, regular_polygon


def _v(x: float, y: float, z: float) -> np.ndarray:
    """A 3-vector (float64)."""
    return np.array([x, y, z], dtype=np.float64)


def pole_mesh(rng: np.random.Generator) -> Mesh:
    """A street lamp, a sign post or a plain post."""
    u = rng.uniform
    kind = rng.choice(3, p=[0.4, 0.4, 0.2])
    if kind == 0:  # street lamp: tall mast, arm over the road (towards -y), lamp head
        h = u(5.0, 9.0)
        r = u(0.07, 0.12)
        color = mt.METAL * u(0.6, 1.2)
        arm = u(1.0, 2.2)
        return merge([
            prism(regular_polygon(6, r), 0.0, h, Mat.METAL, color, top_scale=0.7),
            beam((0, 0, h - 0.05), (0, -arm, h + 0.15), 0.04, Mat.METAL, color, sides=4),
            box((-0.15, -arm - 0.5, h), (0.15, -arm + 0.1, h + 0.18), Mat.METAL, color),
        ])
    if kind == 1:  # sign post with a plate
        h = u(2.0, 2.8)
        plate = mt.SIGN_COLORS[rng.integers(len(mt.SIGN_COLORS))]
        size = u(0.5, 0.8)
        shape = regular_polygon(int(rng.choice([3, 4, 8, 16])), size / 2, np.pi / 2)
        face = prism(shape, -0.01, 0.01, Mat.SIGN, plate)
        # plate stands upright facing along the street (normal along x): (x, y, z) -> (z, x, y)
        face = Mesh(face.vertices[:, [2, 0, 1]] + _v(0.06, 0.0, h), face.faces, face.material, face.color)
        return merge([prism(regular_polygon(6, 0.035), 0.0, h + size / 2, Mat.METAL, mt.METAL), face])
    h = u(0.8, 3.5)  # bollard / post
    return prism(regular_polygon(8, u(0.05, 0.15)), 0.0, h, Mat.METAL, mt.pick(rng, mt.WALL))


def wall_mesh(length: float, rng: np.random.Generator) -> Mesh:
    """A wall or fence segment of ``length`` m along x, 0.5-2.6 m high."""
    u = rng.uniform
    h = u(0.5, 2.6)
    t = u(0.15, 0.4)
    color = mt.pick(rng, mt.WALL)
    parts = [box((-length / 2, 0.0, 0.0), (length / 2, t, h), Mat.WALL, color)]
    if rng.random() < 0.3:  # coping on top
        parts.append(box((-length / 2, -0.04, h), (length / 2, t + 0.04, h + 0.08), Mat.WALL, 0.8 * color))
    return merge(parts)


def building_mesh(width: float, depth: float, height: float, rng: np.random.Generator) -> Mesh:
    """A block building: facade along x at y = 0 facing -y, windows on the street facade and sides."""
    u = rng.uniform
    color = mt.pick(rng, mt.FACADE)
    parts = [box((-width / 2, 0.0, 0.0), (width / 2, depth, height), Mat.FACADE, color)]
    floor_h = u(2.8, 3.4)
    win_w = u(0.9, 1.6)
    win_h = u(1.2, 1.7)
    pitch = win_w + u(0.8, 2.0)
    ground_floor = u(0.0, 1.0) < 0.5
    glass = mt.WINDOW * u(0.7, 1.3)
    n_cols = int((width - 1.0) // pitch)
    n_rows = int((height - 0.8) // floor_h)
    xs = (np.arange(n_cols) - (n_cols - 1) / 2) * pitch
    rows = []
    for row in range(n_rows):
        z0 = row * floor_h + (0.3 if row == 0 and ground_floor else 0.9)
        wh = (floor_h - 0.6) if row == 0 and ground_floor else win_h
        if z0 + wh > height - 0.3:
            break
        rows.append((z0, z0 + wh))
    if rows and n_cols > 0:  # all window quads at once, 3 cm in front of the facade
        z = np.array(rows)
        x0 = np.repeat(xs - win_w / 2, len(z))
        x1 = np.repeat(xs + win_w / 2, len(z))
        z0, z1 = np.tile(z[:, 0], n_cols), np.tile(z[:, 1], n_cols)
        y = np.full_like(x0, -0.03)
        v = np.stack([np.column_stack(c) for c in ((x0, y, z0), (x1, y, z0), (x1, y, z1), (x0, y, z1))], axis=1)
        n = len(x0)
        f = (np.array([[0, 1, 2], [0, 2, 3]])[None] + 4 * np.arange(n)[:, None, None]).reshape(-1, 3)
        parts.append(Mesh(v.reshape(-1, 3), f, np.full(2 * n, Mat.WINDOW, np.uint8),
                          np.tile(np.asarray(glass, np.float32), (2 * n, 1))))
    if rng.random() < 0.6:  # roof edge
        parts.append(box((-width / 2 - 0.1, -0.15, height), (width / 2 + 0.1, depth + 0.1, height + 0.25),
                         Mat.ROOF, 0.6 * color))
    return merge(parts)


def tree_mesh(rng: np.random.Generator, street: bool = False) -> Mesh:
    """A tree: trunk and one to three irregular crown blobs starting above the trunk.

    Street trees (``street``) are pruned to clear traffic: crowns start 3.2-4.5 m up, at most 2.5 m wide.
    """
    u = rng.uniform
    h_trunk = u(3.2, 4.5) if street else u(1.8, 3.5)
    crown_r = u(1.2, 2.5) if street else u(1.2, 3.2)
    r_trunk = u(0.1, 0.25)
    parts = [prism(regular_polygon(6, r_trunk), 0.0, h_trunk + 0.5, Mat.BARK, mt.BARK * u(0.7, 1.3),
                   top_scale=0.7)]
    green = mt.pick(rng, mt.FOLIAGE, 0.12)
    for _ in range(int(rng.integers(1, 4))):
        radii = crown_r * np.array([u(0.8, 1.1), u(0.8, 1.1), u(0.8, 1.2)])
        c = np.array([u(-0.3, 0.3) * crown_r, u(-0.3, 0.3) * crown_r, h_trunk + 1.2 * radii[2]])
        parts.append(ellipsoid(c, radii, Mat.FOLIAGE, green * u(0.8, 1.2), roughness=0.18, rng=rng))
    return merge(parts)


def bush_mesh(length: float, rng: np.random.Generator) -> Mesh:
    """A bush or a hedge of ``length`` m along x."""
    u = rng.uniform
    h = u(0.6, 2.2)
    green = mt.pick(rng, mt.FOLIAGE, 0.12)
    n = max(1, int(length / (1.5 * h)))
    parts = []
    for i in range(n):
        x = (i - (n - 1) / 2) * length / n
        parts.append(ellipsoid((x, 0.0, h * 0.5), (length / n * 0.7, u(0.5, 1.0), h * 0.55), Mat.FOLIAGE,
                               green * u(0.85, 1.15), roughness=0.2, rng=rng))
    m = merge(parts)
    lo = m.bounds()[0]
    return m.transformed(np.eye(3), (0.0, 0.0, -lo[2] - 0.05))
