"""KITTI labels of a rendered scene: 2D box, truncation, occlusion, DontCare regions.

For every object of a labelled kind (Car, Van, Truck, Pedestrian, Cyclist):

1. Projection: the mesh (velodyne) goes to rect and through P2 into the image; mesh edges
   crossing the plane rect depth = 0.1 m are cut there, so objects reaching behind the camera
   project correctly. The extent of the projected mesh is the object's image-plane extent
   (not clipped to the image).
2. Coverage: camera rays are cast through a pixel grid over that extent (stride chosen so that at
   most about 3,000 rays are cast; stride 1 for small objects) against the object *alone*. Hits
   inside the image form the object's in-image silhouette; hits outside it are its truncated part.
   A silhouette sample is *visible* when the rendered image shows this very object at that pixel.
3. Fields:
   * truncated = 1 - (silhouette samples inside the image) / (all silhouette samples), i.e. the
     fraction of the object's image-plane area that lies outside the image;
   * occluded fraction f = 1 - visible / (silhouette samples inside the image); the KITTI level
     is 0 (fully visible) if f < 0.10, 1 (partly occluded) if f < 0.50, else 2 (largely occluded);
   * bbox = the projected extent clipped to [0, W-1] x [0, H-1]: the amodal box of the whole
     projected object (visible and occluded parts), as KITTI annotators drew the object's extent;
   * dimensions, location, rotation_y: the box the mesh was placed in (already rounded to
     0.01); alpha = rotation_y - atan2(x, z).
4. Which line an object gets:
   * none when it is out of view (extent misses the image) or hidden (fewer than
     :data:`MIN_VISIBLE_PX` visible pixels or under 5 % of its in-image silhouette visible);
   * ``DontCare`` when KITTI would not have annotated it: 2D box lower than
     :data:`DONTCARE_MAX_HEIGHT_PX` pixels, farther than :data:`DONTCARE_MIN_DEPTH_M`, or without a
     single LiDAR return;
   * otherwise a labelled line of its type.
   Labelled lines come first (nearest first), then the DontCare lines.

Difficulty (reference.md §5.2, cumulative sets): easy = height >= 40 px, occluded <= 0,
truncated <= 0.15; moderate = >= 25 px, <= 1, <= 0.30; hard = >= 25 px, <= 2, <= 0.50.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robustbench3d.geometry import alpha_from_rotation_y, box_corners, project_boxes_to_image
from robustbench3d.kitti.labels import Labels
from robustbench3d.synth.camera import pixel_directions
from robustbench3d.synth.raytrace import SceneGeometry
from robustbench3d.synth.scene import Scene

NEAR_DEPTH_M = 0.1
MAX_COVERAGE_RAYS = 3000
OCCLUSION_THRESHOLDS = (0.10, 0.50)  # occluded fraction limits of levels 0 and 1
MIN_VISIBLE_PX = 20
MIN_VISIBLE_FRACTION = 0.05
DONTCARE_MAX_HEIGHT_PX = 16.0
DONTCARE_MIN_DEPTH_M = 72.0
#: (min 2D height px, max occlusion level, max truncation) of easy, moderate, hard.
DIFFICULTY_LIMITS = ((40.0, 0, 0.15), (25.0, 1, 0.30), (25.0, 2, 0.50))


@dataclass(frozen=True)
class ObjectAnnotation:
    """What the annotator decided about one object of a labelled kind.

    Attributes:
        index: index into ``scene.objects``.
        status: 'label', 'dontcare', 'hidden' or 'out_of_view'.
        truncation: fraction of the image-plane silhouette outside the image.
        occluded_fraction: fraction of the in-image silhouette hidden by other objects.
        visible_px: estimated number of visible pixels.
        bbox: (4,) clipped 2D box (left, top, right, bottom), pixels.
        lidar_points: LiDAR returns on the object.
    """

    index: int
    status: str
    truncation: float
    occluded_fraction: float
    visible_px: float
    bbox: np.ndarray
    lidar_points: int


def occlusion_level(occluded_fraction: float) -> int:
    """KITTI occlusion state 0/1/2 from the occluded fraction (:data:`OCCLUSION_THRESHOLDS`)."""
    return int(np.searchsorted(np.asarray(OCCLUSION_THRESHOLDS), occluded_fraction, side="right"))


def difficulty(bbox_height: np.ndarray, occluded: np.ndarray, truncated: np.ndarray) -> np.ndarray:
    """Exclusive KITTI difficulty group per object: 0 easy, 1 moderate (not easy), 2 hard (not
    moderate), 3 ignored at every level."""
    h = np.asarray(bbox_height, np.float64)
    occ = np.asarray(occluded)
    tr = np.asarray(truncated, np.float64)
    group = np.full(h.shape, 3, dtype=np.int64)
    for level in (2, 1, 0):
        min_h, max_occ, max_tr = DIFFICULTY_LIMITS[level]
        group[(h >= min_h) & (occ <= max_occ) & (tr <= max_tr)] = level
    return group


def _projected_extent(scene: Scene, vertices_velo: np.ndarray, faces: np.ndarray) -> np.ndarray | None:
    """(umin, vmin, umax, vmax) of the mesh projected with P2 after cutting at NEAR_DEPTH_M; None if
    the whole mesh is behind that plane."""
    calib = scene.calib
    rect = calib.velo_to_rect_points(vertices_velo)
    uv, depth = calib.rect_to_image(rect)
    keep = depth >= NEAR_DEPTH_M
    if not keep.any():
        return None
    pts = [uv[keep]]
    if not keep.all():
        e = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        da, db = depth[e[:, 0]], depth[e[:, 1]]
        cross = (da - NEAR_DEPTH_M) * (db - NEAR_DEPTH_M) < 0
        if cross.any():
            a, b = rect[e[cross, 0]], rect[e[cross, 1]]
            t = ((NEAR_DEPTH_M - da[cross]) / (db[cross] - da[cross]))[:, None]
            pts.append(calib.rect_to_image(a + t * (b - a))[0])
    p = np.concatenate(pts)
    return np.array([p[:, 0].min(), p[:, 1].min(), p[:, 0].max(), p[:, 1].max()])


def _coverage(scene: Scene, geometry: SceneGeometry, index: int, extent: np.ndarray,
              object_id: np.ndarray) -> tuple[int, int, int, int]:
    """(silhouette samples, of them inside the image, of those visible, stride in px)."""
    w, h = scene.image_size
    u0, v0 = np.ceil(extent[:2] - 1e-9)
    u1, v1 = np.floor(extent[2:] + 1e-9)
    area = max(u1 - u0 + 1, 1.0) * max(v1 - v0 + 1, 1.0)
    stride = max(1, int(np.ceil(np.sqrt(area / MAX_COVERAGE_RAYS))))
    us = np.arange(u0, u1 + 1, stride) if u1 >= u0 else np.array([np.round((extent[0] + extent[2]) / 2)])
    vs = np.arange(v0, v1 + 1, stride) if v1 >= v0 else np.array([np.round((extent[1] + extent[3]) / 2)])
    uu, vv = np.meshgrid(us, vs)
    uu, vv = uu.ravel(), vv.ravel()
    origin, dirs = pixel_directions(scene.day, uu, vv)
    sil = geometry.hits_object_alone(index, origin, dirs)
    inside = sil & (uu >= 0) & (uu <= w - 1) & (vv >= 0) & (vv <= h - 1)
    ui, vi = uu[inside].astype(np.int64), vv[inside].astype(np.int64)
    visible = int(np.count_nonzero(object_id[vi, ui] == index))
    return int(sil.sum()), int(inside.sum()), visible, stride


def annotate(scene: Scene, geometry: SceneGeometry, object_id: np.ndarray,
             point_object: np.ndarray) -> tuple[Labels, list[ObjectAnnotation]]:
    """KITTI labels of a scene given the rendered object-id image and the LiDAR point owners.

    Args:
        object_id: (H, W) int32 object index per pixel (-1 sky), from the camera render.
        point_object: (N,) int32 object index per LiDAR point.
    Returns:
        The frame's labels and one :class:`ObjectAnnotation` per object of a labelled kind.
    """
    w, h = scene.image_size
    n_points = np.bincount(np.asarray(point_object, np.int64), minlength=len(scene.objects))
    records: list[ObjectAnnotation] = []
    rows: list[tuple[int, float, str, float, int, np.ndarray, int]] = []
    labelled = scene.labelled_indices()
    objs = [scene.objects[i] for i in labelled]
    # cheap reject first: the mesh lies inside its box, so a box missing the image hides the mesh too
    corners = box_corners(np.array([o.dimensions for o in objs]).reshape(-1, 3),
                          np.array([o.location for o in objs]).reshape(-1, 3), np.array([o.rotation_y for o in objs]))
    in_view = project_boxes_to_image(corners, scene.calib, (w, h), near=0.5 * NEAR_DEPTH_M)[1]
    for i, obj, seen in zip(labelled, objs, in_view, strict=True):
        extent = _projected_extent(scene, obj.mesh.vertices, obj.mesh.faces) if seen else None
        if extent is None or extent[2] < 0 or extent[3] < 0 or extent[0] > w - 1 or extent[1] > h - 1:
            records.append(ObjectAnnotation(i, "out_of_view", 1.0, 1.0, 0.0, np.zeros(4), int(n_points[i])))
            continue
        bbox = np.array([max(extent[0], 0.0), max(extent[1], 0.0), min(extent[2], w - 1.0), min(extent[3], h - 1.0)])
        u0, v0 = np.ceil(bbox[:2]).astype(int)
        u1, v1 = np.floor(bbox[2:]).astype(int)
        if not np.any(object_id[v0:v1 + 1, u0:u1 + 1] == i):  # no pixel shows it: hidden, skip the silhouette
            records.append(ObjectAnnotation(i, "hidden", 0.0, 1.0, 0.0, bbox, int(n_points[i])))
            continue
        total, inside, visible, stride = _coverage(scene, geometry, i, extent, object_id)
        trunc = 1.0 - inside / total if total else 1.0
        occ_frac = 1.0 - visible / inside if inside else 1.0
        visible_px = visible * stride * stride
        if visible_px < MIN_VISIBLE_PX or occ_frac > 1.0 - MIN_VISIBLE_FRACTION:
            status = "hidden"
        elif (bbox[3] - bbox[1] < DONTCARE_MAX_HEIGHT_PX or obj.location[2] > DONTCARE_MIN_DEPTH_M
              or n_points[i] == 0):
            status = "dontcare"
        else:
            status = "label"
        records.append(ObjectAnnotation(i, status, trunc, occ_frac, float(visible_px), bbox, int(n_points[i])))
        if status != "hidden":
            rows.append((0 if status == "label" else 1, float(obj.location[2]), status, trunc,
                         occlusion_level(occ_frac), bbox, i))
    rows.sort(key=lambda r: (r[0], r[1]))
    return _labels(scene, rows), records


def _labels(scene: Scene, rows: list) -> Labels:
    n = len(rows)
    types = np.empty(n, dtype=object)
    truncated = np.empty(n)
    occluded = np.empty(n, dtype=np.int64)
    alpha = np.empty(n)
    bbox = np.empty((n, 4))
    dims = np.empty((n, 3))
    loc = np.empty((n, 3))
    ry = np.empty(n)
    for k, (_, _, status, trunc, occ, box, i) in enumerate(rows):
        obj = scene.objects[i]
        bbox[k] = np.round(box, 2)
        if status == "label":
            types[k] = obj.kind
            truncated[k] = np.round(trunc, 2)
            occluded[k] = occ
            dims[k] = obj.dimensions
            loc[k] = obj.location
            ry[k] = obj.rotation_y
            alpha[k] = np.round(alpha_from_rotation_y(np.array([obj.rotation_y]), obj.location[None])[0], 2)
        else:  # the KITTI DontCare line: DontCare -1 -1 -10 l t r b -1 -1 -1 -1000 -1000 -1000 -10
            types[k] = "DontCare"
            truncated[k], occluded[k], alpha[k] = -1.0, -1, -10.0
            dims[k] = -1.0
            loc[k] = -1000.0
            ry[k] = -10.0
    return Labels(type=types, truncated=truncated, occluded=occluded, alpha=alpha, bbox=bbox, dimensions=dims,
                  location=loc, rotation_y=ry)
