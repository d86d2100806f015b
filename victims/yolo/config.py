"""YOLO layouts as darknet-style layer lists, and the detector configuration.

Four layouts (reference §2): ``"mini"`` — the CPU-sized KITTI car detector of §2.3 (input
640x192, tiny-style backbone, heads at stride 16 and 8) and the default; ``"mini3"`` — ``mini``
plus a stride-32 head, at 960x288 (the shipped detector, fine-tuned from ``mini``); ``"tiny"`` —
yolov3-tiny (13 conv layers, strides 32 and 16); ``"v3"`` — YOLOv3 with Darknet-53 (75 conv layers,
strides 32, 16, 8). Layer semantics follow darknet cfgs: ``Route`` indices are relative when
negative, absolute otherwise; a ``HeadConv`` is the linear 1x1 conv producing A·(5 + C)
channels for the ``Yolo`` layer that follows it; a ``Yolo`` layer passes its input through.

Anchors are (w, h) in input pixels; each ``Yolo`` layer uses the anchors listed in its mask.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any


@dataclass(frozen=True)
class Conv:
    filters: int
    size: int = 3
    stride: int = 1


@dataclass(frozen=True)
class MaxPool:
    size: int = 2
    stride: int = 2


@dataclass(frozen=True)
class Route:
    layers: tuple[int, ...]


@dataclass(frozen=True)
class Shortcut:
    source: int = -3


@dataclass(frozen=True)
class Upsample:
    scale: int = 2


@dataclass(frozen=True)
class HeadConv:
    pass


@dataclass(frozen=True)
class Yolo:
    mask: tuple[int, ...]


Layer = Conv | MaxPool | Route | Shortcut | Upsample | HeadConv | Yolo


def mini_layers() -> list[Layer]:
    """§2.3: conv16-32-64-128-256 with 2x2 max-pools; heads at stride 16 (12x40 at 640x192) and 8."""
    return [
        Conv(16), MaxPool(), Conv(32), MaxPool(), Conv(64), MaxPool(),
        Conv(128),                                   # 6: stride 8, routed to the fine head
        MaxPool(), Conv(256),                        # 8: stride 16
        Conv(128, 1), Conv(256), HeadConv(), Yolo((3, 4, 5)),
        Route((-4,)), Conv(64, 1), Upsample(), Route((-1, 6)),
        Conv(128), HeadConv(), Yolo((0, 1, 2)),
    ]


def mini3_layers() -> list[Layer]:
    """``mini`` (its 20 layers unchanged, so trained ``mini`` weights initialise it) plus a third
    head at stride 32 branching off the stride-16 features (layer 8): max-pool, conv256-128(1x1)-
    256-128(1x1)-256. Its receptive field is ~286 px (the ``mini`` heads' ~110 px cannot see the
    edges of large, near cars)."""
    return [
        *mini_layers(),
        Route((8,)), MaxPool(),                      # 21: stride 32
        Conv(256), Conv(128, 1), Conv(256), Conv(128, 1), Conv(256), HeadConv(), Yolo((6, 7, 8)),
    ]


def tiny_layers() -> list[Layer]:
    """yolov3-tiny.cfg (§2.2)."""
    return [
        Conv(16), MaxPool(), Conv(32), MaxPool(), Conv(64), MaxPool(), Conv(128), MaxPool(),
        Conv(256),                                   # 8: stride 16
        MaxPool(), Conv(512), MaxPool(2, 1), Conv(1024),
        Conv(256, 1), Conv(512), HeadConv(), Yolo((3, 4, 5)),
        Route((-4,)), Conv(128, 1), Upsample(), Route((-1, 8)),
        Conv(256), HeadConv(), Yolo((0, 1, 2)),
    ]


def v3_layers() -> list[Layer]:
    """yolov3.cfg: Darknet-53 backbone and three detection heads."""
    layers: list[Layer] = [Conv(32)]

    def stage(filters: int, blocks: int) -> None:
        layers.append(Conv(filters, 3, 2))
        for _ in range(blocks):
            layers.extend([Conv(filters // 2, 1), Conv(filters), Shortcut(-3)])

    stage(64, 1)
    stage(128, 2)
    stage(256, 8)   # last shortcut: layer 36 (stride 8)
    stage(512, 8)   # layer 61 (stride 16)
    stage(1024, 4)  # layer 74 (stride 32)

    def head(filters: int, mask: tuple[int, ...]) -> None:
        layers.extend([Conv(filters, 1), Conv(filters * 2), Conv(filters, 1), Conv(filters * 2),
                       Conv(filters, 1), Conv(filters * 2), HeadConv(), Yolo(mask)])

    head(512, (6, 7, 8))
    layers.extend([Route((-4,)), Conv(256, 1), Upsample(), Route((-1, 61))])
    head(256, (3, 4, 5))
    layers.extend([Route((-4,)), Conv(128, 1), Upsample(), Route((-1, 36))])
    head(128, (0, 1, 2))
    return layers


LAYOUTS = {"mini": mini_layers, "mini3": mini3_layers, "tiny": tiny_layers, "v3": v3_layers}

#: Anchors (w, h) px at 640x192 for KITTI cars, sorted by area; replace by k-means on the
#: training boxes (:func:`robustbench3d.victims.yolo.anchors.kmeans_anchors`) before training.
MINI_ANCHORS = ((14.0, 10.0), (24.0, 16.0), (38.0, 26.0), (60.0, 40.0), (96.0, 62.0), (160.0, 100.0))
MINI3_ANCHORS = (*((w * 1.5, h * 1.5) for w, h in MINI_ANCHORS), (200.0, 130.0), (300.0, 170.0), (450.0, 230.0))
TINY_ANCHORS = ((10.0, 14.0), (23.0, 27.0), (37.0, 58.0), (81.0, 82.0), (135.0, 169.0), (344.0, 319.0))
V3_ANCHORS = ((10.0, 13.0), (16.0, 30.0), (33.0, 23.0), (30.0, 61.0), (62.0, 45.0), (59.0, 119.0),
              (116.0, 90.0), (156.0, 198.0), (373.0, 326.0))


@dataclass(frozen=True)
class YoloConfig:
    """A YOLO detector.

    Attributes:
        layout: "mini", "tiny" or "v3".
        input_size: (width, height) of the network input in pixels (multiples of the max stride).
        class_names: detected classes (sigmoid per class).
        anchors: (w, h) in input pixels, indexed by the ``Yolo`` masks.
        ignore_thresh: predictions whose box overlaps any GT (or ignore box) above this IoU get no
            "no object" loss.
        obj_scale, noobj_scale: weights of the objectness BCE for assigned / unassigned priors.
        assign: ``"best"`` — each GT trains the single best-shaped anchor (YOLOv3 paper); ``"multi"``
            — also every other anchor whose width and height ratios to the GT are below
            ``anchor_ratio`` (in the cell of that anchor's head containing the GT centre).
        box_loss: ``"mse"`` on σ(t_x), σ(t_y), t_w, t_h (2019 PyTorch-YOLOv3), or ``"giou"`` on the
            decoded box (input pixels).
        obj_target: objectness target of an assigned prior: ``"binary"`` (1) or ``"iou"`` (the
            detached IoU of its decoded box with its GT, as the current PyTorch-YOLOv3 port), so the
            score ranks boxes by localisation quality.
        conf_threshold: minimum objectness x class probability kept by :meth:`detect`.
        nms_threshold: IoU above which NMS suppresses a lower-scored box of the same class.
        nms_merge: replace each kept box by the score-weighted mean of itself and the boxes it
            suppresses (the 2019 PyTorch-YOLOv3 port's NMS; the score is the kept box's).
        flip_tta: test-time augmentation: the network also sees the mirrored image, whose priors
            are mirrored back and pooled with the others before NMS (best with ``nms_merge``).
        max_detections: cap per image after NMS.
        fill: letterbox padding value (in [0, 1]).
    """

    layout: str = "mini"
    input_size: tuple[int, int] = (640, 192)
    class_names: tuple[str, ...] = ("Car",)
    anchors: tuple[tuple[float, float], ...] = MINI_ANCHORS
    ignore_thresh: float = 0.5
    obj_scale: float = 1.0
    noobj_scale: float = 1.0
    assign: str = "best"
    anchor_ratio: float = 4.0
    box_loss: str = "mse"
    obj_target: str = "binary"
    conf_threshold: float = 0.05
    nms_threshold: float = 0.4
    nms_merge: bool = False
    flip_tta: bool = False
    max_detections: int = 100
    fill: float = 0.5

    @property
    def num_classes(self) -> int:
        return len(self.class_names)

    def layers(self) -> list[Layer]:
        return LAYOUTS[self.layout]()

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> YoloConfig:
        d = dict(data)
        d["input_size"] = tuple(d["input_size"])
        d["class_names"] = tuple(d["class_names"])
        d["anchors"] = tuple(tuple(float(v) for v in a) for a in d["anchors"])
        return cls(**d)


#: Fields that change only how detections are read off the network (not its weights or training):
#: ``victims pack --yolo-option`` may set them on a trained detector.
INFERENCE_FIELDS = ("conf_threshold", "nms_threshold", "nms_merge", "flip_tta", "max_detections")

MINI = YoloConfig()
MINI3 = replace(MINI, layout="mini3", input_size=(960, 288), anchors=MINI3_ANCHORS)
TINY = replace(MINI, layout="tiny", input_size=(416, 416), anchors=TINY_ANCHORS, ignore_thresh=0.7)
V3 = replace(MINI, layout="v3", input_size=(416, 416), anchors=V3_ANCHORS, ignore_thresh=0.7)
CONFIGS: dict[str, YoloConfig] = {"mini": MINI, "mini3": MINI3, "tiny": TINY, "v3": V3}

#: Loss variants (reference §2.1): ``"v3"`` — the 2019 PyTorch-YOLOv3 loss (one prior per GT,
#: MSE coordinates, binary objectness); ``"iou"`` — several priors per GT, GIoU box loss and IoU
#: objectness targets (the current port's choices), which trains far faster on a CPU budget.
LOSSES: dict[str, dict[str, Any]] = {
    "v3": {"assign": "best", "box_loss": "mse", "obj_target": "binary"},
    "iou": {"assign": "multi", "box_loss": "giou", "obj_target": "iou"},
}
