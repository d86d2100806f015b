"""Box overlaps: hand-computed cases, a shapely brute-force reference, and property tests."""

from __future__ import annotations

import math
import warnings
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from shapely.geometry import Polygon

from robustbench3d.eval.iou import (
    bev_iou,
    bev_overlap,
    bev_ratio,
    box3d_iou,
    box3d_overlap,
    clip_convex,
    footprint_corners,
    image_iou,
    image_overlap,
    polygon_area,
)

EPS = np.finfo(np.float64).eps


def box(x: float, z: float, l: float, w: float, ry: float = 0.0, y: float = 1.5, h: float = 1.5) -> np.ndarray:
    """One (1, 7) box in label order h, w, l, x, y, z, ry."""
    return np.array([[h, w, l, x, y, z, ry]], dtype=np.float64)


# ---- independent reference (shapely, corners written out here) -------------------------
def ref_polygon(b: np.ndarray) -> Polygon:
    _, w, l, x, _, z, ry = b
    c, s = math.cos(ry), math.sin(ry)
    pts = []
    for u, v in ((l / 2, w / 2), (l / 2, -w / 2), (-l / 2, -w / 2), (-l / 2, w / 2)):
        pts.append((x + c * u + s * v, z - s * u + c * v))
    return Polygon(pts)


def ref_bev_iou(a: np.ndarray, b: np.ndarray) -> float:
    pa, pb = ref_polygon(a), ref_polygon(b)
    inter = pa.intersection(pb).area
    union = pa.area + pb.area - inter
    return inter / union if union > 0 else 0.0


def _ref_corners(b: np.ndarray) -> list[tuple[float, float]]:
    return list(ref_polygon(b).exterior.coords)[:4]


def exact_bev_iou(a: np.ndarray, b: np.ndarray) -> float:
    """BEV IoU of the float corners in exact rational arithmetic (scalar convex clipping).

    GEOS (shapely) can be wrong when edges nearly coincide (e.g. boxes sharing an edge up to
    round-off), so degenerate pairs are checked against this instead.
    """

    def area(poly: list[tuple[Fraction, Fraction]]) -> Fraction:
        n = len(poly)
        return sum((poly[i][0] * poly[(i + 1) % n][1] - poly[(i + 1) % n][0] * poly[i][1] for i in range(n)),
                   Fraction(0)) / 2

    pa = [(Fraction(x), Fraction(z)) for x, z in _ref_corners(a)]
    pb = [(Fraction(x), Fraction(z)) for x, z in _ref_corners(b)]
    if area(pb) < 0:
        pb.reverse()
    if area(pa) < 0:
        pa.reverse()
    out = pa
    for i in range(4):
        (ax, az), (bx, bz) = pb[i], pb[(i + 1) % 4]

        def side(p: tuple[Fraction, Fraction], ax=ax, az=az, bx=bx, bz=bz) -> Fraction:
            return (bx - ax) * (p[1] - az) - (bz - az) * (p[0] - ax)

        src, out = out, []
        for k in range(len(src)):
            p, q = src[k], src[(k + 1) % len(src)]
            sp, sq = side(p), side(q)
            if sp >= 0:
                out.append(p)
            if (sp >= 0) != (sq >= 0):
                t = sp / (sp - sq)
                out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
        if not out:
            return 0.0
    inter = area(out) if len(out) >= 3 else Fraction(0)
    union = area(pa) + area(pb) - inter
    return float(inter / union) if union > 0 else 0.0


def ref_3d_iou(a: np.ndarray, b: np.ndarray) -> float:
    inter = ref_polygon(a).intersection(ref_polygon(b)).area
    dy = max(0.0, min(a[4], b[4]) - max(a[4] - a[0], b[4] - b[0]))
    vi = inter * dy
    union = a[0] * a[1] * a[2] + b[0] * b[1] * b[2] - vi
    return vi / union if union > 0 else 0.0


