"""The roof object: a deformable, per-vertex coloured icosphere, its box constraint and its smoothness.

Object frame (metres): centre at the origin, axes those of the car it sits on (the KITTI box's local
frame, :func:`robustbench3d.geometry.box_corners`): x along the car's length (its heading), y down,
z along its width. The template is an icosphere (:func:`robustbench3d.sensors.mesh.icosphere`) of a
:class:`Family`: its subdivision level (:data:`LEVELS`: 2, 3 or 4, i.e. 162, 642 or 2562 vertex colours)
and radius (:data:`RADIUS_RANGE`, m); the default family (:data:`DEFAULT_FAMILY`, ``l2-r0.40``) is the
level-2 icosphere of radius :data:`RADIUS` (162 vertices, 320 faces). An object is its family's template
displaced per vertex, with a per-vertex RGB colour in [0, 1].

Box constraint: every vertex stays inside the axis-aligned box ``|v| <= bounds`` (default the
initial sphere's bounding box, +-radius: +-0.4 m for the default family; each half extent in [1 mm, 1 m],
:data:`MAX_BOUND_M`). Two implementations:

* tanh reparametrisation (:func:`tanh_vertices`, :meth:`RoofObject.torch_vertices`), used by the
  optimisation and by :func:`random_shape`: ``v = b * tanh(atanh((1 - eps) * v0 / b) + delta)``,
  smooth and inside the box for every ``delta``;
* projection (:func:`clamp_to_box`), a clamp for projected-gradient steps.
  :class:`RoofObject` itself projects nothing: it refuses vertices outside the box.

A :class:`RoofObject` holds its arrays at the precision of the object file (vertices float32
values rounded towards the centre so they stay in the box, colours multiples of 1/255), so writing
and reading it back (:mod:`robustbench3d.attacks.objectfile`) is exact. The template is stored the
same way, so the undeformed sphere has displacement exactly 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from typing import TYPE_CHECKING

import numpy as np

from robustbench3d.sensors.mesh import icosphere

if TYPE_CHECKING:
    import torch

#: The default family's template: the level-2 icosphere of radius 0.40 m (162 vertices, 320 faces).
RADIUS = 0.40
LEVEL = 2
N_VERTICES = 162
N_FACES = 320
#: Half extents (m) of the default box: the bounding box of the initial sphere.
BOUNDS = (RADIUS, RADIUS, RADIUS)
#: The icosphere levels an object family may have: 162, 642 or 2562 vertices, each with its own colour (the
#: colour freedom of the dose-response sweep, issue #36). Level 5 (10242 vertices) would put ~20 vertices in a
#: pixel of a car at 10 m and take ~4x level 4's render time for nothing the sensors resolve.
LEVELS = (2, 3, 4)
#: The radius range of an object family (m), whole centimetres (the family's name records the radius to the
#: centimetre). It stays a roof object: a KITTI car's roof is about 1.3 m by 1.8 m, so a sphere of radius 0.6 m
#: (1.2 m across) still fits on it at the +-5 cm EOT jitter; below 0.2 m a sphere is a few LiDAR returns at
#: 20 m and no longer a dose worth measuring. Its box is +-radius (within MAX_BOUND_M).
RADIUS_RANGE = (0.2, 0.6)
#: The range of each half extent of a box (m). At most 1 m: the object fits in a 2 m cube, about the size
#: of a KITTI car's roof (a car is ~1.6 m wide and its roof ~1.3 m by ~1.8 m), so anything larger is no
#: longer a roof object (and a 1e6 m box takes minutes and gigabytes to render, a 3e38 m one nothing at
#: all). At least 1 mm: a smaller box holds no object the LiDAR (2 cm range noise) or a pixel can resolve.
MIN_BOUND_M, MAX_BOUND_M = 1e-3, 1.0
#: The (1 - eps) shrink inside atanh, so that template vertices on the box faces map to finite values.
TANH_EPS = 1e-3
#: The benign sphere's colour (8-bit mid grey).
NEUTRAL_GREY = 128 / 255


def check_family(level: object, radius: object) -> tuple[int, float]:
    """(level, radius rounded to the centimetre) of an object family; ValueError ``field 'level': ...`` or
    ``field 'radius': ...`` naming the range otherwise (level one of :data:`LEVELS`, radius in
    :data:`RADIUS_RANGE` m in whole centimetres)."""
    if isinstance(level, (bool, np.bool_)) or not isinstance(level, (int, np.integer)) or int(level) not in LEVELS:
        raise ValueError(f"field 'level': expected an icosphere level in {{{', '.join(map(str, LEVELS))}}} "
                         f"({', '.join(str(_n_vertices(k)) for k in LEVELS)} vertex colours), got {level!r}")
    lo, hi = RADIUS_RANGE
    ok = (isinstance(radius, (int, float, np.integer, np.floating)) and not isinstance(radius, (bool, np.bool_))
          and bool(np.isfinite(radius)) and lo - 1e-9 <= float(radius) <= hi + 1e-9
          and abs(float(radius) * 100 - round(float(radius) * 100)) <= 1e-6)
    if not ok:
        raise ValueError(f"field 'radius': expected a radius in [{lo:g}, {hi:g}] m in whole centimetres (a roof "
                         f"object on a KITTI car roof, ~1.3 x 1.8 m), got {radius!r}")
    return int(level), round(float(radius), 2)


def _n_vertices(level: int) -> int:
    return 10 * 4 ** level + 2


@dataclass(frozen=True)
class Family:
    """An object family: the icosphere template of subdivision ``level`` (:data:`LEVELS`) and ``radius`` (m,
    :data:`RADIUS_RANGE`, rounded to the centimetre); checked on construction (:func:`check_family`)."""

    level: int = LEVEL
    radius: float = RADIUS

    def __post_init__(self) -> None:
        level, radius = check_family(self.level, self.radius)
        object.__setattr__(self, "level", level)
        object.__setattr__(self, "radius", radius)

    @property
    def name(self) -> str:
        """``l<level>-r<radius, 2 decimals>``, e.g. ``l2-r0.40`` for the default family."""
        return f"l{self.level}-r{self.radius:.2f}"

    @property
    def bounds(self) -> tuple[float, float, float]:
        """Half extents (m) of the family's box: the bounding box of its sphere, +-radius."""
        return (self.radius, self.radius, self.radius)

    @property
    def n_vertices(self) -> int:
        """10 * 4^level + 2."""
        return _n_vertices(self.level)

    @property
    def n_faces(self) -> int:
        """20 * 4^level."""
        return 20 * 4 ** self.level

    @property
    def is_default(self) -> bool:
        return self == DEFAULT_FAMILY

    def record(self) -> dict[str, object]:
        """The object file's ``template`` record of this family."""
        return {"kind": "icosphere", "level": self.level, "radius": self.radius, "vertices": self.n_vertices,
                "faces": self.n_faces}


