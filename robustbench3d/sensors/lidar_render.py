"""Render meshes into a LiDAR scan: culled, differentiable HDL-64E ray casting with occlusion both ways.

Frame: velodyne (x forward, y left, z up; m). Rays: the scan's own beam pattern
(:mod:`robustbench3d.sensors.lidar_beams`: the generator's rays on generated scans, per-laser measured phases
on real KITTI scans); of each laser only the rays passing within the mesh's bounding sphere (plus one azimuth
step) are cast, each at the faces whose bounding spheres it can pass through (one compiled pass that finds and
tests these pairs, :meth:`~robustbench3d.sensors.lidar_beams.BeamPattern.sphere_nearest`, inside
:func:`~robustbench3d.sensors.raycast.cast_ray_search`). Per ray the nearest surface over all meshes
wins. A scan point is on a ray when it belongs to the same laser and lies within half a firing step
(0.09 deg) of its azimuth; its range is measured from that laser's origin. On a ray hitting a mesh at t:

* original points farther than t are removed (the mesh blocks them, whether or not it returns);
* if an original point is nearer than t, the mesh is hidden there (no point added);
* otherwise a return is added when t is inside the range gate (1 m, 120 m], with reflectance from
  :mod:`robustbench3d.sensors.lidar_model` (material car paint, albedo = the vertex colours interpolated at
  the hit, incidence angle, range), optionally dropped (``dropout``) and moved along the ray (``range_noise_m``).

Without ``rng`` everything is deterministic; random draws come only from ``rng``: first the dropout
(one uniform per candidate return), then the range noise (one normal per kept return).

``render_lidar(..., cull=False)`` is the full-scene reference the culling is measured against: every ray of
the pattern is cast at every face of every mesh (all pairs, in chunks of :data:`FULL_SCENE_CHUNK_PAIRS`, with
the same element-wise test) and every scan point is matched to its ray; the cull is conservative, so both
give the same scan, bit for bit, at a far higher cost.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from robustbench3d.sensors import lidar_model as lm
from robustbench3d.sensors.lidar_beams import BeamPattern, estimate_pattern, ring_ids_of
from robustbench3d.sensors.lidar_table_kernels import rows_but
from robustbench3d.sensors.materials import Mat
from robustbench3d.sensors.mesh import dot3, face_normals
from robustbench3d.sensors.pattern_cache import PatternCache
from robustbench3d.sensors.raycast import PairSearch, cast_ray_pair_chunks, cast_ray_search

#: Albedo of meshes given without colours (linear RGB).
DEFAULT_ALBEDO = 0.5
#: Material of the rendered meshes (reflectivity tinted by the albedo's luminance).
MESH_MATERIAL = Mat.PAINT
#: (ray, face) pairs per chunk of the full-scene cast (``cull=False``): about 20 MB of temporaries (small enough
#: to stay in cache: 2x faster per pair than 1 << 20).
FULL_SCENE_CHUNK_PAIRS = 1 << 16

MeshInput = tuple[object, object, object]

__all__ = ["FULL_SCENE_CHUNK_PAIRS", "LidarRenderResult", "MeshInput", "PreparedScan", "TracedHits", "prepare_scan",
           "render_lidar", "render_lidar_torch", "trace_meshes"]


@dataclass(frozen=True)
class PreparedScan:
    """A scan with its beam pattern and each point's ray (reuse it to render the same frame many times).

    Attributes:
        scan: (N, 4) float32 x, y, z, reflectance (a float32 input is used as is, not copied).
        pattern: the scan's :class:`~robustbench3d.sensors.lidar_beams.BeamPattern`.
        ring: (N,) int64 laser of each point (an id the sensor lacks gets no ray and the range from the
            velodyne origin).
        point_ray: (N,) int64 index into ``pattern.rays`` of the ray each point lies on, -1 if none.
        range_m: (N,) distance of each point from its laser's origin, m (NaN for the points away from the rays
            when the matching is restricted to some of them).
        by_ray: (N,) point indices stably sorted by ``point_ray`` (the points without a ray, -1, first; each
            ray's points in scan order).
        sorted_ray: (N,) ``point_ray[by_ray]``.
    """

    scan: np.ndarray
    pattern: BeamPattern
    ring: np.ndarray
    point_ray: np.ndarray
    range_m: np.ndarray
    by_ray: np.ndarray
    sorted_ray: np.ndarray

    def points_on(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For ray indices (K,): (which of the K, point index) pairs of the points lying on them."""
        lo = np.searchsorted(self.sorted_ray, rays, "left")
        hi = np.searchsorted(self.sorted_ray, rays, "right")
        n = hi - lo
        owner = np.repeat(np.arange(len(rays)), n)
        pos = np.repeat(lo - np.concatenate([[0], np.cumsum(n)[:-1]]), n) + np.arange(n.sum())
        return owner, self.by_ray[pos]

    def ranges_on(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`points_on` and each point's ``range_m`` (m)."""
        owner, point = self.points_on(rays)
        return owner, point, self.range_m[point]


@dataclass(frozen=True)
class _RayPoints:
    """The points of a scan on some of its rays, all a render reads of the scan besides its rows: what
    :func:`_prepare_rays` finds for the culled rays, without its (N,) arrays.

    Attributes:
        scan, pattern: as :class:`PreparedScan`'s.
        index: (K,) int64 the points with a ray, stably sorted by ray (each ray's points in scan order).
        ray: (K,) int64 their rays (non-decreasing).
        range_m: (K,) float64 their distances from their lasers' origins, m.
    """

    scan: np.ndarray
    pattern: BeamPattern
    index: np.ndarray
    ray: np.ndarray
    range_m: np.ndarray

    def ranges_on(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`PreparedScan.ranges_on`: for ray indices (K,) the (which of the K, point index, range) of the
        points lying on them, each ray's points in scan order."""
        lo = np.searchsorted(self.ray, rays, "left")
        n = np.searchsorted(self.ray, rays, "right") - lo
        owner = np.repeat(np.arange(len(rays)), n)
        pos = np.repeat(lo - np.concatenate([[0], np.cumsum(n)[:-1]]), n) + np.arange(n.sum())
        return owner, self.index[pos], self.range_m[pos]


def prepare_scan(scan: np.ndarray, ring_ids: np.ndarray | None = None,
                 pattern: BeamPattern | None = None, rays: np.ndarray | None = None) -> PreparedScan:
    """Laser ids (given, else :func:`~robustbench3d.sensors.lidar_beams.scan_ring_ids`), beam pattern (given,
    else estimated from the scan) and each point's ray.

    ``rays`` (indices into ``pattern.rays``) restricts the ray matching to the points that can lie on them
    (:meth:`~robustbench3d.sensors.lidar_beams.BeamPattern.near_rays`; the others get ray -1, range NaN):
    enough, and much cheaper, to render meshes whose culled rays
    (:meth:`~robustbench3d.sensors.lidar_beams.BeamPattern.cull`) are among them."""
    return _prepare_rays(*_scan_pattern(scan, ring_ids, pattern), rays)


def _prepare_rays(pts: np.ndarray, ring: np.ndarray, pattern: BeamPattern, az: np.ndarray | None,
                  rays: np.ndarray | None) -> PreparedScan:
    """:func:`prepare_scan` of checked points, their laser ids, pattern and azimuths (:func:`_scan_pattern`);
    ``az`` None: computed here, on a laser-ordered scan only for the points of the lasers of ``rays``."""
    if az is None:
        az = _azimuths(pts, ring, None if rays is None else pattern.ray_rings(np.asarray(rays, dtype=np.int64)))
    sub: slice | np.ndarray = slice(None)
    if rays is not None:
        sub = np.flatnonzero(pattern.near_rays(np.asarray(rays, dtype=np.int64), ring, az))
    xyz, az = pts[sub, :3].astype(np.float64), az[sub]
    rk = ring[sub]
    h0 = np.where((rk >= 0) & (rk < pattern.sensor.num_lasers),
                  pattern.sensor.origin_z[np.clip(rk, 0, pattern.sensor.num_lasers - 1)], 0.0)
    point_ray = np.full(len(pts), -1, dtype=np.int64)
    rng_m = np.full(len(pts), np.nan)
    ray_sub = pattern.nearest_ray(rk, az)
    point_ray[sub] = ray_sub
    rng_m[sub] = np.sqrt(xyz[:, 0] ** 2 + xyz[:, 1] ** 2 + (xyz[:, 2] - h0) ** 2)
    # by_ray = np.argsort(point_ray, kind="stable"): the points without a ray (-1) first, then the few with one
    # (those of ``sub``, increasing, whose nearest ray is found), stably by ray
    has = ray_sub >= 0
    on = np.flatnonzero(has) if isinstance(sub, slice) else sub[has]
    on = on[np.argsort(ray_sub[has], kind="stable")]
    free = np.ones(len(pts), dtype=bool)
    free[on] = False
    n_off = len(pts) - len(on)
    by_ray = np.empty(len(pts), dtype=np.int64)
    by_ray[:n_off] = np.flatnonzero(free)
    by_ray[n_off:] = on
    sorted_ray = np.full(len(pts), -1, dtype=np.int64)
    sorted_ray[n_off:] = point_ray[on]
    return PreparedScan(pts, pattern, ring, point_ray, rng_m, by_ray, sorted_ray)


def _ray_points(pts: np.ndarray, ring: np.ndarray, pattern: BeamPattern, az: np.ndarray | None, rays: np.ndarray
                ) -> _RayPoints:
    """The points of ``rays`` (:func:`_prepare_rays` of the same arguments restricted to them: the same points,
    rays and ranges, bit for bit) without (N,) arrays: the azimuths (``az`` (N,) if given) of the rays' lasers'
    points only (on a laser-ordered scan their one span, else every point), the near points among them
    (:meth:`~robustbench3d.sensors.lidar_beams.BeamPattern.near_rays`), their nearest rays and ranges."""
    lasers = pattern.ray_rings(rays)
    lo, hi = _laser_span(ring, lasers)
    part = np.zeros(0) if hi <= lo else _span_azimuths(pts, lo, hi) if az is None else az[lo:hi]
    sub = lo + np.flatnonzero(pattern.near_rays(rays, ring[lo:hi], part)) if hi > lo else np.zeros(0, np.int64)
    xyz, az_sub, rk = pts[sub, :3].astype(np.float64), part[sub - lo], ring[sub]
    h0 = np.where((rk >= 0) & (rk < pattern.sensor.num_lasers),
                  pattern.sensor.origin_z[np.clip(rk, 0, pattern.sensor.num_lasers - 1)], 0.0)
    ray_sub = pattern.nearest_ray(rk, az_sub)
    rng_m = np.sqrt(xyz[:, 0] ** 2 + xyz[:, 1] ** 2 + (xyz[:, 2] - h0) ** 2)
    has = np.flatnonzero(ray_sub >= 0)
    order = has[np.argsort(ray_sub[has], kind="stable")]
    return _RayPoints(pts, pattern, sub[order], ray_sub[order], rng_m[order])


def _laser_span(ring: np.ndarray, lasers: np.ndarray) -> tuple[int, int]:
    """(lo, hi): on a laser-ordered scan the rows of the lasers from the lowest to the highest of ``lasers``
    ((0, 0) for none), else every row (the span :func:`_azimuths` computes)."""
    if len(ring) and np.all(ring[1:] >= ring[:-1]):
        if len(lasers) == 0:
            return 0, 0
        return int(np.searchsorted(ring, lasers.min(), "left")), int(np.searchsorted(ring, lasers.max(), "right"))
    return 0, len(ring)


def _span_azimuths(pts: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """degrees(atan2(y, x)) (hi - lo,) float64 of the float32 points ``pts[lo:hi]`` (as :func:`_azimuths`)."""
    part = np.arctan2(pts[lo:hi, 1].astype(np.float64), pts[lo:hi, 0].astype(np.float64))
    np.degrees(part, out=part)
    return part


def _azimuths(pts: np.ndarray, ring: np.ndarray, lasers: np.ndarray | None) -> np.ndarray:
    """degrees(atan2(y, x)) (N,) float64 of float32 points (N, 4); with ``lasers`` (laser ids) on a laser-ordered
    scan only from the first to the last of those lasers' points (NaN elsewhere: never read there, see
    :meth:`~robustbench3d.sensors.lidar_beams.BeamPattern.near_rays`), the same values element by element."""
    lo, hi = 0, len(pts)
    if lasers is not None and len(ring) and np.all(ring[1:] >= ring[:-1]):
        if len(lasers) == 0:
            return np.full(len(pts), np.nan)
        lo = int(np.searchsorted(ring, lasers.min(), "left"))
        hi = int(np.searchsorted(ring, lasers.max(), "right"))
    part = np.arctan2(pts[lo:hi, 1].astype(np.float64), pts[lo:hi, 0].astype(np.float64))
    np.degrees(part, out=part)
    if (lo, hi) == (0, len(pts)):
        return part
    az = np.full(len(pts), np.nan)
    az[lo:hi] = part
    return az


def _checked_points(scan: np.ndarray, ring_ids: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(float32 points (N, 4), laser ids (N,): given, else recovered from the scan)."""
    pts = np.asarray(scan)
    if pts.ndim != 2 or pts.shape[1] != 4:
        raise ValueError(f"render_lidar: field 'scan': expected shape (N, 4), got {pts.shape}")
    pts = pts.astype(np.float32, copy=False)
    return pts, ring_ids_of(pts, ring_ids, "render_lidar")


def _scan_pattern(scan: np.ndarray, ring_ids: np.ndarray | None, pattern: BeamPattern | None
                  ) -> tuple[np.ndarray, np.ndarray, BeamPattern, np.ndarray]:
    """(float32 points (N, 4), laser ids (N,), beam pattern, azimuths degrees(atan2(y, x)) (N,) float64) of
    :func:`prepare_scan`."""
    pts, ring = _checked_points(scan, ring_ids)
    az = _azimuths(pts, ring, None)
    if pattern is None:
        pattern = estimate_pattern(pts, ring, azimuth_deg=az)
    return pts, ring, pattern, az


@dataclass(frozen=True)
class TracedHits:
    """Nearest mesh hit per ray, after occlusion by the scan (no range gate, noise or dropout yet).

    Attributes:
        ray: (K,) int64 ray index into ``pattern.rays`` of each ray hitting a mesh (nearest over meshes).
        mesh: (K,) int64 mesh index; face: (K,) int64 face index.
        t, u, v: (K,) torch float64 distance (m) and barycentrics, differentiable w.r.t. that mesh's vertices.
        hidden: (K,) bool, a nearer original return lies on the ray.
        removed_index: (P,) int64 scan points on the hit rays beyond the mesh, increasing.
        tests: ray-triangle tests made.
    """

    ray: np.ndarray
    mesh: np.ndarray
    face: np.ndarray
    t: torch.Tensor
    u: torch.Tensor
    v: torch.Tensor
    hidden: np.ndarray
    removed_index: np.ndarray
    tests: int


def _mesh_tensors(meshes: Sequence[MeshInput]) -> list[tuple[torch.Tensor, np.ndarray]]:
    """Per mesh (vertices (V, 3) float64 tensor, faces (F, 3) int64 copy), each checked (shapes, face indices in
    range, finite vertices, albedo shape; ValueError naming the mesh). A faces object given for several meshes (the
    attack's one object placed on each car) is copied and its index range found once."""
    out = []
    seen: dict[int, tuple[object, np.ndarray, int, int]] = {}  # id(faces) -> (faces, copy, min, max)
    for i, m in enumerate(meshes):
        if len(m) != 3:
            raise ValueError(f"render_lidar: field 'meshes[{i}]': expected (vertices, faces, albedo_rgb or None)")
        v, f, col = m
        vn = None if isinstance(v, torch.Tensor) else np.asarray(v, dtype=np.float64)
        vt = v if vn is None else torch.as_tensor(vn)
        if vt.dtype != torch.float64:
            vt = vt.to(torch.float64)
        known = seen.get(id(f))
        if known is None or known[0] is not f:
            fa = np.array(f, dtype=np.int64)  # a copy: read-only inputs are fine for torch.from_numpy
            known = (f, fa, int(fa.min()) if fa.size else 0, int(fa.max()) if fa.size else -1)
            seen[id(f)] = known
        fa, f_min, f_max = known[1:]
        if vt.dim() != 2 or vt.shape[1] != 3 or fa.ndim != 2 or fa.shape[1] != 3:
            raise ValueError(f"render_lidar: field 'meshes[{i}]': vertices must be (V, 3) and faces (F, 3)")
        if len(fa) and (f_min < 0 or f_max >= len(vt)):
            raise ValueError(f"render_lidar: field 'meshes[{i}]': face indices outside [0, {len(vt)})")
        if not (bool(torch.isfinite(vt.detach()).all()) if vn is None else np.isfinite(vn).all()):  # vt shares vn
            raise ValueError(f"render_lidar: field 'meshes[{i}]': vertices contain NaN or inf")
        shape = None if col is None else tuple(col.shape) if isinstance(col, torch.Tensor) else np.shape(col)
        if shape is not None and shape != (len(vt), 3):
            raise ValueError(f"render_lidar: field 'meshes[{i}]': albedo must be (V, 3) = ({len(vt)}, 3) "
                             f"(one colour per vertex), got {shape}")
        out.append((vt, fa))
    return out


def _culled_rays(pattern: BeamPattern, meshes: list[tuple[torch.Tensor, np.ndarray]]) -> list[np.ndarray]:
    """Per mesh the rays (increasing indices into ``pattern.rays``) passing within its bounding sphere (centre of
    its vertex box), widened by one azimuth step (:meth:`~robustbench3d.sensors.lidar_beams.BeamPattern.cull`);
    empty for a mesh without faces. The boxes and radii of all meshes come from their stacked vertices (per-mesh
    minima and maxima by ``reduceat``, row norms element-wise): the same values as mesh by mesh."""
    out = [np.zeros(0, dtype=np.int64) for _ in meshes]
    culled = [i for i, (_, fa) in enumerate(meshes) if len(fa)]
    if culled:
        verts = [meshes[i][0].detach().numpy() for i in culled]
        counts = np.array([len(vn) for vn in verts])
        start = np.cumsum(counts) - counts
        vn = np.concatenate(verts)
        centres = 0.5 * (np.minimum.reduceat(vn, start, axis=0) + np.maximum.reduceat(vn, start, axis=0))
        radii = np.maximum.reduceat(np.linalg.norm(vn - np.repeat(centres, counts, axis=0), axis=1), start)
        for i, rays in zip(culled, pattern.cull_many(centres, radii), strict=True):
            out[i] = rays
    return out


def _prepared(scan: np.ndarray | PreparedScan, meshes: Sequence[MeshInput], ring_ids: np.ndarray | None,
              patterns: PatternCache | None = None, cull: bool = True
              ) -> tuple[PreparedScan | _RayPoints, list[tuple[torch.Tensor, np.ndarray]], list[np.ndarray]]:
    """(prepared scan, checked meshes, culled rays per mesh); a raw scan's points are matched only to the culled
    rays (:func:`_ray_points`). ``cull=False``: every ray for every mesh, and every point of the scan matched to
    its ray."""
    mts = _mesh_tensors(meshes)
    if isinstance(scan, PreparedScan):
        if cull:
            return scan, mts, _culled_rays(scan.pattern, mts)
        return (_prepare_rays(scan.scan, scan.ring, scan.pattern, None, None), mts,
                _every_ray(scan.pattern, mts))
    az: np.ndarray | None = None
    if patterns is None:
        pts, ring, pattern, az = _scan_pattern(scan, ring_ids, None)
    else:  # a kept pattern needs the azimuths of the culled rays' lasers only (_prepare_rays)
        pts, ring = _checked_points(scan, ring_ids)
        key, kept = patterns.lookup(pts, ring_ids)
        if kept is None:
            az = _azimuths(pts, ring, None)
            kept = estimate_pattern(pts, ring, azimuth_deg=az)
            patterns.store(key, kept)
        pattern = kept
    if not cull:
        return _prepare_rays(pts, ring, pattern, az, None), mts, _every_ray(pattern, mts)
    culls = _culled_rays(pattern, mts)
    return _ray_points(pts, ring, pattern, az, _union(pattern, culls)), mts, culls


def _union(pattern: BeamPattern, culls: list[np.ndarray]) -> np.ndarray:
    """The rays of any of ``culls`` (indices into ``pattern``'s rays), increasing: ``np.unique`` of their
    concatenation, from a mask over the revolution's rays."""
    if not culls:
        return np.zeros(0, dtype=np.int64)
    mask = np.zeros(int(pattern.ring_start[-1]), dtype=bool)
    for cull in culls:
        mask[cull] = True
    return np.flatnonzero(mask)


def _every_ray(pattern: BeamPattern, meshes: list[tuple[torch.Tensor, np.ndarray]]) -> list[np.ndarray]:
    """The full-scene "cull": every ray of the revolution for each mesh."""
    every = np.arange(int(pattern.ring_start[-1]), dtype=np.int64)
    return [every for _ in meshes]


def _all_pairs(n_rays: int, n_faces: int, chunk: int) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
    """Every (ray, face) pair of ``n_rays`` x ``n_faces``, ray-major, in chunks of whole rays (about ``chunk``
    pairs, at least one ray)."""
    rays_per_chunk = max(1, chunk // max(n_faces, 1))
    faces = torch.arange(n_faces, dtype=torch.int64)
    for lo in range(0, n_rays, rays_per_chunk):
        hi = min(n_rays, lo + rays_per_chunk)
        yield torch.arange(lo, hi, dtype=torch.int64).repeat_interleave(n_faces), faces.repeat(hi - lo)


def trace_meshes(prep: PreparedScan, meshes: Sequence[MeshInput]) -> TracedHits:
    """Cast the culled rays of ``prep``'s pattern at each mesh, keep the nearest hit per ray, and apply the
    occlusion by the scan's points (see the module docstring)."""
    mts = _mesh_tensors(meshes)
    return _trace(prep, mts, _culled_rays(prep.pattern, mts))


def _face_spheres(stacked: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(centres (F, 3), radii (F,)) of the faces' bounding spheres (centre of the corners' box), inflated by 1e-3
    of the radius (+1e-9 m), far more than the ray test's barycentric tolerance (1e-6 of an edge); ``stacked``:
    vertices (V, 3) float64 and faces (F, 3) indexing them."""
    a, b, c = (stacked[0][stacked[1][:, j]] for j in range(3))
    centre = 0.5 * (np.minimum(np.minimum(a, b), c) + np.maximum(np.maximum(a, b), c))
    # |x - centre|^2 as ((x - centre) ** 2).sum(1) adds it, without a reduction along a short axis (dot3)
    da, db, dc = a - centre, b - centre, c - centre
    radius = np.sqrt(np.maximum(np.maximum(dot3(da, da), dot3(db, db)), dot3(dc, dc))) * (1 + 1e-3) + 1e-9
    return centre, radius


def _face_pairs(pattern: BeamPattern, mts: list[tuple[torch.Tensor, np.ndarray]], culls: list[np.ndarray],
                idx: np.ndarray, stacked: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Candidate (ray, face) pairs of :func:`_trace`'s cast, formed in numpy (the reference of
    :func:`_sphere_search`, which tests the same pairs as it finds them): (positions in ``idx``, faces of the
    concatenated meshes ``mts``): each face with the rays of its mesh's cull (``culls``) that can pass through the
    face's bounding sphere (:func:`_face_spheres`, :meth:`~robustbench3d.sensors.lidar_beams.BeamPattern.sphere_rays`):
    every pair that can pass the test is among them, so the cast finds the same hits as testing each ray of a
    mesh's cull against all of its faces. ``stacked``: the meshes' vertices (V, 3) float64 and faces (F, 3) indexing
    them, concatenated in order (as :func:`_trace` builds them for the cast)."""
    centre, radius = _face_spheres(stacked)
    mesh = np.repeat(np.arange(len(mts)), [len(fa) for _, fa in mts])
    rings = [pattern.ray_rings(cull) for cull in culls]  # only the lasers of the mesh's cull can be kept
    face, ray = pattern.sphere_rays(centre, radius, np.array([r.min() for r in rings])[mesh],
                                    np.array([r.max() for r in rings])[mesh])
    position = np.full(int(pattern.ring_start[-1]), -1, dtype=np.int64)  # of each ray of the revolution in idx
    position[idx] = np.arange(len(idx))
    member = np.zeros((len(mts), len(idx)), dtype=bool)  # mesh m culled ray idx[k]
    member[np.repeat(np.arange(len(mts)), [len(cull) for cull in culls]), position[np.concatenate(culls)]] = True
    at = position[ray]
    keep = np.flatnonzero(at >= 0)
    keep = keep[member[mesh[face[keep]], at[keep]]]
    return at[keep], face[keep]


def _sphere_search(pattern: BeamPattern, mts: list[tuple[torch.Tensor, np.ndarray]], culls: list[np.ndarray],
                   idx: np.ndarray, stacked: tuple[np.ndarray, np.ndarray]) -> PairSearch:
    """The no-grad search of :func:`_trace`'s cast (:data:`~robustbench3d.sensors.raycast.PairSearch`): the pairs of
    :func:`_face_pairs` tested as the compiled kernel finds them
    (:func:`~robustbench3d.sensors.lidar_kernels.sphere_pairs_nearest`: each face's sphere against its mesh's culled
    rays, laser by laser, as runs of consecutive rays): the same nearest faces, t and pair count as
    :func:`~robustbench3d.sensors.pair_search.search_pairs` of those pairs, without forming them. Arguments as
    :func:`_face_pairs`."""
    centre, radius = _face_spheres(stacked)
    mesh = np.repeat(np.arange(len(mts)), [len(fa) for _, fa in mts])
    runs = pattern.cull_runs(culls, idx)

    def search(table: np.ndarray | None, d_cols: np.ndarray, h: np.ndarray | None, t_min: float, tol: float
               ) -> tuple[np.ndarray, np.ndarray, int]:
        if table is None or h is None:
            raise ValueError("render_lidar: the cast needs faces and per-ray laser heights")
        return pattern.sphere_nearest(centre, radius, mesh, runs, table, d_cols, h, t_min, tol)

    return search


def _trace(prep: PreparedScan | _RayPoints, mts: list[tuple[torch.Tensor, np.ndarray]], culls: list[np.ndarray],
           cull: bool = True) -> TracedHits:
    """:func:`trace_meshes` with the meshes checked and culled: all meshes in one cast (faces concatenated, so
    the nearest face over them is the nearest hit over the meshes; equal t: the lower mesh) of the union of
    their culled rays, each face tested only with the rays of its mesh's cull that can reach it
    (:func:`_sphere_search`, ``cast_ray_search``): the hits of casting each mesh's culled rays at its faces.
    ``cull=False``: every ray of ``idx`` (the union of ``culls``) with every face (:func:`_all_pairs`)."""
    with_faces = [i for i, (_, fa) in enumerate(mts) if len(fa) and len(culls[i])]
    idx = _union(prep.pattern, [culls[i] for i in with_faces])
    if len(idx) == 0:
        z = torch.zeros(0, dtype=torch.float64)
        e = np.zeros(0, dtype=np.int64)
        return TracedHits(e, e, e, z, z, z, np.zeros(0, dtype=bool), e, 0)
    v_off = np.cumsum([0] + [len(mts[i][0]) for i in with_faces])
    f_off = np.cumsum([0] + [len(mts[i][1]) for i in with_faces])
    vt = mts[with_faces[0]][0] if len(with_faces) == 1 else torch.cat([mts[i][0] for i in with_faces])
    fa = np.concatenate([mts[i][1] + v_off[k] for k, i in enumerate(with_faces)])
    origins, dirs = prep.pattern.ray_geometry(idx)
    if cull:
        search = _sphere_search(prep.pattern, [mts[i] for i in with_faces], [culls[i] for i in with_faces], idx,
                                (vt.detach().numpy(), fa))
        rh = cast_ray_search(vt, torch.from_numpy(fa), torch.from_numpy(dirs), torch.zeros(3, dtype=torch.float64),
                             search, torch.from_numpy(origins[:, 2]), name="render_lidar", checked=True)
    else:
        rh = cast_ray_pair_chunks(vt, torch.from_numpy(fa), torch.from_numpy(dirs),
                                  torch.zeros(3, dtype=torch.float64),
                                  _all_pairs(len(idx), len(fa), FULL_SCENE_CHUNK_PAIRS),
                                  torch.from_numpy(origins[:, 2]), name="render_lidar")
    sel = torch.nonzero(rh.hit).reshape(-1)
    gface = rh.face[sel].numpy()
    part = np.searchsorted(f_off, gface, "right") - 1
    ray, mesh, face = idx[sel.numpy()], np.asarray(with_faces, dtype=np.int64)[part], gface - f_off[part]
    t, u, v = rh.t[sel], rh.u[sel], rh.v[sel]
    owner, pidx, rp = prep.ranges_on(ray)
    tn = t.detach().numpy()
    hidden = np.zeros(len(ray), dtype=bool)
    hidden[owner[rp < tn[owner]]] = True
    removed = np.unique(pidx[(rp > tn[owner]) & ~hidden[owner]])
    return TracedHits(ray, mesh, face, t, u, v, hidden, removed, rh.tests)


@dataclass(frozen=True)
class LidarRenderResult:
    """Attacked scan.

    Attributes:
        scan: (M, 4) float32, the original points minus ``removed_index``, in order, then ``added``.
        added: (K, 4) float32 x, y, z, reflectance of the mesh returns.
        added_torch: (K, 3) torch float64 the same points, differentiable w.r.t. the mesh vertices.
        removed_index: (P,) int64 indices into the input scan of the points removed (behind a mesh).
        object_index: (K,) int64 mesh of each added point.
        face_index: (K,) int64 face of each added point.
        ray_index: (K,) int64 ray (into ``pattern.rays``) of each added point.
        pattern: the beam pattern used.
        tests: ray-triangle tests made.
    """

    scan: np.ndarray
    added: np.ndarray
    added_torch: torch.Tensor
    removed_index: np.ndarray
    object_index: np.ndarray
    face_index: np.ndarray
    ray_index: np.ndarray
    pattern: BeamPattern
    tests: int


def _albedo(meshes: Sequence[MeshInput], mesh: np.ndarray, u: np.ndarray, v: np.ndarray, corners: np.ndarray,
            n_vertices: Sequence[int]) -> np.ndarray:
    """(K, 3) float32 vertex colours interpolated at the hits ((1 - u - v) c0 + u c1 + v c2), clipped to [0, 1]
    (:data:`DEFAULT_ALBEDO` on meshes without colours): ``corners`` (K, 3) are the hit faces' vertex indices into
    the meshes' stacked vertices, ``n_vertices`` the meshes' vertex counts (colour tables checked to match by
    :func:`_mesh_tensors`); all hits in one product over the stacked colours."""
    out = np.full((len(mesh), 3), DEFAULT_ALBEDO, dtype=np.float64)
    cols = [None if col is None else np.asarray(col.detach() if isinstance(col, torch.Tensor) else col,
                                                dtype=np.float64) for _, _, col in meshes]
    if any(c is not None for c in cols):
        table = np.concatenate([np.zeros((nv, 3)) if c is None else c for c, nv in zip(cols, n_vertices,
                                                                                         strict=True)])
        k = np.flatnonzero(np.array([c is not None for c in cols], dtype=bool)[mesh])
        w = np.stack([1 - u[k] - v[k], u[k], v[k]], axis=1)
        out[k] = np.einsum("kj,kjc->kc", w, table[corners[k]])
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def render_lidar(scan: np.ndarray | PreparedScan, meshes: Sequence[MeshInput], *,
                 rng: np.random.Generator | None = None, range_noise_m: float = 0.0, dropout: float = 0.0,
                 ring_ids: np.ndarray | None = None, patterns: PatternCache | None = None,
                 cull: bool = True) -> LidarRenderResult:
    """Render ``meshes`` into ``scan`` (see the module docstring).

    Args:
        scan: (N, 4) velodyne x, y, z, reflectance, or a :class:`PreparedScan` (faster when reused).
        meshes: (vertices (V, 3) velodyne m, numpy or torch float64 (may require grad), faces (F, 3),
            albedo (V, 3) linear RGB in [0, 1] or None for grey).
        rng: source of the dropout and range-noise draws (required when either is on).
        range_noise_m: standard deviation of the Gaussian range noise, clipped at 3 sd, m.
        dropout: probability that a mesh return is dropped.
        ring_ids: (N,) laser of each point when known (else recovered from the scan).
        patterns: where the estimated beam pattern of a raw ``scan`` is looked up and kept
            (:class:`~robustbench3d.sensors.pattern_cache.PatternCache`; the same result, faster on a scan seen
            before).
        cull: cast only the rays that can reach a mesh, each at the faces it can reach (default); False: the
            full-scene reference, every ray at every face (module docstring; the same result, far slower).
    """
    if not 0.0 <= dropout < 1.0:
        raise ValueError(f"render_lidar: field 'dropout': must be in [0, 1), got {dropout!r}")
    if not (np.isfinite(range_noise_m) and range_noise_m >= 0.0):
        raise ValueError(f"render_lidar: field 'range_noise_m': must be >= 0, got {range_noise_m!r}")
    if (dropout > 0 or range_noise_m > 0) and rng is None:
        raise ValueError("render_lidar: field 'rng': required when dropout or range_noise_m is on")
    prep, mts, culls = _prepared(scan, meshes, ring_ids, patterns, bool(cull))
    tr = _trace(prep, mts, culls, bool(cull))
    keep = ~tr.hidden & lm.in_range(tr.t.detach().numpy())
    if dropout > 0 and keep.any():
        keep[keep] = rng.random(int(keep.sum())) >= dropout
    sel = np.flatnonzero(keep)
    ray, mesh, face = tr.ray[sel], tr.mesh[sel], tr.face[sel]
    selt = torch.from_numpy(sel)
    t = tr.t[selt]
    if range_noise_m > 0 and len(sel):
        sd = range_noise_m
        t = t + torch.from_numpy(np.clip(rng.normal(0.0, sd, len(sel)), -3 * sd, 3 * sd))
    ray_o, ray_d = prep.pattern.ray_geometry(ray)
    o, d = torch.from_numpy(ray_o), torch.from_numpy(ray_d)
    pts_t = o + t[:, None] * d
    added = np.empty((len(sel), 4), dtype=np.float32)
    added[:, :3] = pts_t.detach().numpy()
    if len(sel):
        u, v = tr.u[selt].detach().numpy(), tr.v[selt].detach().numpy()
        verts = [m[0].detach().numpy() if isinstance(m[0], torch.Tensor) else np.asarray(m[0], dtype=np.float64)
                 for m in meshes]
        v_off = np.cumsum([0] + [len(vi) for vi in verts])
        f_off = np.cumsum([0] + [len(fa) for _, fa in mts])
        corners = np.concatenate([fa + v_off[i] for i, (_, fa) in enumerate(mts)])[f_off[mesh] + face]
        normals = face_normals(np.concatenate(verts), corners)  # all hit faces at once (element-wise)
        albedo = _albedo(meshes, mesh, u, v, corners, [len(vi) for vi in verts])
        rho = lm.material_reflectivity(np.full(len(sel), int(MESH_MATERIAL)), albedo)
        refl = lm.reflectance_mean(rho, lm.cos_incidence(normals, ray_d), t.detach().numpy())
        added[:, 3] = lm.quantize_reflectance(refl, np.zeros(len(sel), dtype=bool))
    return LidarRenderResult(_without_rows(prep.scan, tr.removed_index, added), added, pts_t, tr.removed_index, mesh,
                             face, ray, prep.pattern, tr.tests)


def _without_rows(scan: np.ndarray, removed: np.ndarray, added: np.ndarray) -> np.ndarray:
    """(M, 4): the rows of ``scan`` (N, 4) but ``removed`` (increasing, distinct), in order, then ``added``:
    ``np.concatenate([scan[kept], added])``, bit for bit, float32 rows copied as their bytes, run by run between
    the removed rows (:func:`~robustbench3d.sensors.lidar_table_kernels.rows_but`)."""
    if scan.dtype != np.float32:
        kept = np.ones(len(scan), dtype=bool)
        kept[removed] = False
        return np.concatenate([scan[kept], added])
    out = rows_but(scan, removed, len(added))
    out[len(out) - len(added):] = added
    return out


def render_lidar_torch(scan: np.ndarray | PreparedScan, meshes: Sequence[MeshInput],
                       ring_ids: np.ndarray | None = None) -> tuple[torch.Tensor, np.ndarray]:
    """The mesh returns of :func:`render_lidar` without noise or dropout, as a differentiable tensor (the
    scan is not assembled and no reflectance computed: the optimisation's fast path).

    Returns:
        (K, 3) torch float64 points (velodyne, m) with gradients w.r.t. the mesh vertices, and (K,) int64
        mesh index of each.
    """
    prep, mts, culls = _prepared(scan, meshes, ring_ids)
    tr = _trace(prep, mts, culls)
    sel = np.flatnonzero(~tr.hidden & lm.in_range(tr.t.detach().numpy()))
    ray = tr.ray[sel]
    ray_o, ray_d = prep.pattern.ray_geometry(ray)
    pts = torch.from_numpy(ray_o) + tr.t[torch.from_numpy(sel)][:, None] * torch.from_numpy(ray_d)
    return pts, tr.mesh[sel]
