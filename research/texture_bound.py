"""How far any texture of the roof object can move the 2D detector: a per-frame, per-pixel bound.

For each of the first N val frames of the embedded dataset with target cars, the pixels of a mask are set
free (one colour logit per pixel and channel, colour = sigmoid(logit), starting at the shaded grey object, or
at the photo for ``box``) and optimised against that frame alone with Adam, minimising for every target car
the sum over its 2D candidates of IoU >= 0.5 of ``-log(1 - objectness * class probability)`` (the image
loss's terms, from logits).
With the ``bounds`` mask this attacker is stronger than any universal object within the bounds: every shape
inside the bounds' box covers a subset of the box's pixels, and it picks the colour of every pixel separately
for each frame instead of 162 vertex colours shared by all cars. The masks:

* ``object``: every pixel the undeformed sphere (r = 0.40 m) on each car's roof covers (its coverage alpha);
* ``bounds``: every pixel the bounds' box (0.8 m cube, an 8-vertex mesh) placed the same way covers;
* both rendered without scene occlusion, so also the pixels a nearer object would hide (a superset);
* ``box``: each car's whole ground-truth 2D box (a control: the optimiser can remove a car when it may
  repaint all of it);
* ``vertex``: the 162 vertex colours of the undeformed sphere (the issue's parametrisation), shaded and
  rendered; ``vertex-shape``: those and the shape (the tanh box parametrisation's displacements, Adam lr
  :data:`LR_SHAPE`), adv-object's image branch.

The loss of the vertex masks (``LOSS``, default ``sum``; the pixel masks always use ``sum``) can instead be, per
car, ``lse``: the log-sum-exp over its candidates of ``log(o c)`` (the log of the summed scores, pushed down
without saturating), or ``hinge``: ``softplus`` of that minus ``log`` :data:`HINGE_SCORE` (no more push once the
car's scores sum below the hinge), or ``iou``: the sum over its candidates of ``-log(1 - o c IoU)`` with the
candidate box's IoU with the car differentiable (the decoded box of the detector's prior; the loss and candidates
of ``train_iou_loss.py``), so that the boxes that survive may also be moved off the car instead of only scored
down.

``START`` (vertex masks only, default ``grey``): the colours the per-frame optimisation starts from, ``grey``,
``adv-texture`` (the shipped universal object's) or ``rand:S`` (colour logits drawn from N(0, 2^2), seed S).

Each attacked image (rounded to 8 bits, the clean scan) goes through the whole victim with its own 2D
detections, and Car BEV AP @0.7 (R40, easy / moderate / hard) is computed over the N frames.

Usage: python research/texture_bound.py [N] [STEPS] [MASKS] [LOSS] [START]
       (default 20 50 object,bounds,box sum grey)
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import replace

import numpy as np
import torch
import torch.nn.functional as F
from train_iou_loss import box_gradients, iou_weighted_losses

from robustbench3d.attacks.base import target_cars
from robustbench3d.attacks.losses import neg_log_one_minus_product
from robustbench3d.attacks.object import BOUNDS, benign_sphere, tanh_vertices, template_faces
from robustbench3d.attacks.objectfile import load_object
from robustbench3d.attacks.placement import cars_of, place_on_roof
from robustbench3d.attacks.shipped import shipped_object
from robustbench3d.datasets import load_ground_truth, resolve_dataset
from robustbench3d.eval.kitti_eval import evaluate
from robustbench3d.sensors.camera_render import render_camera, render_camera_torch
from robustbench3d.victims import create_victim

GREY = 0.5
#: The unit cube [-1, 1]^3 as 12 outward triangles.
CUBE_VERTS = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
CUBE_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                       [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
LR = 0.1
LR_VERTEX = 0.5
LR_SHAPE = 0.05
LOSSES = ("sum", "lse", "hinge", "iou")
HINGE_SCORE = 0.02


def free_pixels(frame, cars, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) coverage alpha in [0, 1] of the pixels set free and (H, W, 3) their starting colours in [0, 1]:
    the shaded grey sphere for the object masks, the photo for ``box``."""
    h, w = frame.image.shape[:2]
    photo = frame.image.astype(np.float64) / 255.0
    if kind == "box":
        m = np.zeros((h, w))
        for u0, v0, u1, v1 in cars.bbox:
            m[int(np.floor(v0)):int(np.ceil(v1)) + 1, int(np.floor(u0)):int(np.ceil(u1)) + 1] = 1.0
        return m, photo
    if kind == "object":
        verts, faces = benign_sphere().vertices(), template_faces()
    elif kind == "bounds":
        verts, faces = CUBE_VERTS * np.asarray(BOUNDS), CUBE_FACES
    else:
        raise SystemExit(f"unknown mask {kind!r}: expected object, bounds or box")
    meshes = [(place_on_roof(verts, car)[0], faces, np.full((len(verts), 3), GREY)) for car in cars_of(cars)]
    res = render_camera(frame.image, frame.calib, meshes)
    a = res.alpha.astype(np.float64)[..., None]
    with np.errstate(divide="ignore", invalid="ignore"):  # the object's colour c of rendered = a c + (1 - a) photo
        start = np.where(a > 0, (res.image / 255.0 - (1 - a) * photo) / a, photo)
    return a[..., 0], start


