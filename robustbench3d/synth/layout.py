"""Random scene layout: where vehicles, people and clutter go (pure function of a Generator).

Frames: road coordinates (s along the main road, d to its left; see
:mod:`robustbench3d.synth.road`) for placement, velodyne for the resulting meshes, rect for the
KITTI boxes. Traffic drives on the right: lanes with d < 0 go towards +s (like the ego car),
lanes with d > 0 towards -s.

What is placed (per side of the road, s from -25 m to 100 m; the roadside from -55 m to 140 m):

* parked vehicles: parallel rows at the kerb (small gaps, occasional larger ones) or
  perpendicular bays, mostly cars, some vans and the odd truck; headings along the road
  (parallel) or across it (bays) with a few degrees of noise;
* moving traffic in every lane (both directions) and on the cross street (headings across the
  main road);
* pedestrians on the sidewalks, cyclists at the right edge of the lanes;
* clutter the detector must reject: buildings with windows, walls, trees, bushes and hedges,
  street lamps, sign posts and bollards.

Vehicle sizes follow the KITTI label statistics (Car mean l, w, h = 3.88, 1.63, 1.53 m, sd about
0.40 / 0.10 / 0.14 m).
"""

from __future__ import annotations

import numpy as np

from robustbench3d.synth import materials as mt
from robustbench3d.synth.calibs import CameraDay, sample_camera_day
from robustbench3d.synth.clutter import building_mesh, bush_mesh, pole_mesh, tree_mesh, wall_mesh
from robustbench3d.synth.mesh import Mesh
from robustbench3d.synth.people import cyclist_mesh, extents, pedestrian_mesh
from robustbench3d.synth.road import Road, Side, sample_road
from robustbench3d.synth.scene import (
    Lighting,
    Scene,
    SceneObject,
    ground_mesh,
    kitti_pose,
    place_labelled,
    place_static,
    quantize,
    sidewalk_mesh,
)
from robustbench3d.synth.vehicles import CAR_STYLES, car_mesh, truck_mesh, van_mesh

#: KITTI Car size statistics (l, w, h): mean and standard deviation, m.
CAR_SIZE_MEAN = np.array([3.88, 1.63, 1.53])
CAR_SIZE_SD = np.array([0.40, 0.10, 0.14])
_CAR_SIZE_CORR = np.array([[1.0, 0.6, 0.1], [0.6, 1.0, 0.3], [0.1, 0.3, 1.0]])
#: Ego vehicle footprint plus the gaps kept free ahead of and behind it, velodyne frame (x0, x1, y0, y1),
#: m: nothing is placed there.
EGO_FOOTPRINT = (-8.0, 6.5, -1.2, 1.2)
S_RANGE = (-25.0, 100.0)
#: Buildings, walls and vegetation line the road further out, as the upper lasers reach 80 m and more.
ROADSIDE_S_RANGE = (-55.0, 140.0)


def sample_car_size(rng: np.random.Generator) -> np.ndarray:
    """(l, w, h) of a car, m, from a correlated normal around the KITTI statistics (clipped)."""
    cov = _CAR_SIZE_CORR * np.outer(CAR_SIZE_SD, CAR_SIZE_SD)
    lwh = rng.multivariate_normal(CAR_SIZE_MEAN, cov, method="cholesky")
    return np.clip(lwh, [2.9, 1.38, 1.25], [5.4, 2.0, 1.95])


def car_style_for(lwh: np.ndarray, rng: np.random.Generator) -> str:
    """Body style that suits the proportions (tall -> SUV, short -> hatchback, long -> sedan/wagon)."""
    l, _, h = lwh
    w = np.array([
        1.0 + 2.0 * (l > 4.2),  # sedan
        1.0 + 3.0 * (l < 3.8),  # hatchback
        0.6 + 1.5 * (l > 4.3),  # wagon
        0.2 + 4.0 * (h > 1.62),  # suv
    ])
    if h > 1.7:
        w[0] *= 0.2
    return CAR_STYLES[int(rng.choice(4, p=w / w.sum()))]


