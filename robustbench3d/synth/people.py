"""Pedestrian and cyclist meshes.

Frame: object-local, x forward (walking / riding direction), y left, z up, metres. Each builder
returns the mesh centred on its bounding box in x and y with its lowest point at z = 0, so the
KITTI box dimensions are the mesh extents (:func:`extents`).
"""

from __future__ import annotations

import numpy as np

from robustbench3d.synth import materials as mt
from robustbench3d.synth.materials import Mat
from robustbench3d.synth.mesh import BeamSet, Mesh, ellipsoid, merge, rot_y


def _v(x: float, y: float, z: float) -> np.ndarray:
    """A 3-vector (float64)."""
    return np.array([x, y, z], dtype=np.float64)


def _centered(m: Mesh) -> Mesh:
    lo, hi = m.bounds()
    return m.transformed(np.eye(3), (-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]))


def extents(m: Mesh) -> tuple[float, float, float]:
    """(l, w, h) of the mesh's bounding box, m."""
    lo, hi = m.bounds()
    return float(hi[0] - lo[0]), float(hi[1] - lo[1]), float(hi[2] - lo[2])


def pedestrian_mesh(height: float, rng: np.random.Generator) -> Mesh:
    """A walking person about ``height`` m tall (legs and arms swing with a random gait phase)."""
    s = height / 1.75
    u = rng.uniform
    shirt = mt.pick(rng, mt.CLOTH)
    pants = mt.pick(rng, mt.CLOTH)
    skin = mt.pick(rng, mt.SKIN, 0.03)
    hair = np.clip(mt.pick(rng, mt.CLOTH, 0.1) * 0.4, 0, 1)
    shoes = mt.TRIM
    stride = u(-0.45, 0.45)  # leg swing, rad
    hip_z = 0.92 * s
    shoulder_z = 1.45 * s
    hip_w = u(0.08, 0.10) * s
    girth = u(0.9, 1.25)
    parts = []
    beams = BeamSet()
    leg = 0.90 * s
    for side, ang in ((1.0, stride), (-1.0, -stride)):
        top = np.array([0.0, side * hip_w, hip_z])
        knee = top + rot_y(ang) @ np.array([0.0, 0.0, -0.48 * s])
        ankle = knee + rot_y(ang - 0.15 * abs(ang)) @ np.array([0.0, 0.0, -(leg - 0.48 * s)])
        beams.add(top, knee, 0.075 * s * girth, Mat.CLOTH, pants, 0.06 * s * girth)
        beams.add(knee, ankle, 0.058 * s * girth, Mat.CLOTH, pants, 0.045 * s)
        beams.add(ankle + _v(-0.05 * s, 0, -0.02), ankle + _v(0.17 * s, 0, -0.02), 0.045 * s, Mat.TRIM, shoes)
    torso0 = np.array([0.0, 0.0, hip_z - 0.05 * s])
    torso1 = np.array([u(-0.02, 0.05) * s, 0.0, shoulder_z])
    for side in (1.0, -1.0):
        beams.add(torso0 + _v(0, side * 0.07 * s, 0), torso1 + _v(0, side * 0.1 * s, 0),
                  0.11 * s * girth, Mat.CLOTH, shirt, 0.1 * s * girth, sides=6)
        arm_ang = -side * stride * 0.8
        sh = torso1 + np.array([0.0, side * 0.2 * s * min(girth, 1.1), -0.03 * s])
        elbow = sh + rot_y(arm_ang) @ np.array([0.0, side * 0.03 * s, -0.3 * s])
        hand = elbow + rot_y(arm_ang - 0.3) @ np.array([0.0, 0.0, -0.27 * s])
        beams.add(sh, elbow, 0.045 * s * girth, Mat.CLOTH, shirt, 0.04 * s)
        beams.add(elbow, hand, 0.037 * s, Mat.SKIN, skin, 0.03 * s)
    neck = torso1 + np.array([0.0, 0.0, 0.03 * s])
    beams.add(torso1, neck + _v(0, 0, 0.06 * s), 0.045 * s, Mat.SKIN, skin)
    head_c = neck + np.array([0.01 * s, 0.0, 0.17 * s])
    parts.append(ellipsoid(head_c, np.array([0.1, 0.08, 0.115]) * s, Mat.SKIN, skin))
    parts.append(ellipsoid(head_c + np.array([-0.015, 0.0, 0.03]) * s, np.array([0.1, 0.085, 0.1]) * s,
                           Mat.CLOTH, hair))
    if rng.random() < 0.3:  # backpack
        bag = mt.pick(rng, mt.CLOTH)
        beams.add(torso1 + _v(-0.17 * s, 0, -0.05 * s), torso1 + _v(-0.17 * s, 0, -0.4 * s), 0.13 * s,
                  Mat.CLOTH, bag, sides=4)
    parts.append(beams.mesh())
    return _centered(merge(parts))


