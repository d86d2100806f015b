"""Statistics of LiDAR scans, used to compare generated scans with real KITTI ones.

All inputs are velodyne-frame scans (x forward, y left, z up; m) in sensor order. KITTI scans are
stored laser by laser, each laser sweeping counter-clockwise from just above the +x axis; ring
indices come from :func:`robustbench3d.sensors.hdl64e.ring_ids_from_azimuth_wrap`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robustbench3d.sensors.hdl64e import ring_ids_from_azimuth_wrap


@dataclass(frozen=True)
class RingFit:
    """Per-ring cone z = rho * tan(phi) + h0 (rho = horizontal range), least squares."""

    elevation_deg: np.ndarray  # (R,) phi
    origin_height: np.ndarray  # (R,) h0, m
    rms: np.ndarray  # (R,) fit residual, m
    count: np.ndarray  # (R,) points used


def fit_ring_cones(scan: np.ndarray, rings: np.ndarray | None = None,
                   rho_range: tuple[float, float] = (2.5, 70.0)) -> RingFit:
    """Fit each ring's cone over points with rho in ``rho_range`` (m); rings with < 10 points get NaN."""
    rings = ring_ids_from_azimuth_wrap(scan) if rings is None else rings
    rho = np.hypot(scan[:, 0], scan[:, 1]).astype(np.float64)
    z = scan[:, 2].astype(np.float64)
    use = (rho > rho_range[0]) & (rho < rho_range[1])
    n_rings = int(rings.max()) + 1 if len(rings) else 0
    phi = np.full(n_rings, np.nan)
    h0 = np.full(n_rings, np.nan)
    rms = np.full(n_rings, np.nan)
    count = np.zeros(n_rings, dtype=np.int64)
    for r in range(n_rings):
        sel = use & (rings == r)
        count[r] = int(sel.sum())
        if count[r] < 10:
            continue
        a = np.stack([rho[sel], np.ones(count[r])], axis=1)
        (slope, icpt), *_ = np.linalg.lstsq(a, z[sel], rcond=None)
        phi[r] = np.degrees(np.arctan(slope))
        h0[r] = icpt
        rms[r] = float(np.sqrt(np.mean((a @ [slope, icpt] - z[sel]) ** 2)))
    return RingFit(phi, h0, rms, count)


def ground_height(scan: np.ndarray, bin_m: float = 0.02) -> float:
    """Height (m, velodyne z) of the densest 2 cm z-bin among points 4-20 m ahead, |y| < 10 m."""
    x, y, z = scan[:, 0], scan[:, 1], scan[:, 2]
    sel = (x > 4) & (x < 20) & (np.abs(y) < 10) & (z < 0)
    if not sel.any():
        return float("nan")
    zs = z[sel]
    edges = np.arange(zs.min(), zs.max() + 2 * bin_m, bin_m)
    hist, edges = np.histogram(zs, bins=edges)
    k = int(np.argmax(hist))
    return float((edges[k] + edges[k + 1]) / 2)


def azimuth_step_deg(scan: np.ndarray, rings: np.ndarray | None = None) -> float:
    """Median azimuth spacing (deg) between consecutive returns of the same ring."""
    rings = ring_ids_from_azimuth_wrap(scan) if rings is None else rings
    az = np.degrees(np.arctan2(scan[:, 1], scan[:, 0]))
    d = np.diff(az)
    same = (np.diff(rings) == 0) & (np.abs(d) < 1.0)
    return float(np.median(np.abs(d[same]))) if same.any() else float("nan")
