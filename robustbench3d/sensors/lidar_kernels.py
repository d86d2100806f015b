"""Compiled (numba) searches of the LiDAR render over a beam pattern's rays (conventions:
:mod:`robustbench3d.sensors.array_kernels`): which rays can reach a sphere, and the nearest ray of a point.

The pattern (:class:`robustbench3d.sensors.lidar_beams.BeamPattern`) keeps its rays sorted by the key
laser x band + azimuth; these kernels search those keys laser by laser (:func:`_key_search`).

* :func:`cone_cull` is ``BeamPattern.cull_many``, :func:`sphere_ray_ranges` the per-(sphere, laser) part of
  ``BeamPattern.sphere_rays`` and :func:`nearest_rays` ``BeamPattern.nearest_ray`` (``compiled=False`` runs their
  numpy code, the references).
* :func:`sphere_pairs_nearest` is the render's cast: the pairs of ``sphere_ray_ranges`` within each mesh's cull
  (:func:`robustbench3d.sensors.lidar_table_kernels.cull_runs`), tested by
  :func:`robustbench3d.sensors.ray_kernels.nearest_of_pairs`' arithmetic (spelled out here, :func:`_test_face_rays`)
  as they are found (the pairs formed in numpy, ``lidar_render._face_pairs``, are its reference).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _key_search(az: np.ndarray, lo: int, hi: int, k: int, band: float, v: float,
                right: bool) -> int:  # pragma: no cover - compiled
    """``lo + np.searchsorted(keys[lo:hi], v, side)`` (side "right" if ``right`` else "left") of the keys
    ``k * band + az[i]`` of laser k's rays lo..hi - 1, each formed as the key table's, in numpy's order (NaN
    last)."""
    while lo < hi:
        mid = (lo + hi) >> 1
        key = k * band + az[mid]
        # right: v sorts before the key; left: the key does not sort before v (the answer is then at or below mid)
        before = (v < key or (key != key and v == v)) if right else not (key < v or (v != v and key == key))
        if before:
            hi = mid
        else:
            lo = mid + 1
    return lo


@njit(cache=True, nogil=True, inline="always")
def _reach_lasers(c: np.ndarray, r: np.ndarray, i: int, rho: float, first: int, last: int, neg_phi: np.ndarray,
                  top_down: bool, h_lo: float, h_hi: float) -> tuple:  # pragma: no cover - compiled
    """The lasers first..last of sphere i (centre ``c[i]``, radius ``r[i]``, ``rho`` = |c_xy|), narrowed, with
    the lasers ordered top down, to those within the sphere's reach from any apex height in [h_lo, h_hi]."""
    lo_l, hi_l = first, last
    if top_down:
        d_min = np.hypot(rho, c[i, 2] - np.minimum(np.maximum(c[i, 2], h_lo), h_hi))
        if r[i] >= d_min:
            top, bottom = np.inf, -np.inf
        else:
            reach = np.arcsin(np.minimum(r[i] / d_min, 1.0)) + 1e-9
            top = np.arctan2(c[i, 2] - h_lo, rho) + reach
            bottom = np.arctan2(c[i, 2] - h_hi, rho) - reach
        lo_l = max(first, np.searchsorted(neg_phi, -top, side="left"))
        hi_l = min(last, np.searchsorted(neg_phi, -bottom, side="right") - 1)
    return lo_l, hi_l


@njit(cache=True, nogil=True, inline="always")
def _laser_interval(rs: float, rho_s: float, dz: float, sin_phi: float, cos_phi: float, theta: float
                    ) -> tuple:  # pragma: no cover - compiled
    """(reached, lo, hi, wrap) of one laser (elevation sin / cos ``sin_phi``, ``cos_phi``, apex ``dz`` below the centre)
    and a sphere (radius ``rs``, centre at ``rho_s`` from the axis, azimuth ``theta``): whether its cone reaches the
    sphere, the azimuth interval of the rays that can pass through it (degrees, -1..500 for all) and whether rays a turn
    away may reach it too (:meth:`~robustbench3d.sensors.lidar_beams.BeamPattern.sphere_rays`' test)."""
    dist2 = rho_s * rho_s + dz * dz
    kappa = (np.sqrt(np.maximum(dist2 - rs * rs, 0.0)) - sin_phi * dz) / (cos_phi * rho_s)
    kappa = kappa - 1e-9
    full = (rs >= rho_s) or (dist2 <= rs * rs) or (kappa <= -1.0)
    if not (full or kappa <= 1.0):
        return False, 0.0, 0.0, False
    if full:
        return True, -1.0, 500.0, False
    half = np.degrees(np.arccos(np.minimum(np.maximum(kappa, -1.0), 1.0))) + 1e-7
    a, b = theta - half, theta + half
    return True, a, b, a < 1.0 or b > 359.0