DEFAULT_FAMILY = Family()


def to_file_precision(vertices: np.ndarray) -> np.ndarray:
    """(V, 3) float64 copy of ``vertices`` rounded to float32 values, each rounded towards 0 where
    rounding to nearest would move it outwards (so a vertex inside the box stays inside)."""
    v = np.asarray(vertices, dtype=np.float64)
    q32 = v.astype(np.float32)
    out = np.abs(q32.astype(np.float64)) > np.abs(v)
    q32[out] = np.nextafter(q32[out], np.float32(0))
    return q32.astype(np.float64)


def colors_to_file_precision(colors: np.ndarray) -> np.ndarray:
    """(V, 3) float64 colours rounded to multiples of 1/255 (8 bits per channel)."""
    return np.round(np.asarray(colors, dtype=np.float64) * 255.0) / 255.0


@cache
def _template(family: Family) -> tuple[np.ndarray, np.ndarray]:
    v, f = icosphere(family.level, family.radius)
    v = to_file_precision(v)
    v.flags.writeable = f.flags.writeable = False
    return v, f


def template_vertices(family: Family = DEFAULT_FAMILY) -> np.ndarray:
    """(V, 3) read-only template vertices of ``family`` (icosphere(level, radius) at file precision), m;
    (162, 3) of icosphere(2, 0.40) for the default family."""
    return _template(family)[0]


def template_faces(family: Family = DEFAULT_FAMILY) -> np.ndarray:
    """(F, 3) read-only int64 template faces of ``family`` (counter-clockwise seen from outside; (320, 3) for
    the default family)."""
    return _template(family)[1]