# ---- hand-computed cases ----------------------------------------------------------------
def test_image_overlap_hand_cases() -> None:
    a = np.array([[0.0, 0.0, 10.0, 10.0]])
    assert image_overlap(a, np.array([[5.0, 0.0, 15.0, 10.0]]))[0] == pytest.approx(50 / 150)
    assert image_overlap(a, np.array([[10.0, 0.0, 20.0, 10.0]]))[0] == 0.0  # touching: zero width
    assert image_overlap(a, np.array([[20.0, 20.0, 30.0, 30.0]]))[0] == 0.0
    # "det" criterion: intersection over the first (detection) box, e.g. a det inside a DontCare area
    assert image_overlap(a, np.array([[-5.0, -5.0, 50.0, 50.0]]), "det")[0] == 1.0
    assert image_overlap(np.array([[0.0, 0.0, 100.0, 100.0]]), np.array([[0.0, 0.0, 70.0, 100.0]]))[0] == 0.7
    np.testing.assert_allclose(image_iou(a, np.vstack([a, a + 5])), [[1.0, 25 / 175]])



def test_image_overlap_below_one_pixel_and_float32_boxes() -> None:
    a = np.array([[0.0, 0.0, 10.0, 10.0]])
    # overlaps narrower than a pixel still count: w = 0.5 (inter 5, union 195), h = 0.25 (inter 2.5, union 197.5)
    assert image_overlap(a, np.array([[9.5, 0.0, 19.5, 10.0]]))[0] == pytest.approx(1 / 39, abs=1e-15)
    assert image_overlap(a, np.array([[0.0, 9.75, 10.0, 19.75]]))[0] == pytest.approx(1 / 79, abs=1e-15)
    # float32 boxes are measured in float64: 4097^2 = 16785409 is no float32 (it would round to 16785408);
    # inter 4096^2 = 16777216, union 2 * 16785409 - 16777216 = 16793602, all exact in float64
    d, g = np.array([[0, 0, 4097, 4097]], np.float32), np.array([[1, 1, 4098, 4098]], np.float32)
    assert image_overlap(d, g)[0] == 16777216 / 16793602
    assert image_overlap(g, d)[0] == 16777216 / 16793602
    assert image_overlap(d, g, "det")[0] == 16777216 / 16785409