@njit(cache=True, nogil=True, error_model="numpy")
def _sphere_ray_ranges(c: np.ndarray, r: np.ndarray, first: np.ndarray, last: np.ndarray, phi: np.ndarray,
                       sin_phi: np.ndarray, cos_phi: np.ndarray, origin_z: np.ndarray, top_down: bool, h_lo: float,
                       h_hi: float, keys: np.ndarray, band: float) -> tuple:  # pragma: no cover - compiled
    m = len(r)
    neg_phi = -phi
    rho = np.empty(m)
    lo_l, hi_l = first.copy(), last.copy()
    for i in range(m):
        rho[i] = np.hypot(c[i, 0], c[i, 1])
        lo_l[i], hi_l[i] = _reach_lasers(c, r, i, rho[i], first[i], last[i], neg_phi, top_down, h_lo, h_hi)
    count = 0
    for i in range(m):
        count += max(hi_l[i] - lo_l[i] + 1, 0)
    sph, las = np.empty(3 * count, np.int64), np.empty(3 * count, np.int64)
    lo, hi = np.empty(3 * count), np.empty(3 * count)
    wrap = np.empty(count, np.int64)
    n, n_wrap = 0, 0
    for i in range(m):
        theta = np.degrees(np.arctan2(c[i, 1], c[i, 0])) % 360.0
        for k in range(lo_l[i], hi_l[i] + 1):
            reached, a, b, wraps = _laser_interval(r[i], rho[i], c[i, 2] - origin_z[k], sin_phi[k], cos_phi[k], theta)
            if not reached:
                continue
            if wraps:
                wrap[n_wrap] = n
                n_wrap += 1
            sph[n], las[n], lo[n], hi[n] = i, k, a, b
            n += 1
    for turn in (360.0, -360.0):  # a sphere near azimuth 0 may also reach rays a turn away
        for w in range(n_wrap):
            j = wrap[w]
            sph[n], las[n], lo[n], hi[n] = sph[j], las[j], lo[j] + turn, hi[j] + turn
            n += 1
    total = 0
    start, stop = np.empty(n, np.int64), np.empty(n, np.int64)
    for j in range(n):
        a, b = np.minimum(np.maximum(lo[j], -1.0), 500.0), np.minimum(np.maximum(hi[j], -1.0), 500.0)
        start[j] = np.searchsorted(keys, las[j] * band + a, side="left")
        stop[j] = np.searchsorted(keys, las[j] * band + b, side="right")
        total += max(stop[j] - start[j], 0)
    out_s, out_r = np.empty(total, np.int64), np.empty(total, np.int64)
    q = 0
    for j in range(n):
        for ray in range(start[j], stop[j]):
            out_s[q], out_r[q] = sph[j], ray
            q += 1
    return out_s, out_r