def check_bounds(bounds: object) -> np.ndarray:
    """``bounds`` as a (3,) float64 array of half extents, each in [:data:`MIN_BOUND_M`, :data:`MAX_BOUND_M`]
    m; ValueError ``field 'bounds': ...`` otherwise."""
    try:
        b = np.asarray(bounds, dtype=np.float64)
    except (TypeError, ValueError):
        b = np.full(1, np.nan)
    if b.shape != (3,) or not np.all((b >= MIN_BOUND_M) & (b <= MAX_BOUND_M)):
        raise ValueError(f"field 'bounds': expected three half extents in [{MIN_BOUND_M:g}, {MAX_BOUND_M:g}] m "
                         f"(the object must fit in a {2 * MAX_BOUND_M:g} m cube on a car roof), got {bounds!r}")
    return b


def object_problems(vertices: np.ndarray, colors: np.ndarray, bounds: np.ndarray,
                    tolerance: float = 0.0, n_vertices: int = N_VERTICES) -> list[tuple[str, str]]:
    """What is wrong with an object's arrays, as (field, problem) pairs (empty if nothing); vertices
    may leave the box by ``tolerance`` m; ``n_vertices``: the family's vertex count."""
    problems: list[tuple[str, str]] = []
    for name, arr in (("vertices", vertices), ("colors", colors)):
        if arr.shape != (n_vertices, 3):
            problems.append((name, f"expected shape ({n_vertices}, 3), got {arr.shape}"))
        elif not np.all(np.isfinite(arr)):
            bad = int(np.argwhere(~np.isfinite(arr))[0, 0])
            problems.append((name, f"non-finite value (NaN or inf) at vertex {bad}"))
    if problems:
        return problems
    outside = np.any(np.abs(vertices) > bounds + tolerance, axis=1)
    if outside.any():
        k = int(np.argmax(outside))
        problems.append(("vertices", f"{int(outside.sum())} vertices outside the box +-{tuple(bounds.tolist())} m "
                                     f"around the centre (first: vertex {k} at {tuple(vertices[k].tolist())})"))
    bad_color = np.any((colors < 0) | (colors > 1), axis=1)
    if bad_color.any():
        k = int(np.argmax(bad_color))
        problems.append(("colors", f"{int(bad_color.sum())} colours outside [0, 1] "
                                   f"(first: vertex {k} with {tuple(colors[k].tolist())})"))
    return problems


class RoofObject:
    """One universal roof object (object frame, see the module doc) of a :class:`Family` (default
    :data:`DEFAULT_FAMILY`).

    Build it from a displacement of its family's template (``RoofObject(displacement, colors)``) or from
    vertex positions (:meth:`from_vertices`); ``bounds`` default to the family's (+-radius). Vertices outside
    the box or colours outside [0, 1] raise ValueError (project first with :func:`clamp_to_box`, or use
    :func:`tanh_vertices`). The arrays are stored read-only at file precision (see the module doc).
    """

    __slots__ = ("_bounds", "_colors", "_family", "_vertices")

    def __init__(self, displacement: np.ndarray | None = None, colors: np.ndarray | None = None,
                 bounds: object = None, *, family: Family = DEFAULT_FAMILY) -> None:
        n = family.n_vertices
        d = np.zeros((n, 3)) if displacement is None else np.asarray(displacement, dtype=np.float64)
        if d.shape != (n, 3):
            raise ValueError(f"RoofObject: field 'displacement': expected shape ({n}, 3), got {d.shape}")
        self._init(template_vertices(family) + d, colors, bounds, family)

    @classmethod
    def from_vertices(cls, vertices: np.ndarray, colors: np.ndarray | None = None,
                      bounds: object = None, *, family: Family = DEFAULT_FAMILY) -> RoofObject:
        """The object of ``family`` whose (V, 3) object-frame vertices are ``vertices`` (m)."""
        obj = cls.__new__(cls)
        obj._init(np.asarray(vertices, dtype=np.float64), colors, bounds, family)
        return obj

    def _init(self, vertices: np.ndarray, colors: np.ndarray | None, bounds: object, family: Family) -> None:
        if not isinstance(family, Family):
            raise ValueError(f"RoofObject: field 'family': expected a Family, got {family!r}")
        b = check_bounds(family.bounds if bounds is None else bounds)
        n = family.n_vertices
        c = np.full((n, 3), NEUTRAL_GREY) if colors is None else np.asarray(colors, dtype=np.float64)
        problems = object_problems(vertices, c, b, n_vertices=n)
        if problems:
            field, problem = problems[0]
            raise ValueError(f"RoofObject: field '{field}': {problem}")
        self._vertices = to_file_precision(vertices)
        self._colors = colors_to_file_precision(c)
        self._bounds = b
        self._family = family
        for arr in (self._vertices, self._colors, self._bounds):
            arr.flags.writeable = False

    @property
    def family(self) -> Family:
        """The object's family (its template's level and radius)."""
        return self._family

    @property
    def template(self) -> np.ndarray:
        return template_vertices(self._family)

    @property
    def faces(self) -> np.ndarray:
        return template_faces(self._family)

    @property
    def bounds(self) -> np.ndarray:
        """(3,) half extents of the allowed box, m."""
        return self._bounds

    @property
    def colors(self) -> np.ndarray:
        """(V, 3) RGB in [0, 1] (multiples of 1/255)."""
        return self._colors

    @property
    def displacement(self) -> np.ndarray:
        """(V, 3) vertex offsets from the template, m."""
        return self._vertices - template_vertices(self._family)

    def vertices(self) -> np.ndarray:
        """(V, 3) float64 object-frame vertices (a fresh array), inside the box."""
        return self._vertices.copy()

    def torch_vertices(self, delta: torch.Tensor | None = None, eps: float = TANH_EPS) -> torch.Tensor:
        """The tanh parametrisation started at this object: ``b * tanh(atanh((1 - eps) v / b) + delta)``
        (float64, differentiable in ``delta`` (V, 3); ``delta=None`` is zeros). Always inside the box."""
        import torch

        base = torch.from_numpy(np.arctanh((1.0 - eps) * self._vertices / self._bounds))
        d = torch.zeros_like(base) if delta is None else delta.to(torch.float64)
        return torch.from_numpy(self._bounds.copy()) * torch.tanh(base + d)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, RoofObject):
            return NotImplemented
        return (self._family == other._family and np.array_equal(self._vertices, other._vertices)
                and np.array_equal(self._colors, other._colors) and np.array_equal(self._bounds, other._bounds))

    __hash__ = None  # type: ignore[assignment]  # mutable-looking arrays: not hashable

    def __repr__(self) -> str:
        family = "" if self._family.is_default else f"family {self._family.name}, "
        return (f"RoofObject({family}max |displacement| {float(np.abs(self.displacement).max()):.4f} m, "
                f"bounds {tuple(self._bounds.tolist())})")


