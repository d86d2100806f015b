"""Embree ray casting against a scene (``embreex.rtcore_scene.EmbreeScene.run`` directly).

All triangles of a scene go into one Embree mesh (float32, velodyne frame); per-triangle arrays
map a hit back to its object, material and colour. Per-object scenes (one object alone) are
built on demand for the annotation's "what would this object cover if nothing hid it" casts.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from embreex import rtcore, rtcore_scene
from embreex.mesh_construction import TriangleMesh

from robustbench3d.sensors.mesh import face_normals
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


@lru_cache(maxsize=1)
def _device() -> rtcore.EmbreeDevice:
    """The process's Embree device, shared by all scenes (one device per scene costs a device start-up
    for each of the per-object scenes of the annotation)."""
    return rtcore.EmbreeDevice()


def _embree(vertices: np.ndarray, faces: np.ndarray) -> rtcore_scene.EmbreeScene:
    scene = rtcore_scene.EmbreeScene(_device())
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
        self.faces = np.concatenate([m.faces for m in meshes]) + np.repeat(offsets, counts)[:, None]
        #: (F,) int32 object index of each triangle.
        self.tri_object = np.repeat(np.arange(len(meshes), dtype=np.int32), counts)
        #: (F,) uint8 material id of each triangle.
        self.tri_material = np.concatenate([m.material for m in meshes])
        #: (F, 3) float32 linear-RGB albedo of each triangle.
        self.tri_color = np.concatenate([m.color for m in meshes]).astype(np.float32)
        #: (F, 3) float32 unit normals (orientation arbitrary).
        self.face_normals = face_normals(self.vertices, self.faces).astype(np.float32)
        #: (F, 3) float32 first vertex of each triangle.
        self.face_anchor = np.take(self.vertices, self.faces[:, 0], axis=0).astype(np.float32)
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

    def occluded(self, origins: np.ndarray, direction: np.ndarray, max_dist: float) -> np.ndarray:
        """(N,) bool: something lies within ``max_dist`` along the rays from ``origins`` (N, 3) in the
        common unit ``direction`` (3,) (shadow rays)."""
        o = _f32(origins)
        dists = np.full(len(o), max_dist, dtype=np.float32)
        # a single direction row is used for every ray by EmbreeScene.run (no (N, 3) copy of it needed)
        return self._scene.run(o, _f32(direction).reshape(1, 3), dists=dists, query="OCCLUDED") == 0

    def hits_object_alone(self, index: int, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(N,) bool: rays hit object ``index`` when it is alone in the scene."""
        if index not in self._solo:
            self._solo[index] = _embree(self._meshes[index].vertices, self._meshes[index].faces)
        d = _f32(directions)
        o = _f32(np.broadcast_to(origins, d.shape))
        return self._solo[index].run(o, d) >= 0
