"""Black-box universal optimisation of a roof object (``attack train --optimizer cma``): CMA-ES over the
white-box trainer's own parameters, scored through the victim's ``detect`` alone.

**Parameters.** Those of :class:`~robustbench3d.attacks.train.UniversalTrainer`, in its unconstrained
parametrisation, only those the mode optimises: the vertex offsets ``delta`` (V, 3) through
:func:`~robustbench3d.attacks.object.tanh_vertices` (every candidate stays inside the family's box +-radius) for
``adv-shape``, the colour logits (V, 3) through a sigmoid for ``adv-texture``, both for ``adv-object`` (V: the
family's vertices, 162 by default, so 486 or 972 dimensions). A candidate ``x`` is those arrays flattened
(offsets first); the search starts where the white-box trainer starts (offsets 0, colours the neutral grey)
with the initial standard deviation :data:`SHAPE_STEP` per offset and :data:`COLOUR_STEP` per logit. The
parameter a mode does not optimise stays at the white-box trainer's fixed value (the undeformed sphere, the grey).

**Fitness** (lower is better) of a candidate on the generation's frames: the mean over their target cars of
the car's *detection score*, the highest ``score`` among the victim's Car detections whose BEV IoU with the
car is at least 0.7 (the benchmark's matching threshold for Car), 0 when none is; plus ``lambda_lap`` x the
object's Laplacian smoothness (m) in the modes that move the shape, as the white-box loss has it. The
benchmark counts a car as found when a detection matches it at BEV IoU >= 0.7 and ranks the matches by score,
so this is a smooth surrogate of its detected / not-detected: it falls when a car is lost (to 0) and, while no
car flips, when the matched detections' scores fall (which lowers the AP too, as they sink under the false
positives), so the ranking CMA-ES needs has signal long before the first car is lost. The harness scores the
detections against the frame's labels itself; the victim gets frames with ``labels=None``
(:func:`~robustbench3d.victims.base.victim_inputs`).

**Queries.** One ``detect`` of one attacked frame is one query. Each candidate is placed and rendered into
both sensors exactly as a benchmark cell does (:class:`~robustbench3d.attacks.roof.RoofObjectAttack` with
the run's EOT, supersample and occlusion settings, exact occlusion on a generated dataset) on every target car
of each frame, and the frame goes to ``detect`` with the proposals the held-out curve scores with
(:func:`~robustbench3d.attacks.blackbox_run.query_proposals`: the victim's own 2D detector for the modes with a
texture, else ``--lidar-boxes``, whose default ``gt`` becomes ``detector`` for a victim that finds its own
objects, i.e. lists ``detector`` but not ``gt``; the frustum protocols get the record of the placement, as in a
cell). A mode the victim does not list in ``supported_proposals`` is refused before any query. A
generation costs ``population x frames_per_candidate`` queries; the run stops before a generation that would
pass the query budget, so it uses the budget exactly when it is a multiple of that cost and otherwise leaves
the remainder (less than one generation) unused. The held-out curve's queries are counted apart.

**Common random numbers.** Every candidate of generation ``g`` is scored on the same frames, drawn without
replacement from the training frames that have target cars by ``numpy.random.default_rng([seed, g,``
:data:`FRAMES_STREAM` ``])``, with the same EOT draws: frame slot ``k`` uses ``default_rng([seed, g, k,``
:data:`~robustbench3d.attacks.train_config.EOT_STREAM` ``])``. So the ranking inside a generation compares
objects, not frames.

**Why pycma** (``cma``, the optional extra ``blackbox``), rather than nevergrad: it is the reference
implementation of CMA-ES by its author, with the separable variant (option ``CMA_diagonal``) built in; it
depends on numpy alone (nevergrad depends on ``cma`` itself plus bayesian-optimization, pandas and more); its
ask/tell interface lets this harness own the loop, the query count and the checkpoints; with its normal draws
taken from a generator we seed (option ``randn``; ``seed`` NaN so it never touches numpy's global state) it is
deterministic, so a run is a function of (seed, fitness values). Bounds are not needed: the tanh and sigmoid
parametrisations map every real vector into the box and into [0, 1].

**Why the diagonal (separable) variant.** With 486 to 972 dimensions, full CMA-ES learns its covariance matrix
at rates ~2 / n^2 (pycma 4.5 at n = 486, popsize 12: c1 = 8.4e-6, cmu = 1.9e-5), so within a few hundred
generations (the budgets here) it is an isotropic ES that also pays O(n^2) memory and an O(n^3)
eigendecomposition; the diagonal variant (Ros & Hansen 2008) learns one variance per coordinate at rates about
n / 3 larger (c1 = 1.9e-3, cmu = 3.9e-3), O(n) per sample, which is what a few hundred generations can use: a
per-vertex, per-channel step size. Step-size control is CSA (cumulative step-size adaptation), set explicitly:
pycma would pick TPA at n >= 300, whose consistency check draws from numpy's global generator.

**Resume.** The checkpoint ``OBJ.cma.json`` (plain JSON, :mod:`~robustbench3d.attacks.blackbox_run`) holds the
fitness values of every generation, not pycma's internals: a resumed run rebuilds the strategy from the seed
and replays ask/tell with the recorded values (no query), which reproduces its state exactly, and checks the
result against the sha256 of the mean and the step size the checkpoint recorded.

The ``cma`` package is imported only by :func:`import_cma` (the package works without it).
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from robustbench3d.attacks.base import target_cars
from robustbench3d.attacks.object import NEUTRAL_GREY, RoofObject, laplacian_smoothness, template_vertices
from robustbench3d.attacks.train_config import (
    BEV_IOU_DETECTED,
    EOT_DROPOUT,
    EOT_RANGE_NOISE_M,
    EOT_STREAM,
    TrainConfig,
    TrainingError,
)
from robustbench3d.errors import RobustBenchError
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.kitti.labels import Labels

#: The optional dependency (pyproject extra) that provides the ``cma`` package.
EXTRA = "blackbox"
#: Generator streams: each generation's frames; the CMA sampler's normal draws.
FRAMES_STREAM, CMA_STREAM = 0xF4A3, 0xC3A
#: Initial standard deviation of each vertex offset and of each colour logit, the scale of the white-box objects:
#: the shipped adv-shape and adv-object moved their offsets by 0.16 and 0.36 on average (95th percentile 0.47
#: and 0.88; at 0.3 a vertex half-way to its box face moves by ~0.08 m of the 0.4 m radius), and 91 % of the
#: shipped texture's colour channels are saturated (within 0.05 of 0 or 1; mean |logit| 5.7), so the colour
#: draws start at sigmoid(+-3) = 0.05 / 0.95 within one standard deviation: binary-like patterns, as the
#: white-box texture's, where a step of 1 would stay in 0.27 to 0.73 and CSA, at ~2 % per generation in 486
#: dimensions, would need a hundred generations to grow it.
SHAPE_STEP, COLOUR_STEP = 0.3, 3.0
#: Ranges of the black-box settings (inclusive; :class:`BlackBoxSettings`). population (CMA-ES lambda) from 4,
#: the smallest pycma's default rule gives (4 + 3 ln n), to 4096: a generation of 4096 candidates on one frame
#: is ~15 min at ~0.2 s per query, beyond that one step of the strategy costs hours. frames_per_candidate in
#: [1, 1024] as the white-box --batch-cars (a frame holds ~10 cars). query_budget in [1, 1e8] frame queries
#: (1e8 at ~0.2 s each is ~8 months of one core); it must also pay for one generation (checked with the data).
INT_RANGES = {"population": (4, 4096), "frames_per_candidate": (1, 1024), "query_budget": (1, 100_000_000)}
#: Default frames per candidate and generation: two frames hold ~20 target cars on the embedded data, and a
#: generation of the default population (22) costs 44 queries, ~10 s on one core at ~0.22 s per query.
FRAMES_PER_CANDIDATE = 2
#: The car class the fitness reads among the detections (the benchmark's headline class).
CAR = "Car"


def import_cma() -> Any:
    """The ``cma`` module, or a one-line :class:`~robustbench3d.errors.RobustBenchError` naming the extra."""
    try:
        import cma
    except ImportError:
        raise RobustBenchError(f"--optimizer cma needs the package cma (pycma), which is not installed: pip install "
                               f"'robustbench3d[{EXTRA}]'") from None
    return cma


def _check_int(name: str, value: object) -> None:
    """Refuse a setting outside :data:`INT_RANGES` (one line naming the option and the range)."""
    low, high = INT_RANGES[name]
    flag = f"--{name.replace('_', '-')}"
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise TrainingError(f"{flag}: must be an integer in [{low}, {high}], got {value!r}")


@dataclass(frozen=True)
class BlackBoxSettings:
    """The optimiser's settings (module doc): the query budget, the population (None: pycma's default
    ``4 + floor(3 ln n)`` for n dimensions) and the frames each candidate is scored on per generation."""

    query_budget: int
    population: int | None = None
    frames_per_candidate: int = FRAMES_PER_CANDIDATE

    def __post_init__(self) -> None:
        _check_int("query_budget", self.query_budget)
        if self.population is not None:
            _check_int("population", self.population)
        _check_int("frames_per_candidate", self.frames_per_candidate)

    def popsize(self, dimension: int) -> int:
        """The population of a search in ``dimension`` dimensions."""
        return self.population if self.population is not None else 4 + int(3 * math.log(dimension))

    def generation_queries(self, dimension: int) -> int:
        """Frame queries per generation."""
        return self.popsize(dimension) * self.frames_per_candidate

    def record(self, dimension: int, cma_version: str) -> dict[str, Any]:
        """The sidecar's ``made_by.optimizer``."""
        return {"name": "cma", "package": f"cma {cma_version}", "variant": "separable (CMA_diagonal), CSA step size",
                "dimension": dimension, "population": self.popsize(dimension),
                "frames_per_candidate": self.frames_per_candidate, "query_budget": self.query_budget,
                "initial_std": {"shape_offset": SHAPE_STEP, "colour_logit": COLOUR_STEP},
                "fitness": "mean over target cars of the best Car score at BEV IoU >= 0.7 (0 if none)"
                           " + lambda_lap x Laplacian (shape modes)"}

    def identity(self, dimension: int, cma_version: str) -> dict[str, Any]:
        """What a resumed run must share with the checkpoint: the record without the budget (it may grow)."""
        d = self.record(dimension, cma_version)
        d.pop("query_budget")
        return d