class Occupancy:
    """Ground footprints placed so far (oriented rectangles in velodyne x, y) for overlap tests."""

    def __init__(self) -> None:
        x0, x1, y0, y1 = EGO_FOOTPRINT
        self._rects = np.zeros((64, 5))  # cx, cy, half_l, half_w, yaw
        self._rects[0] = [(x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) / 2, (y1 - y0) / 2, 0.0]
        self._n = 1

    def free(self, cx: float, cy: float, half_l: float, half_w: float, yaw: float, margin: float = 0.2) -> bool:
        """True if the rectangle (grown by ``margin``) overlaps no stored footprint."""
        new = np.array([cx, cy, half_l + margin, half_w + margin, yaw])
        rects = self._rects[: self._n]
        reach = np.hypot(rects[:, 2], rects[:, 3]) + np.hypot(new[2], new[3])
        near = np.flatnonzero(np.hypot(rects[:, 0] - cx, rects[:, 1] - cy) < reach)
        return not any(_overlap(new, rects[i]) for i in near)

    def add(self, cx: float, cy: float, half_l: float, half_w: float, yaw: float) -> None:
        if self._n == len(self._rects):
            self._rects = np.concatenate([self._rects, np.zeros_like(self._rects)])
        self._rects[self._n] = [cx, cy, half_l, half_w, yaw]
        self._n += 1


def _corners(r: np.ndarray) -> np.ndarray:
    cx, cy, hl, hw, yaw = r
    c, s = np.cos(yaw), np.sin(yaw)
    loc = np.array([[hl, hw], [hl, -hw], [-hl, -hw], [-hl, hw]])
    return loc @ np.array([[c, s], [-s, c]]) + [cx, cy]


