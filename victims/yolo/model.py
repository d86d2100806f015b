"""YOLO network built from a darknet-style layer list (:mod:`.config`) and its output decoding.

Convolutions are conv-BN-leaky(0.1) without bias; ``HeadConv`` is linear with bias. The network
returns one raw tensor per ``Yolo`` layer, (B, A·(5 + C), H, W), channels per anchor ordered
t_x, t_y, t_w, t_h, t_obj, class logits. :func:`flatten` decodes them (input pixels):
centre = (σ(t_x) + cell_x)·stride, size = anchor·exp(t_w, t_h); objectness and classes are
independent sigmoids, kept as logits. This is the differentiable twin (training, objectness
oracle) of :func:`robustbench3d.victims.yolo.postprocess.decode_heads` (the inference path).

Windows (:meth:`Darknet.forward_window`, :func:`flatten_window`): the head outputs of chosen cells only,
computed from the part of the input they read. Each layer runs its own block on the smallest slice of its
input that gives the cells needed downstream (the needs are propagated back through the layer list: a
3x3 convolution widens them by one position of its input grid, a 2x2 max-pool doubles them, an upsample
halves them, routes and shortcuts unite them); later layers read only its outputs whose inputs were all real
values of that slice or the true border padding of the whole input, and each convolution runs with the
kernel the whole input gets (:func:`_run_block`), so they are the values of the whole forward, bit for bit
(tests/victims/test_objectness_crop.py). In mini3 a stride-32 cell reads input px -127..+158 from its corner on each
axis (286 px), a stride-16 cell -47..+62 (110 px), a stride-8 cell at most -47..+54 (102 px).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from robustbench3d.victims.yolo.config import (
    CONFIGS,
    Conv,
    HeadConv,
    MaxPool,
    Route,
    Shortcut,
    Upsample,
    Yolo,
    YoloConfig,
)
from robustbench3d.victims.yolo.postprocess import MAX_LOG_SCALE


class _MaxPoolSame(nn.Module):
    """Darknet max-pool with stride 1: pad right/bottom by replication, keeping H x W."""

    def __init__(self, size: int):
        super().__init__()
        self.size = size

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p = self.size - 1
        return F.max_pool2d(F.pad(x, (0, p, 0, p), mode="replicate"), self.size, 1)


class _MaxPoolStrided(nn.MaxPool2d):
    """``nn.MaxPool2d``; under ``torch.inference_mode`` a 2x2, stride-2 pool runs as the elementwise maximum
    of its four strided slices: the same maxima (3-6x faster on one core than the pooling kernel on the
    B x C x H x W layout; tests/victims/test_yolo_pool.py). With autograd, or when exported, it is the plain pooling
    op, whose tie rule decides gradients."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not (torch.is_inference_mode_enabled() and self.kernel_size == 2 and self.stride == 2):
            return super().forward(x)
        h, w = x.shape[-2] // 2 * 2, x.shape[-1] // 2 * 2
        rows = torch.maximum(x[..., 0:h:2, :w], x[..., 1:h:2, :w])
        return torch.maximum(rows[..., 0::2], rows[..., 1::2])