class ParamSpace:
    """The candidate vector ``x`` of a mode and the object it stands for (module doc)."""

    def __init__(self, config: TrainConfig) -> None:
        self.config, self.family, self.kind = config, config.family, config.kind
        self.n = self.family.n_vertices
        self.grey_logit = math.log(NEUTRAL_GREY / (1.0 - NEUTRAL_GREY))
        self.dimension = 3 * self.n * (int(self.kind.shape) + int(self.kind.colour))

    def start(self) -> np.ndarray:
        """The white-box trainer's start: offsets 0, grey logits."""
        parts = ([np.zeros(3 * self.n)] if self.kind.shape else []) + \
                ([np.full(3 * self.n, self.grey_logit)] if self.kind.colour else [])
        return np.concatenate(parts)

    def stds(self) -> np.ndarray:
        """Initial standard deviation of each coordinate."""
        parts = ([np.full(3 * self.n, SHAPE_STEP)] if self.kind.shape else []) + \
                ([np.full(3 * self.n, COLOUR_STEP)] if self.kind.colour else [])
        return np.concatenate(parts)

    def split(self, x: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
        """(offsets (V, 3) or None when the shape is fixed, colour logits (V, 3))."""
        x = np.asarray(x, dtype=np.float64).reshape(-1)
        if len(x) != self.dimension:
            raise ValueError(f"a candidate of {len(x)} values, expected {self.dimension}")
        k = 3 * self.n if self.kind.shape else 0
        delta = x[:k].reshape(self.n, 3) if self.kind.shape else None
        logit = x[k:].reshape(self.n, 3) if self.kind.colour else np.full((self.n, 3), self.grey_logit)
        return delta, logit

    def vertices(self, x: np.ndarray) -> np.ndarray:
        """(V, 3) object-frame vertices (m), as :meth:`UniversalTrainer.vertices` maps its offsets."""
        import torch

        from robustbench3d.attacks.object import tanh_vertices

        delta, _ = self.split(x)
        if delta is None:
            return template_vertices(self.family).copy()
        return tanh_vertices(torch.from_numpy(delta.copy()), family=self.family).numpy()

    def colours(self, x: np.ndarray) -> np.ndarray:
        """(V, 3) colours in [0, 1], the sigmoid of the logits."""
        _, logit = self.split(x)
        return 1.0 / (1.0 + np.exp(-logit))

    def object_at(self, x: np.ndarray) -> RoofObject:
        """The object of ``x`` at file precision (what is rendered, written and benchmarked)."""
        return RoofObject.from_vertices(self.vertices(x), self.colours(x), family=self.family)


def mean_digest(mean: np.ndarray) -> str:
    """sha256 of a strategy mean's float64 bytes (the resume check)."""
    return hashlib.sha256(np.ascontiguousarray(mean, dtype=np.float64).tobytes()).hexdigest()


def make_strategy(space: ParamSpace, popsize: int, seed: int) -> Any:
    """A fresh separable CMA-ES (module doc) at the white-box start, its normal draws from
    ``default_rng([seed, CMA_STREAM])``; pycma's own termination criteria are off (the query budget stops)."""
    cma = import_cma()
    from cma.sigma_adaptation import CMAAdaptSigmaCSA

    gen = np.random.default_rng([seed, CMA_STREAM])

    def randn(*shape: int) -> np.ndarray:
        return gen.standard_normal(shape)

    opts = {"seed": np.nan, "randn": randn, "CMA_diagonal": True, "popsize": popsize, "AdaptSigma": CMAAdaptSigmaCSA,
            "CMA_stds": space.stds(), "verbose": -9, "verb_log": 0, "verb_disp": 0, "verb_time": False,
            "tolx": 0, "tolfun": 0, "tolfunhist": 0, "tolflatfitness": np.inf, "tolstagnation": np.inf,
            "tolconditioncov": np.inf, "tolfacupx": np.inf, "tolupsigma": np.inf, "maxiter": np.inf,
            "maxfevals": np.inf}
    return cma.CMAEvolutionStrategy(space.start(), 1.0, opts)


def cma_version() -> str:
    return str(import_cma().__version__)


def car_scores(detections: Labels, targets: Labels) -> np.ndarray:
    """(T,) each target car's detection score (module doc): the highest score among the Car rows of
    ``detections`` with BEV IoU >= 0.7 with it, 0 when none."""
    from robustbench3d.eval.iou import bev_iou

    out = np.zeros(len(targets))
    if len(targets) == 0 or len(detections) == 0:
        return out
    cars = detections.type.astype(str) == CAR
    if not cars.any():
        return out

    def boxes(lab: Labels) -> np.ndarray:
        return np.column_stack([lab.dimensions, lab.location, lab.rotation_y])

    iou = bev_iou(boxes(targets), boxes(detections)[cars])
    scores = np.asarray(detections.score, dtype=np.float64)[cars]
    matched = np.where(iou >= BEV_IOU_DETECTED, scores[None, :], -np.inf).max(axis=1)
    return np.where(np.isfinite(matched), matched, 0.0)


class QueryObjective:
    """The fitness of candidate objects on training frames, through ``victim.detect`` only (module doc).

    Args:
        victim: any :class:`~robustbench3d.victims.base.Detector`; kitti: the dataset; frame_ids, labels: the
        training frames (the held-out ones already cut off); config: the run's settings; source: the proposal
        mode of the queries.
    """

    def __init__(self, victim: Any, kitti: KittiDataset, frame_ids: list[str], labels: list[Labels],
                 config: TrainConfig, source: str) -> None:
        listed = tuple(getattr(victim, "supported_proposals", ()))
        if source not in listed:  # train_blackbox refuses this up front; the guard keeps every caller honest
            raise TrainingError(f"the queries' proposals {source!r} are not among the victim's supported_proposals "
                                f"({', '.join(listed) or 'none'})")
        self.victim, self.kitti, self.config, self.source = victim, kitti, config, source
        self.frame_ids, self.labels = frame_ids, labels
        #: Positions (in ``frame_ids``) of the frames with target cars: the ones generations draw.
        self.usable = [i for i, lab in enumerate(labels) if len(target_cars(lab))]
        self.queries = 0

    def attack(self, obj: RoofObject) -> Any:
        """The roof-object attack of ``obj`` with the run's EOT and sensor settings, bound to the dataset."""
        from robustbench3d.attacks.roof import RoofObjectAttack

        eot = self.config.eot
        attack = RoofObjectAttack(obj, eot="jitter" in eot,
                                  range_noise_m=EOT_RANGE_NOISE_M if "range-noise" in eot else 0.0,
                                  dropout=EOT_DROPOUT if "dropout" in eot else 0.0,
                                  supersample=self.config.supersample, occlusion=self.config.occlusion)
        attack.bind_dataset(self.kitti)
        return attack

    def frames(self, generation: int, count: int) -> list[int]:
        """The positions of generation ``generation``'s ``count`` frames (module doc)."""
        rng = np.random.default_rng([self.config.seed, generation, FRAMES_STREAM])
        return [self.usable[int(i)] for i in rng.choice(len(self.usable), size=count, replace=False)]

    def frame_scores(self, attack: Any, position: int, rng: np.random.Generator) -> np.ndarray:
        """(T,) car scores (:func:`car_scores`) of the target cars of frame ``position`` attacked by ``attack``
        with generator ``rng``: one query."""
        from robustbench3d.victims.base import victim_inputs

        fid, gt = self.frame_ids[position], self.labels[position]
        targets = target_cars(gt)
        clean = self.kitti.lazy_frame(fid, gt)
        record = None
        if self.source in ("gt-object", "gt-append"):
            frame, record = attack.apply_recorded(clean, targets, rng)
        else:
            frame = attack.apply(clean, targets, rng)
        bare, given = victim_inputs([frame], [gt], self.source, objects=None if record is None else [record])
        dets = self.victim.detect(bare, given)
        self.queries += 1
        if not isinstance(dets, list) or len(dets) != 1 or not isinstance(dets[0], Labels):
            raise TrainingError(f"frame {fid}: the victim's detect returned {type(dets).__name__}, not one Labels "
                                "per frame")
        return car_scores(dets[0], targets)

    def fitness(self, obj: RoofObject, generation: int, frames: list[int]) -> float:
        """The fitness of ``obj`` on ``frames`` of ``generation`` (module doc), ``len(frames)`` queries."""
        attack = self.attack(obj)
        total, cars = 0.0, 0
        for slot, position in enumerate(frames):
            rng = np.random.default_rng([self.config.seed, generation, slot, EOT_STREAM])
            scores = self.frame_scores(attack, position, rng)
            total += float(scores.sum())
            cars += len(scores)
        value = total / cars + shape_penalty(obj, self.config)
        if not math.isfinite(value):
            raise TrainingError(f"generation {generation}: the fitness is not finite ({value}): the victim gave "
                                "NaN or inf scores; stopping")
        return value


def shape_penalty(obj: RoofObject, config: TrainConfig) -> float:
    """``lambda_lap`` x the Laplacian smoothness of the object's vertices (m) in the modes that move the shape,
    else 0."""
    if not config.kind.shape:
        return 0.0
    return config.lambda_lap * laplacian_smoothness(obj.vertices())