def test_polygon_area_by_hand() -> None:
    unit = np.array([[[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]])
    assert polygon_area(unit).tolist() == [1.0]
    assert polygon_area(unit[:, ::-1]).tolist() == [-1.0]  # clockwise: negative
    # only the first ``count`` vertices: the triangle (1, 1), (3, 1), (1, 3) of area 2; the 4th vertex is ignored
    tri = np.array([[[1.0, 1.0], [3.0, 1.0], [1.0, 3.0], [5.0, 6.0]]])
    assert polygon_area(tri, np.array([3])).tolist() == [2.0]  # the edge (5, 6) -> (1, 1) would add -1 / 2
    # float32 corners are summed in float64: 4097^2 = 16785409 exactly (float32 would round to 16785408)
    sq = np.array([[[0, 0], [4097, 0], [4097, 4097], [0, 4097]]], np.float32)
    assert polygon_area(sq).tolist() == [16785409.0]


def test_3d_overlap_of_float32_boxes_is_computed_in_float64() -> None:
    """The heights of float32 boxes are subtracted in float64 (100.1 - 1.3 rounds differently in float32):
    the overlap equals that of the same values given as float64, and 5.6 / 15.2 by hand (footprints 4 x 2
    shifted 0.5 m: 7 of 8 m^2; y spans [98.8, 100.1] and [99.3, 100.6]: 0.8 of 1.3 m)."""
    a = np.array([[1.3, 2.0, 4.0, 0.0, 100.1, 0.0, 0.0]], np.float32)
    b = np.array([[1.3, 2.0, 4.0, 0.5, 100.6, 0.0, 0.0]], np.float32)
    expect = box3d_overlap(a.astype(np.float64), b.astype(np.float64))[0]
    assert expect == pytest.approx(5.6 / 15.2, rel=1e-6)
    assert box3d_overlap(a, b)[0] == expect and box3d_iou(a, b)[0, 0] == expect
    assert box3d_overlap(b, a)[0] == box3d_overlap(b.astype(np.float64), a.astype(np.float64))[0]



def test_bev_overlap_and_clipping_of_float32_boxes_are_computed_in_float64() -> None:
    """Footprint areas of float32 boxes (4.1 x 1.7 is no float32 product) and the clipped polygon are
    float64: the same overlap and vertices as for the same values given as float64."""
    a = np.array([[1.5, 1.7, 4.1, 0.3, 1.5, 10.2, 0.3]], np.float32)
    b = np.array([[1.5, 1.8, 3.9, 0.9, 1.5, 10.5, -0.2]], np.float32)
    a64, b64 = a.astype(np.float64), b.astype(np.float64)
    expect = bev_overlap(a64, b64)[0]
    assert 0.4 < expect < 0.5
    assert bev_overlap(a, b)[0] == expect and bev_overlap(b, a)[0] == bev_overlap(b64, a64)[0]
    assert footprint_corners(a).tobytes() == footprint_corners(a64).tobytes()  # cos, sin of a float32 yaw
    sa, sb = footprint_corners(a64).astype(np.float32), footprint_corners(b64).astype(np.float32)
    want, n_want, _ = clip_convex(sa.astype(np.float64), sb.astype(np.float64))
    for subject, clip in ((sa, sb.astype(np.float64)), (sa.astype(np.float64), sb)):
        got, n_got, overflow = clip_convex(subject, clip)
        assert overflow is False and n_got.tolist() == n_want.tolist() and got.dtype == np.float64
        assert got.tobytes() == want.tobytes()
    # a float32 quadrilateral clipped by a square to a heptagon: its edge vectors (3.1 - -0.7, ...) are float64 too
    quad = np.array([[[-0.7, 0.3], [3.1, -0.9], [2.3, 3.9], [0.1, 2.1]]], np.float32)
    square = np.array([[[0.0, 0.0], [2.0, 0.0], [2.0, 2.5], [0.0, 2.5]]], np.float32)
    want, n_want, _ = clip_convex(quad.astype(np.float64), square.astype(np.float64))
    got, n_got, _ = clip_convex(quad, square)
    assert n_got.tolist() == n_want.tolist() and n_want[0] >= 4 and got.tobytes() == want.tobytes()


def test_ratio_of_zero_areas_is_zero_and_written() -> None:
    """Zero (or negative, non-finite) denominators give 0: written, not left in uninitialised memory (the
    result would reuse the freshly freed block full of 0.7), and without numpy's 'where without out' warning."""
    num, area = np.full(64, 0.5), np.zeros(64)
    junk = np.full(64, 0.7)
    del junk
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not bev_ratio(num, area, area, "det").any()
    junk = np.full(64, 0.7)
    del junk
    assert not bev_ratio(num, area, np.zeros(64)).any()
    assert bev_ratio(np.array([1.0, 1.0, 1.0]), np.array([2.0, -1.0, np.inf]), np.zeros(3), "det").tolist() == [
        0.5, 0.0, 0.0]


def test_bev_hand_cases() -> None:
    sq = box(0, 0, 2, 2)
    assert bev_overlap(sq, box(1, 0, 2, 2))[0] == pytest.approx(1 / 3, abs=1e-15)
    assert bev_overlap(sq, box(0, 1, 2, 2))[0] == pytest.approx(1 / 3, abs=1e-15)
    # A square and itself turned by 45 degrees: the intersection is a regular octagon, IoU = 1/sqrt(2).
    assert bev_overlap(sq, box(0, 0, 2, 2, ry=math.pi / 4))[0] == pytest.approx(1 / math.sqrt(2), abs=1e-14)
    assert bev_overlap(sq, box(2, 0, 2, 2))[0] == 0.0  # sharing an edge only
    assert bev_overlap(sq, box(5, 5, 2, 2))[0] == 0.0
    assert bev_overlap(box(0, 0, 1, 1), box(0, 0, 4, 2))[0] == pytest.approx(1 / 8, abs=1e-15)
    # ry = pi/2 turns a 4 x 2 box into a 2 x 4 one: against the unturned box, inter 4, union 12.
    assert bev_overlap(box(0, 0, 4, 2), box(0, 0, 4, 2, ry=math.pi / 2))[0] == pytest.approx(1 / 3, abs=1e-14)
    # "det" criterion: the detection's own area, e.g. fully inside a large DontCare footprint.
    assert bev_overlap(box(0, 0, 1, 1), box(0, 0, 10, 10), "det")[0] == pytest.approx(1.0, abs=1e-15)
    assert bev_overlap(box(0.5, 0, 1, 1), box(0, 0, 1, 1), "det")[0] == pytest.approx(0.5, abs=1e-15)


def test_3d_hand_cases() -> None:
    a = box(0, 0, 4, 2, y=2.0, h=2.0)  # spans y in [0, 2]
    assert box3d_overlap(a, box(0, 0, 4, 2, y=3.0, h=2.0))[0] == pytest.approx(1 / 3, abs=1e-15)
    assert box3d_overlap(a, box(0, 0, 4, 2, y=4.0, h=2.0))[0] == 0.0  # stacked, touching
    assert box3d_overlap(a, box(2, 0, 4, 2, y=2.0, h=2.0))[0] == pytest.approx(1 / 3, abs=1e-15)
    inner = box(0, 0, 4, 2, y=2.0, h=1.0)  # the lower half of a
    assert box3d_overlap(inner, a, "det")[0] == pytest.approx(1.0, abs=1e-15)
    assert box3d_overlap(a, inner, "det")[0] == pytest.approx(0.5, abs=1e-15)
    assert box3d_overlap(inner, a)[0] == pytest.approx(0.5, abs=1e-15)


def test_devkit_dontcare_lines_never_overlap_in_bev_or_3d() -> None:
    dontcare = np.array([[-1.0, -1.0, -1.0, -1000.0, -1000.0, -1000.0, -10.0]])
    car = box(3, 20, 3.9, 1.6)
    assert bev_overlap(car, dontcare, "det")[0] == 0.0
    assert box3d_overlap(car, dontcare, "det")[0] == 0.0
    # Negative dimensions are taken by magnitude: a -1 x -1 footprint is a 1 m square (turned by -10 rad).
    corners = footprint_corners(dontcare)[0]
    np.testing.assert_allclose(np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1), 1.0, atol=1e-9)
    np.testing.assert_allclose(corners.mean(axis=0), [-1000.0, -1000.0], atol=1e-9)