def _overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Separating-axis test of two oriented rectangles (cx, cy, half_l, half_w, yaw)."""
    ca, cb = _corners(a), _corners(b)
    for yaw in (a[4], b[4]):
        for axis in (np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])):
            pa, pb = ca @ axis, cb @ axis
            if pa.max() < pb.min() or pb.max() < pa.min():
                return False
    return True


def sample_lighting(rng: np.random.Generator) -> Lighting:
    """Sun direction/strength and sky colours: clear, hazy or overcast."""
    u = rng.uniform
    weather = rng.choice(3, p=[0.5, 0.3, 0.2])  # clear, hazy, overcast
    el = np.radians(u(15, 65))
    az = u(0, 2 * np.pi)
    sun = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    if weather == 0:
        zenith, horizon, sun_i, amb, haze = (0.18, 0.32, 0.75), (0.62, 0.72, 0.86), u(2.4, 3.0), u(0.35, 0.5), u(
            600, 1500)
    elif weather == 1:
        zenith, horizon, sun_i, amb, haze = (0.42, 0.50, 0.66), (0.75, 0.78, 0.82), u(1.6, 2.2), u(0.5, 0.7), u(
            250, 600)
    else:
        zenith, horizon, sun_i, amb, haze = (0.66, 0.68, 0.72), (0.80, 0.81, 0.83), u(0.3, 0.6), u(0.9, 1.2), u(
            200, 500)
    warm = np.array([1.0, u(0.92, 1.0), u(0.82, 0.95)])
    return Lighting(sun_direction=sun, sun_color=sun_i * warm, sky_zenith=np.array(zenith) * u(0.9, 1.1),
                    sky_horizon=np.array(horizon) * u(0.92, 1.05), ambient=amb, haze_distance=haze,
                    exposure=u(0.85, 1.15))


class _Builder:
    """Accumulates the objects of one scene."""

    def __init__(self, rng: np.random.Generator, day: CameraDay, road: Road):
        self.rng = rng
        self.day = day
        self.road = road
        self.occ = Occupancy()
        self.objects: list[SceneObject] = []

    # ---- labelled objects -----------------------------------------------------------------
    def vehicle(self, kind: str, s: float, d: float, rel_yaw: float, margin: float = 0.2) -> bool:
        """Place a Car / Van / Truck with its centre at road (s, d), heading road + rel_yaw."""
        rng = self.rng
        if kind == "Car":
            l, w, h = sample_car_size(rng)
        elif kind == "Van":
            l, w, h = (np.clip(rng.normal(5.07, 0.45), 4.2, 6.5), np.clip(rng.normal(1.90, 0.10), 1.7, 2.15),
                       np.clip(rng.normal(2.21, 0.22), 1.8, 2.8))
        else:
            l, w, h = (np.clip(rng.normal(10.1, 2.5), 6.0, 16.0), np.clip(rng.normal(2.59, 0.12), 2.3, 2.8),
                       np.clip(rng.normal(3.25, 0.35), 2.6, 4.0))
        return self._labelled(kind, s, d, rel_yaw, np.array([l, w, h]), margin)

    def person(self, kind: str, s: float, d: float, rel_yaw: float) -> bool:
        height = self.rng.normal(1.76, 0.11) if kind == "Pedestrian" else self.rng.normal(1.74, 0.08)
        return self._labelled(kind, s, d, rel_yaw, np.array([0.0, 0.0, float(np.clip(height, 1.45, 2.0))]), 0.15)

    def _labelled(self, kind: str, s: float, d: float, rel_yaw: float, lwh: np.ndarray, margin: float) -> bool:
        rng, road = self.rng, self.road
        x, y, road_yaw = road.to_velo(np.array([s]), np.array([d]))
        x, y, yaw = float(x[0]), float(y[0]), float(road_yaw[0] + rel_yaw)
        if kind in ("Pedestrian", "Cyclist"):
            local = (pedestrian_mesh if kind == "Pedestrian" else cyclist_mesh)(float(lwh[2]), rng)
            lwh = np.array(extents(local))
        if not self.occ.free(x, y, lwh[0] / 2, lwh[1] / 2, yaw, margin):
            return False
        dims_lwh = quantize(lwh)
        if kind == "Car":
            local = car_mesh(*dims_lwh, car_style_for(dims_lwh, rng), mt.pick(rng, mt.CAR_PAINT), rng)
        elif kind == "Van":
            local = van_mesh(*dims_lwh, mt.pick(rng, mt.VAN_PAINT), rng)
        elif kind == "Truck":
            local = truck_mesh(*dims_lwh, mt.pick(rng, mt.VAN_PAINT), mt.pick(rng, mt.FACADE), rng)
        else:
            l, w, h = dims_lwh
            local = local.scaled_to_box((-l / 2, -w / 2, 0.0), (l / 2, w / 2, h))
        z = float(road.surface_z(np.array([x]), np.array([y]))[0])
        loc, ry = kitti_pose(self.day.calib, np.array([x, y, z]), yaw)
        dims_hwl = dims_lwh[[2, 1, 0]]
        self.objects.append(place_labelled(kind, local, dims_hwl, loc, ry, self.day.calib))
        self.occ.add(x, y, lwh[0] / 2, lwh[1] / 2, yaw)
        return True

    # ---- clutter ----------------------------------------------------------------------
    def static(self, kind: str, mesh: Mesh, s: float, d: float, rel_yaw: float, half_l: float, half_w: float,
               sink: float = 0.0, check: bool = True) -> bool:
        x, y, road_yaw = self.road.to_velo(np.array([s]), np.array([d]))
        x, y, yaw = float(x[0]), float(y[0]), float(road_yaw[0] + rel_yaw)
        if check and not self.occ.free(x, y, half_l, half_w, yaw, 0.1):
            return False
        z = float(self.road.surface_z(np.array([x]), np.array([y]))[0]) - sink
        self.objects.append(place_static(kind, mesh, np.array([x, y, z]), yaw))
        self.occ.add(x, y, half_l, half_w, yaw)
        return True


def _vehicle_kind(rng: np.random.Generator, p_van: float, p_truck: float) -> str:
    r = rng.random()
    return "Truck" if r < p_truck else ("Van" if r < p_truck + p_van else "Car")


def _parked(b: _Builder, side: Side) -> None:
    road, rng = b.road, b.rng
    if side.parking == "parallel":
        s = S_RANGE[0] + rng.uniform(0, 5)
        toward = 0.0 if side.sign < 0 or rng.random() < 0.15 else np.pi
        while s < S_RANGE[1]:
            gap = rng.uniform(5.0, 20.0) if rng.random() < 0.25 else rng.uniform(0.6, 3.5)
            length = 4.2
            s += gap + length / 2
            if road.in_cross_street(np.array([s]), 4.0)[0]:
                s += 2.0
                continue
            d = side.sign * (road.curb_d(side) - 1.0 - rng.uniform(0.1, 0.4))
            yaw = toward + rng.normal(0, 0.04) + (np.pi if rng.random() < 0.08 else 0.0)
            b.vehicle(_vehicle_kind(rng, 0.10, 0.02), s, d, yaw, margin=0.15)
            s += length / 2
    elif side.parking == "perpendicular":
        pitch = rng.uniform(2.4, 2.9)
        d = side.sign * (road.lanes_edge(side) + 2.5 + rng.uniform(-0.2, 0.2))
        for s in np.arange(S_RANGE[0], S_RANGE[1], pitch):
            if rng.random() < 0.6 and not road.in_cross_street(np.array([s]), 4.0)[0]:
                yaw = side.sign * np.pi / 2 + (np.pi if rng.random() < 0.5 else 0.0) + rng.normal(0, 0.08)
                b.vehicle(_vehicle_kind(rng, 0.08, 0.0), s + rng.normal(0, 0.15), d + rng.normal(0, 0.2), yaw,
                          margin=0.1)


def _traffic(b: _Builder, side: Side) -> None:
    road, rng = b.road, b.rng
    for lane in range(side.lanes):
        d_lane = side.sign * (lane + 0.5) * road.lane_width
        toward = 0.0 if side.sign < 0 else np.pi
        s = S_RANGE[0] + rng.uniform(0, 25)
        while s < S_RANGE[1]:
            s += rng.uniform(6.0, 45.0)
            b.vehicle(_vehicle_kind(rng, 0.10, 0.07), s, d_lane + rng.normal(0, 0.2), toward + rng.normal(0, 0.025))
    if side.sign < 0:  # cyclists at the right edge of the rightmost lane
        for _ in range(rng.poisson(0.5)):
            s = rng.uniform(4.0, 60.0)
            b.person("Cyclist", s, -(road.lanes_edge(side) - 0.6), rng.normal(0, 0.05))


def _cross_traffic(b: _Builder) -> None:
    road, rng = b.road, b.rng
    if road.cross_s is None:
        return
    for direction in (1.0, -1.0):
        lane_off = -direction * road.cross_half_width / 2
        t = -70.0 + rng.uniform(0, 20)
        while t < 70.0:
            t += rng.uniform(8.0, 35.0)
            b.vehicle(_vehicle_kind(rng, 0.1, 0.05), road.cross_s + lane_off, t,
                      direction * np.pi / 2 + rng.normal(0, 0.03))


def _sidewalk_life(b: _Builder, side: Side) -> None:
    road, rng = b.road, b.rng
    d_curb = road.curb_d(side)
    for _ in range(rng.poisson(1.8)):
        s = rng.uniform(-10.0, 70.0)
        d = side.sign * (d_curb + rng.uniform(0.4, max(side.sidewalk - 0.4, 0.5)))
        b.person("Pedestrian", s, d, (0.0 if rng.random() < 0.5 else np.pi) + rng.normal(0, 0.3))
    if road.cross_s is not None and rng.random() < 0.4:  # someone crossing the main road near the junction
        b.person("Pedestrian", road.cross_s - road.cross_half_width - 1.0, rng.uniform(-d_curb, d_curb),
                 side.sign * np.pi / 2 + rng.normal(0, 0.2))
    # street furniture near the kerb
    s = S_RANGE[0] + rng.uniform(0, 20)
    while s < S_RANGE[1]:
        s += rng.uniform(12.0, 40.0)
        if not road.in_cross_street(np.array([s]), 1.0)[0]:
            b.static("pole", pole_mesh(rng), s, side.sign * (d_curb + 0.35), 0.0 if side.sign > 0 else np.pi, 0.2, 0.2)
    if rng.random() < 0.35:  # a row of street trees on the sidewalk
        s = S_RANGE[0] + rng.uniform(0, 8)
        while s < S_RANGE[1]:
            s += rng.uniform(7.0, 14.0)
            if not road.in_cross_street(np.array([s]), 2.0)[0]:
                b.static("tree", tree_mesh(rng, street=True), s, side.sign * (d_curb + 0.8), 0.0, 0.3, 0.3)


def _roadside(b: _Builder, side: Side) -> None:
    road, rng = b.road, b.rng
    d0 = road.sidewalk_outer_d(side) + side.setback
    yaw_face = 0.0 if side.sign > 0 else np.pi  # local +y points away from the road
    kind = side.roadside
    s, s_end = ROADSIDE_S_RANGE
    while s < s_end:
        if kind == "buildings" or (kind == "walls" and rng.random() < 0.25):
            width = rng.uniform(8.0, 30.0)
            if not road.in_cross_street(np.array([s + width / 2]), width / 2 + 3.0)[0]:
                depth = rng.uniform(8.0, 15.0)
                mesh = building_mesh(width, depth, rng.uniform(5.0, 22.0), rng)
                b.static("building", mesh, s + width / 2, side.sign * d0, yaw_face, width / 2, 0.5, sink=0.3,
                         check=False)
            s += width + (rng.uniform(2.0, 10.0) if rng.random() < 0.3 else 0.0)
        elif kind == "walls":
            length = rng.uniform(5.0, 25.0)
            if not road.in_cross_street(np.array([s + length / 2]), length / 2 + 2.0)[0]:
                b.static("wall", wall_mesh(length, rng), s + length / 2, side.sign * d0, yaw_face, length / 2, 0.3,
                         sink=0.1, check=False)
            s += length + rng.uniform(0.0, 4.0)
        else:  # vegetation / open land: trees and hedges, sparse when open
            step = rng.uniform(4.0, 10.0) if kind == "vegetation" else rng.uniform(10.0, 30.0)
            s += step
            if road.in_cross_street(np.array([s]), 3.0)[0]:
                continue
            if rng.random() < 0.3:
                length = rng.uniform(2.0, 8.0)
                b.static("bush", bush_mesh(length, rng), s, side.sign * (d0 + 0.8), yaw_face, length / 2, 0.8,
                         check=False)
            else:
                off = rng.uniform(0.5, 4.0)
                b.static("tree", tree_mesh(rng, street=side.setback + off < 3.0), s, side.sign * (d0 + off), 0.0,
                         0.3, 0.3, check=False)
    # a second, deeper line (trees or buildings) so the upper lasers see something
    s, s_end = ROADSIDE_S_RANGE
    while s < s_end:
        s += rng.uniform(6.0, 25.0)
        d_back = side.sign * (d0 + rng.uniform(12.0, 35.0))
        if road.in_cross_street(np.array([s]), 6.0)[0]:
            continue
        if rng.random() < 0.5:
            width = rng.uniform(10.0, 30.0)
            b.static("building", building_mesh(width, rng.uniform(8.0, 15.0), rng.uniform(6.0, 25.0), rng), s,
                     d_back, yaw_face, width / 2, 0.5, sink=0.3, check=False)
        else:
            b.static("tree", tree_mesh(rng), s, d_back, 0.0, 0.3, 0.3, check=False)


def sample_scene(rng: np.random.Generator, day: CameraDay | None = None) -> Scene:
    """A complete random scene (road, lighting, all objects with meshes in the velodyne frame)."""
    day = sample_camera_day(rng) if day is None else day
    road = sample_road(rng)
    lighting = sample_lighting(rng)
    b = _Builder(rng, day, road)
    b.objects.append(SceneObject("ground", ground_mesh(road)))
    for side in (road.left, road.right):
        walk = sidewalk_mesh(road, side, ROADSIDE_S_RANGE)
        if walk is not None:
            b.objects.append(SceneObject("sidewalk", walk))
    for side in (road.left, road.right):
        _traffic(b, side)
    _cross_traffic(b)
    for side in (road.left, road.right):
        _parked(b, side)
        _sidewalk_life(b, side)
    for side in (road.left, road.right):
        _roadside(b, side)
    return Scene(day=day, road=road, lighting=lighting, objects=b.objects)
