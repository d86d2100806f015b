"""Triangle meshes with per-face material and colour, and the primitives the object builders use.

Object-local frame of every builder: x forward (length), y left (width), z up, metres; labelled
objects have their bottom centre at the origin.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from robustbench3d.sensors.mesh import icosphere
from robustbench3d.synth.materials import Mat


@dataclass(frozen=True, eq=False)
class Mesh:
    """Triangles with a material id and a linear-RGB colour per face.

    Attributes:
        vertices: (V, 3) float64, m.
        faces: (F, 3) int64 vertex indices.
        material: (F,) uint8 :class:`~robustbench3d.synth.materials.Mat` ids.
        color: (F, 3) float32 linear RGB albedo in [0, 1].
    """

    vertices: np.ndarray
    faces: np.ndarray
    material: np.ndarray
    color: np.ndarray

    @property
    def num_faces(self) -> int:
        return len(self.faces)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners of the axis-aligned bounding box."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> Mesh:
        """Vertices mapped by x -> rotation @ x + translation."""
        v = self.vertices @ np.asarray(rotation, dtype=np.float64).T + np.asarray(translation, dtype=np.float64)
        return Mesh(v, self.faces, self.material, self.color)

    def scaled_to_box(self, lo: np.ndarray, hi: np.ndarray) -> Mesh:
        """Scale and shift each axis so that the bounding box becomes exactly [lo, hi]."""
        vmin, vmax = self.bounds()
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        scale = (hi - lo) / np.maximum(vmax - vmin, 1e-12)
        v = np.clip((self.vertices - vmin) * scale + lo, lo, hi)
        # pin the extreme vertices exactly onto the box faces
        v = np.where(self.vertices == vmin, lo, np.where(self.vertices == vmax, hi, v))
        return Mesh(v, self.faces, self.material, self.color)


def merge(meshes: list[Mesh]) -> Mesh:
    """One mesh holding all triangles of ``meshes``."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return Mesh(
        np.concatenate([m.vertices for m in meshes]),
        np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)]),
        np.concatenate([m.material for m in meshes]),
        np.concatenate([m.color for m in meshes]),
    )


def _faces_colored(vertices: np.ndarray, faces: np.ndarray, material: Mat | np.ndarray,
                   color: np.ndarray) -> Mesh:
    f = len(faces)
    mat = np.full(f, np.asarray(material, dtype=np.uint8))
    col = np.full((f, 3), np.asarray(color, dtype=np.float32))
    return Mesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64), mat, col)


def rot_z(yaw: float) -> np.ndarray:
    """3x3 rotation about z by ``yaw`` rad (x towards y)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(pitch: float) -> np.ndarray:
    """3x3 rotation about y by ``pitch`` rad (z towards x)."""
    c, s = np.cos(pitch), np.sin(pitch)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_x(roll: float) -> np.ndarray:
    """3x3 rotation about x by ``roll`` rad (y towards z)."""
    c, s = np.cos(roll), np.sin(roll)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


_BOX_FACES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                       [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])


def box(lo: np.ndarray, hi: np.ndarray, material: Mat, color: np.ndarray) -> Mesh:
    """Axis-aligned box [lo, hi] (12 triangles)."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], dtype=np.float64)
    return _faces_colored(v, _BOX_FACES, material, color)


def prism(polygon: np.ndarray, z0: float, z1: float, material: Mat, color: np.ndarray,
          top_scale: float = 1.0, caps: bool = True) -> Mesh:
    """Convex polygon (K, 2) in the xy-plane extruded from z0 to z1 (top shrunk by ``top_scale``)."""
    p = np.asarray(polygon, dtype=np.float64)
    k = len(p)
    bottom = np.column_stack([p, np.full(k, z0)])
    top = np.column_stack([p * top_scale, np.full(k, z1)])
    v = np.concatenate([bottom, top])
    i = np.arange(k)
    j = (i + 1) % k
    faces = [np.stack([i, j, j + k], 1), np.stack([i, j + k, i + k], 1)]
    if caps:
        fan = np.arange(1, k - 1)
        faces.append(np.stack([np.zeros(k - 2, int), fan + 1, fan], 1))
        faces.append(np.stack([np.full(k - 2, k), fan + k, fan + k + 1], 1))
    return _faces_colored(v, np.concatenate(faces), material, color)


def regular_polygon(n: int, radius: float, phase: float = 0.0) -> np.ndarray:
    """(n, 2) vertices of a regular polygon; ``phase`` rotates it (rad)."""
    a = phase + 2 * np.pi * np.arange(n) / n
    return radius * np.column_stack([np.cos(a), np.sin(a)])


def cylinder_y(center: np.ndarray, radius: float, width: float, n: int, material: Mat,
               color: np.ndarray) -> Mesh:
    """Cylinder with its axis along y (a wheel), a vertex at the very bottom."""
    m = prism(regular_polygon(n, radius, -np.pi / 2), -width / 2, width / 2, material, color)
    # prism axis is z: map (x, y, z) -> (x, z, y) and fix handedness by flipping the faces
    v = m.vertices[:, [0, 2, 1]] + np.asarray(center, dtype=np.float64)
    return Mesh(v, m.faces[:, ::-1].copy(), m.material, m.color)