def test_identical_boxes_give_exactly_one() -> None:
    rng = np.random.default_rng(1)
    b = np.column_stack([rng.uniform(1, 3, 500), rng.uniform(0.5, 3, 500), rng.uniform(0.5, 12, 500),
                         rng.uniform(-60, 60, 500), rng.uniform(-2, 3, 500), rng.uniform(0, 80, 500),
                         rng.uniform(-math.pi, math.pi, 500)])
    assert np.all(bev_overlap(b, b) == 1.0)
    assert np.all(box3d_overlap(b, b) == 1.0)


# ---- brute-force reference ----------------------------------------------------------------
def _random_boxes(rng: np.random.Generator, n: int, spread: float) -> np.ndarray:
    return np.column_stack([
        rng.uniform(0.5, 3, n), rng.uniform(0.3, 3, n), rng.uniform(0.3, 8, n),
        rng.uniform(-spread, spread, n), rng.uniform(-1, 1, n), rng.uniform(-spread, spread, n),
        rng.uniform(-math.pi, math.pi, n),
    ])


def test_matches_shapely_reference_on_random_pairs() -> None:
    rng = np.random.default_rng(7)
    a, b = _random_boxes(rng, 1500, 3.0), _random_boxes(rng, 1500, 3.0)
    # Near-degenerate pairs too: shared centre and yaw, tiny yaw differences, yaw + pi, shared edges.
    b[:200, 3:] = a[:200, 3:]
    b[200:400, 3:6] = a[200:400, 3:6]
    b[200:400, 6] = a[200:400, 6] + rng.normal(0, 1e-9, 200)
    b[400:500] = a[400:500]
    b[400:500, 6] += math.pi
    b[500:600] = a[500:600]
    b[500:600, 3] += a[500:600, 2] * np.cos(a[500:600, 6])  # shift by a length along the box axis
    b[500:600, 5] -= a[500:600, 2] * np.sin(a[500:600, 6])
    # Close neighbours (large overlaps in general position).
    b[600:1100] = a[600:1100]
    b[600:1100, 3:6] += rng.normal(0, 0.3, (500, 3))
    b[600:1100, 6] += rng.normal(0, 0.3, 500)
    b[600:1100, :3] *= 1 + rng.normal(0, 0.1, (500, 3))
    fast_bev, fast_3d = bev_overlap(a, b), box3d_overlap(a, b)
    # General position: shapely.
    ref_bev = np.array([ref_bev_iou(p, q) for p, q in zip(a[600:], b[600:], strict=True)])
    ref_3d = np.array([ref_3d_iou(p, q) for p, q in zip(a[600:], b[600:], strict=True)])
    np.testing.assert_allclose(fast_bev[600:], ref_bev, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fast_3d[600:], ref_3d, rtol=0, atol=1e-9)
    assert (ref_bev > 0.5).sum() > 100 and (ref_3d > 0.5).sum() > 50  # large overlaps are exercised
    # Near-degenerate pairs: exact rational arithmetic.
    exact = np.array([exact_bev_iou(p, q) for p, q in zip(a[:600], b[:600], strict=True)])
    np.testing.assert_allclose(fast_bev[:600], exact, rtol=0, atol=1e-9)
    np.testing.assert_allclose(bev_iou(a[:30], b[:40]),
                               [[ref_bev_iou(p, q) for q in b[:40]] for p in a[:30]], rtol=0, atol=1e-9)
    np.testing.assert_allclose(box3d_iou(a[:30], b[:40]),
                               [[ref_3d_iou(p, q) for q in b[:40]] for p in a[:30]], rtol=0, atol=1e-9)


