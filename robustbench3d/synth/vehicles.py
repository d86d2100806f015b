"""Vehicle meshes: cars (sedan, hatchback, wagon, SUV), vans and trucks.

Frame: object-local, x forward, y left, z up, origin at the bottom centre; metres. Every builder
returns a mesh whose bounding box is exactly the requested (l, w, h) box, so the KITTI 3D box
of a placed vehicle contains it tightly.

A car body is a loft through cross-sections along its length. The side profile has a nose,
hood, windshield, roof, rear window and trunk (or tailgate); the body is cut out above the
wheels (wheel arches), the cabin narrows towards the roof (tumblehome), and the corners are
rounded in plan view. Faces carry glass (windows), lights, dark trim and paint materials; the
four wheels are separate dark cylinders with light rims.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from robustbench3d.synth import materials as mt
from robustbench3d.synth.materials import Mat
from robustbench3d.synth.mesh import Mesh, box, cylinder_y, loft, merge, regular_polygon

CAR_STYLES = ("sedan", "hatchback", "wagon", "suv")

# segment k of a ring joins ring points k and k+1 (see _rings); their roles:
_LOWER, _UPPER, _WINDOW, _ROOF_EDGE, _ROOF, _BOTTOM = 0, 1, 2, 3, 4, 5
_SEGMENT_ROLE = np.array([_LOWER, _UPPER, _WINDOW, _ROOF_EDGE, _ROOF, _ROOF_EDGE, _WINDOW, _UPPER, _LOWER,
                          _BOTTOM])
_IS_LOWER, _IS_UPPER, _IS_WINDOW, _IS_BOTTOM = (np.isin(_SEGMENT_ROLE, r) for r in (_LOWER, _UPPER, _WINDOW, _BOTTOM))
_IS_TOP = np.isin(_SEGMENT_ROLE, (_ROOF, _ROOF_EDGE))
#: Body colour per material (float32, indexed by material id); the paint row is set per car.
_BODY_COLORS = np.zeros((len(Mat), 3), dtype=np.float32)
for _m, _c in ((Mat.GLASS, mt.GLASS), (Mat.TRIM, mt.TRIM), (Mat.HEADLIGHT, mt.HEADLIGHT),
               (Mat.TAILLIGHT, mt.TAILLIGHT)):
    _BODY_COLORS[_m] = _c


def _rings(half_width: np.ndarray, z_bot: np.ndarray, z_belt: np.ndarray, z_top: np.ndarray,
           roof_half: float) -> np.ndarray:
    """(M, 10, 3) cross-section points (x = 0, y, z) at M stations.

    Per side from the bottom: sill corner, widest point, shoulder (belt line), roof edge, roof.
    On the hood and trunk (z_top close to the belt line) the upper points collapse onto the top.
    """
    zb = np.minimum(z_belt, z_top - 0.03)
    cabin = np.clip((z_top - zb) / 0.35, 0.0, 1.0)  # 0 on hood/trunk, 1 under the roof
    y4 = 0.96 * half_width + cabin * (roof_half - 0.96 * half_width)
    ys = np.stack([0.90 * half_width, half_width, 0.985 * half_width, y4, 0.6 * y4], axis=1)
    zs = np.stack([z_bot, z_bot + 0.45 * (zb - z_bot), zb, zb + 0.85 * (z_top - zb), z_top], axis=1)
    y = np.concatenate([ys, -ys[:, ::-1]], axis=1)
    z = np.concatenate([zs, zs[:, ::-1]], axis=1)
    return np.stack([np.zeros_like(y), y, z], axis=2)


def _profile(u: np.ndarray, knots: list[tuple[float, float]]) -> np.ndarray:
    ku, kz = zip(*sorted(knots), strict=True)
    return np.interp(u, ku, kz)


def _body(l: float, w: float, h: float, p: dict, paint: np.ndarray) -> Mesh:
    """Lofted body of a car/van with shape parameters ``p`` (fractions of l along x, metres up)."""
    uf, ur, rw = p["axle_front"], p["axle_rear"], p["wheel_radius"]
    ra = rw * 1.12 / l  # arch half-length in u
    a1, a2, a3, a4 = p["windshield"], p["roof_front"], p["roof_rear"], p["deck"]
    ub = 0.5 * (a2 + a3)
    stations = [0.0, 0.025, 0.07, 0.14, a1, a2, ub - 0.012, ub + 0.012, a3, a4, 0.975, 1.0,
                uf - ra, uf - 0.55 * ra, uf, uf + 0.55 * ra, uf + ra,
                ur - ra, ur - 0.55 * ra, ur, ur + 0.55 * ra, ur + ra]
    u = np.unique(np.clip(np.round(np.array(stations), 4), 0.0, 1.0))
    top = _profile(u, [(0.0, p["z_nose"]), (0.03, p["z_hood"] - 0.05), (0.12, p["z_hood"]),
                       (a1, p["z_hood"] + 0.03), (a2, h), (a3, h - 0.01), (a4, p["z_deck"]),
                       (0.985, p["z_deck"] - 0.02), (1.0, p["z_tail"])])
    belt = _profile(u, [(0.0, p["z_hood"]), (a1, p["z_hood"] + 0.03), (1.0, p["z_hood"] + 0.08)])
    arch_top = 2 * rw * 0.93
    low = p["clearance"]
    bot = _profile(u, [(0.0, low + 0.12), (0.06, low + 0.03), (uf - ra, low + 0.02), (uf - 0.55 * ra, arch_top * 0.88),
                       (uf, arch_top), (uf + 0.55 * ra, arch_top * 0.88), (uf + ra, low), (ur - ra, low),
                       (ur - 0.55 * ra, arch_top * 0.88), (ur, arch_top), (ur + 0.55 * ra, arch_top * 0.88),
                       (ur + ra, low + 0.02), (0.95, low + 0.05), (1.0, low + 0.14)])
    plan = 1.0 - 0.10 * np.clip(1 - u / 0.15, 0, 1) ** 2 - 0.07 * np.clip((u - 0.88) / 0.12, 0, 1) ** 2
    rings = _rings(w / 2 * plan, bot, belt, top, p["roof_half"] * w / 2)
    rings[:, :, 0] = (0.5 - u[:, None]) * l  # u = 0 is the front (x = +l/2)

    # materials of the bands between stations (columns: ring segments, see _SEGMENT_ROLE)
    um = 0.5 * (u[:-1] + u[1:])
    mat = np.full((len(um), len(_SEGMENT_ROLE)), Mat.PAINT, dtype=np.uint8)
    side_glass = (um > a1 + 0.015) & (um < p["side_glass_end"]) & ~((um > ub - 0.012) & (um < ub + 0.012))
    mat[side_glass[:, None] & _IS_WINDOW] = Mat.GLASS
    windshield = (um > a1) & (um < a2)
    rear_glass = (um > a3) & (um < a4 - 0.01)
    mat[(windshield | rear_glass)[:, None] & _IS_TOP] = Mat.GLASS
    mat[:, _IS_BOTTOM] = Mat.TRIM
    front_band = um < 0.05
    rear_band = um > 0.965
    mat[front_band[:, None] & _IS_UPPER] = Mat.HEADLIGHT
    mat[rear_band[:, None] & _IS_UPPER] = Mat.TAILLIGHT
    bumper = (um < 0.05) | (um > 0.965)
    mat[bumper[:, None] & _IS_LOWER] = Mat.TRIM
    palette = _BODY_COLORS.copy()
    palette[Mat.PAINT] = paint
    color = palette[mat]
    return loft(rings, mat, color, (Mat.PAINT, Mat.PAINT), (0.8 * paint, paint))


@lru_cache(maxsize=1)
def _unit_wheel() -> Mesh:
    """Tyre (octagonal prism, radius 1, width 1, axis y, centred) with a flat rim disc on the +y face."""
    tyre = cylinder_y((0.0, 0.0, 0.0), 1.0, 1.0, 8, Mat.TYRE, mt.TYRE)
    poly = regular_polygon(8, 0.6, -np.pi / 2 + np.pi / 8)
    fan = np.arange(1, 7)
    rim = Mesh(np.column_stack([poly[:, 0], np.full(8, 0.51), poly[:, 1]]),
               np.stack([np.zeros(6, np.int64), fan, fan + 1], 1), np.full(6, Mat.RIM, np.uint8),
               np.tile(mt.RIM.astype(np.float32), (6, 1)))
    return merge([tyre, rim])


@lru_cache(maxsize=4)
def _wheel_set(n: int) -> Mesh:
    """Faces, materials and colours (read-only) of ``n`` unit wheels, left and right ones alternating
    (the right ones mirrored, so their faces are flipped); the vertices are left empty."""
    unit = _unit_wheel()
    faces = np.concatenate([(unit.faces if k % 2 == 0 else unit.faces[:, ::-1]) + k * len(unit.vertices)
                            for k in range(n)])
    out = Mesh(np.empty((0, 3)), faces, np.tile(unit.material, n), np.tile(unit.color, (n, 1)))
    for a in (out.faces, out.material, out.color):
        a.flags.writeable = False
    return out


def _wheels(l: float, w: float, p: dict, axles: list[float]) -> Mesh:
    """Four (or more) wheels of radius p['wheel_radius'] at the axle stations (fractions of l from the front)."""
    rw = p["wheel_radius"]
    tw = min(0.22, 0.14 * w)
    unit = _unit_wheel()
    wheels = [(ua, side) for ua in axles for side in (1.0, -1.0)]
    centers = np.array([[(0.5 - ua) * l, side * (w / 2 - 0.02 - tw / 2), rw] for ua, side in wheels])
    scales = np.array([[rw, side * tw, rw] for _, side in wheels])
    topology = _wheel_set(len(wheels))
    verts = (unit.vertices * scales[:, None] + centers[:, None]).reshape(-1, 3)
    return Mesh(verts, topology.faces, topology.material, topology.color)


def car_shape(style: str, l: float, w: float, h: float, rng: np.random.Generator) -> dict:
    """Random shape parameters of a car body of the given style (fractions of l, metres)."""
    u = rng.uniform
    rw = float(np.clip(u(0.29, 0.33) * (h / 1.5) ** 0.5, 0.27, 0.38))
    p = {
        "wheel_radius": rw, "clearance": u(0.12, 0.18), "axle_front": u(0.16, 0.21), "axle_rear": u(0.77, 0.82),
        "roof_half": u(0.74, 0.82),
    }
    z_hood = h * u(0.55, 0.63)
    if style == "sedan":
        a1 = u(0.30, 0.36)
        a2 = a1 + u(0.13, 0.17)
        a3 = u(0.64, 0.70)
        a4 = a3 + u(0.12, 0.16)
        z_deck = z_hood + u(0.0, 0.08)
        z_tail = z_deck - u(0.03, 0.08)
        glass_end = a3 + 0.04
    elif style == "hatchback":
        a1 = u(0.27, 0.33)
        a2 = a1 + u(0.14, 0.18)
        a3 = u(0.78, 0.84)
        a4 = u(0.95, 0.97)
        z_deck = z_hood + u(0.06, 0.14)
        z_tail = z_deck - u(0.15, 0.25)
        glass_end = a3 - 0.02
    elif style == "wagon":
        a1 = u(0.29, 0.34)
        a2 = a1 + u(0.13, 0.17)
        a3 = u(0.86, 0.90)
        a4 = u(0.96, 0.975)
        z_deck = h - u(0.10, 0.18)
        z_tail = z_hood - u(0.0, 0.08)
        glass_end = a3 - 0.01
        p["clearance"] = u(0.12, 0.16)
    elif style == "suv":
        z_hood = h * u(0.58, 0.66)
        a1 = u(0.26, 0.31)
        a2 = a1 + u(0.12, 0.16)
        a3 = u(0.84, 0.89)
        a4 = u(0.95, 0.97)
        z_deck = h - u(0.12, 0.22)
        z_tail = z_hood - u(0.0, 0.06)
        glass_end = a3 - 0.02
        p["clearance"] = u(0.17, 0.22)
    else:
        raise ValueError(f"unknown car style {style!r}; expected one of {CAR_STYLES}")
    p.update(windshield=a1, roof_front=a2, roof_rear=a3, deck=a4, z_hood=z_hood, z_nose=z_hood - u(0.10, 0.18),
             z_deck=z_deck, z_tail=z_tail, side_glass_end=glass_end)
    return p


def car_mesh(l: float, w: float, h: float, style: str, paint: np.ndarray, rng: np.random.Generator) -> Mesh:
    """A car filling exactly the box [-l/2, l/2] x [-w/2, w/2] x [0, h] (m)."""
    p = car_shape(style, l, w, h, rng)
    m = merge([_body(l, w, h, p, paint), _wheels(l, w, p, [p["axle_front"], p["axle_rear"]])])
    return m.scaled_to_box((-l / 2, -w / 2, 0.0), (l / 2, w / 2, h))


def van_mesh(l: float, w: float, h: float, paint: np.ndarray, rng: np.random.Generator) -> Mesh:
    """A van (box-shaped body, short hood, tall roof) filling the box exactly."""
    u = rng.uniform
    z_hood = h * u(0.42, 0.50)
    a1 = u(0.10, 0.17)
    p = {
        "wheel_radius": u(0.32, 0.36), "clearance": u(0.16, 0.22), "axle_front": u(0.13, 0.18),
        "axle_rear": u(0.74, 0.82), "roof_half": u(0.88, 0.94), "windshield": a1, "roof_front": a1 + u(0.08, 0.12),
        "roof_rear": u(0.95, 0.97), "deck": u(0.985, 0.99), "z_hood": z_hood, "z_nose": z_hood - u(0.12, 0.2),
        "z_deck": h - 0.05, "z_tail": h * u(0.8, 0.9),
    }
    p["side_glass_end"] = p["roof_front"] + 0.18 if rng.random() < 0.6 else p["roof_rear"] - 0.03
    m = merge([_body(l, w, h, p, paint), _wheels(l, w, p, [p["axle_front"], p["axle_rear"]])])
    return m.scaled_to_box((-l / 2, -w / 2, 0.0), (l / 2, w / 2, h))


def truck_mesh(l: float, w: float, h: float, paint: np.ndarray, cargo: np.ndarray,
               rng: np.random.Generator) -> Mesh:
    """A box truck: cab at the front, cargo box behind, 2-3 axles; fills the box exactly."""
    u = rng.uniform
    cab_l = u(1.9, 2.5)
    cab_h = min(h, u(2.6, 3.1))
    rw = u(0.45, 0.52)
    chassis_z = rw * 1.6
    # cab: a short loft (nearly vertical windshield) placed at the front
    p = {
        "wheel_radius": rw, "clearance": 0.35, "axle_front": 0.45, "axle_rear": 0.95, "roof_half": 0.9,
        "windshield": 0.08, "roof_front": 0.3, "roof_rear": 0.97, "deck": 0.99, "z_hood": cab_h * 0.5,
        "z_nose": cab_h * 0.4, "z_deck": cab_h - 0.05, "z_tail": cab_h - 0.1, "side_glass_end": 0.6,
    }
    cab = _body(cab_l, w * 0.97, cab_h, p, paint)
    cab = cab.transformed(np.eye(3), (l / 2 - cab_l / 2, 0.0, 0.0))
    box_x0 = -l / 2
    box_x1 = l / 2 - cab_l - 0.15
    cargo_box = box((box_x0, -w / 2, chassis_z), (box_x1, w / 2, h), Mat.FACADE, cargo)
    chassis = box((-l / 2 + 0.3, -w / 2 + 0.25, chassis_z - 0.35), (l / 2 - 0.2, w / 2 - 0.25, chassis_z),
                  Mat.TRIM, mt.TRIM)
    bumper = box((box_x0 - 0.0, -w / 2 + 0.1, chassis_z - 0.45), (box_x0 + 0.12, w / 2 - 0.1, chassis_z - 0.25),
                 Mat.TRIM, mt.TRIM)
    axles = [(cab_l * 0.5) / l]
    n_rear = 2 if l > 8.5 else 1
    for k in range(n_rear):
        axles.append(1.0 - (0.12 + 0.1 * k) * (8.0 / max(l, 8.0)))
    wp = {"wheel_radius": rw}
    wheels = _wheels(l, w, wp, axles)
    m = merge([cab, cargo_box, chassis, bumper, wheels])
    return m.scaled_to_box((-l / 2, -w / 2, 0.0), (l / 2, w / 2, h))