def tanh_vertices(delta: torch.Tensor, start: np.ndarray | None = None, bounds: object = None,
                  eps: float = TANH_EPS, *, family: Family = DEFAULT_FAMILY) -> torch.Tensor:
    """Box-constrained vertices ``b * tanh(atanh((1 - eps) * v0 / b) + delta)`` (torch, dtype of
    ``delta``); ``start`` ``v0`` defaults to ``family``'s template, ``bounds`` to its box. Inside ``|v| <= b``
    for every finite delta."""
    import torch

    b = check_bounds(family.bounds if bounds is None else bounds)
    v0 = template_vertices(family) if start is None else np.asarray(start, dtype=np.float64)
    base = torch.tensor(np.arctanh((1.0 - eps) * v0 / b), dtype=delta.dtype)
    return torch.tensor(b, dtype=delta.dtype) * torch.tanh(base + delta)


def clamp_to_box(vertices: np.ndarray | torch.Tensor, bounds: object = BOUNDS) -> np.ndarray | torch.Tensor:
    """The projection: each coordinate clamped to ``[-b, b]`` (numpy or torch; torch keeps gradients
    inside the box and zeroes them on clamped coordinates)."""
    b = check_bounds(bounds)
    if isinstance(vertices, np.ndarray):
        return np.clip(vertices, -b, b)
    import torch

    bt = torch.tensor(b, dtype=vertices.dtype)
    return torch.clamp(vertices, -bt, bt)


# ---- uniform Laplacian -----------------------------------------------------------------------