# ---- properties -----------------------------------------------------------------------------
size = st.floats(1e-6, 30.0).map(float)
coord = st.floats(-1e4, 1e4)
yaw = st.one_of(st.floats(-math.pi, math.pi),
                st.sampled_from([math.pi, -math.pi, math.pi - 1e-12, -math.pi + 1e-12, 0.0, math.pi / 2]))
boxes7 = st.tuples(size, size, size, coord, st.floats(-5, 5), coord, yaw).map(lambda t: np.array([t]))


def _tolerance(a: np.ndarray, b: np.ndarray) -> float:
    """Round-off bound: coordinates' precision relative to the smallest footprint side."""
    extent = max(abs(a[0, 3]), abs(a[0, 5]), abs(b[0, 3]), abs(b[0, 5]), 1.0) + max(a[0, :3].max(), b[0, :3].max())
    smallest = min(a[0, 1], a[0, 2], b[0, 1], b[0, 2], a[0, 0], b[0, 0])
    return 1e-9 + 256 * EPS * extent / smallest


@settings(max_examples=300, deadline=None)
@given(boxes7, boxes7)
def test_overlap_is_finite_in_range_and_symmetric(a: np.ndarray, b: np.ndarray) -> None:
    for f in (bev_overlap, box3d_overlap):
        ab, ba = f(a, b)[0], f(b, a)[0]
        assert np.isfinite(ab) and 0.0 <= ab <= 1.0
        assert abs(ab - ba) <= _tolerance(a, b)
    for f in (bev_overlap, box3d_overlap):
        assert 0.0 <= f(a, b, "det")[0] <= 1.0


@settings(max_examples=300, deadline=None)
@given(boxes7)
def test_identical_boxes_overlap_one(a: np.ndarray) -> None:
    assert bev_overlap(a, a)[0] == 1.0
    assert box3d_overlap(a, a)[0] == 1.0


@settings(max_examples=300, deadline=None)
@given(boxes7, st.floats(-0.5, 0.5), st.floats(-0.5, 0.5), st.floats(-3, 3), st.floats(-3, 3),
       st.floats(-math.pi, math.pi), st.floats(-2, 2), st.floats(-2, 2), st.floats(-1, 1))