def sphere_ray_ranges(centers: np.ndarray, radii: np.ndarray, first: np.ndarray, last: np.ndarray,
                      phi: np.ndarray, origin_z: np.ndarray, keys: np.ndarray, band: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(sphere (K,), ray (K,)) of :meth:`robustbench3d.sensors.lidar_beams.BeamPattern.sphere_rays` (its
    docstring) for float64 ``centers`` (M, 3), ``radii`` (M,), int64 laser bounds (M,), the lasers' elevations
    ``phi`` (L,) (rad) and apex heights ``origin_z`` (L,) (m), the pattern's sorted ray ``keys`` and ``band``."""
    if len(first) != len(radii) or len(last) != len(radii) or len(centers) != len(radii):
        raise ValueError(f"sphere_ray_ranges: {len(centers)} centres, {len(radii)} radii, {len(first)} / {len(last)} "
                         "laser bounds")
    # the lasers that exist (the numpy code's reach test clips them so for lasers ordered top down)
    first, last = np.maximum(first, 0), np.minimum(last, len(phi) - 1)
    top_down = bool(np.all(np.diff(phi) < 0))
    h_lo, h_hi = float(origin_z.min()), float(origin_z.max())
    return _sphere_ray_ranges(np.ascontiguousarray(centers, np.float64), np.ascontiguousarray(radii, np.float64),
                              np.ascontiguousarray(first, np.int64), np.ascontiguousarray(last, np.int64),
                              np.ascontiguousarray(phi), np.sin(phi), np.cos(phi),
                              np.ascontiguousarray(origin_z, np.float64), top_down, h_lo, h_hi,
                              np.ascontiguousarray(keys), float(band))


@njit(cache=True, nogil=True)
def _nearest_rays(ring: np.ndarray, az: np.ndarray, ring_start: np.ndarray, raz: np.ndarray, lowest: float,
                  highest: float, max_deg: float, band: float) -> np.ndarray:  # pragma: no cover - compiled
    n_lasers = len(ring_start) - 1
    out = np.full(len(ring), -1, np.int64)
    reach_down = lowest + 360.0 - max_deg - 1e-6
    reach_up = highest - 360.0 + max_deg + 1e-6
    for i in range(len(ring)):
        r = ring[i]
        if r < 0 or r >= n_lasers:
            continue
        a = az[i]
        first, last = ring_start[r], ring_start[r + 1] - 1
        best, gap = -1, np.inf
        for turn in (-360.0, 0.0, 360.0):
            if (turn < 0.0 and not a >= reach_down) or (turn > 0.0 and not a <= reach_up):
                continue
            pos = _key_search(raz, ring_start[r], ring_start[r + 1], r, band, r * band + a + turn, False)
            for cand in (pos - 1, pos):
                if cand >= first and cand <= last:
                    g = np.abs(raz[cand] - (a + turn))
                    if g < gap:
                        best, gap = cand, g
        if gap <= max_deg:
            out[i] = best
    return out


def nearest_rays(ring: np.ndarray, az: np.ndarray, ring_start: np.ndarray, raz: np.ndarray,
                 az_range: tuple[float, float], max_deg: float, band: float) -> np.ndarray:
    """:meth:`robustbench3d.sensors.lidar_beams.BeamPattern.nearest_ray`'s numpy code point by point: per point
    (laser ``ring`` (N,), azimuth ``az`` (N,) already taken modulo 360) the ray of its laser nearest in azimuth
    among the pattern's (azimuths ``raz`` (R,), laser k's from ``ring_start[k]`` (L + 1,), lowest and highest
    ``az_range``) within ``max_deg``, or -1. The pattern's sorted keys k x ``band`` + raz are searched laser by
    laser, which ends where the search over all keys does when the caller keeps the rays' azimuths in [-1, 361)
    and ``band`` >= 1000 (a point's key, k x band + [-360, 720), then sorts between the lower and the higher
    lasers' rays)."""
    ring, az = np.ascontiguousarray(ring, np.int64), np.ascontiguousarray(az, np.float64)
    if len(ring) != len(az) or len(ring_start) < 1 or ring_start[-1] != len(raz) or np.any(np.diff(ring_start) < 0):
        raise ValueError(f"nearest_rays: {len(ring)} lasers for {len(az)} azimuths, or laser starts {ring_start} "
                         f"for {len(raz)} rays")
    return _nearest_rays(ring, az, np.ascontiguousarray(ring_start, np.int64), np.ascontiguousarray(raz, np.float64),
                         float(az_range[0]), float(az_range[1]), float(max_deg), float(band))


@njit(cache=True, nogil=True, error_model="numpy")
def _cone_cull(c: np.ndarray, radii: np.ndarray, sin_phi: np.ndarray, cos_phi: np.ndarray, origin_z: np.ndarray,
               margin_deg: float, az: np.ndarray, ring_start: np.ndarray, band: float
               ) -> tuple:  # pragma: no cover - compiled
    m, n_lasers = len(radii), len(sin_phi)
    counts = np.zeros(m, np.int64)
    chunks = []
    for i in range(m):
        r = radii[i] * (1 + 1e-9) + 1e-9
        r2 = r * r
        rho = np.hypot(c[i, 0], c[i, 1])
        theta = np.degrees(np.arctan2(c[i, 1], c[i, 0])) % 360.0
        starts = np.empty(3 * n_lasers, np.int64)
        stops = np.empty(3 * n_lasers, np.int64)
        n = 0
        for k in range(n_lasers):
            cz = c[i, 2] - origin_z[k]
            dist2 = rho * rho + cz * cz
            if dist2 <= r2:
                kappa = -np.inf
            else:
                kappa = (np.sqrt(np.maximum(dist2 - r2, 0.0)) - sin_phi[k] * cz) / (cos_phi[k] * rho)
                if np.isnan(kappa):
                    kappa = np.inf
            kappa = kappa - 1e-9
            if not kappa <= 1.0:
                continue
            half = np.degrees(np.arccos(np.minimum(np.maximum(kappa, -1.0), 1.0))) + margin_deg
            for turn in (-360.0, 0.0, 360.0):  # a full laser gets its whole range three times (merged below)
                if half >= 180.0:
                    lo, hi = -1.0, 500.0
                else:
                    lo = np.minimum(np.maximum(theta - half + turn, -1.0), 500.0)
                    hi = np.minimum(np.maximum(theta + half + turn, -1.0), 500.0)
                a = _key_search(az, ring_start[k], ring_start[k + 1], k, band, k * band + lo, False)
                b = _key_search(az, ring_start[k], ring_start[k + 1], k, band, k * band + hi, True)
                if b > a:
                    starts[n], stops[n] = a, b
                    n += 1
        order = np.argsort(starts[:n])
        rays = np.empty(0, np.int64)
        if n:
            total = 0
            for j in range(n):
                total += stops[j] - starts[j]
            rays = np.empty(total, np.int64)
            q, reach = 0, -1  # rays below reach are out already
            for j in order:
                for ray in range(max(starts[j], reach), stops[j]):
                    rays[q] = ray
                    q += 1
                reach = max(reach, stops[j])
            rays = rays[:q]
        counts[i] = len(rays)
        chunks.append(rays)
    out = np.empty(counts.sum(), np.int64)
    q = 0
    for i in range(m):
        out[q:q + counts[i]] = chunks[i]
        q += counts[i]
    return out, counts


def cone_cull(centers: np.ndarray, radii: np.ndarray, phi: np.ndarray, origin_z: np.ndarray, margin_deg: float,
              az: np.ndarray, ring_start: np.ndarray, band: float) -> list[np.ndarray]:
    """Per sphere (float64 ``centers`` (M, 3), ``radii`` (M,)) the sorted rays of
    :meth:`robustbench3d.sensors.lidar_beams.BeamPattern.cull_many` (its docstring): lasers' elevations ``phi``
    (L,) (rad), apex heights ``origin_z`` (L,) (m), the pattern's ray azimuths ``az`` (R,), laser k's from
    ``ring_start[k]`` (L + 1,), whose sorted keys k x ``band`` + az are searched laser by laser. The caller makes
    sure that the azimuths lie in [-1, 361) degrees and ``band`` >= 1000: then a key of laser k's band,
    k x band + [-1, 500], sorts after every lower laser's ray and before every higher laser's, so that the search
    over all keys ends within the laser's rays."""
    if len(ring_start) != len(phi) + 1 or ring_start[-1] != len(az) or np.any(np.diff(ring_start) < 0):
        raise ValueError(f"cone_cull: {len(az)} rays, laser starts {ring_start} for {len(phi)} lasers")
    rays, counts = _cone_cull(np.ascontiguousarray(centers, np.float64), np.ascontiguousarray(radii, np.float64),
                              np.sin(phi), np.cos(phi), np.ascontiguousarray(origin_z, np.float64), float(margin_deg),
                              np.ascontiguousarray(az, np.float64), np.ascontiguousarray(ring_start, np.int64),
                              float(band))
    return np.split(rays, np.cumsum(counts)[:-1])


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _test_face_rays(p_lo: int, p_hi: int, f: int, g0: float, g1: float, g2: float, g3: float, g4: float, g5: float,
                    g6: float, g7: float, g8: float, g9: float, g10: float, g11: float, g12: float, g13: float,
                    g14: float, g15: float, g16: float, g17: float, d_cols: np.ndarray, h: np.ndarray, t_min: float,
                    tol: float, best_face: np.ndarray, best_t: np.ndarray) -> None:  # pragma: no cover - compiled
    """Face f (its column g0..g17 of the offset test table) against the consecutive rays p_lo..p_hi - 1: the arithmetic
    of :func:`robustbench3d.sensors.ray_kernels.nearest_of_pairs` (offsets on; ``np.sign`` spelled out as numba
    evaluates it) and the choice of its ``_keep_if_nearer``, with the verdict's tests all evaluated and the nearest kept
    by selects, so that the loop has no branch (vectorised); t = t*det / det is used only where the verdict holds (det >
    0)."""
    for p in range(p_lo, p_hi):
        d0, d1, d2 = d_cols[0, p], d_cols[1, p], d_cols[2, p]
        det = g0 * d0 + g1 * d1 + g2 * d2
        un = g3 * d0 + g4 * d1 + g5 * d2
        vn = g6 * d0 + g7 * d1 + g8 * d2
        tn = g9
        hr = h[p]
        un = un + hr * (g11 * d0 + g12 * d1 + g13 * d2)
        vn = vn + hr * (g14 * d0 + g15 * d1 + g16 * d2)
        tn = tn + hr * g17
        sign = 1.0 if tn > 0.0 else (-1.0 if tn < 0.0 else tn)
        det, un, vn, tn = det * sign, un * sign, vn * sign, np.abs(tn)
        slack = tol * det
        ok = (det > g10) & (un >= -slack) & (vn >= -slack) & (un + vn <= det + slack) & (tn > t_min * det)
        t = tn / det
        bt, bf = best_t[p], best_face[p]
        better = ok & ((t < bt) | ((t == bt) & (f < bf)))
        best_t[p] = t if better else bt
        best_face[p] = f if better else bf


@njit(cache=True, nogil=True, error_model="numpy")
def _sphere_pairs_nearest(c: np.ndarray, r: np.ndarray, face_mesh: np.ndarray, mesh_first: np.ndarray,
                          mesh_last: np.ndarray, ptr: np.ndarray, run_start: np.ndarray, run_stop: np.ndarray,
                          run_pos: np.ndarray, phi: np.ndarray, sin_phi: np.ndarray, cos_phi: np.ndarray,
                          origin_z: np.ndarray, top_down: bool, h_lo: float, h_hi: float, az: np.ndarray,
                          band: float, table: np.ndarray, d_cols: np.ndarray, h: np.ndarray, t_min: float,
                          tol: float, best_face: np.ndarray, best_t: np.ndarray) -> int:  # pragma: no cover - compiled
    n_lasers = len(phi)
    neg_phi = -phi
    tests = 0
    for i in range(len(r)):
        m = face_mesh[i]
        rho = np.hypot(c[i, 0], c[i, 1])
        lo_l, hi_l = _reach_lasers(c, r, i, rho, mesh_first[m], mesh_last[m], neg_phi, top_down, h_lo, h_hi)
        theta = np.degrees(np.arctan2(c[i, 1], c[i, 0])) % 360.0
        # face i's column of the test table (the arithmetic of ray_kernels.nearest_of_pairs, offsets on)
        g0, g1, g2, g3, g4, g5 = table[0, i], table[1, i], table[2, i], table[3, i], table[4, i], table[5, i]
        g6, g7, g8, g9, g10 = table[6, i], table[7, i], table[8, i], table[9, i], table[10, i]
        g11, g12, g13, g14 = table[11, i], table[12, i], table[13, i], table[14, i]
        g15, g16, g17 = table[15, i], table[16, i], table[17, i]
        for k in range(lo_l, hi_l + 1):
            q0, q1 = ptr[m * n_lasers + k], ptr[m * n_lasers + k + 1]
            if q0 == q1:  # the mesh culled no ray of this laser
                continue
            reached, a, b, wraps = _laser_interval(r[i], rho, c[i, 2] - origin_z[k], sin_phi[k], cos_phi[k], theta)
            if not reached:
                continue
            for turn in range(3 if wraps else 1):  # a sphere near azimuth 0 may also reach rays a turn away
                lo, hi = a, b
                if turn == 1:
                    lo, hi = a + 360.0, b + 360.0
                elif turn == 2:
                    lo, hi = a - 360.0, b - 360.0
                lo, hi = np.minimum(np.maximum(lo, -1.0), 500.0), np.minimum(np.maximum(hi, -1.0), 500.0)
                key_lo, key_hi = k * band + lo, k * band + hi
                for q in range(q0, q1):
                    rs, re = run_start[q], run_stop[q]
                    # the range's rays among the run's: the whole pattern's key search clipped to [rs, re]
                    s = _key_search(az, rs, re, k, band, key_lo, False)
                    e = _key_search(az, rs, re, k, band, key_hi, True)
                    if e > s:
                        tests += e - s
                        _test_face_rays(run_pos[q] + s - rs, run_pos[q] + e - rs, i, g0, g1, g2, g3, g4, g5, g6, g7,
                                        g8, g9, g10, g11, g12, g13, g14, g15, g16, g17, d_cols, h, t_min, tol,
                                        best_face, best_t)
    return tests


def sphere_pairs_nearest(centers: np.ndarray, radii: np.ndarray, face_mesh: np.ndarray,
                         runs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], phi: np.ndarray,
                         origin_z: np.ndarray, az: np.ndarray, band: float, table: np.ndarray, d_cols: np.ndarray,
                         h: np.ndarray, t_min: float, tol: float) -> tuple[np.ndarray, np.ndarray, int]:
    """The nearest face of each culled ray among the faces whose bounding sphere it can pass through: (face (R,) int64
    or -1, t (R,) or +inf, pairs tested), the search of :func:`robustbench3d.sensors.pair_search.search_pairs`
    (:func:`~robustbench3d.sensors.ray_kernels.nearest_of_pairs`, offsets on) over the pairs of
    :func:`sphere_ray_ranges` (each face's sphere, ``centers`` (F, 3), ``radii`` (F,), on the lasers of its mesh's cull)
    whose ray is in the face's mesh's cull, without forming the pairs: the same verdicts, nearest faces, t and count.

    Args:
        face_mesh: (F,) mesh of each face, indexing the meshes of ``runs``
            (:func:`~robustbench3d.sensors.lidar_table_kernels.cull_runs` of their culls, whose ``idx`` numbers the R
            rays).
        phi, origin_z, az, band: the lasers' elevations (rad) and apex heights, the pattern's ray azimuths
            (degrees; laser k's ray i has the key k x ``band`` + az[i] of the pattern's sorted keys).
        table: (18, F) per-face test table with offsets (:func:`robustbench3d.sensors.ray_faces._face_tables`),
            float64; ``d_cols`` (3, R) the rays' directions by component, ``h`` (R,) their apex heights.
    """
    ptr, run_start, run_stop, run_pos = runs
    n_lasers, n_rays = len(phi), d_cols.shape[1]
    n_meshes = (len(ptr) - 1) // max(n_lasers, 1)
    face_mesh = np.ascontiguousarray(face_mesh, np.int64)
    if table.dtype != np.float64 or d_cols.dtype != np.float64 or h.dtype != np.float64:
        raise ValueError(f"sphere_pairs_nearest: table {table.dtype}, directions {d_cols.dtype} and heights "
                         f"{h.dtype} must be float64")
    if (len(face_mesh) != len(radii) or table.shape != (18, len(radii)) or len(h) != n_rays
            or (len(face_mesh) and (face_mesh.min() < 0 or face_mesh.max() >= n_meshes))
            or (len(run_start) and (run_start.min() < 0 or run_stop.max() > len(az) or run_pos.min() < 0
                                    or (run_pos + run_stop - run_start).max() > n_rays))):
        raise ValueError(f"sphere_pairs_nearest: {len(radii)} spheres, {len(face_mesh)} meshes of faces, table "
                         f"{table.shape}, {n_rays} rays and {len(h)} heights, or runs outside {n_meshes} meshes, "
                         f"{len(az)} pattern rays or {n_rays} rays")
    has = np.diff(ptr).reshape(n_meshes, n_lasers) > 0
    lasers = np.arange(n_lasers)
    mesh_first = np.where(has, lasers, n_lasers).min(axis=1) if n_meshes else np.zeros(0, np.int64)
    mesh_last = np.where(has, lasers, -1).max(axis=1) if n_meshes else np.zeros(0, np.int64)
    best_face = np.full(n_rays, -1, np.int64)
    best_t = np.full(n_rays, np.inf)
    top_down = bool(np.all(np.diff(phi) < 0))
    h_lo, h_hi = float(origin_z.min()), float(origin_z.max())
    tests = _sphere_pairs_nearest(
        np.ascontiguousarray(centers, np.float64), np.ascontiguousarray(radii, np.float64), face_mesh,
        mesh_first.astype(np.int64), mesh_last.astype(np.int64), ptr, run_start, run_stop, run_pos,
        np.ascontiguousarray(phi), np.sin(phi), np.cos(phi), np.ascontiguousarray(origin_z, np.float64), top_down,
        h_lo, h_hi, np.ascontiguousarray(az, np.float64), float(band), np.ascontiguousarray(table),
        np.ascontiguousarray(d_cols), np.ascontiguousarray(h), float(t_min), float(tol), best_face, best_t)
    return best_face, best_t, int(tests)
