"""Drawing a frame (:func:`render`): the picture ``robustbench3d show`` writes and the report's scene figures use.

Top: the camera-2 image with each labelled object's 3D box projected (near-plane clipped) and
DontCare regions outlined. Bottom: a bird's-eye view of the scan in the velodyne frame (x forward
= up in the picture, y left = left), points coloured by height, with the boxes' footprints; highlighted
points (an attack object's LiDAR returns) in yellow, enlarged to 3 x 3 px.

numpy imported inside the functions (``robustbench3d show --help`` stays fast).
"""

from __future__ import annotations

CLASS_COLOURS: dict[str, tuple[int, int, int]] = {
    "Car": (0, 255, 0), "Van": (255, 200, 0), "Truck": (255, 120, 0), "Pedestrian": (255, 0, 255),
    "Person_sitting": (200, 0, 255), "Cyclist": (0, 200, 255), "Tram": (255, 255, 255), "Misc": (160, 160, 160),
    "DontCare": (120, 120, 255),
}


#: The range of ``--bev-range`` (m): from 5 m (the panel is (range + 2 m) / (1.6 range) image widths tall, so
#: shorter ranges make ever taller pictures) to 200 m (beyond the HDL-64E's 120 m reach; a 1e9 m range would
#: draw 1e8 range rings).
BEV_RANGE_M = (5.0, 200.0)


def bev_range_problem(bev_range: float) -> str | None:
    """Why ``bev_range`` (m) is outside :data:`BEV_RANGE_M` (None: it is inside)."""
    low, high = BEV_RANGE_M
    if not low <= bev_range <= high:  # NaN fails too
        return f"expected a range in [{low:g}, {high:g}] m"
    return None

#: Colour of the attack object's LiDAR returns in the bird's-eye view.
OBJECT_POINT_COLOUR = (255, 255, 0)


def render(frame, detections=None, bev_range: float = 70.0, highlight=None):
    """Return an (H, W, 3) uint8 picture of ``frame`` (a :class:`~robustbench3d.kitti.Frame`);
    ``highlight`` (K, >=3) velodyne points are drawn in :data:`OBJECT_POINT_COLOUR` over the BEV."""
    import numpy as np
    from PIL import Image, ImageDraw

    from robustbench3d.geometry import BOX_EDGES

    problem = bev_range_problem(bev_range)
    if problem is not None:
        raise ValueError(f"render: field 'bev_range': {problem}, got {bev_range!r}")
    calib = frame.calib
    width, height = frame.image_size
    # (colour, corners (8, 3) rect) of every drawn box: labels in class colours, detections red.
    drawn = [(CLASS_COLOURS.get(cls, (255, 255, 255)), c) for cls, c in _solid_boxes(frame.labels)]
    drawn += [((255, 0, 0), c) for _, c in _solid_boxes(detections)]

    top = Image.fromarray(frame.image).convert("RGB")
    draw = ImageDraw.Draw(top)
    for colour, c in drawn:
        for i, j in BOX_EDGES:
            seg = _clip_segment(c[i], c[j], near=0.1)
            if seg is not None:
                (u0, v0), (u1, v1) = calib.rect_to_image(np.stack(seg))[0]
                draw.line([(float(u0), float(v0)), (float(u1), float(v1))], fill=colour, width=2)
    if frame.labels is not None:
        for box in frame.labels.bbox[frame.labels.type == "DontCare"]:
            draw.rectangle([float(v) for v in box], outline=CLASS_COLOURS["DontCare"], width=1)

    # Bird's-eye view: velodyne x in [-2, range] -> rows (far at the top), y in [-0.8 r, 0.8 r] -> columns.
    half = 0.8 * bev_range
    scale = width / (2 * half)  # px per m, square pixels
    bev_h = round((bev_range + 2.0) * scale)
    bev = np.zeros((bev_h, width, 3), dtype=np.uint8)
    x, y, z = frame.scan[:, 0], frame.scan[:, 1], frame.scan[:, 2]
    col = ((half - y) * scale).astype(np.int64)
    row = ((bev_range - x) * scale).astype(np.int64)
    ok = (col >= 0) & (col < width) & (row >= 0) & (row < bev_h)
    t = np.clip((z[ok] + 2.0) / 3.0, 0, 1)
    colours = np.stack([80 + 175 * t, 80 + 175 * (1 - np.abs(2 * t - 1)), 255 - 175 * t], axis=1).astype(np.uint8)
    bev[row[ok], col[ok]] = colours
    if highlight is not None and len(highlight):
        hc = ((half - highlight[:, 1]) * scale).astype(np.int64)
        hr = ((bev_range - highlight[:, 0]) * scale).astype(np.int64)
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                r, c = hr + dr, hc + dc
                inside = (c >= 0) & (c < width) & (r >= 0) & (r < bev_h)
                bev[r[inside], c[inside]] = OBJECT_POINT_COLOUR
    bev_img = Image.fromarray(bev)
    bdraw = ImageDraw.Draw(bev_img)
    for colour, c in drawn:
        v = calib.rect_to_velo_points(c[:4])
        bdraw.polygon([(float((half - p[1]) * scale), float((bev_range - p[0]) * scale)) for p in v],
                      outline=colour, width=2)
    # Sensor position and 10 m range rings.
    cx, cy = half * scale, bev_range * scale
    for r in range(10, int(bev_range) + 1, 10):
        rr = r * scale
        bdraw.arc([cx - rr, cy - rr, cx + rr, cy + rr], 180, 360, fill=(60, 60, 60))
    bdraw.ellipse([cx - 4, cy - 4, cx + 4, cy + 4], fill=(255, 255, 255))

    out = Image.new("RGB", (width, height + bev_h))
    out.paste(top, (0, 0))
    out.paste(bev_img, (0, height))
    return np.asarray(out)


def _solid_boxes(labels):
    """(type, (8, 3) rect corners) of every non-DontCare object; nothing for None."""
    from robustbench3d.geometry import box_corners

    if labels is None:
        return []
    real = labels.type != "DontCare"
    corners = box_corners(labels.dimensions[real], labels.location[real], labels.rotation_y[real])
    return list(zip(labels.type[real], corners, strict=True))


def _clip_segment(a, b, near: float):
    """Clip a rect-frame segment to z >= near; None when it lies entirely behind."""
    za, zb = a[2], b[2]
    if za < near and zb < near:
        return None
    if za >= near and zb >= near:
        return a, b
    t = (near - za) / (zb - za)
    cut = a + t * (b - a)
    return (cut, b) if za < near else (a, cut)