class BeamSet:
    """Prisms between point pairs (limbs, frames, posts), built together in one vectorised pass."""

    def __init__(self) -> None:
        self._items: list[tuple[np.ndarray, np.ndarray, float, float, int, np.ndarray, int]] = []

    def add(self, p0: np.ndarray, p1: np.ndarray, radius: float, material: Mat, color: np.ndarray,
            radius1: float | None = None, sides: int = 5) -> None:
        """A closed prism of ``sides`` sides from p0 to p1, radius tapering to ``radius1``."""
        self._items.append((np.asarray(p0, np.float64), np.asarray(p1, np.float64), float(radius),
                            float(radius if radius1 is None else radius1), int(material),
                            np.asarray(color, np.float32), int(sides)))

    def mesh(self) -> Mesh:
        parts = []
        for sides in sorted({it[6] for it in self._items}):
            items = [it for it in self._items if it[6] == sides]
            p0 = np.array([it[0] for it in items])
            p1 = np.array([it[1] for it in items])
            r0 = np.array([it[2] for it in items])[:, None, None]
            r1 = np.array([it[3] for it in items])[:, None, None]
            d = p1 - p0
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            a = np.where((np.abs(d[:, 0]) < 0.9)[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
            e1 = np.cross(d, a)
            e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
            e2 = np.cross(d, e1)
            poly = regular_polygon(sides, 1.0)
            offs = poly[None, :, :1] * e1[:, None, :] + poly[None, :, 1:] * e2[:, None, :]  # (K, sides, 3)
            verts = np.concatenate([p0[:, None] + r0 * offs, p1[:, None] + r1 * offs], axis=1)
            k = sides
            i = np.arange(k)
            j = (i + 1) % k
            fan = np.arange(1, k - 1)
            tmpl = np.concatenate([np.stack([i, j, j + k], 1), np.stack([i, j + k, i + k], 1),
                                   np.stack([np.zeros(k - 2, int), fan + 1, fan], 1),
                                   np.stack([np.full(k - 2, k), fan + k, fan + k + 1], 1)])
            n = len(items)
            faces = (tmpl[None] + 2 * k * np.arange(n)[:, None, None]).reshape(-1, 3)
            mat = np.repeat(np.array([it[4] for it in items], np.uint8), len(tmpl))
            col = np.repeat(np.array([it[5] for it in items], np.float32), len(tmpl), axis=0)
            parts.append(Mesh(verts.reshape(-1, 3), faces.astype(np.int64), mat, col))
        return merge(parts)


def beam(p0: np.ndarray, p1: np.ndarray, radius: float, material: Mat, color: np.ndarray,
         radius1: float | None = None, sides: int = 5) -> Mesh:
    """Closed prism of ``sides`` sides from point p0 to p1 (radius tapering to ``radius1``)."""
    bs = BeamSet()
    bs.add(p0, p1, radius, material, color, radius1, sides)
    return bs.mesh()


@lru_cache(maxsize=64)
def _loft_faces(m: int, k: int) -> np.ndarray:
    """Faces (read-only) of :func:`loft` for M rings of K points: the quads, then both caps."""
    idx = np.arange(m * k).reshape(m, k)
    a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)
    c, d = idx[1:], np.roll(idx[1:], -1, axis=1)
    quads = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    ring0 = np.arange(k)
    ring1 = (m - 1) * k + np.arange(k)
    cap0 = np.stack([np.full(k, m * k), np.roll(ring0, -1), ring0], 1)
    cap1 = np.stack([np.full(k, m * k + 1), ring1, np.roll(ring1, -1)], 1)
    faces = np.concatenate([quads, cap0, cap1])
    faces.flags.writeable = False
    return faces


def loft(rings: np.ndarray, material: np.ndarray, color: np.ndarray, cap_material: tuple[Mat, Mat],
         cap_color: tuple[np.ndarray, np.ndarray]) -> Mesh:
    """Closed tube through M rings of K points each, capped at both ends.

    Args:
        rings: (M, K, 3) ring points; ring m+1 follows ring m along the tube.
        material: (M-1, K) material of the quad between ring points (m, k), (m, k+1) and ring m+1.
        color: (M-1, K, 3) colour of those quads.
        cap_material, cap_color: of the first and last ring's cap (a fan from the ring centroid).
    """
    r = np.asarray(rings, dtype=np.float64)
    m, k = r.shape[:2]
    quad_mat = material.reshape(-1)
    mat = np.concatenate([quad_mat, quad_mat, np.full(k, cap_material[0]), np.full(k, cap_material[1])])
    quad_col = color.reshape(-1, 3)
    cap_col = [np.broadcast_to(np.asarray(c, np.float32), (k, 3)) for c in cap_color]
    col = np.concatenate([quad_col, quad_col, *cap_col])
    centers = np.stack([r[0].mean(axis=0), r[-1].mean(axis=0)])
    verts = np.concatenate([r.reshape(-1, 3), centers])
    return Mesh(verts, _loft_faces(m, k), mat.astype(np.uint8), col.astype(np.float32))


def ellipsoid(center: np.ndarray, radii: np.ndarray, material: Mat, color: np.ndarray, level: int = 1,
              roughness: float = 0.0, rng: np.random.Generator | None = None) -> Mesh:
    """Ellipsoid from an icosphere (level 1: 80 faces); ``roughness`` jitters radii by that fraction."""
    v, f = icosphere(level)
    if roughness > 0:
        if rng is None:
            raise ValueError("roughness needs a Generator")
        v *= 1.0 + roughness * rng.uniform(-1.0, 1.0, size=(len(v), 1))
    return _faces_colored(v * np.asarray(radii) + np.asarray(center), f, material, color)