def _bike_wheel(center: np.ndarray, radius: float, n: int = 12) -> Mesh:
    """Flat tyre ring (annulus of radii 0.86 r .. r, 4 cm thick) in the xz-plane."""
    a = 2 * np.pi * np.arange(n) / n
    outer = np.column_stack([radius * np.cos(a), radius * np.sin(a)])
    inner = 0.86 * outer
    rings = []
    for y in (-0.02, 0.02):
        rings.append(np.column_stack([outer[:, 0], np.full(n, y), outer[:, 1]]))
        rings.append(np.column_stack([inner[:, 0], np.full(n, y), inner[:, 1]]))
    v = np.concatenate(rings) + np.asarray(center)
    o0, i0, o1, i1 = 0, n, 2 * n, 3 * n
    i = np.arange(n)
    j = (i + 1) % n
    faces = []
    for a0, a1 in ((o0, i0), (o1, i1), (o0, o1), (i0, i1)):
        faces += [np.stack([a0 + i, a0 + j, a1 + j], 1), np.stack([a0 + i, a1 + j, a1 + i], 1)]
    f = np.concatenate(faces)
    return Mesh(v, f.astype(np.int64), np.full(len(f), Mat.TYRE, np.uint8),
                np.tile(np.asarray(mt.TYRE, np.float32), (len(f), 1)))


def cyclist_mesh(height: float, rng: np.random.Generator) -> Mesh:
    """A person riding a bicycle; ``height`` is the approximate total height (m)."""
    u = rng.uniform
    s = height / 1.74
    r = u(0.33, 0.36)
    wb = u(1.0, 1.1)
    frame = mt.pick(rng, mt.VAN_PAINT)
    shirt = mt.pick(rng, mt.CLOTH)
    pants = mt.pick(rng, mt.CLOTH)
    skin = mt.pick(rng, mt.SKIN, 0.03)
    rear = np.array([-wb / 2, 0.0, r])
    front = np.array([wb / 2, 0.0, r])
    crank = np.array([-wb / 2 + 0.42, 0.0, r - 0.02])
    seat = np.array([-wb / 2 + 0.3, 0.0, r + 0.55 * s])
    bar = np.array([wb / 2 - 0.12, 0.0, r + 0.62 * s])
    parts = [_bike_wheel(rear, r), _bike_wheel(front, r)]
    beams = BeamSet()
    stem = bar - _v(0.05, 0, 0.1)
    for p0, p1 in ((rear, crank), (rear, seat), (crank, seat), (crank, stem), (seat, stem), (front, bar)):
        beams.add(p0, p1, 0.018, Mat.METAL, frame, sides=4)
    half_bar = u(0.26, 0.31)
    beams.add(bar + _v(0, -half_bar, 0), bar + _v(0, half_bar, 0), 0.015, Mat.METAL, mt.TRIM, sides=4)
    beams.add(seat + _v(-0.08, 0, 0.03), seat + _v(0.1, 0, 0.03), 0.04, Mat.TRIM, mt.TRIM, sides=4)
    # rider
    lean = u(0.35, 0.7)  # forward lean of the torso, rad from vertical
    hip = seat + np.array([-0.02, 0.0, 0.08])
    shoulder = hip + 0.55 * s * np.array([np.sin(lean), 0.0, np.cos(lean)])
    phase = u(0, 2 * np.pi)
    for side, ph in ((1.0, phase), (-1.0, phase + np.pi)):
        pedal = crank + np.array([0.17 * np.cos(ph), side * 0.12, 0.17 * np.sin(ph)])
        hp = hip + _v(0, side * 0.1, 0)
        mid = 0.5 * (hp + pedal)
        dist = np.linalg.norm(pedal - hp)
        bend = np.sqrt(max(0.45 ** 2 * s * s - (dist / 2) ** 2, 0.0))
        knee = mid + bend * np.array([0.85, 0.0, 0.5]) / np.linalg.norm([0.85, 0.5])
        beams.add(hp, knee, 0.07 * s, Mat.CLOTH, pants, 0.055 * s)
        beams.add(knee, pedal, 0.05 * s, Mat.CLOTH, pants, 0.04 * s)
        sh = shoulder + _v(0, side * 0.19 * s, 0)
        hand = bar + _v(0, side * (half_bar - 0.04), 0)
        beams.add(sh, hand, 0.042 * s, Mat.CLOTH if rng.random() < 0.6 else Mat.SKIN, shirt, 0.035 * s)
    beams.add(hip, shoulder, 0.15 * s, Mat.CLOTH, shirt, 0.17 * s, sides=6)
    head_c = shoulder + np.array([0.1, 0.0, 0.2]) * s
    parts.append(ellipsoid(head_c, np.array([0.1, 0.08, 0.115]) * s, Mat.SKIN, skin))
    helmet = rng.random() < 0.5
    parts.append(ellipsoid(head_c + np.array([-0.01, 0.0, 0.035]) * s, np.array([0.12, 0.1, 0.1]) * s,
                           Mat.CLOTH, mt.pick(rng, mt.VAN_PAINT if helmet else mt.CLOTH)))
    parts.append(beams.mesh())
    return _centered(merge(parts))