def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """(E, 2) unique undirected edges (i < j) of a triangle mesh, sorted."""
    f = np.asarray(faces, dtype=np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def uniform_laplacian(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(V, V) dense uniform Laplacian as PyTorch3D builds it: ``L[i, j] = 1/deg(i)`` for each
    neighbour j, ``L[i, i] = -1`` (a row of zeros for an isolated vertex)."""
    e = mesh_edges(faces)
    adj = np.zeros((n_vertices, n_vertices))
    adj[e[:, 0], e[:, 1]] = adj[e[:, 1], e[:, 0]] = 1.0
    deg = adj.sum(axis=1)
    lap = adj / np.where(deg > 0, deg, 1.0)[:, None]
    lap[np.arange(n_vertices), np.arange(n_vertices)] = np.where(deg > 0, -1.0, 0.0)
    return lap


@cache
def _level_laplacian(level: int) -> np.ndarray:
    """The read-only uniform Laplacian of the icosphere template of ``level`` (the faces of a level are the
    same at every radius)."""
    lap = uniform_laplacian(template_faces(Family(level, RADIUS)), _n_vertices(level))
    lap.flags.writeable = False
    return lap


def _template_laplacian(n_vertices: int) -> np.ndarray:
    """The template Laplacian of the family level with ``n_vertices`` vertices; ValueError for another count."""
    for level in LEVELS:
        if _n_vertices(level) == n_vertices:
            return _level_laplacian(level)
    raise ValueError(f"laplacian_smoothness: field 'vertices': {n_vertices} vertices are no template's "
                     f"({', '.join(str(_n_vertices(k)) for k in LEVELS)}); pass the faces")


@cache
def _torch_laplacian(n_vertices: int, dtype: torch.dtype) -> torch.Tensor:
    """:func:`_template_laplacian` as a torch tensor of ``dtype`` (kept: level 4's is 52 MB in float64)."""
    import torch

    return torch.tensor(_template_laplacian(n_vertices), dtype=dtype)


def laplacian_smoothness(vertices: np.ndarray, faces: np.ndarray | None = None) -> float:
    """Mean over vertices of ``|mean of the 1-ring neighbours - vertex|`` (PyTorch3D's uniform
    ``mesh_laplacian_smoothing``), m; ``faces`` default to the template's of the vertices' family level
    (told by their count)."""
    v = np.asarray(vertices, dtype=np.float64)
    lap = _template_laplacian(len(v)) if faces is None else uniform_laplacian(faces, len(v))
    return float(np.linalg.norm(lap @ v, axis=1).mean())


def laplacian_smoothness_torch(vertices: torch.Tensor, faces: np.ndarray | None = None) -> torch.Tensor:
    """Torch twin of :func:`laplacian_smoothness` (scalar, differentiable in ``vertices``; the
    Laplacian is a constant). A vertex at exactly its neighbours' mean contributes gradient 0."""
    import torch

    n = vertices.shape[0]
    lap = _torch_laplacian(n, vertices.dtype) if faces is None else torch.tensor(uniform_laplacian(faces, n),
                                                                                 dtype=vertices.dtype)
    r = lap @ vertices
    sq = (r * r).sum(dim=1)
    nonzero = sq > 0
    norm = torch.where(nonzero, torch.sqrt(torch.where(nonzero, sq, torch.ones_like(sq))), torch.zeros_like(sq))
    return norm.mean()


# ---- the controls' objects -------------------------------------------------------------------

def benign_sphere(family: Family = DEFAULT_FAMILY) -> RoofObject:
    """The undeformed sphere of ``family`` in neutral grey."""
    return RoofObject(family=family)


def _low_order_basis(directions: np.ndarray) -> np.ndarray:
    """(V, 8) real spherical-harmonic-like polynomials of degree 1 and 2 of unit ``directions``."""
    x, y, z = directions.T
    return np.stack([x, y, z, x * y, y * z, z * x, x * x - y * y, 3 * z * z - 1], axis=1)


def random_shape(seed: int, amplitude: float = 0.3, family: Family = DEFAULT_FAMILY) -> RoofObject:
    """A seeded random smooth deformation of ``family``'s template inside its box, with random colours.

    The deformation is the tanh parametrisation with ``delta`` a random combination of the 8
    degree-1 and degree-2 spherical-harmonic-like polynomials of each template vertex's direction
    (coefficients normal with sd ``amplitude``), so it is smooth over the sphere and inside the box;
    colours are uniform in [0, 1] per vertex and channel.
    """
    import torch

    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"random_shape: field 'seed': must be an integer >= 0, got {seed!r}")
    rng = np.random.default_rng(int(seed))
    coeffs = rng.normal(0.0, amplitude, size=(8, 3))
    colors = rng.random((family.n_vertices, 3))
    v0 = template_vertices(family)
    delta = _low_order_basis(v0 / np.linalg.norm(v0, axis=1, keepdims=True)) @ coeffs
    with torch.no_grad():
        vertices = tanh_vertices(torch.from_numpy(delta), family=family).numpy()
    return RoofObject.from_vertices(vertices, colors, family=family)
