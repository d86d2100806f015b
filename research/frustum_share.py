"""Share of a roof object's LiDAR returns inside its own car's frustum (the car's ground-truth 2D box), and
share of the frustum's original points the object removes, over the first N val frames of the embedded
dataset, the undeformed sphere on every target car (docs/attacks.md).

Usage: python research/frustum_share.py [N]   (default 100)
"""

from __future__ import annotations

import sys

import numpy as np

from robustbench3d.attacks.base import target_cars
from robustbench3d.attacks.object import benign_sphere, template_faces
from robustbench3d.attacks.placement import cars_of, place_on_roof, rect_to_velo
from robustbench3d.datasets import load_ground_truth, resolve_dataset
from robustbench3d.sensors.lidar_render import render_lidar
from robustbench3d.victims.fpointnet.frustum import extract_frustum, project_scan

BANDS = ((0.0, 20.0, "< 20 m"), (20.0, 40.0, "20-40 m"), (40.0, np.inf, "> 40 m"))


def main(n: int) -> None:
    dataset = resolve_dataset(None, "val", progress=False)
    gt = load_ground_truth(dataset, n)
    kitti = dataset.kitti()
    vertices, faces = benign_sphere().vertices(), template_faces()
    returns = inside = frustum_points = removed = n_cars = 0
    per_band = {name: [0, 0] for _, _, name in BANDS}
    for frame_id in gt.frame_ids:
        frame = kitti.frame(frame_id)
        cars = target_cars(frame.labels)
        if len(cars) == 0:
            continue
        meshes = [(rect_to_velo(place_on_roof(vertices, car)[0], frame.calib), faces, None) for car in cars_of(cars)]
        res = render_lidar(frame.scan, meshes)
        clean = project_scan(frame.scan, frame.calib, frame.image_size)
        for j in range(len(cars)):
            mine = res.added[res.object_index == j]
            own = extract_frustum(project_scan(mine, frame.calib, frame.image_size), cars.bbox[j], frame.calib)
            cut = extract_frustum(clean, cars.bbox[j], frame.calib)
            distance = float(np.hypot(cars.location[j, 0], cars.location[j, 2]))
            band = next(name for lo, hi, name in BANDS if lo <= distance < hi)
            per_band[band][0] += len(mine)
            per_band[band][1] += len(own)
            returns += len(mine)
            inside += len(own)
            frustum_points += len(cut)
            removed += int(np.isin(cut.indices, res.removed_index).sum())
            n_cars += 1
    print(f"{n_cars} cars, {returns} object returns, {inside} inside their car's GT-box frustum "
          f"({inside / max(returns, 1):.1%}); frustum points removed by the object {removed} of {frustum_points} "
          f"({removed / max(frustum_points, 1):.2%})")
    for name, (total, own) in per_band.items():
        print(f"  {name}: {own} of {total} returns in the frustum ({own / max(total, 1):.1%})")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 100)
