"""Frame shards: a cell's frames cut into contiguous pieces that worker processes compute.

A :class:`Shard` is (cell, frame range). :func:`run_shard` runs in a worker (a local process pool or
a Ray task, :mod:`robustbench3d.runner.executors`): it creates the cell's victim once per worker
process (and keeps it for later shards), prepares its own copy of the run's attack for that victim,
attacks, detects and writes the shard's ``NNNNNN.txt`` result files into the cell's
``data.partial/`` (each atomically, tmp + rename), then records the shard as done in
``shards.partial/<first>-<last>.json`` (fingerprint, frame ids and each file's sha256). It returns
:class:`ShardResult`: each frame's result-file text plus the worker's timings. A shard is
idempotent: run twice (a retried task), it writes the same bytes under the same names.

A cell's first shard also checks the victim it holds for determinism
(:func:`~robustbench3d.runner.flags.determinism`: two ``detect`` calls on the split's first frame,
clean, once per victim x proposal source in the worker process) and returns the verdict
(``ShardResult.victim_probe``, also kept in its record), so the parent never creates the victim.

Shards start at multiples of the batch size and hold whole batches, so every ``detect`` call sees
the same frames as in the one-process path, and the attack randomness is per frame
(:func:`~robustbench3d.runner.cell.attack_rng`): the result files are the same bytes.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import socket
import sys
import time
import traceback
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from robustbench3d.attacks.base import Attack
from robustbench3d.errors import DataFormatError, RobustBenchError
from robustbench3d.fileio import atomic_write_text, read_user_text
from robustbench3d.kitti.dataset import KittiDataset
from robustbench3d.kitti.labels import Labels
from robustbench3d.provenance import determinism_flags, peak_rss_mb, reset_peak_rss
from robustbench3d.runner.cell import (
    PARTIAL,
    SHARD_MARKS,
    CellFailure,
    detect_frames,
    prepare_attack,
    victim_failure,
)
from robustbench3d.runner.config import CellKey
from robustbench3d.runner.flags import determinism, probe_flags

#: Frames per shard before rounding up to whole batches: about 5 s of the shipped cascade per shard,
#: so scheduling costs little and two workers stay busy to the end of a 100-frame cell.
SHARD_FRAMES = 16


def shard_ranges(frames: int, batch_size: int, shard_frames: int = SHARD_FRAMES) -> list[tuple[int, int]]:
    """``[start, stop)`` index ranges covering ``frames`` frames: contiguous, in order, each a whole
    number of batches (``shard_frames`` rounded up to a multiple of ``batch_size``) but the last."""
    if frames < 1 or batch_size < 1 or shard_frames < 1:
        raise ValueError(f"shard_ranges: frames {frames}, batch_size {batch_size}, shard_frames {shard_frames}")
    size = -(-shard_frames // batch_size) * batch_size
    return [(start, min(start + size, frames)) for start in range(0, frames, size)]


@dataclass(frozen=True)
class CellJob:
    """What every shard of one cell needs besides its frames (sent with each shard; small)."""

    key: CellKey
    cell_dir: str
    fingerprint: str
    victim_spec: Any  # the registry's VictimSpec (pickled by reference to its factory)
    victim_kwargs: dict[str, Any]
    attack: bytes  # the run's attack instance, bound to the dataset, pickled
    kitti: KittiDataset
    seed: int
    batch_size: int

    @property
    def victim_key(self) -> str:
        factory = self.victim_spec.factory
        ident = f"{getattr(factory, '__module__', '')}:{getattr(factory, '__qualname__', repr(factory))}"
        return f"{self.key.victim}|{ident}|{json.dumps(self.victim_kwargs, sort_keys=True, default=str)}"

    @property
    def attack_key(self) -> str:
        return f"{self.key.attack}|{hashlib.sha256(self.attack).hexdigest()}"


@dataclass(frozen=True)
class Shard:
    """Frames ``[start, stop)`` of a cell (with their ground truth)."""

    job: CellJob
    index: int
    start: int
    frames: tuple[tuple[str, Labels], ...]

    @property
    def frame_ids(self) -> list[str]:
        return [fid for fid, _ in self.frames]

    @property
    def mark_path(self) -> Path:
        ids = self.frame_ids
        return Path(self.job.cell_dir) / SHARD_MARKS / f"{ids[0]}-{ids[-1]}.json"


@dataclass
class ShardResult:
    """What a worker returns for a shard.

    ``status``: ``ok`` (``texts`` holds each frame's result file), ``skipped`` (the victim does not
    support the cell's proposal source), ``error`` (``reason``, ``traceback``) or ``bad_input`` (a
    file the user gave is malformed; ``bad_input`` holds the :class:`DataFormatError`'s fields).
    """

    cell: str
    index: int
    status: str
    frame_ids: list[str]
    texts: list[str] = field(default_factory=list)
    reason: str | None = None
    traceback: str | None = None
    bad_input: tuple[str, str, int | None, str | None] | None = None
    started: float = 0.0  # epoch seconds
    finished: float = 0.0
    cpu_seconds: float = 0.0
    peak_rss_mb: float | None = None
    pid: int = 0
    host: str = ""
    determinism: dict[str, Any] = field(default_factory=dict)
    #: The victim's determinism verdict (``victim-nondeterministic`` flags, empty: deterministic) from the
    #: cell's first shard when it is ``ok``; None for the other shards.
    victim_probe: list[dict[str, str]] | None = None
    reused: bool = False
    unexpected: bool = False  # the error's cause is not a RobustBenchError (its traceback is worth showing)


# ---- the worker side -------------------------------------------------------------------------------

_VICTIMS: dict[str, Any] = {}  # victim key -> victim, or the CellFailure of its creation
_ATTACKS: dict[tuple[str, str], Attack] = {}  # (attack key, victim key) -> an attack prepared for that victim
_PROBES: dict[tuple[str, str], list[dict[str, str]]] = {}  # (victim key, proposals) -> determinism verdict


#: The environment variables :func:`worker_setup` sets to one thread (for libraries not loaded yet).
THREAD_VARS: tuple[str, ...] = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def worker_setup() -> None:
    """One intra-op thread in this process (the processes are the parallelism): float32 reductions
    then add up in one order, so a victim's result files do not depend on the machine's core count.
    Sets the thread variables for libraries not loaded yet and torch's count if it is; idempotent."""
    for var in THREAD_VARS:
        os.environ[var] = "1"
    torch = sys.modules.get("torch")
    if torch is not None and torch.get_num_threads() != 1:
        torch.set_num_threads(1)


def _victim(job: CellJob) -> Any:
    key = job.victim_key
    if key not in _VICTIMS:
        try:
            _VICTIMS[key] = job.victim_spec.create(**job.victim_kwargs)
        except DataFormatError:
            raise  # a bad file the user pointed at: the command exits 2
        except Exception as exc:
            _VICTIMS[key] = victim_failure(job.key.victim, exc)
    got = _VICTIMS[key]
    if isinstance(got, CellFailure):
        raise got
    return got


def _attack(job: CellJob, victim: Any) -> Attack:
    key = (job.attack_key, job.victim_key)
    if key not in _ATTACKS:
        attack = pickle.loads(job.attack)
        prepare_attack(attack, job.key.attack, victim)
        _ATTACKS[key] = attack
    return _ATTACKS[key]


def _probe(job: CellJob, victim: Any, first: tuple[str, Labels]) -> list[dict[str, str]]:
    """The determinism verdict of this process's victim on the split's first frame ``first`` (memoised)."""
    key = (job.victim_key, job.key.proposals)
    if key not in _PROBES:
        _PROBES[key] = determinism(victim, job.key.proposals, job.kitti, *first)
    return [dict(f) for f in _PROBES[key]]


def _sha256_text(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def run_shard(shard: Shard) -> ShardResult:
    """Compute one shard in this process (see the module doc); never raises for a failing victim or
    attack (the result says ``error``) nor for bad input (``bad_input``)."""
    worker_setup()
    job = shard.job
    result = ShardResult(cell=job.key.dirname, index=shard.index, status="ok", frame_ids=shard.frame_ids,
                         started=time.time(), pid=os.getpid(), host=socket.gethostname())
    cpu0, rss_reset = time.process_time(), reset_peak_rss()
    try:
        victim = _victim(job)
        worker_setup()  # the victim may have loaded torch
        supported = tuple(victim.supported_proposals)
        if job.key.proposals not in supported:
            result.status = "skipped"
            result.reason = (f"victim {job.key.victim!r} supports proposals {', '.join(supported)} only "
                             f"(not {job.key.proposals!r})")
        else:
            attack = _attack(job, victim)
            partial = Path(job.cell_dir) / PARTIAL
            partial.mkdir(parents=True, exist_ok=True)
            found = detect_frames(victim, job.key.victim, attack, job.key.attack, job.key.proposals, job.kitti,
                                  job.seed, job.batch_size, list(shard.frames), partial)
            result.texts = [text for text, _ in found]
            mark: dict[str, Any] = {"fingerprint": job.fingerprint, "frames": result.frame_ids,
                                    "sha256": [_sha256_text(t) for t in result.texts]}
            if shard.index == 0:
                result.victim_probe = mark["victim_probe"] = _probe(job, victim, shard.frames[0])
            atomic_write_text(shard.mark_path, json.dumps(mark))
    except DataFormatError as exc:
        result.status, result.reason = "bad_input", str(exc)
        result.bad_input = (str(exc.path), exc.problem, exc.line, exc.field)
    except CellFailure as exc:
        cause = exc.__cause__ or exc
        result.status, result.reason = "error", str(exc)
        result.unexpected = not isinstance(cause, RobustBenchError)
        result.traceback = "".join(traceback.format_exception(type(cause), cause, cause.__traceback__))
    result.finished = time.time()
    result.cpu_seconds = time.process_time() - cpu0
    peak = peak_rss_mb()
    result.peak_rss_mb = round(peak, 1) if rss_reset and peak is not None else None
    result.determinism = determinism_flags()
    return result


# ---- the parent side -------------------------------------------------------------------------------

def finished_shard(shard: Shard) -> ShardResult | None:
    """The shard as an earlier, interrupted run left it, if its record matches this cell's fingerprint
    and frames, every result file is there with the recorded sha256 and, for a cell's first shard, the
    record holds the determinism verdict (else None)."""
    try:
        mark = json.loads(read_user_text(shard.mark_path))
    except (OSError, ValueError, RobustBenchError):
        return None
    if not isinstance(mark, dict) or mark.get("fingerprint") != shard.job.fingerprint \
            or mark.get("frames") != shard.frame_ids or not isinstance(mark.get("sha256"), list):
        return None
    probe = probe_flags(mark.get("victim_probe")) if shard.index == 0 else None
    if shard.index == 0 and probe is None:
        return None
    texts = []
    partial = Path(shard.job.cell_dir) / PARTIAL
    for fid, want in zip(shard.frame_ids, mark["sha256"], strict=False):
        try:
            text = read_user_text(partial / f"{fid}.txt")
        except (OSError, RobustBenchError):
            return None
        if _sha256_text(text) != want:
            return None
        texts.append(text)
    if len(texts) != len(shard.frame_ids):
        return None
    return ShardResult(cell=shard.job.key.dirname, index=shard.index, status="ok", frame_ids=shard.frame_ids,
                       texts=texts, victim_probe=probe, reused=True)


def settle_files(cell_dir: Path, frame_ids: Sequence[str], texts: Sequence[str]) -> None:
    """Make ``cell_dir/data.partial`` hold exactly one file per frame with the shards' texts: write any
    that is missing or differs (a worker on a machine that does not share ``cell_dir``), remove
    anything else (a killed worker's temporary file, a frame of an earlier, longer run)."""
    partial = cell_dir / PARTIAL
    partial.mkdir(parents=True, exist_ok=True)
    wanted = {f"{fid}.txt": text for fid, text in zip(frame_ids, texts, strict=True)}
    for path in partial.iterdir():
        if path.name not in wanted:
            if path.is_dir():
                raise RobustBenchError(f"{path}: unexpected directory among a cell's result files")
            path.unlink()
    for name, text in wanted.items():
        path = partial / name
        try:
            same = path.read_bytes() == text.encode("utf-8")
        except FileNotFoundError:
            same = False
        if not same:
            atomic_write_text(path, text)


__all__ = ["SHARD_FRAMES", "THREAD_VARS", "CellJob", "Shard", "ShardResult", "finished_shard", "run_shard",
           "settle_files", "shard_ranges", "worker_setup"]
