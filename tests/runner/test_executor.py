"""Frame shards on executors (``run --executor local|ray``): the same result files and summary as the
one-process path, a killed Ray worker's shard redone with every frame counted once, an interrupted
cell resumed from its finished shards."""

from __future__ import annotations

import importlib.util
import os
import signal
import sys
import threading
import time
from pathlib import Path

import pytest

from robustbench3d.cli import main
from robustbench3d.errors import RobustBenchError
from robustbench3d.results import read_summary
from robustbench3d.runner import RunConfig, run_benchmark
from robustbench3d.runner.executors import LocalExecutor, RayExecutor, make_executor
from robustbench3d.runner.shards import shard_ranges, worker_setup
from robustbench3d.victims import VICTIMS, create_victim
from robustbench3d.victims.spec import Capabilities, EntryInfo, VictimSpec

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("rb3d_lidar_cluster") is None,
    reason="example plugin not installed: pip install -c constraints.txt -e examples/lidar_cluster_victim",
)

FRAMES = 6
#: Timing and host fields: the only provenance that may differ between executors.
TIMINGS = ("started", "finished", "seconds", "cpu_seconds", "peak_rss_mb", "executor")


@pytest.fixture(scope="module")
def dataset(shared_split) -> Path:
    """Six generated frames, all in the val split."""
    return shared_split(FRAMES, seed=5, val_fraction=1.0)


@pytest.fixture
def one_thread():
    """This process as a worker: one intra-op thread (restored afterwards)."""
    import torch

    threads, env = torch.get_num_threads(), {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS",
                                                                            "OPENBLAS_NUM_THREADS")}
    worker_setup()
    yield
    torch.set_num_threads(threads)
    for k, v in env.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


