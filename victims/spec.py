"""The victim side's words, standard library only: what the victim registry holds (:class:`VictimSpec`), and,
re-exported from :mod:`robustbench3d.victims.capabilities` where they are defined, what a victim declares
(:class:`Capabilities`, :class:`EntryInfo`) and the proposal modes (:data:`PROPOSAL_SOURCES`).

Kept free of numpy/torch, so ``robustbench3d.victims`` (and ``victims list``, ``run --help``) stay
cheap; the contract these words describe is :mod:`robustbench3d.victims.base`, which :meth:`VictimSpec.create`
checks (importing it then: the contract imports the words from below, never this module).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from robustbench3d.registry import Spec
from robustbench3d.victims.capabilities import (
    BACKENDS,
    GT_PROPOSAL_SOURCES,
    MODALITIES,
    OBJECT_PROPOSAL_SOURCES,
    PROPOSAL_SOURCES,
    PROTOCOL_LABELS,
    Capabilities,
    EntryInfo,
    ProposalSource,
    describe_sources,
)

if TYPE_CHECKING:
    from robustbench3d.victims.base import Detector


@dataclass(frozen=True)
class VictimSpec(Spec["Detector"]):
    """A factory returning a :class:`~robustbench3d.victims.base.Detector`, plus its
    :class:`EntryInfo`. :meth:`create` checks the contract the capabilities declare."""

    info: EntryInfo

    def create(self, **kwargs: Any) -> Detector:
        from robustbench3d.victims.base import check_victim

        victim = self.factory(**kwargs)
        check_victim(victim, self.info.capabilities)
        return victim


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
    "VictimSpec",
    "describe_sources",
]
