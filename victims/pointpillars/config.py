"""Configuration of the PointPillars-style network (standard library + the pillar grid; no torch), shared by
the torch model, the numpy glue and the ONNX twin."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from robustbench3d.victims.pointpillars.pillars import PillarGrid

#: Output channels of the head, in order.
HEAD_CHANNELS: tuple[str, ...] = ("heatmap", "dx", "dy", "z", "log_l", "log_w", "log_h", "sin", "cos")


@dataclass(frozen=True)
class PointPillarsConfig:
    """Grid, channel widths and layer counts. ``out_stride``: output cell = out_stride pillars."""

    grid: PillarGrid = field(default_factory=PillarGrid)
    pillar_channels: int = 64
    block_channels: tuple[int, int, int] = (64, 128, 128)
    block_layers: tuple[int, int, int] = (3, 4, 3)
    up_channels: int = 64
    head_channels: int = 64

    @property
    def out_stride(self) -> int:
        return 2

    def to_dict(self) -> dict:
        d = asdict(self)
        d["block_channels"], d["block_layers"] = list(self.block_channels), list(self.block_layers)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> PointPillarsConfig:
        d = dict(d)
        return cls(grid=PillarGrid(**d.pop("grid")), block_channels=tuple(d.pop("block_channels")),
                   block_layers=tuple(d.pop("block_layers")), **d)


def output_shape(cfg: PointPillarsConfig) -> tuple[int, int]:
    """(H, W) of the output map: ceil(ny / 2), ceil(nx / 2)."""
    return (cfg.grid.ny + 1) // 2, (cfg.grid.nx + 1) // 2
