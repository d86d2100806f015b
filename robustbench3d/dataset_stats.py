"""LiDAR and label statistics of KITTI-layout datasets, side by side (``robustbench3d data stats``).

Used to check the embedded generator against real KITTI: points per frame, per-ring cone
elevation and origin height, azimuth step, ground height, and LiDAR points on cars at 10/20/40 m.
"""

from __future__ import annotations

#: Distance bins (centre, half width) in m for "points on a car".
CAR_DISTANCE_BINS: tuple[tuple[float, float], ...] = ((10.0, 2.5), (20.0, 2.5), (40.0, 5.0))


def dataset_statistics(root: str, max_frames: int | None = None, split: str | None = None) -> dict:
    """Statistics over the first ``max_frames`` frames of a KITTI-layout dataset (velodyne frame, m)."""
    import numpy as np

    from robustbench3d.errors import DataFormatError
    from robustbench3d.eval.rules import TARGET_CLASS
    from robustbench3d.geometry import points_in_boxes
    from robustbench3d.kitti import KittiDataset
    from robustbench3d.scan_stats import azimuth_step_deg, fit_ring_cones, ground_height
    from robustbench3d.sensors.hdl64e import ring_ids_from_azimuth_wrap

    ds = KittiDataset(root, split=split)
    ids = ds.frame_ids[:max_frames] if max_frames else ds.frame_ids
    points, rings, grounds, steps, phis, h0s = [], [], [], [], [], []
    car_points: dict[float, list[int]] = {c: [] for c, _ in CAR_DISTANCE_BINS}
    for fid in ids:
        scan = ds.scan(fid)
        if not len(scan):
            raise DataFormatError(ds.path("scan", fid), "empty scan (0 points); LiDAR statistics need points")
        rid = ring_ids_from_azimuth_wrap(scan)
        fit = fit_ring_cones(scan, rid)
        points.append(len(scan))
        rings.append(int(rid.max()) + 1)
        grounds.append(ground_height(scan))
        steps.append(azimuth_step_deg(scan, rid))
        if len(fit.elevation_deg) == 64:
            phis.append(fit.elevation_deg)
            h0s.append(fit.origin_height)
        labels = ds.labels(fid)
        if labels is None:
            continue
        cars = labels.type == TARGET_CLASS
        if not cars.any():
            continue
        calib = ds.calib(fid)
        rect = calib.velo_to_rect_points(scan[:, :3])
        inside = points_in_boxes(rect, labels.dimensions[cars], labels.location[cars], labels.rotation_y[cars])
        dist = np.hypot(labels.location[cars, 0], labels.location[cars, 2])
        for centre, half in CAR_DISTANCE_BINS:
            for k in np.flatnonzero(np.abs(dist - centre) <= half):
                car_points[centre].append(int(inside[:, k].sum()))
    phi = np.nanmedian(np.stack(phis), axis=0) if phis else None
    h0 = np.nanmedian(np.stack(h0s), axis=0) if h0s else None
    return {
        "root": str(root),
        "frames": len(ids),
        "points_per_frame": {"mean": float(np.mean(points)), "min": int(np.min(points)), "max": int(np.max(points))},
        "rings": {"min": int(np.min(rings)), "max": int(np.max(rings))},
        "ring_elevation_deg": None if phi is None else [round(float(v), 4) for v in phi],
        "ring_origin_height_m": None if h0 is None else [round(float(v), 4) for v in h0],
        "azimuth_step_deg": float(np.nanmedian(steps)),
        "ground_height_m": float(np.nanmedian(grounds)),
        "car_points_by_distance": {
            f"{c:g}m": {"cars": len(v), "median": float(np.median(v)) if v else None} for c, v in car_points.items()
        },
    }


def format_comparison(stats: list[dict]) -> str:
    """Readable table: one column per dataset, plus the max per-ring elevation difference to the first."""
    import numpy as np

    from robustbench3d.bench import dict_table

    def row(name: str, fn) -> dict:
        return {"statistic": name, **{f"[{i}] {s['root']}": fn(s) for i, s in enumerate(stats)}}

    rows = [
        row("frames", lambda s: s["frames"]),
        row("points/frame mean", lambda s: round(s["points_per_frame"]["mean"])),
        row("points/frame min..max", lambda s: f"{s['points_per_frame']['min']}..{s['points_per_frame']['max']}"),
        row("rings", lambda s: f"{s['rings']['min']}..{s['rings']['max']}"),
        row("ring 0 / 31 / 32 / 63 elevation deg",
            lambda s: "n/a" if s["ring_elevation_deg"] is None else
            " / ".join(f"{s['ring_elevation_deg'][k]:.2f}" for k in (0, 31, 32, 63))),
        row("upper / lower block h0 m",
            lambda s: "n/a" if s["ring_origin_height_m"] is None else
            f"{np.mean(s['ring_origin_height_m'][:32]):.3f} / {np.mean(s['ring_origin_height_m'][32:]):.3f}"),
        row("azimuth step deg", lambda s: round(s["azimuth_step_deg"], 4)),
        row("ground height m", lambda s: round(s["ground_height_m"], 3)),
    ]
    ref = stats[0]["ring_elevation_deg"]
    if ref is not None:
        rows.append(row("max |d elevation| vs first, deg",
                        lambda s: "n/a" if s["ring_elevation_deg"] is None else
                        round(float(np.max(np.abs(np.subtract(s["ring_elevation_deg"], ref)))), 4)))
    for key in stats[0]["car_points_by_distance"]:
        rows.append(row(f"points on a car at {key} (median, n)",
                        lambda s, k=key: "n/a" if not s["car_points_by_distance"][k]["cars"] else
                        f"{s['car_points_by_distance'][k]['median']:g} ({s['car_points_by_distance'][k]['cars']})"))
    return dict_table(rows)
