"""Road layout and ground surface of a procedural scene.

Frames: velodyne (x forward, y left, z up; m) and road coordinates (s, d): arc length s along the
main road's centreline (s = 0 level with the sensor, increasing ahead) and signed lateral offset
d (+ left of the centreline). The centreline is a circular arc of curvature ``curvature`` (1/m,
+ bends left) or a straight line; the ego car drives in a right-hand lane at ``ego_offset`` with
a small yaw relative to the road.

Cross-section of each side (from the centreline outwards): traffic lanes, an optional parking
strip (parallel: 2.2 m, perpendicular: 5.0 m), a kerb and a raised sidewalk, then the roadside
zone (buildings, walls, vegetation). An optional straight cross street meets the main road at
s = ``cross_s``.

The ground is z = g(x, y) (velodyne): -1.73 m under the sensor plus a mild slope, curvature and
undulation; sidewalks sit ``curb_height`` above it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robustbench3d.sensors.hdl64e import MOUNT_HEIGHT_M

PARKING_WIDTH = {"none": 0.0, "parallel": 2.2, "perpendicular": 5.0}


@dataclass(frozen=True)
class Side:
    """One side of the main road. ``sign`` is +1 for the left side (d > 0), -1 for the right."""

    sign: int
    lanes: int
    parking: str  # 'none', 'parallel' or 'perpendicular'
    sidewalk: float  # sidewalk width, m
    roadside: str  # 'buildings', 'walls', 'vegetation' or 'open'
    setback: float  # gap between sidewalk and the roadside objects, m


@dataclass(frozen=True)
class Road:
    """Geometry of the main road (and optional cross street) relative to the ego vehicle."""

    curvature: float
    ego_offset: float  # lateral position of the sensor in road coordinates (d), m
    ego_yaw: float  # heading of the ego car relative to the road tangent at s = 0, rad
    lane_width: float
    left: Side
    right: Side
    curb_height: float
    cross_s: float | None  # s of the cross street's axis, or None
    cross_half_width: float
    ground: tuple[float, ...]  # slope_x, slope_y, curv_x, amplitude, wavenumber, phase

    # ---- cross-section -----------------------------------------------------------------
    def lanes_edge(self, side: Side) -> float:
        """|d| of the outer edge of the traffic lanes on ``side``."""
        return side.lanes * self.lane_width

    def curb_d(self, side: Side) -> float:
        """|d| of the kerb (road surface ends, sidewalk begins)."""
        return self.lanes_edge(side) + PARKING_WIDTH[side.parking]

    def sidewalk_outer_d(self, side: Side) -> float:
        return self.curb_d(side) + side.sidewalk

    def in_cross_street(self, s: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: s lies within the cross street's width (+ margin)."""
        s = np.asarray(s, dtype=np.float64)
        if self.cross_s is None:
            return np.zeros(s.shape, dtype=bool)
        return np.abs(s - self.cross_s) < self.cross_half_width + margin

    # ---- coordinates -------------------------------------------------------------------
    def _road_xy_to_velo(self, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        qx, qy = px, py - self.ego_offset
        c, s = np.cos(self.ego_yaw), np.sin(self.ego_yaw)
        return c * qx + s * qy, -s * qx + c * qy

    def _velo_to_road_xy(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c, s = np.cos(self.ego_yaw), np.sin(self.ego_yaw)
        return c * x - s * y, s * x + c * y + self.ego_offset

    def to_velo(self, s: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Road (s, d) -> velodyne (x, y) and the road's heading there (rad, velodyne yaw)."""
        s = np.asarray(s, dtype=np.float64)
        d = np.asarray(d, dtype=np.float64)
        k = self.curvature
        if abs(k) < 1e-6:
            px, py, th = s, d, np.zeros_like(s)
        else:
            th = k * s
            px = np.sin(th) / k - d * np.sin(th)
            py = (1 - np.cos(th)) / k + d * np.cos(th)
        x, y = self._road_xy_to_velo(px, py)
        return x, y, th - self.ego_yaw

    def to_road(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Velodyne (x, y) -> road (s, d)."""
        px, py = self._velo_to_road_xy(np.asarray(x, np.float64), np.asarray(y, np.float64))
        k = self.curvature
        if abs(k) < 1e-6:
            return px, py
        r = 1.0 / k
        sg = np.sign(r)
        qx, qy = px, py - r
        d = r - sg * np.hypot(qx, qy)
        s = np.arctan2(sg * qx, -sg * qy) / k
        return s, d

    # ---- surfaces ----------------------------------------------------------------------
    def ground_z(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Terrain height g(x, y) in the velodyne frame (m); g(0, 0) = -1.73."""
        ax, ay, cx, amp, kw, ph = self.ground
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        return (-MOUNT_HEIGHT_M + ax * x + ay * y + cx * x * x
                + amp * (np.sin(kw * (x + 0.5 * y) + ph) - np.sin(ph)))

    def on_sidewalk(self, s: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(N,) bool: road coordinates lie on a (raised) sidewalk."""
        out = np.zeros(np.shape(s), dtype=bool)
        for side in (self.left, self.right):
            a = side.sign * np.asarray(d)
            out |= (a >= self.curb_d(side)) & (a <= self.sidewalk_outer_d(side))
        return out & ~self.in_cross_street(s)

    def surface_z(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height of whatever one stands on at (x, y): terrain or sidewalk top (m, velodyne)."""
        s, d = self.to_road(x, y)
        return self.ground_z(x, y) + self.curb_height * self.on_sidewalk(s, d)

    def road_surface(self, s: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(N,) bool: asphalt (lanes, parking strips, the cross street)."""
        d = np.asarray(d)
        on_main = (d <= self.curb_d(self.left)) & (d >= -self.curb_d(self.right))
        return on_main | self.in_cross_street(s)

    def lane_paint(self, s: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(N,) bool: white road markings (edge lines, dashed lane lines, centre line)."""
        s = np.asarray(s)
        d = np.asarray(d)
        half = 0.06
        paint = np.zeros(s.shape, dtype=bool)
        dash = np.mod(s, 9.0) < 3.0
        for side in (self.left, self.right):
            edge = side.sign * (self.lanes_edge(side) - 0.25)
            paint |= np.abs(d - edge) < half
            for i in range(1, side.lanes):
                paint |= (np.abs(d - side.sign * i * self.lane_width) < half) & dash
        paint |= np.abs(d) < half * (1.0 + (self.left.lanes + self.right.lanes > 2))
        return paint & ~self.in_cross_street(s, 1.0)


def sample_road(rng: np.random.Generator) -> Road:
    """A random road layout (urban street, residential street or wide road)."""
    u = rng.uniform
    kind = rng.choice(3, p=[0.45, 0.3, 0.25])  # urban, residential, wide road
    lane_w = u(3.0, 3.7)
    if kind == 2:
        lanes = (int(rng.integers(2, 4)), int(rng.integers(2, 4)))
        parking = ("none", "none")
        roadside = ("vegetation", "walls", "buildings", "open")
        rs_p = [0.4, 0.25, 0.2, 0.15]
    else:
        lanes = (1, 1) if kind == 1 or rng.random() < 0.5 else (2, 2)
        opts = ["parallel", "perpendicular", "none"]
        pw = [0.75, 0.1, 0.15] if kind == 1 else [0.6, 0.1, 0.3]
        parking = (str(rng.choice(opts, p=pw)), str(rng.choice(opts, p=pw)))
        roadside = ("buildings", "vegetation", "walls", "open")
        rs_p = [0.65, 0.2, 0.1, 0.05] if kind == 0 else [0.35, 0.45, 0.15, 0.05]
    sides = []
    for sign, n_lanes, park in ((1, lanes[0], parking[0]), (-1, lanes[1], parking[1])):
        sides.append(Side(sign=sign, lanes=n_lanes, parking=park, sidewalk=u(1.5, 4.0),
                          roadside=str(rng.choice(roadside, p=rs_p)), setback=u(0.0, 5.0)))
    right_lanes = sides[1].lanes
    ego_lane = int(rng.integers(0, right_lanes))
    ego_offset = -(ego_lane + 0.5) * lane_w + rng.normal(0.0, 0.25)
    curvature = 0.0 if rng.random() < 0.5 else rng.normal(0.0, 0.006)
    cross = u(14.0, 50.0) if (kind != 2 and rng.random() < 0.35) else None
    ground = (rng.normal(0, 0.008), rng.normal(0, 0.008), rng.normal(0, 8e-5), u(0.0, 0.15),
              2 * np.pi / u(50.0, 150.0), u(0, 2 * np.pi))
    return Road(curvature=float(curvature), ego_offset=float(ego_offset), ego_yaw=float(rng.normal(0, 0.03)),
                lane_width=float(lane_w), left=sides[0], right=sides[1], curb_height=u(0.1, 0.16),
                cross_s=None if cross is None else float(cross), cross_half_width=u(5.0, 8.0),
                ground=tuple(float(g) for g in ground))