def masks_of_object(frame, cars) -> np.ndarray:
    """(H, W) coverage of the undeformed sphere on every car (the ``object`` mask)."""
    return free_pixels(frame, cars, "object")[0]


def attack_frame(victim, frame, cars, mask: np.ndarray, start: np.ndarray, steps: int
                 ) -> tuple[np.ndarray, float, float]:
    """(attacked uint8 image, first loss, last loss) after ``steps`` Adam steps on the free pixels."""
    photo = torch.from_numpy(frame.image.astype(np.float64) / 255.0)
    alpha = torch.from_numpy(mask)[..., None]
    p = np.clip(start, 0.01, 0.99)
    logit = torch.tensor(np.log(p / (1 - p)), dtype=torch.float64, requires_grad=True)
    return optimise(victim, cars, [{"params": [logit], "lr": LR}], steps,
                    lambda: photo * (1 - alpha) + alpha * torch.sigmoid(logit), "sum")


def start_logits(start: str) -> np.ndarray:
    """(162, 3) colour logits the vertex masks start from (``START``, module doc)."""
    if start == "grey":
        return np.zeros((162, 3))
    if start == "adv-texture":
        shipped = shipped_object("adv-texture")
        if shipped is None:
            raise SystemExit("start adv-texture: no shipped object of that name (attacks/objects/manifest.json)")
        c = np.clip(load_object(shipped.path).colors, 1e-3, 1 - 1e-3)
        return np.log(c / (1 - c))
    if start.startswith("rand:"):
        return np.random.default_rng(int(start[5:])).normal(0.0, 2.0, (162, 3))
    raise SystemExit(f"unknown start {start!r}: expected grey, adv-texture or rand:SEED")


def attack_frame_vertices(victim, frame, cars, steps: int, loss: str, shape: bool = False, start: str = "grey"
                          ) -> tuple[np.ndarray, float, float]:
    """As :func:`attack_frame`, but the free parameters are the 162 vertex colours of the undeformed sphere on
    every car of the frame (the issue's parametrisation, one colour set per frame; with ``shape`` also the
    vertex displacements of the tanh box parametrisation), rendered with :func:`render_camera_torch` (shading,
    3 x 3 edge samples, no scene occlusion); Adam lr :data:`LR_VERTEX` on the colour logits, starting at
    :func:`start_logits`, and :data:`LR_SHAPE` on the displacements, starting at the sphere."""
    photo = torch.from_numpy(frame.image.astype(np.float64) / 255.0)
    faces = template_faces()
    logit = torch.tensor(start_logits(start), dtype=torch.float64, requires_grad=True)
    delta = torch.zeros((162, 3), dtype=torch.float64, requires_grad=True)
    groups = [{"params": [logit], "lr": LR_VERTEX}] + ([{"params": [delta], "lr": LR_SHAPE}] if shape else [])
    fixed = [torch.from_numpy(place_on_roof(benign_sphere().vertices(), car)[0]) for car in cars_of(cars)]

    def image() -> torch.Tensor:
        placed = [place_on_roof(tanh_vertices(delta), car)[0] for car in cars_of(cars)] if shape else fixed
        return render_camera_torch(photo, frame.calib, [(p, faces, torch.sigmoid(logit)) for p in placed])

    return optimise(victim, cars, groups, steps, image, loss)


def car_losses(cands, n: int, loss: str) -> torch.Tensor:
    """The loss of :data:`LOSSES` (module doc) summed over the ``n`` cars, from the candidates of IoU >= 0.5."""
    keep = cands.iou >= 0.5
    a, b = cands.objectness_logit[keep], cands.class_logit[keep]
    if loss == "sum":
        return neg_log_one_minus_product(a, b).sum()
    if loss == "iou":
        return iou_weighted_losses(cands, n).sum()
    a, b = a.double(), b.double()
    log_score = -F.softplus(-a) - F.softplus(-b)  # log(o c) from the logits
    owner = cands.target_index[keep]
    per_car = [torch.logsumexp(log_score[owner == k], 0) for k in range(n) if bool((owner == k).any())]
    if not per_car:
        return torch.zeros((), dtype=torch.float64)
    lse = torch.stack(per_car)
    return (lse if loss == "lse" else F.softplus(lse - float(np.log(HINGE_SCORE)))).sum()


