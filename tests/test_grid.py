"""Grids of independent tasks (facelab.grid): serial (here or in a child process) and on
Dask, render grids byte-identical either way, a worker SIGKILLed or the render child aborted
mid-clip costs a retry and nothing else."""

from __future__ import annotations

import csv
import fcntl
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from facelab.errors import StageError
from facelab.grid import Cluster, GridTask, Shared, check_shared, run_grid

ROOT = Path(__file__).resolve().parents[1]
KATO = ROOT / "protocols" / "kato2021.yaml"
FACELAB = str(Path(sys.executable).parent / "facelab")
# kato2021's six clips, small and at 5 fps (393 frames, not 2,370 at 30): what the grid tests
# compare - the clips' bytes, serial against Dask - does not depend on the frame rate
SMALL = ("--size", "160x90", "--fps", "5")


def square(x: int) -> int:
    return x * x


def refuse_odd(x: int) -> int:
    if x % 2:
        raise StageError(f"{x} is odd")
    return x


def crash(x: int) -> int:
    raise RuntimeError("a bug")


def total(values: np.ndarray, scale: int) -> float:
    return float(values.sum() * scale)


def _abort() -> None:
    """Die as a native library's abort() does (SIGABRT), leaving no core file."""
    import resource

    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    os.abort()


def abort_once(marker: str, x: int) -> int:
    if not Path(marker).exists():
        Path(marker).write_text("aborted once", encoding="utf-8")
        _abort()
    return 10 * x


def always_abort(x: int) -> int:
    _abort()
    return x


class Counted:
    """A value that counts, in the process it arrives in, how often it was unpickled."""

    loads = 0

    def __reduce__(self):
        return (_arrived, ())


def _arrived() -> Counted:
    Counted.loads += 1
    return Counted()


def arrivals(_value: Counted, _k: int) -> tuple[int, int]:
    return os.getpid(), Counted.loads


def where_and_what(_k: int) -> tuple[str, str | None]:
    return os.getcwd(), os.environ.get("FACELAB_GRID_TEST")


def test_serial_grid_runs_every_task_and_reports_refusals() -> None:
    seen = []
    events = []
    report = run_grid(
        (GridTask(f"t{i}", refuse_odd, (i,)) for i in range(5)),
        cluster=Cluster(),
        on_result=lambda k, v: seen.append((k, v)),
        progress=lambda k, e, d, f, r: events.append((k, e, d, f)),
    )
    assert report.results == {"t0": 0, "t2": 2, "t4": 4}
    assert report.failed == {"t1": "1 is odd", "t3": "3 is odd"}
    assert seen == [("t0", 0), ("t2", 2), ("t4", 4)]
    assert events[-1] == ("t4", "done", 3, 2) and len(events) == 5
    assert report.retried == [] and "3/5 done, 2 failed" in report.summary()


def test_a_bug_in_a_task_keeps_its_traceback() -> None:
    with pytest.raises(RuntimeError, match="a bug"):
        run_grid([GridTask("x", crash, (1,))], cluster=Cluster())