class Darknet(nn.Module):
    """The network of a :class:`YoloConfig`. ``forward(images (B, 3, H, W) in [0, 1])`` returns the
    raw head outputs; attributes ``head_strides`` and ``head_masks`` describe them."""

    def __init__(self, cfg: YoloConfig):
        super().__init__()
        self.cfg = cfg
        self.specs = cfg.layers()
        self.blocks = nn.ModuleList()
        channels: list[int] = []
        strides: list[int] = []
        self.head_strides: list[int] = []
        self.head_masks: list[tuple[int, ...]] = []
        in_ch, stride = 3, 1
        nout = 5 + cfg.num_classes
        for i, spec in enumerate(self.specs):
            block: nn.Module = nn.Identity()
            if isinstance(spec, Conv):
                block = nn.Sequential(
                    nn.Conv2d(in_ch, spec.filters, spec.size, spec.stride, (spec.size - 1) // 2, bias=False),
                    nn.BatchNorm2d(spec.filters), nn.LeakyReLU(0.1))
                in_ch, stride = spec.filters, stride * spec.stride
            elif isinstance(spec, MaxPool):
                block = _MaxPoolStrided(spec.size, spec.stride) if spec.stride > 1 else _MaxPoolSame(spec.size)
                stride *= spec.stride
            elif isinstance(spec, Route):
                idx = [self._absolute(i, j) for j in spec.layers]
                in_ch, stride = sum(channels[j] for j in idx), strides[idx[0]]
            elif isinstance(spec, Upsample):
                block = nn.Upsample(scale_factor=spec.scale, mode="nearest")
                stride //= spec.scale
            elif isinstance(spec, HeadConv):
                nxt = self.specs[i + 1]
                if not isinstance(nxt, Yolo):
                    raise ValueError(f"layer {i}: HeadConv must be followed by a Yolo layer")
                block = nn.Conv2d(in_ch, len(nxt.mask) * nout, 1, bias=True)
                in_ch = len(nxt.mask) * nout
            elif isinstance(spec, Yolo):
                self.head_strides.append(stride)
                self.head_masks.append(spec.mask)
            elif not isinstance(spec, Shortcut):
                raise TypeError(f"unknown layer spec {spec!r}")
            self.blocks.append(block)
            channels.append(in_ch)
            strides.append(stride)
        used = sorted(a for m in self.head_masks for a in m)
        if used != list(range(len(cfg.anchors))):
            raise ValueError(f"Yolo masks {self.head_masks} do not cover the {len(cfg.anchors)} anchors")

    @staticmethod
    def _absolute(i: int, j: int) -> int:
        return i + j if j < 0 else j

    def forward(self, images: torch.Tensor) -> list[torch.Tensor]:
        outputs: list[torch.Tensor] = []
        heads: list[torch.Tensor] = []
        x = images
        for i, (spec, block) in enumerate(zip(self.specs, self.blocks, strict=True)):
            if isinstance(spec, Route):
                x = torch.cat([outputs[self._absolute(i, j)] for j in spec.layers], dim=1)
            elif isinstance(spec, Shortcut):
                x = outputs[i - 1] + outputs[i + spec.source]
            elif isinstance(spec, Yolo):
                heads.append(x)
            else:
                x = block(x)
            outputs.append(x)
        return heads

    # ---- windows ---------------------------------------------------------------------------
    def _sources(self, i: int) -> list[int]:
        """Layers whose outputs layer ``i`` reads (-1: the input image)."""
        spec = self.specs[i]
        if isinstance(spec, Route):
            return [self._absolute(i, j) for j in spec.layers]
        if isinstance(spec, Shortcut):
            return [i - 1, i + spec.source]
        return [i - 1]

    def layer_sizes(self, height: int, width: int) -> list[tuple[int, int]]:
        """(rows, columns) of every layer's output grid for an input of ``height`` x ``width`` px."""
        sizes: list[tuple[int, int]] = []
        for i, spec in enumerate(self.specs):
            src = self._sources(i)[0]
            h, w = (height, width) if src < 0 else sizes[src]
            sizes.append((_out_size(spec, h), _out_size(spec, w)))
        return sizes

    def needed_windows(self, windows: Sequence[Window | None], height: int,
                       width: int) -> tuple[list[Window | None], Window | None]:
        """Per layer the window of its output grid that the head ``windows`` (one per head, in head order,
        None: none of that head's cells) need, and the window of the input image they read."""
        sizes = self.layer_sizes(height, width)
        need: list[Window | None] = [None] * len(self.specs)
        heads = [i for i, spec in enumerate(self.specs) if isinstance(spec, Yolo)]
        if len(windows) != len(heads):
            raise ValueError(f"{len(windows)} head windows for a network with {len(heads)} heads")
        for i, win in zip(heads, windows, strict=True):
            need[i] = window_hull(need[i], win)
        image: Window | None = None
        for i in range(len(self.specs) - 1, -1, -1):
            if need[i] is None:
                continue
            for src in self._sources(i):
                size = (height, width) if src < 0 else sizes[src]
                reads = _reads_window(self.specs[i], need[i], size)
                if src < 0:
                    image = window_hull(image, reads)
                else:
                    need[src] = window_hull(need[src], reads)
        return need, image

    def forward_window(self, images: torch.Tensor | WindowedHead, windows: Sequence[Window | None],
                       input_hw: tuple[int, int] | None = None, batch: int | None = None) -> list[WindowedHead | None]:
        """The head outputs of the cells in ``windows`` (per head ((row0, row1), (col0, col1)) half-open cell
        ranges of that head's grid, or None), each computed from the slice of the input it reads: the values
        of the same cells of :meth:`forward` on the whole input, bit for bit (module doc; each convolution
        runs with the kernel family it gets on the whole input, see :func:`_run_block`). ``images``:
        the whole (B, 3, H, W) input, or a part of an input of ``input_hw`` = (H, W) px holding the window
        :meth:`needed_windows` names. ``batch``: the size of the batch whose whole-input forward this
        matches, when ``images`` is a part of it (PyTorch's kernel choice depends on it). Differentiable
        w.r.t. ``images``.

        A layer's result is kept as its block returned it, a window of its grid that holds the needed one
        (plus positions, at the slice's edges, that no later layer reads): each consumer slices what it
        reads, so every value takes one slice on its way (and its gradient one copy back)."""
        source = images if isinstance(images, WindowedHead) else WindowedHead(images, 0, 0)
        if input_hw is None:
            if isinstance(images, WindowedHead):
                raise ValueError("forward_window: a part of the input needs input_hw, the whole input's (H, W)")
            input_hw = (images.shape[-2], images.shape[-1])
        height, width = input_hw
        sizes = self.layer_sizes(height, width)
        need, _ = self.needed_windows(windows, height, width)
        out: list[WindowedHead | None] = [None] * len(self.specs)
        heads: list[WindowedHead | None] = []
        for i, (spec, block) in enumerate(zip(self.specs, self.blocks, strict=True)):
            win = need[i]
            if win is None:
                if isinstance(spec, Yolo):
                    heads.append(None)
                continue
            if isinstance(spec, Route):
                out[i] = WindowedHead(torch.cat([_slice(out[j], win) for j in self._sources(i)], dim=1), *_origin(win))
            elif isinstance(spec, Shortcut):
                a, b = self._sources(i)
                out[i] = WindowedHead(_slice(out[a], win) + _slice(out[b], win), *_origin(win))
            elif isinstance(spec, Yolo):
                h = len(heads)
                out[i] = WindowedHead(_slice(out[i - 1], win), *_origin(win))
                heads.append(None if windows[h] is None else
                             WindowedHead(_slice(out[i], windows[h]), *_origin(windows[h])))
            else:
                src = source if i == 0 else out[i - 1]
                size = (height, width) if i == 0 else sizes[i - 1]
                (r0, r1, fr), (c0, c1, fc) = (_reads(spec, lo, hi, n) for (lo, hi), n in zip(win, size, strict=True))
                x = _slice(src, ((r0, r1), (c0, c1)))
                if isinstance(spec, MaxPool) and spec.stride > 1:
                    out[i] = WindowedHead(_max_pool(x, spec), fr, fc)
                else:
                    whole = (max(batch or 0, x.shape[0]), x.shape[1], *size)
                    out[i] = _run_block(block, x, ((r0, r1), (c0, c1)), (fr, fc), whole)
        return heads


def _origin(win: Window) -> tuple[int, int]:
    return win[0][0], win[1][0]


#: A half-open range [lo, hi) of positions along one axis of a layer's grid.
Span = tuple[int, int]
#: (rows, columns) spans of a layer's grid.
Window = tuple[Span, Span]


@dataclass(frozen=True)
class WindowedHead:
    """Outputs of a window of a layer's grid: ``values`` (B, C, rows, cols) whose [0, 0] is cell (row0, col0)."""

    values: torch.Tensor
    row0: int
    col0: int


def _out_size(spec: object, n: int) -> int:
    """Output length along one axis of a layer whose input is ``n`` long."""
    if isinstance(spec, Conv):
        return (n - 1) // spec.stride + 1  # padding (size - 1) // 2, odd sizes
    if isinstance(spec, MaxPool):
        return (n - spec.size) // spec.stride + 1 if spec.stride > 1 else n
    if isinstance(spec, Upsample):
        return n * spec.scale
    return n


def _reads(spec: object, lo: int, hi: int, n_in: int) -> tuple[int, int, int]:
    """(in_lo, in_hi, first): the input positions [in_lo, in_hi) (one axis, input ``n_in`` long) the
    layer's block runs on to give the outputs [lo, hi) as the whole input does, and the output position
    of the result's first element. Slices start on the layer's stride grid; a slice edge inside the
    input is at least the kernel's reach from every output kept (the block's own zero / replicate padding
    there only touches outputs that are dropped); at the input's border the padding is the true one."""
    if isinstance(spec, Conv):
        r, st = (spec.size - 1) // 2, spec.stride
        in_lo = max(0, lo * st - -(-r // st) * st)
        return in_lo, min(n_in, (hi - 1) * st + r + 1), in_lo // st
    if isinstance(spec, MaxPool):
        if spec.stride > 1:
            return lo * spec.stride, (hi - 1) * spec.stride + spec.size, lo
        return lo, min(n_in, hi + spec.size - 1), lo
    if isinstance(spec, Upsample):
        return lo // spec.scale, (hi - 1) // spec.scale + 1, (lo // spec.scale) * spec.scale
    return lo, hi, lo


def _reads_window(spec: object, win: Window, size: tuple[int, int]) -> Window:
    (r0, r1, _), (c0, c1, _) = (_reads(spec, lo, hi, n) for (lo, hi), n in zip(win, size, strict=True))
    return (r0, r1), (c0, c1)


def _conv_backend(conv: nn.Conv2d, shape: tuple[int, ...]) -> object:
    """The kernel family ``F.conv2d`` picks for ``conv`` on an input of ``shape`` (None where torch cannot
    say). PyTorch picks oneDNN or its own im2col kernels by input size; the two round differently, while
    one family gives an output the same value on any slice that holds its inputs."""
    select = getattr(torch._C, "_select_conv_backend", None)
    if select is None:
        return None
    try:
        x = torch.empty(1, dtype=conv.weight.dtype).expand(*shape)
        return select(x, conv.weight, conv.bias, list(conv.stride), list(conv.padding), list(conv.dilation),
                      False, [0, 0], conv.groups)
    except (RuntimeError, TypeError):
        return None


def _max_pool(x: torch.Tensor, spec: MaxPool) -> torch.Tensor:
    """The strided max-pool of ``spec`` on a channels-last copy of ``x`` (PyTorch's vectorised kernel, ~3x
    faster on one core): the same maxima and, in ties, the same chosen inputs (so the same gradients) as
    on ``x`` itself (tests/victims/test_objectness_crop.py compares the two paths, ties of the letterbox fill
    included); returned contiguous, as the convolution that follows expects."""
    y = F.max_pool2d(x.contiguous(memory_format=torch.channels_last), spec.size, spec.stride)
    return y.contiguous()


def _run_block(block: nn.Module, x: torch.Tensor, reads: Window, first: tuple[int, int],
               whole: tuple[int, ...]) -> WindowedHead:
    """``block`` on ``x``, the ``reads`` window of its input (whose whole is of shape ``whole``); ``first``:
    the output position of the result's first element when run on the slice.

    A convolution gives an output the same value on any input that holds the output's inputs only when it
    runs the same kernel in the same place. PyTorch picks oneDNN or its own im2col + BLAS product by input
    size; the two round differently, and a BLAS product's rounding depends on where an output falls in it.
    So a convolution that oneDNN runs on the whole input runs on the slice, zeros added below / right (and,
    if that is not enough, zero images to the batch of the whole input) until PyTorch picks oneDNN for it too
    (the zeros only reach outputs that are dropped, or at the input's border stand where its zero padding
    stands); any other runs on the whole grid, the slice placed where it lies and zeros elsewhere (PyTorch's
    own kernels serve 1x1 convolutions on one thread: cheap on the whole grid)."""
    conv = block[0] if isinstance(block, nn.Sequential) else block
    if not isinstance(conv, nn.Conv2d) or conv.padding_mode != "zeros":
        return WindowedHead(block(x), *first)
    family = _conv_backend(conv, whole)
    names = getattr(torch._C, "_ConvBackend", None)
    if family is None or names is None:
        return WindowedHead(block(x), *first)  # torch cannot say: the slice (equal to kernel rounding)
    if family != names.Mkldnn:
        (r0, r1), (c0, c1) = reads
        return WindowedHead(block(F.pad(x, (c0, whole[3] - c1, r0, whole[2] - r1))), 0, 0)
    b, c, h, w = x.shape
    for batch in sorted({b, max(b, whole[0])}):  # PyTorch also picks oneDNN for any batch of two or more
        for rows in range(h, max(h, whole[2]) + 1):
            for cols in range(w if rows == h else max(w, whole[3]), max(w, whole[3]) + 1):
                if _conv_backend(conv, (batch, c, rows, cols)) == family:
                    return WindowedHead(block(_zero_padded(x, batch - b, rows - h, cols - w))[:b], *first)
    return WindowedHead(block(x), *first)


def _zero_padded(x: torch.Tensor, images: int, rows: int, cols: int) -> torch.Tensor:
    """``x`` with zeros added: ``images`` more images, ``rows`` below and ``cols`` right."""
    if rows or cols:
        x = F.pad(x, (0, cols, 0, rows))
    if images:
        x = torch.cat([x, x.new_zeros(images, *x.shape[1:])])
    return x


def window_hull(a: Window | None, b: Window | None) -> Window | None:
    """The smallest window containing both (None: empty)."""
    if a is None or b is None:
        return a if b is None else b
    return ((min(a[0][0], b[0][0]), max(a[0][1], b[0][1])), (min(a[1][0], b[1][0]), max(a[1][1], b[1][1])))


def _slice(src: WindowedHead | None, win: Window) -> torch.Tensor:
    """The part of ``src`` covering ``win`` (which it must contain)."""
    assert src is not None
    (r0, r1), (c0, c1) = win
    h, w = src.values.shape[-2:]
    if not (src.row0 <= r0 and r1 <= src.row0 + h and src.col0 <= c0 and c1 <= src.col0 + w):
        raise AssertionError(f"window {win} is not inside the computed {(src.row0, src.col0, h, w)}")
    if (r0, r1, c0, c1) == (src.row0, src.row0 + h, src.col0, src.col0 + w):
        return src.values
    return src.values[..., r0 - src.row0:r1 - src.row0, c0 - src.col0:c1 - src.col0]


@dataclass
class YoloPredictions:
    """All priors of all heads, flattened (P priors per image, head by head, then anchor, row, column).

    Attributes:
        boxes: (B, P, 4) decoded cx, cy, w, h in input pixels (differentiable).
        raw: (B, P, 4) t_x, t_y, t_w, t_h.
        obj_logit: (B, P) objectness logits.
        cls_logit: (B, P, C) class logits.
        anchor: (P,) int64 global anchor index; grid: (P, 2) int64 cell (column, row);
        stride: (P,) float stride in pixels; head: (P,) int64 head index.
        layout: per head (stride, grid rows, grid columns, anchor mask, offset of its first prior).
        index: None when the P priors are all the priors of the input; for the priors of windows
            (:func:`flatten_window`) the (P,) int64 position of each in the whole input's flattening
            (``layout`` and ``grid`` then describe the whole input).
    """

    boxes: torch.Tensor
    raw: torch.Tensor
    obj_logit: torch.Tensor
    cls_logit: torch.Tensor
    anchor: torch.Tensor
    grid: torch.Tensor
    stride: torch.Tensor
    head: torch.Tensor
    layout: list[HeadLayout]
    index: torch.Tensor | None = None

    @property
    def prior_id(self) -> torch.Tensor:
        """(P,) int64 position of each prior in the whole input's flattening."""
        return self.index if self.index is not None else torch.arange(self.obj_logit.shape[1])


@dataclass(frozen=True)
class HeadLayout:
    stride: int
    rows: int
    cols: int
    mask: tuple[int, ...]
    offset: int


def flatten(heads: list[torch.Tensor], net: Darknet) -> YoloPredictions:
    """Decode raw head outputs of ``net`` into :class:`YoloPredictions`."""
    return _flatten([WindowedHead(h, 0, 0) for h in heads], net, [tuple(h.shape[-2:]) for h in heads], False)


def flatten_window(heads: Sequence[WindowedHead | None], net: Darknet, input_hw: tuple[int, int]) -> YoloPredictions:
    """Decode the windowed head outputs of :meth:`Darknet.forward_window` (input ``input_hw`` = (H, W) px)
    into :class:`YoloPredictions` of their priors, with the whole input's cells, box centres and prior
    positions (``index``); a head without a window contributes no priors."""
    sizes = net.layer_sizes(*input_hw)
    yolo = [i for i, spec in enumerate(net.specs) if isinstance(spec, Yolo)]
    grids = [sizes[i] for i in yolo]
    return _flatten(heads, net, grids, True)


def _flatten(heads: Sequence[WindowedHead | None], net: Darknet, grids: Sequence[tuple[int, int]],
             windowed: bool) -> YoloPredictions:
    """Priors of each head's window, cells and prior positions those of a grid of ``grids[h]`` cells."""
    cfg = net.cfg
    nout = 5 + cfg.num_classes
    parts: list[torch.Tensor] = []
    boxes: list[torch.Tensor] = []
    meta: dict[str, list[torch.Tensor]] = {"anchor": [], "grid": [], "stride": [], "head": [], "index": []}
    layout: list[HeadLayout] = []
    offset = 0
    for h, (win, (full_h, full_w), stride, mask) in enumerate(
            zip(heads, grids, net.head_strides, net.head_masks, strict=True)):
        a = len(mask)
        layout.append(HeadLayout(int(stride), full_h, full_w, tuple(mask), offset))
        if win is not None:
            raw = win.values
            b, _, gh, gw = raw.shape
            p = raw.view(b, a, nout, gh, gw).permute(0, 1, 3, 4, 2).reshape(b, a * gh * gw, nout)
            gy, gx = torch.meshgrid(torch.arange(gh) + win.row0, torch.arange(gw) + win.col0, indexing="ij")
            grid = torch.stack([gx, gy], dim=-1).reshape(1, gh * gw, 2).expand(a, -1, -1).reshape(-1, 2)
            anchors = torch.tensor([cfg.anchors[k] for k in mask], dtype=raw.dtype)
            anc = anchors[:, None, :].expand(-1, gh * gw, -1).reshape(-1, 2)
            xy = (torch.sigmoid(p[..., 0:2]) + grid.to(raw.dtype)) * stride
            wh = anc * torch.exp(p[..., 2:4].clamp(max=MAX_LOG_SCALE))
            boxes.append(torch.cat([xy, wh], dim=-1))
            parts.append(p)
            meta["anchor"].append(torch.tensor(mask, dtype=torch.int64)[:, None].expand(-1, gh * gw).reshape(-1))
            meta["grid"].append(grid)
            meta["stride"].append(torch.full((a * gh * gw,), float(stride)))
            meta["head"].append(torch.full((a * gh * gw,), h, dtype=torch.int64))
            if windowed:
                cell = (gy * full_w + gx).reshape(1, -1)
                meta["index"].append((offset + torch.arange(a)[:, None] * (full_h * full_w) + cell).reshape(-1))
        offset += a * full_h * full_w
    if not parts:
        raise ValueError("no head window: nothing to decode")
    allp = torch.cat(parts, dim=1)
    return YoloPredictions(
        boxes=torch.cat(boxes, dim=1), raw=allp[..., 0:4], obj_logit=allp[..., 4], cls_logit=allp[..., 5:],
        anchor=torch.cat(meta["anchor"]), grid=torch.cat(meta["grid"]), stride=torch.cat(meta["stride"]),
        head=torch.cat(meta["head"]), layout=layout, index=torch.cat(meta["index"]) if windowed else None,
    )


def build_model(cfg: YoloConfig | str = "mini", seed: int = 0) -> Darknet:
    """A freshly initialised network, weights drawn from a torch RNG seeded with ``seed``."""
    if isinstance(cfg, str):
        cfg = CONFIGS[cfg]
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return Darknet(cfg)


def conv_layer_count(net: Darknet) -> int:
    """Number of convolution layers (darknet counts the linear head convs too)."""
    return sum(isinstance(m, nn.Conv2d) for m in net.modules())