class ProbeVictim:
    """TEST ONLY: lidar-cluster's detections; the first detect call (over all processes) that gets frame
    ``frame`` creates ``<hold>/held`` holding its pid, then sleeps (``mode="sleep"``: to be killed) or
    raises KeyboardInterrupt (``mode="interrupt"``). ``hold`` is a directory (a file argument would enter
    the cell's fingerprint by its hash)."""

    supported_proposals = ("detector",)

    def __init__(self, hold: str, mode: str, frame: str):
        self.inner = create_victim("lidar-cluster")
        self.hold, self.mode, self.frame = hold, mode, frame

    def detect(self, frames, proposals="detector"):
        if any(f.frame_id == self.frame for f in frames):
            try:
                fd = os.open(os.path.join(self.hold, "held"), os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                pass
            else:
                os.write(fd, f"{os.getpid()}\n".encode())
                os.close(fd)
                if self.mode == "interrupt":
                    raise KeyboardInterrupt
                time.sleep(600)
        return self.inner.detect(frames, proposals)


VICTIMS.register("test-probe", VictimSpec(
    factory=ProbeVictim,
    info=EntryInfo(Capabilities(modalities=("lidar",), backend="other", gradients=False, deterministic=True))))


def result_files(out: Path) -> dict[str, bytes]:
    """Every result file of a run, by ``cell/name``; nothing else may lie in a cell's ``data/``."""
    return {f"{p.parent.parent.name}/{p.name}": p.read_bytes() for p in sorted(out.glob("cells/*/data/*"))}


def comparable(cells: list[dict]) -> list[dict]:
    """Cells without timings and host fields, and without the run's output directory."""
    out = []
    for cell in cells:
        prov = {k: v for k, v in cell["provenance"].items() if k not in TIMINGS}
        prov["run"] = {k: v for k, v in prov["run"].items() if k != "out"}
        # whether torch is loaded depends on what else the process ran; the thread settings must agree
        prov["determinism"] = {k: v for k, v in prov["determinism"].items() if not k.startswith("torch")}
        out.append({**cell, "provenance": prov})
    return out


def differences(a, b, where: str = "") -> list[str]:
    """Paths at which two JSON values differ (empty: equal)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for k in sorted(set(a) | set(b), key=str)
                for d in differences(a.get(k, "<missing>"), b.get(k, "<missing>"), f"{where}.{k}")]
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True)) for d in differences(x, y, f"{where}[{i}]")]
    return [] if a == b else [f"{where}: {a!r} != {b!r}"]


def test_shard_ranges_are_whole_batches_covering_every_frame():
    assert shard_ranges(10, 4, 4) == [(0, 4), (4, 8), (8, 10)]
    assert shard_ranges(10, 4, 5) == [(0, 8), (8, 10)]  # 5 frames round up to two batches of 4
    assert shard_ranges(10, 3, 2) == [(0, 3), (3, 6), (6, 9), (9, 10)]
    assert shard_ranges(3, 4, 16) == [(0, 3)]
    assert shard_ranges(1, 1, 1) == [(0, 1)]
    with pytest.raises(ValueError):
        shard_ranges(0, 4, 4)


def test_executor_arguments_are_checked(tmp_path, capsys):
    assert make_executor("local", 1) is None  # one job: everything in this process
    assert isinstance(make_executor("local", 2), LocalExecutor)
    with pytest.raises(RobustBenchError, match=r"--jobs must be an integer in 1\.\.1024 \(worker processes\), got 0"):
        make_executor("local", 0)
    with pytest.raises(RobustBenchError, match="--address joins a Ray cluster"):
        make_executor("local", 2, "127.0.0.1:6379")
    assert main(["run", "--victims", "lidar-cluster", "--out", str(tmp_path / "r"), "--jobs", "0"]) == 2
    assert "--jobs must be an integer in 1..1024" in capsys.readouterr().err


def _serial_and_sharded(config, tmp_path: Path) -> tuple:
    serial = run_benchmark(config(tmp_path / "serial"), lambda line: None)
    with LocalExecutor(2, shard_frames=2) as executor:  # 3 shards of 2 frames per cell
        sharded = run_benchmark(config(tmp_path / "sharded"), lambda line: None, executor=executor)
    files = result_files(tmp_path / "sharded")
    assert files == result_files(tmp_path / "serial")
    assert differences(comparable(sharded.summary), comparable(serial.summary)) == []
    assert differences(comparable(read_summary(tmp_path / "sharded" / "summary.json")),
                       comparable(read_summary(tmp_path / "serial" / "summary.json"))) == []
    for cell in sharded.cells:
        if cell["status"] == "ok":
            executor_record = cell["provenance"]["executor"]
            assert executor_record["shards"] == 3 and executor_record["shards_reused"] == 0
            assert f":{os.getpid()}" not in " ".join(executor_record["workers"])  # computed by the workers
            assert cell["provenance"]["cpu_seconds"] > 0 and cell["metrics"]["meta"]["frames"] == FRAMES
    for cell_dir in (tmp_path / "sharded" / "cells").iterdir():
        assert sorted(p.name for p in cell_dir.iterdir()) in (["cell.json"], ["cell.json", "data"])
    return sharded, files


def test_local_shards_give_the_one_process_results(dataset, tmp_path, one_thread):
    def config(out: Path) -> RunConfig:
        return RunConfig(victims=("lidar-cluster",), attacks=("none", "random-shape"), proposals=("detector", "gt"),
                         out=out, data=dataset, batch_size=2, progress=False)

    sharded, files = _serial_and_sharded(config, tmp_path)
    assert [(c["attack"], c["proposals"], c["status"]) for c in sharded.cells] == [
        ("none", "detector", "ok"), ("none", "gt", "skipped"), ("random-shape", "detector", "ok"),
        ("random-shape", "gt", "skipped")]  # the skip is found by the workers, which create the victim
    assert len(files) == 2 * FRAMES


def test_local_shards_give_the_one_process_results_of_a_torch_victim(dataset, tmp_path, one_thread):
    def config(out: Path) -> RunConfig:
        return RunConfig(victims=("fpointnet-v1-lite",), attacks=("none",), proposals=("gt",), out=out, data=dataset,
                         batch_size=2, progress=False)

    sharded, files = _serial_and_sharded(config, tmp_path)
    assert [c["status"] for c in sharded.cells] == ["ok"] and len(files) == FRAMES
    assert sharded.cells[0]["provenance"]["determinism"]["torch_num_threads"] == 1


@pytest.mark.slow
def test_local_shards_give_the_one_process_results_on_a_grid(dataset, tmp_path, one_thread):
    def config(out: Path) -> RunConfig:
        return RunConfig(victims=("lidar-cluster", "fpointnet-v1-lite"), attacks=("none", "random-shape"),
                         proposals=("detector", "gt"), out=out, data=dataset, batch_size=2, progress=False)

    sharded, files = _serial_and_sharded(config, tmp_path)
    assert [c["status"] for c in sharded.cells] == ["ok", "skipped", "ok", "skipped"] + ["ok"] * 4
    assert len(files) == 6 * FRAMES


def test_an_interrupted_cell_resumes_from_its_finished_shards(dataset, tmp_path, one_thread):
    hold = tmp_path / "hold"
    hold.mkdir()
    out = tmp_path / "run"
    config = RunConfig(victims=("test-probe",), attacks=("none",), proposals=("detector",), out=out, data=dataset,
                       batch_size=2, progress=False,
                       victim_args={"test-probe": {"hold": str(hold), "mode": "interrupt", "frame": "000005"}})
    with LocalExecutor(2, shard_frames=2) as executor, pytest.raises(KeyboardInterrupt):
        run_benchmark(config, lambda line: None, executor=executor)  # frame 5 is in the last of 3 shards
    cell_dir = out / "cells" / "test-probe+none+detector"
    assert not (cell_dir / "cell.json").exists() and len(list((cell_dir / "shards.partial").iterdir())) == 2
    with LocalExecutor(2, shard_frames=2) as executor:
        resumed = run_benchmark(config, lambda line: None, executor=executor)
    (cell,) = resumed.cells
    assert cell["status"] == "ok" and cell["provenance"]["executor"]["shards_reused"] == 2
    assert not (cell_dir / "shards.partial").exists() and not (cell_dir / "data.partial").exists()
    serial = run_benchmark(RunConfig(victims=("lidar-cluster",), attacks=("none",), proposals=("detector",),
                                     out=tmp_path / "serial", data=dataset, batch_size=2, progress=False),
                           lambda line: None)
    assert cell["metrics"] == serial.cells[0]["metrics"]
    assert ({k.split("/")[1]: v for k, v in result_files(out).items()}
            == {k.split("/")[1]: v for k, v in result_files(tmp_path / "serial").items()})


def _kill_when_held(hold: Path, killed: list[int], deadline: float) -> None:
    while time.monotonic() < deadline:
        try:
            text = hold.read_text()
        except FileNotFoundError:
            text = ""
        if text.endswith("\n"):
            pid = int(text)
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
            return
        time.sleep(0.05)


@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="ray not installed: pip install '.[ray]'")
def test_ray_redoes_a_killed_workers_shard_and_reproduces_the_local_summary(dataset, tmp_path, one_thread):
    import ray.cloudpickle

    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the probe victim, for Ray's workers
    hold = tmp_path / "hold"
    hold.mkdir()
    probe = {"hold": str(hold), "mode": "sleep", "frame": "000003"}

    def config(out: Path) -> RunConfig:
        return RunConfig(victims=("test-probe",), attacks=("none", "random-shape"), proposals=("detector",),
                         out=out, data=dataset, batch_size=2, progress=False, victim_args={"test-probe": probe})

    (hold / "held").write_text("0\n")  # held already: the local reference run never sleeps
    with LocalExecutor(2, shard_frames=2) as executor:
        local = run_benchmark(config(tmp_path / "local"), lambda line: None, executor=executor)
    (hold / "held").unlink()
    killed: list[int] = []
    killer = threading.Thread(target=_kill_when_held, args=(hold / "held", killed, time.monotonic() + 120), daemon=True)
    killer.start()
    with RayExecutor(2, shard_frames=2) as executor:
        on_ray = run_benchmark(config(tmp_path / "ray"), lambda line: None, executor=executor)
    killer.join()
    assert len(killed) == 1 and killed[0] != os.getpid()  # a Ray worker held frame 3 and was killed
    assert [c["status"] for c in on_ray.cells] == ["ok", "ok"]
    # every frame exactly once: one result file per frame, evaluated once, the same bytes as locally
    files = result_files(tmp_path / "ray")
    assert sorted(files) == sorted(f"test-probe+{a}+detector/{i:06d}.txt" for a in ("none", "random-shape")
                                   for i in range(FRAMES))
    assert files == result_files(tmp_path / "local")
    assert all(c["metrics"]["meta"]["frames"] == FRAMES for c in on_ray.cells)
    assert differences(comparable(on_ray.summary), comparable(local.summary)) == []
    assert [c["provenance"]["executor"]["shards"] for c in on_ray.cells] == [3, 3]


def test_a_killed_local_worker_is_replaced_and_its_shards_redone(dataset, tmp_path, one_thread):
    hold = tmp_path / "hold"
    hold.mkdir()
    probe = {"hold": str(hold), "mode": "sleep", "frame": "000003"}
    config = RunConfig(victims=("test-probe",), attacks=("none",), proposals=("detector",), out=tmp_path / "run",
                       data=dataset, batch_size=2, progress=False, victim_args={"test-probe": probe})
    killed: list[int] = []
    killer = threading.Thread(target=_kill_when_held, args=(hold / "held", killed, time.monotonic() + 120),
                              daemon=True)
    killer.start()
    with LocalExecutor(2, shard_frames=2) as executor:
        report = run_benchmark(config, lambda line: None, executor=executor)
    killer.join()
    assert len(killed) == 1 and killed[0] != os.getpid()
    (cell,) = report.cells
    assert cell["status"] == "ok" and cell["metrics"]["meta"]["frames"] == FRAMES
    serial = run_benchmark(RunConfig(victims=("lidar-cluster",), attacks=("none",), proposals=("detector",),
                                     out=tmp_path / "serial", data=dataset, batch_size=2, progress=False),
                           lambda line: None)
    assert cell["metrics"] == serial.cells[0]["metrics"]
    assert ({k.split("/")[1]: v for k, v in result_files(tmp_path / "run").items()}
            == {k.split("/")[1]: v for k, v in result_files(tmp_path / "serial").items()})