def optimise(victim, cars, groups: list[dict], steps: int, image_of: Callable[[], torch.Tensor], loss: str
             ) -> tuple[np.ndarray, float, float]:
    """``steps`` Adam steps on the parameter ``groups``, the (H, W, 3) image in [0, 1] being ``image_of()``,
    minimising :func:`car_losses`: (last image as uint8, first loss, last loss)."""
    opt = torch.optim.Adam(groups)
    boxes = [np.asarray(cars.bbox, np.float64)]
    first = last = float("nan")
    for step in range(steps + 1):
        image = image_of()
        if step == steps:
            break
        value = car_losses(victim.objectness(image.permute(2, 0, 1)[None].float(), boxes), len(cars), loss)
        first = value.item() if step == 0 else first
        last = value.item()
        if not value.requires_grad:
            break
        opt.zero_grad()
        value.backward()
        opt.step()
    return np.clip(np.round(image.detach().numpy() * 255.0), 0, 255).astype(np.uint8), first, last


def main(n: int, steps: int, kinds: list[str], loss: str = "sum", start: str = "grey") -> None:
    if loss not in LOSSES:
        raise SystemExit(f"unknown loss {loss!r}: expected one of {', '.join(LOSSES)}")
    with box_gradients() if loss == "iou" else nullcontext():  # iou: the candidates' IoUs keep their gradients
        measure(n, steps, kinds, loss, start)


def measure(n: int, steps: int, kinds: list[str], loss: str, start: str) -> None:
    """The table of the module doc (``main`` without its checks)."""
    torch.manual_seed(0)
    victim = create_victim("fpointnet-v1-lite")
    dataset = resolve_dataset(None, "val", progress=False)
    kitti = dataset.kitti()
    gt = load_ground_truth(dataset, None)
    frames = [kitti.frame(f) for f, lab in zip(gt.frame_ids, gt.labels, strict=True) if len(target_cars(lab))][:n]
    labels = [f.labels for f in frames]
    clean = victim.detect([replace(f, labels=None) for f in frames], "detector")
    rows = [("clean", evaluate(labels, clean), 0.0, 0.0, 0.0, 0.0)]
    for kind in kinds:
        t0 = time.time()
        attacked, first, last, share = [], [], [], []
        for f in frames:
            cars = target_cars(f.labels)
            if kind in ("vertex", "vertex-shape"):
                m = masks_of_object(f, cars)
                image, a, b = attack_frame_vertices(victim, f, cars, steps, loss, shape=kind == "vertex-shape",
                                                    start=start)
            else:
                m, colours = free_pixels(f, cars, kind)
                image, a, b = attack_frame(victim, f, cars, m, colours, steps)
            attacked.append(replace(f, image=image, labels=None))
            first.append(a)
            last.append(b)
            share.append(m.sum())
        dets = victim.detect(attacked, "detector")
        box_px = sum(float(np.prod(np.maximum(c.bbox[:, 2:] - c.bbox[:, :2], 0), axis=1).sum())
                     for c in (target_cars(f.labels) for f in frames))
        rows.append((kind, evaluate(labels, dets), float(np.mean(first)), float(np.mean(last)),
                     sum(share) / box_px, time.time() - t0))
    n_cars = sum(len(target_cars(lab)) for lab in labels)
    print(f"{len(frames)} val frames, {n_cars} target cars, {steps} Adam steps per frame, loss {loss}, start {start}")
    print(f"{'mask':10} {'free px / box px':>16} {'loss first':>10} {'loss last':>10} "
          f"{'BEV R40 E / M / H':>22} {'rel. drop M':>11} {'s':>6}")
    ref = rows[0][1]["Car"]["bev"]["R40"]
    for kind, res, a, b, share, sec in rows:
        ap = res["Car"]["bev"]["R40"]
        e, m, h = (ap[k] for k in ("easy", "moderate", "hard"))
        drop = (ref["moderate"] - m) / ref["moderate"]
        print(f"{kind:10} {share:16.3f} {a:10.3f} {b:10.3f} {e:8.2f} / {m:5.2f} / {h:5.2f} {drop:11.1%} {sec:6.0f}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 20, int(sys.argv[2]) if len(sys.argv) > 2 else 50,
         (sys.argv[3] if len(sys.argv) > 3 else "object,bounds,box").split(","),
         sys.argv[4] if len(sys.argv) > 4 else "sum", sys.argv[5] if len(sys.argv) > 5 else "grey")