def test_invariant_under_a_common_rigid_motion(a: np.ndarray, dx: float, dz: float, dyaw: float, ds: float,
                                              theta: float, tx: float, tz: float, ty: float) -> None:
    # b: a's neighbour (offset in units of a's size, turned, rescaled), so the pair overlaps often.
    b = a.copy()
    b[0, 3] += dx * a[0, 2]
    b[0, 5] += dz * a[0, 1]
    b[0, 6] += dyaw
    b[0, 1:3] *= math.exp(ds / 3)

    def move(x: np.ndarray) -> np.ndarray:
        out = x.copy()
        c, s = math.cos(theta), math.sin(theta)
        out[0, 3] = c * x[0, 3] + s * x[0, 5] + tx * 10
        out[0, 5] = -s * x[0, 3] + c * x[0, 5] + tz * 10
        out[0, 4] += ty
        out[0, 6] += theta
        return out

    tol = _tolerance(a, b) + _tolerance(move(a), move(b))
    for f in (bev_overlap, box3d_overlap):
        assert abs(f(a, b)[0] - f(move(a), move(b))[0]) <= tol


@settings(max_examples=200, deadline=None)
@given(st.floats(1e-3, 50.0), st.floats(1e-6, 1e-3), st.floats(-1, 1), st.floats(-math.pi, math.pi),
       st.floats(-1e4, 1e4), st.floats(-1e4, 1e4))
def test_extreme_aspect_ratios_match_reference(long: float, thin: float, shift: float, ry: float,
                                               x: float, z: float) -> None:
    assume(long / thin > 100)
    a = box(x, z, long, thin, ry)
    b = box(x + shift * long * math.cos(ry), z - shift * long * math.sin(ry), long, thin, ry + 1e-3)
    got = bev_overlap(a, b)[0]
    assert np.isfinite(got) and 0.0 <= got <= 1.0
    # Relative to the box centres, shapely is exact enough to compare against.
    a0, b0 = a.copy(), b.copy()
    a0[0, [3, 5]] -= [x, z]
    b0[0, [3, 5]] -= [x, z]
    assert abs(got - ref_bev_iou(a0[0], b0[0])) <= _tolerance(a, b) * 10


def test_yaw_wraps_around_pi() -> None:
    a = box(3.0, 7.0, 4.0, 1.7, ry=math.pi - 1e-12)
    b = box(3.0, 7.0, 4.0, 1.7, ry=-math.pi + 1e-12)
    assert bev_overlap(a, b)[0] == pytest.approx(1.0, abs=1e-9)
    assert box3d_overlap(a, b)[0] == pytest.approx(1.0, abs=1e-9)


def test_far_from_origin_and_tiny_boxes_stay_exact() -> None:
    # 1e-6 m boxes 1e4 m away: offsets are taken relative to the GT centre, so IoU keeps ~6 digits.
    a = box(1e4, -1e4, 2e-6, 1e-6)
    b = box(1e4 + 1e-6, -1e4, 2e-6, 1e-6)
    assert bev_overlap(a, b)[0] == pytest.approx(1 / 3, rel=1e-5)
    assert not np.isnan(box3d_overlap(a, b)).any()


def test_degenerate_footprints_give_zero_not_nan() -> None:
    zero = box(0, 0, 0.0, 0.0)
    assert bev_overlap(zero, zero)[0] == 0.0
    assert bev_overlap(zero, box(0, 0, 2, 2))[0] == 0.0
    assert box3d_overlap(box(0, 0, 2, 2, h=0.0), box(0, 0, 2, 2, h=0.0))[0] == 0.0
    assert bev_overlap(box(0, 0, 2, 2), zero, "det")[0] == 0.0


@settings(max_examples=300, deadline=None)
@given(boxes7, st.sampled_from([0.0, 1e-15, 1e-9, math.pi / 2, math.pi]), st.sampled_from([0.0, 0.5, 1.0]))
def test_clipping_never_overflows_on_near_degenerate_pairs(a: np.ndarray, dyaw: float, shift: float) -> None:
    b = a.copy()
    b[0, 6] += dyaw
    b[0, 3] += shift * a[0, 2] * math.cos(a[0, 6])
    b[0, 5] -= shift * a[0, 2] * math.sin(a[0, 6])
    origin = a[:, [3, 5]]
    _, count, overflow = clip_convex(footprint_corners(b, origin), footprint_corners(a, origin))
    assert not overflow
    assert count[0] <= 8