def test_a_grid_in_a_child_process_survives_its_native_crashes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The render grid's default: tasks in one child process. A task whose child aborts is run
    again in a new child; one that aborts every time fails with how its child died; the rest
    are untouched, refusals and bugs come back as in this process."""
    child = Cluster(child_process=True)
    tasks = [GridTask("once", abort_once, (str(tmp_path / "marker"), 4)),
             GridTask("square", square, (3,)), GridTask("always", always_abort, (0,)),
             GridTask("odd", refuse_odd, (1,)), GridTask("after", square, (5,))]  # fmt: skip
    report = run_grid(tasks, cluster=child)
    assert report.results == {"once": 40, "square": 9, "after": 25}
    assert report.retried == ["once", "always"]
    assert report.failed["odd"] == "1 is odd"
    assert "died 2 times (killed by SIGABRT: a crash below" in report.failed["always"]
    assert "serially in a child process" in report.summary()
    assert "re-run after its child process died: always, once" in report.summary()
    with pytest.raises(RuntimeError, match="a bug") as bug:  # with the child's traceback
        run_grid([GridTask("x", crash, (1,))], cluster=child)
    assert "in the grid child" in str(bug.value.__cause__) and "def crash" not in str(bug.value)
    assert 'raise RuntimeError("a bug")' in str(bug.value.__cause__)
    with pytest.raises(AttributeError, match="local object"):  # it cannot travel: said here
        run_grid([GridTask("local", lambda x: x, (1,))], cluster=child)
    # a shared value goes to the child once per grid; the caller's folder and environment at
    # the time of the grid, not of the child's start
    shared = Shared("counted", Counted())
    for grid in (1, 2):
        seen = run_grid([GridTask(f"s{i}", arrivals, (shared, i)) for i in range(3)],
                        cluster=child).results  # fmt: skip
        pids, loads = zip(*seen.values(), strict=True)
        assert set(pids) != {os.getpid()} and len(set(pids)) == 1
        assert loads == (grid, grid, grid)  # once in each grid (a grid lets it go after)
    monkeypatch.setenv("FACELAB_GRID_TEST", "set later")
    monkeypatch.chdir(tmp_path)
    there = run_grid([GridTask("w", where_and_what, (0,))], cluster=child).results["w"]
    assert there == (str(tmp_path), "set later")


def test_keys_are_unique_and_clusters_are_checked() -> None:
    with pytest.raises(StageError, match="two grid tasks have the key 'a'"):
        run_grid([GridTask("a", square, (1,)), GridTask("a", square, (2,))], cluster=Cluster())
    with pytest.raises(StageError, match="not both"):
        Cluster(workers=2, scheduler="tcp://h:8786")
    with pytest.raises(StageError, match="tcp://host:8786"):
        Cluster(scheduler="h:8786")
    with pytest.raises(StageError, match="at least 1"):
        Cluster(workers=0)


def test_an_unreachable_scheduler_is_named() -> None:
    with pytest.raises(
        StageError, match=r"cannot reach the Dask scheduler at tcp://127\.0\.0\.1:9"
    ):
        run_grid(
            [GridTask("a", square, (1,))],
            cluster=Cluster(scheduler="tcp://127.0.0.1:9", connect_timeout_s=1.0),
        )


def test_a_grid_with_nothing_to_run_starts_and_joins_no_cluster() -> None:
    """A render whose clips are all reused has no tasks: no scheduler is reached (this one
    does not exist: joining it would fail) and no workers are started."""
    cluster = Cluster(scheduler="tcp://127.0.0.1:9", connect_timeout_s=1.0)
    report = run_grid(iter(()), cluster=cluster)
    assert (report.results, report.failed, report.start_s) == ({}, {}, 0.0)


def test_the_readmes_slurm_recipe_makes_single_thread_worker_jobs() -> None:
    from dask_jobqueue import SLURMCluster

    with SLURMCluster(
        cores=1, processes=1, memory="4GB", walltime="02:00:00",
        job_script_prologue=["source /path/to/facelab/.venv/bin/activate"],
    ) as cluster:  # fmt: skip
        script = cluster.job_script()
    assert "--nthreads 1" in script and "source /path/to/facelab/.venv/bin/activate" in script
    assert "#SBATCH --cpus-per-task=1" in script
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert "SLURMCluster(" in readme and "job_script_prologue" in readme


def test_shared_inputs_are_checked_by_content() -> None:
    digest = lambda v: str(int(v.sum()))  # noqa: E731
    assert check_shared(np.ones(3), sha256="3", content_hash=digest, what="x") is not None
    with pytest.raises(StageError, match="the avatar arrived with content hash 4"):
        check_shared(np.ones(4), sha256="3", content_hash=digest, what="the avatar")


def test_a_clip_whose_bytes_do_not_match_is_not_written(tmp_path: Path) -> None:
    from facelab.stimuli.render.task import RenderedClip, write_clip

    good = RenderedClip("c", b"abc", __import__("hashlib").sha256(b"abc").hexdigest(),
                        1, 30, 2, 2, 1 / 30, 0.0, 1)  # fmt: skip
    info = write_clip(good, out=tmp_path / "c.mp4")
    assert (tmp_path / "c.mp4").read_bytes() == b"abc" and info.sha256 == good.sha256
    bad = RenderedClip("d", b"abd", good.sha256, 1, 30, 2, 2, 1 / 30, 0.0, 1)
    with pytest.raises(StageError, match="do not match their hash"):
        write_clip(bad, out=tmp_path / "d.mp4")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.mp4"]  # no temporary left


def test_a_worker_refuses_audio_that_is_not_what_was_sent() -> None:
    from facelab.stimuli.avatar import default_head
    from facelab.stimuli.render.renderer import RenderSettings
    from facelab.stimuli.render.task import ClipFrames, render_clip
    from facelab.stimuli.speech.audio import Speech

    head = default_head()
    job = ClipFrames(
        clip_id="c", weights=np.zeros((3, len(head.target_names)), np.float32), poses=None,
        audio=Speech(np.zeros(4800, np.float32), 48_000), audio_sha256="0" * 64, fps=30,
        settings=RenderSettings(width=64, height=64), framing_sha256=head.content_hash(),
        drawn_sha256=head.content_hash(),
    )  # fmt: skip
    with pytest.raises(StageError, match="the audio of c arrived with content hash"):
        render_clip(job, head, head)


# --- on a local Dask cluster ------------------------------------------------------------------


@pytest.mark.slow
def test_dask_grid_gives_the_serial_results_and_refusals() -> None:
    data = Shared("ones", np.ones(1000))
    tasks = [GridTask(f"s{i}", total, (data, i)) for i in range(6)]
    tasks += [GridTask("odd", refuse_odd, (3,))]
    serial = run_grid(tasks, cluster=Cluster())
    dask = run_grid(tasks, cluster=Cluster(workers=2), window=3)
    assert dask.results == serial.results and dask.failed == {"odd": "3 is odd"}
    assert dask.retried == [] and "local Dask cluster of 2" in dask.where


def _clips(folder: Path) -> dict[str, str]:
    with open(folder / "clips.csv", newline="", encoding="utf-8") as f:
        return {r["clip_id"]: r["sha256"] for r in csv.DictReader(f)}


def _render(out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [FACELAB, "render", str(KATO), *SMALL, "--out", str(out), *extra],
        capture_output=True, text=True, check=False,
    )  # fmt: skip


@pytest.fixture(scope="session")
def serial_clips(tmp_path_factory: pytest.TempPathFactory, worker_id: str) -> dict[str, str]:
    """kato2021 rendered in the command itself (no cluster): the clips' hashes. Rendered once
    for the whole run: parallel workers share the folder (the first renders, under a lock)."""
    base = tmp_path_factory.getbasetemp()
    root = base if worker_id == "master" else base.parent  # shared by the run's workers
    out = root / "kato2021-serial-160x90-5fps"
    with open(root / "kato2021-serial-160x90-5fps.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (out / "clips.csv").is_file():
            serial = _render(out, "--quiet")
            assert serial.returncode == 0, serial.stderr
    return _clips(out)


@pytest.mark.slow
def test_render_on_two_workers_matches_serial_and_survives_a_killed_worker(
    tmp_path: Path, serial_clips: dict[str, str]
) -> None:
    import psutil  # installed with dask.distributed

    proc = subprocess.Popen(
        [FACELAB, "render", str(KATO), *SMALL, "--out", str(tmp_path / "dask"), "--workers", "2"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    killed = None
    deadline = time.monotonic() + 240
    while killed is None and proc.poll() is None and time.monotonic() < deadline:
        # a worker is mid-clip while its ffmpeg runs: kill the worker, not the command
        for child in psutil.Process(proc.pid).children(recursive=True):
            try:
                if (
                    child.name() == "ffmpeg"
                    and child.parent().pid != proc.pid
                    and time.time() - child.create_time() > 0.1  # inside the clip
                ):
                    killed = child.parent().pid
                    os.kill(killed, signal.SIGKILL)
                    break
            except psutil.NoSuchProcess:
                continue
        time.sleep(0.05)
    out, err = proc.communicate(timeout=300)
    assert killed is not None, "no worker was seen rendering"
    assert proc.returncode == 0, err
    retried = re.search(r"(\d+) retried", out)
    assert "re-run after a worker was lost" in out and retried and int(retried[1]) >= 1, out
    assert _clips(tmp_path / "dask") == serial_clips
    leftovers = [p.name for p in (tmp_path / "dask").iterdir() if p.name.startswith(".")]
    assert leftovers == []
    again = _render(tmp_path / "dask", "--workers", "2")
    assert again.returncode == 0 and "(0 rendered, 6 reused)" in again.stdout, again.stdout


@pytest.mark.slow
def test_a_render_child_that_aborts_mid_clip_costs_that_clip_a_rerun(
    tmp_path: Path, serial_clips: dict[str, str]
) -> None:
    """`facelab render` renders in a child process: an OpenGL driver aborting there mid-clip
    (SIGABRT, as llvmpipe did twice in the suite) re-runs that clip in a new child; the clips
    are those of an undisturbed render."""
    import psutil

    proc = subprocess.Popen(
        [FACELAB, "render", str(KATO), *SMALL, "--out", str(tmp_path / "clips")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    aborted = aborted_tmp = None
    deadline = time.monotonic() + 240
    while aborted is None and proc.poll() is None and time.monotonic() < deadline:
        for child in psutil.Process(proc.pid).children(recursive=True):
            try:
                parent = child.parent()
                # the grid child with an encoder running: inside a clip
                if parent and child.name() == "ffmpeg" and "child_serve" in parent.cmdline()[-2]:
                    aborted, aborted_tmp = parent, parent.environ()["TMPDIR"]
                    aborted.rlimit(psutil.RLIMIT_CORE, (0, 0))  # no core file
                    aborted.send_signal(signal.SIGABRT)
                    break
            except (psutil.NoSuchProcess, IndexError):
                continue
        time.sleep(0.02)
    out, err = proc.communicate(timeout=300)
    assert aborted is not None, "the render child was not seen rendering"
    assert proc.returncode == 0, err
    assert "(serially in a child process)" in out
    assert re.search(r"1 retried.*re-run after its child process died: \S+", out), out
    assert _clips(tmp_path / "clips") == serial_clips
    assert not [p.name for p in (tmp_path / "clips").iterdir() if p.name.startswith(".")]
    assert not Path(aborted_tmp).exists()  # the aborted child's temporary folder is gone


@pytest.mark.slow
def test_render_through_a_scheduler_and_workers_started_by_hand(
    tmp_path: Path, serial_clips: dict[str, str]
) -> None:
    """The README's two-machine recipe on one machine: `dask scheduler`, `dask worker`."""
    dask = str(Path(sys.executable).parent / "dask")
    port = 18786 + os.getpid() % 1000
    scheduler = subprocess.Popen(
        [dask, "scheduler", "--port", str(port), "--no-dashboard"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    worker = subprocess.Popen(
        [dask, "worker", f"tcp://127.0.0.1:{port}", "--nworkers", "2", "--nthreads", "1",
         "--no-dashboard"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        time.sleep(3)  # the workers register
        remote = _render(tmp_path / "remote", "--scheduler", f"tcp://127.0.0.1:{port}")
        assert remote.returncode == 0, remote.stderr
        assert f"Dask scheduler tcp://127.0.0.1:{port}" in remote.stdout
        assert _clips(tmp_path / "remote") == serial_clips
    finally:
        for proc in (worker, scheduler):
            proc.terminate()
            proc.wait(timeout=30)


@pytest.mark.slow
def test_power_simulation_on_workers_matches_the_serial_one() -> None:
    from facelab.experiment.simulated_power import simulated_power
    from facelab.protocol import load_protocol

    protocol = load_protocol(KATO)
    runs = [
        simulated_power(
            protocol, n_values=[8], sims=12, rng=np.random.default_rng(5), jobs=1, cluster=c
        )
        for c in (Cluster(), Cluster(workers=2))
    ]
    assert runs[0].power.equals(runs[1].power)
    assert runs[0].precision.equals(runs[1].precision)
