"""What a victim declares, standard library only: its :class:`Capabilities`, the :class:`EntryInfo` of its
registry entry, and the proposal modes (frustum protocols, :data:`PROPOSAL_SOURCES`) with the words every
listing prints for them (:data:`PROTOCOL_LABELS`).

The one definition of these words, below both :mod:`robustbench3d.victims.base` (the contract, which uses
them) and :mod:`robustbench3d.victims.spec` (the registry's :class:`~robustbench3d.victims.spec.VictimSpec`,
which checks that contract and re-exports them: plugins import them from there).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Literal, get_args

MODALITIES: tuple[str, ...] = ("camera", "lidar")
BACKENDS: tuple[str, ...] = ("torch", "onnx", "other")
_SHA256 = re.compile(r"^[0-9a-f]{64}$")

#: A cell's proposal mode (frustum protocol): the victim's own 2D detector; the frame's ground-truth 2D boxes;
#: each target car's GT box united with the image box of the object on its roof; or the GT boxes with that
#: car's object returns added to its frustum (see :mod:`robustbench3d.victims.base`).
ProposalSource = Literal["detector", "gt", "gt-object", "gt-append"]
PROPOSAL_SOURCES: tuple[str, ...] = get_args(ProposalSource)
#: The modes whose boxes the harness builds from the labels: types given, scores 1, scored as ground truth.
GT_PROPOSAL_SOURCES: tuple[str, ...] = ("gt", "gt-object", "gt-append")
#: The modes the harness builds from an attack's record of its objects as well as from the labels.
OBJECT_PROPOSAL_SOURCES: tuple[str, ...] = ("gt-object", "gt-append")
#: How each proposal mode is told to a reader: the one place these words live; everything that prints a
#: protocol uses them.
PROTOCOL_LABELS: dict[str, str] = {
    "detector": "the victim's own 2D detector",
    "gt": "GT 2D boxes (object outside the frustum)",
    "gt-object": "GT 2D box united with the object's projected box",
    "gt-append": "GT-box frustum plus the car's object returns",
}


@dataclass(frozen=True)
class Capabilities:
    """What a registered victim uses and offers.

    Attributes:
        modalities: sensors used, a subset of ``("camera", "lidar")``.
        backend: "torch", "onnx" or "other" (e.g. numpy).
        gradients: True if it exposes differentiable quantities to attacks (white box).
        deterministic: True if identical inputs give bit-identical outputs across calls.
    """

    modalities: tuple[str, ...]
    backend: str
    gradients: bool
    deterministic: bool

    def __post_init__(self) -> None:
        mods = tuple(self.modalities)
        if not mods or len(set(mods)) != len(mods) or any(m not in MODALITIES for m in mods):
            raise ValueError(f"modalities must be distinct values of {MODALITIES}, got {mods}")
        object.__setattr__(self, "modalities", tuple(m for m in MODALITIES if m in mods))
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {self.backend!r}")

    def as_dict(self) -> dict[str, Any]:
        return {"modalities": list(self.modalities), "backend": self.backend,
                "gradients": self.gradients, "deterministic": self.deterministic}


@dataclass(frozen=True)
class EntryInfo:
    """Metadata every registered victim declares.

    Attributes:
        capabilities: see :class:`Capabilities`.
        weights_sha256: lowercase hex sha256 of the shipped weights file, None until weights ship.
        summary: one line for listings.
    """

    capabilities: Capabilities
    weights_sha256: str | None = None
    summary: str = ""

    def __post_init__(self) -> None:
        if self.weights_sha256 is not None and not _SHA256.match(self.weights_sha256):
            raise ValueError(f"weights_sha256 must be 64 lowercase hex digits, got {self.weights_sha256!r}")

    def as_dict(self) -> dict[str, Any]:
        return {"capabilities": self.capabilities.as_dict(), "weights_sha256": self.weights_sha256,
                "summary": self.summary}


def describe_sources(sources: tuple[str, ...] = PROPOSAL_SOURCES) -> str:
    """``"detector: the victim's own 2D detector; gt: GT 2D boxes (object outside the frustum); ..."``: each
    proposal source with its protocol's words (:data:`PROTOCOL_LABELS`)."""
    return "; ".join(f"{s}: {PROTOCOL_LABELS[s]}" for s in sources)


__all__ = [
    "BACKENDS",
    "GT_PROPOSAL_SOURCES",
    "MODALITIES",
    "OBJECT_PROPOSAL_SOURCES",
    "PROPOSAL_SOURCES",
    "PROTOCOL_LABELS",
    "Capabilities",
    "EntryInfo",
    "ProposalSource",
    "describe_sources",
]
