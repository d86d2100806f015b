"""What the attack registry holds: :class:`AttackSpec` (a factory plus metadata) and the victim
requirements an attack declares (:class:`AttackRequirements`, checked against the victim's
:class:`~robustbench3d.victims.spec.Capabilities`: attacks know the victim contract, victims never
know attacks).

Standard library only, so importing ``robustbench3d.attacks`` loads no numpy/torch.
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from robustbench3d.errors import RobustBenchError
from robustbench3d.ranges import FRAMES_RANGE, SEED_RANGE
from robustbench3d.registry import Spec
from robustbench3d.victims.spec import Capabilities

if TYPE_CHECKING:
    from robustbench3d.attacks.base import Attack


#: The largest seed the attack commands accept (``show``/``attack apply`` draw a frame's attack from ``(seed, frame
#: id)`` as ``run`` does, ``attack train`` its batches and EOT): the range of ``run --seed``
#: (:data:`robustbench3d.ranges.SEED_RANGE`).
MAX_SEED = SEED_RANGE[1]
#: The most frames ``--max-frames`` may ask for (:data:`robustbench3d.ranges.FRAMES_RANGE`, as ``run --max-frames``).
MAX_FRAMES = FRAMES_RANGE[1]


def check_seed(seed: object, option: str = "--seed") -> int:
    """``seed`` if it is an integer in [0, :data:`MAX_SEED`]; else :class:`RobustBenchError` naming ``option``."""
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
        raise RobustBenchError(f"{option} {seed}: expected an integer in [0, 2**32 - 1] (as run --seed)")
    return seed


def check_max_frames(max_frames: object, option: str = "--max-frames") -> None:
    """Refuse a ``--max-frames`` that is not None nor an integer in [1, :data:`MAX_FRAMES`]."""
    if max_frames is None:
        return
    if isinstance(max_frames, bool) or not isinstance(max_frames, int) or not 1 <= max_frames <= MAX_FRAMES:
        raise RobustBenchError(f"{option} {max_frames}: expected an integer in [1, {MAX_FRAMES}] "
                               "(or no --max-frames: every frame)")


class AttackSpecError(RobustBenchError):
    """An attack factory refused its parameters or built something that is not an Attack."""


@dataclass(frozen=True)
class AttackRequirements:
    """What a victim must offer for an attack to be applied against it in a benchmark cell.

    Attributes:
        needs_gradients: the attack queries the victim's white-box oracles while it is applied
            (it receives the victim through :meth:`~robustbench3d.attacks.base.Attack.prepare`);
            the victim must declare ``gradients``. Objects crafted beforehand (a universal mesh
            loaded from a file) need no gradients at evaluation time, even if their crafting did.
        needs_camera: the attack acts through the camera only (e.g. a texture), so a victim that
            does not use the camera cannot be affected; the cell is skipped instead.
        needs_lidar: the same for the LiDAR (e.g. a shape perturbation seen only by the scan).
    """

    needs_gradients: bool = False
    needs_camera: bool = False
    needs_lidar: bool = False

    def unmet(self, capabilities: Capabilities) -> str | None:
        """Why a victim with ``capabilities`` cannot be attacked, or None if it can."""
        missing = []
        if self.needs_camera and "camera" not in capabilities.modalities:
            missing.append("the camera")
        if self.needs_lidar and "lidar" not in capabilities.modalities:
            missing.append("the LiDAR")
        if self.needs_gradients and not capabilities.gradients:
            missing.append("gradients (white-box oracles)")
        if not missing:
            return None
        offers = "+".join(capabilities.modalities) + (", gradients" if capabilities.gradients else ", no gradients")
        return f"needs {' and '.join(missing)}; the victim offers {offers}"

    def as_dict(self) -> dict[str, bool]:
        return {"needs_gradients": self.needs_gradients, "needs_camera": self.needs_camera,
                "needs_lidar": self.needs_lidar}


@dataclass(frozen=True)
class AttackSpec(Spec["Attack"]):
    """A factory ``(**params) -> Attack`` plus metadata; :meth:`create` checks the parameters.

    Attributes:
        factory: builds an :class:`~robustbench3d.attacks.base.Attack` (a class or a function).
        requirements: what the victim must offer (:class:`AttackRequirements`).
        summary: one line for listings.
    """

    requirements: AttackRequirements = field(default_factory=AttackRequirements)
    summary: str = ""

    def create(self, **params: Any) -> Attack:
        """Build the attack; unknown or missing parameters, or a factory that does not return an
        :class:`~robustbench3d.attacks.base.Attack`, raise :class:`AttackSpecError`."""
        from robustbench3d.attacks.base import Attack

        try:
            inspect.signature(self.factory).bind(**params)
        except TypeError as exc:
            raise AttackSpecError(f"invalid parameters {params}: {exc}") from None
        except ValueError:  # no signature available (builtins): let the call decide
            pass
        attack = self.factory(**params)
        if not isinstance(attack, Attack):
            raise AttackSpecError(f"factory returned a {type(attack).__name__}, not an Attack")
        return attack
