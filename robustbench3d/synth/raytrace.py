"""Embree ray casting against a scene (``embreex.rtcore_scene.EmbreeScene.run`` directly).

All triangles of a scene go into one Embree mesh (float32, velodyne frame); per-triangle arrays
map a hit back to its object, material and colour. Per-object scenes (one object alone) are
built on demand for the annotation's "what would this object cover if nothing hid it" casts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from robustbench3d.synth.scene import Scene


@dataclass(frozen=True)
class Hits:
    """First hits of a batch of rays.

    Attributes:
        prim: (N,) int32 triangle index, -1 for a miss.
        t: (N,) float32 distance along the (unit) ray, m; meaningless for misses.
        normal: (N, 3) float32 unnormalised geometric normal of the hit triangle.
    """

    prim: np.ndarray
    t: np.ndarray
    normal: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return self.prim >= 0


def _embree(vertices: np.ndarray, faces: np.ndarray) -> rtcore_scene.EmbreeScene:
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, np.ascontiguousarray(vertices, dtype=np.float32), np.ascontiguousarray(faces, dtype=np.int32))
    return scene


def _f32(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)


class SceneGeometry:
    """The triangles of a :class:`~robustbench3d.synth.scene.Scene`, ready for ray queries."""

    def __init__(self, scene: Scene):
        meshes = [o.mesh for o in scene.objects]
        counts = np.array([m.num_faces for m in meshes])
        offsets = np.concatenate([[0], np.cumsum([len(m.vertices) for m in meshes])[:-1]])
        self.vertices = np.concatenate([m.vertices for m in meshes])
        self.faces = np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)])
        #: (F,) int32 object index of each triangle.
        self.tri_object = np.repeat(np.arange(len(meshes), dtype=np.int32), counts)
        #: (F,) uint8 material id of each triangle.
        self.tri_material = np.concatenate([m.material for m in meshes])
        #: (F, 3) float32 linear-RGB albedo of each triangle.
        self.tri_color = np.concatenate([m.color for m in meshes]).astype(np.float32)
        v = self.vertices[self.faces]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        #: (F, 3) float32 unit normals (orientation arbitrary).
        self.face_normals = (n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)).astype(np.float32)
        #: (F, 3) float32 first vertex of each triangle.
        self.face_anchor = v[:, 0].astype(np.float32)
        self._meshes = meshes
        self._scene = _embree(self.vertices, self.faces)
        self._solo: dict[int, rtcore_scene.EmbreeScene] = {}

    @property
    def num_triangles(self) -> int:
        return len(self.faces)

    def intersect(self, origins: np.ndarray, directions: np.ndarray, max_dist: float | None = None) -> Hits:
        """Nearest hits of rays (origins (N, 3) or (3,), unit directions (N, 3); velodyne frame)."""
        d = _f32(directions)
        o = _f32(np.broadcast_to(origins, d.shape))
        dists = None if max_dist is None else np.full(len(d), max_dist, dtype=np.float32)
        out = self._scene.run(o, d, dists=dists, output=1)
        return Hits(out["primID"], out["tfar"], out["Ng"])

    def occluded(self, origins: np.ndarray, directions: np.ndarray, max_dist: float) -> np.ndarray:
        """(N,) bool: something lies along the ray within ``max_dist`` (shadow rays)."""
        d = _f32(directions)
        o = _f32(np.broadcast_to(origins, d.shape))
        dists = np.full(len(d), max_dist, dtype=np.float32)
        return self._scene.run(o, d, dists=dists, query="OCCLUDED") == 0

    def hits_object_alone(self, index: int, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(N,) bool: rays hit object ``index`` when it is alone in the scene."""
        if index not in self._solo:
            self._solo[index] = _embree(self._meshes[index].vertices, self._meshes[index].faces)
        d = _f32(directions)
        o = _f32(np.broadcast_to(origins, d.shape))
        return self._solo[index].run(o, d) >= 0
