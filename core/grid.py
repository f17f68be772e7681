"""Grids of independent tasks, run here one after another or on a Dask cluster.

A stimulus grid (every clip of a protocol, every level of an impression model, every emotion
x mode of a behaviour set) and a simulation-based power analysis are lists of independent
tasks. :func:`run_grid` runs such a list

- **serially** in this process (the default: no cluster, nothing to install), or serially in
  **one child process** (``Cluster(child_process=True)``; render grids use it by default): a
  native crash there - a software OpenGL driver that aborts mid-frame - costs that task one
  re-run in a new child, not the whole command; or
- on **Dask** (``dask.distributed``): a local cluster of ``workers`` processes with one thread
  each (``--workers N``), or a running scheduler (``--scheduler tcp://host:8786``) whose
  workers were started elsewhere (``dask worker``, ``dask-jobqueue`` on SLURM/PBS/SGE).

Tasks must be pure: the same arguments give the same result, so the scheduler may run a task
twice or re-run it after a worker died. Large inputs shared by many tasks (an avatar, an audio
track) are wrapped in :class:`Shared`: sent to the cluster once, named by their content hash,
and the task checks that hash before use (:func:`check_shared`). Results come back to this
process, which alone writes files - so a killed worker never leaves a partial output.

A task that raises is reported as failed (not retried: facelab's errors are deterministic);
a task whose worker died is re-run by the scheduler and reported as retried
(:class:`GridReport`). ``dask`` is imported only here.
"""

from __future__ import annotations

import atexit
import contextlib
import importlib
import itertools
import os
import pickle
import shutil
import signal
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

from facelab.errors import FacelabError, StageError

__all__ = [
    "SERIAL",
    "Cluster",
    "GridReport",
    "GridTask",
    "Progress",
    "Shared",
    "check_shared",
    "grid_child_pid",
    "run_grid",
]


@dataclass(frozen=True)
class Cluster:
    """Where a grid runs: serially (both ``None``), on ``workers`` local processes, or on the
    Dask scheduler at ``scheduler`` (``tcp://host:8786``). ``pin_cores`` pins local worker i
    to CPU i (benchmarks: one worker = one single-core machine)."""

    workers: int | None = None
    scheduler: str | None = None
    pin_cores: bool = False
    connect_timeout_s: float = 20.0
    #: serial only: the tasks run one after another in a child process (see the module doc)
    child_process: bool = False

    def __post_init__(self) -> None:
        if self.workers is not None and self.scheduler is not None:
            raise StageError("give --workers N or --scheduler ADDRESS, not both")
        if self.workers is not None and self.workers < 1:
            raise StageError(f"--workers must be at least 1, got {self.workers}")
        if self.scheduler is not None and "://" not in self.scheduler:
            raise StageError(
                f"--scheduler {self.scheduler!r}: expected an address such as tcp://host:8786"
            )

    @property
    def serial(self) -> bool:
        return self.workers is None and self.scheduler is None

    def describe(self) -> str:
        if self.scheduler is not None:
            return f"Dask scheduler {self.scheduler}"
        if self.workers is not None:
            return f"local Dask cluster of {self.workers} single-thread worker processes"
        return "serially in a child process" if self.child_process else "serially in this process"


SERIAL = Cluster()


@dataclass(frozen=True)
class Shared:
    """A large input many tasks use, sent to the cluster once and checked by ``sha256``."""

    sha256: str
    value: Any = field(repr=False, compare=False)


@dataclass(frozen=True)
class GridTask:
    """One independent task: ``fn(*args)`` (``fn`` importable by workers, ``args`` picklable;
    :class:`Shared` arguments are replaced by their value)."""

    key: str
    fn: Callable[..., Any]
    args: tuple = ()


@dataclass
class GridReport:
    """What happened to a grid: results by key (None for every key when the grid was run with
    ``keep_results=False``), failures (key -> reason), re-run keys."""

    where: str
    results: dict[str, Any] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)
    retried: list[str] = field(default_factory=list)
    wall_s: float = 0.0
    start_s: float = 0.0  # starting (or connecting to) the cluster
    keep_results: bool = True

    def summary(self) -> str:
        n = len(self.results) + len(self.failed)
        text = (
            f"{len(self.results)}/{n} done, {len(self.failed)} failed, "
            f"{len(self.retried)} retried, {self.wall_s:.1f} s ({self.where})"
        )
        if self.retried:
            lost = "its child process died" if self.where.endswith("child process") else (
                "a worker was lost")  # fmt: skip
            text += f"; re-run after {lost}: " + ", ".join(sorted(self.retried))
        return text


def check_shared(value: Any, *, sha256: str, content_hash: Callable[[Any], str], what: str) -> Any:
    """``value`` if its content hash is ``sha256``; else a StageError (a worker was given the
    wrong or a corrupted input)."""
    got = content_hash(value)
    if got != sha256:
        raise StageError(f"{what} arrived with content hash {got[:12]}, expected {sha256[:12]}")
    return value


Progress = Callable[[str, str, int, int, int], None]
"""``progress(key, event, done, failed, retried)``; event is ``done``, ``failed`` or (from a
render command, for a clip whose file already matches) ``reused``."""


def run_grid(
    tasks: Iterable[GridTask],
    *,
    cluster: Cluster,
    on_result: Callable[[str, Any], None] | None = None,
    progress: Progress | None = None,
    window: int | None = None,
    keep_results: bool = True,
) -> GridReport:
    """Run every task; ``on_result(key, result)`` is called in this process as each finishes
    (in completion order). ``tasks`` may be a generator: on a cluster at most ``window``
    tasks (default 4 per worker) are made and in flight at a time, so a large grid's inputs
    are never all in memory. ``keep_results=False`` keeps no result in the report once
    ``on_result`` has had it (a render grid's mp4 bytes are not all held at once). Keys must
    be unique."""
    started = time.perf_counter()
    report = GridReport(where=cluster.describe(), keep_results=keep_results)
    unique = _unique(tasks)
    if cluster.serial and cluster.child_process:
        _run_in_child(unique, report, on_result, progress)
    elif cluster.serial:
        _run_serial(unique, report, on_result, progress)
    else:
        _run_dask(unique, cluster, report, on_result, progress, window)
    report.wall_s = time.perf_counter() - started
    return report


def _unique(tasks: Iterable[GridTask]) -> Iterator[GridTask]:
    seen: set[str] = set()
    for task in tasks:
        if task.key in seen:
            raise StageError(f"two grid tasks have the key {task.key!r}")
        seen.add(task.key)
        yield task


def _value(arg: Any) -> Any:
    return arg.value if isinstance(arg, Shared) else arg


def _record(report, key, outcome, on_result, progress) -> None:
    ok, value = outcome
    if ok:
        report.results[key] = value if report.keep_results else None
        if on_result is not None:
            on_result(key, value)
    else:
        report.failed[key] = value
    if progress is not None:
        progress(
            key, "done" if ok else "failed", len(report.results), len(report.failed),
            len(report.retried),
        )  # fmt: skip


def _run_serial(tasks, report, on_result, progress) -> None:
    for task in tasks:
        try:
            outcome = (True, task.fn(*(_value(a) for a in task.args)))
        except FacelabError as exc:
            outcome = (False, str(exc))
        _record(report, task.key, outcome, on_result, progress)


# --- one child process ------------------------------------------------------------------------

#: times a task is started when the child process running it dies (a new child each time)
CHILD_ATTEMPTS = 2

#: the child's first lines: stdlib only until the parent's sys.path is in place
_CHILD_BOOT = (
    "import sys; from multiprocessing.connection import Connection; "
    "conn = Connection(int(sys.argv[1])); sys.path[:] = conn.recv(); "
    "from facelab.grid import child_serve; child_serve(conn)"
)


@dataclass(frozen=True)
class _Held:
    """A :class:`Shared` value the child already holds, named by its hash."""

    sha256: str


class _ChildDiedError(Exception):
    def __init__(self, returncode: int | None):
        super().__init__(returncode)
        self.returncode = returncode

    def __str__(self) -> str:
        code = self.returncode
        if code is not None and code < 0:
            try:
                name = signal.Signals(-code).name
            except ValueError:
                name = f"signal {-code}"
            return (f"killed by {name}: a crash below facelab's own code, such as an OpenGL "
                    "driver or a codec")  # fmt: skip
        return f"it exited with status {code}"


class _GridChildTracebackError(Exception):
    """The traceback of an exception raised in the grid child (its text)."""


def child_serve(conn: Any) -> None:  # the grid child's main
    """Answer calls on ``conn`` until it closes. ``("grid",)`` lets the shared values held go;
    a call ``(environ, cwd, payload)`` runs the pickled ``(fn, args)`` in ``payload`` once
    the caller's environment and folder are in place (a module imported for ``fn`` sees
    them) and replies ``("ok", result)``, ``("failed", message)`` for a FacelabError or
    ``("raised", pickled exception or None, traceback text)`` for anything else."""
    try:
        _serve(conn)
    finally:  # the folder the parent made for this child (a killed child's is the parent's)
        tmp = tempfile.gettempdir()
        if os.path.basename(tmp).startswith("facelab-grid-child-"):
            shutil.rmtree(tmp, ignore_errors=True)


def _serve(conn: Any) -> None:
    held: dict[str, Any] = {}
    while True:
        try:
            call = conn.recv()
        except (EOFError, OSError):
            return
        if call == ("grid",):
            held.clear()
            continue
        environ, cwd, payload = call
        try:
            if environ != os.environ:
                os.environ.clear()
                os.environ.update(environ)
            os.chdir(cwd)
            fn, args = pickle.loads(payload)
            values = []
            for arg in args:
                if isinstance(arg, Shared):
                    held[arg.sha256] = arg.value
                values.append(held[arg.sha256] if isinstance(arg, Shared | _Held) else arg)
            reply: tuple = ("ok", fn(*values))
        except FacelabError as exc:
            reply = ("failed", str(exc))
        except Exception as exc:
            try:
                pickled = pickle.dumps(exc)
            except Exception:
                pickled = None
            reply = ("raised", pickled, traceback.format_exc())
        try:
            try:
                conn.send(reply)
            except (pickle.PicklingError, TypeError, AttributeError) as exc:  # the result
                conn.send(("raised", None, f"its result could not be sent back: {exc}"))
        except OSError:  # the parent is gone
            return


class _Child:
    """A Python process that runs grid tasks for this one, started once and kept for the
    next grid (its imports and an open renderer are paid for once); replaced if it dies. It
    runs in a session of its own (a terminal's Ctrl-C is the parent's to handle; it ends the
    child) with a temporary folder of its own, removed with it (a child killed mid-clip
    leaves nothing behind)."""

    def __init__(self) -> None:
        import socket
        import subprocess
        import sys
        from multiprocessing.connection import Connection

        self.owner = os.getpid()
        self.tmp = tempfile.mkdtemp(prefix="facelab-grid-child-")
        mine, theirs = socket.socketpair()
        self.proc = subprocess.Popen(
            [sys.executable, "-c", _CHILD_BOOT, str(theirs.fileno())],
            pass_fds=(theirs.fileno(),), env=self._environ(), start_new_session=True,
        )  # fmt: skip
        theirs.close()
        self.conn = Connection(mine.detach())
        self.conn.send([os.fspath(p) for p in sys.path if isinstance(p, str | os.PathLike)])
        self.sent: set[str] = set()

    def _environ(self) -> dict[str, str]:
        return {**os.environ, "TMPDIR": self.tmp}

    def alive(self) -> bool:
        return self.proc.poll() is None

    def forget(self) -> None:
        """The grid is over: the child lets its shared values go."""
        self.conn.send(("grid",))
        self.sent = set()

    def call(self, fn: Callable[..., Any], args: tuple) -> tuple[bool, Any]:
        """``fn(*args)`` in the child: (True, result) or (False, a FacelabError's message);
        a bug's exception is raised here (with the child's traceback as its cause);
        :class:`_ChildDiedError` if the child died."""
        sent = []
        for arg in args:
            if isinstance(arg, Shared) and arg.sha256 in self.sent:
                arg = _Held(arg.sha256)
            sent.append(arg)
        payload = pickle.dumps((fn, tuple(sent)))  # an argument that does not pickle: here
        message = (self._environ(), os.getcwd(), payload)
        try:
            self.conn.send(message)
            self.sent |= {a.sha256 for a in args if isinstance(a, Shared)}
            reply = self.conn.recv()
        except (EOFError, OSError):
            self.close()
            raise _ChildDiedError(self.proc.returncode) from None
        except BaseException:  # interrupted mid-task: a later reply would answer another call
            self.proc.kill()
            self.close()
            raise
        if reply[0] == "raised":
            _, pickled, text = reply
            try:
                exc = pickle.loads(pickled) if pickled is not None else None
            except Exception:
                exc = None
            if not isinstance(exc, BaseException):
                exc = RuntimeError(f"{getattr(fn, '__name__', fn)} failed in the grid child")
            raise exc from _GridChildTracebackError(f"\n\n(in the grid child)\n{text}")
        return reply[0] == "ok", reply[1]

    def close(self) -> None:
        """Let the child go (it ends when its socket closes), wait for it, and remove its
        temporary folder."""
        self.conn.close()
        try:
            self.proc.wait(10)
        except Exception:
            self.proc.kill()
            self.proc.wait()
        shutil.rmtree(self.tmp, ignore_errors=True)


_child: list[_Child] = []  # this process's grid child, while it lives
_child_lock = threading.Lock()


def grid_child_pid() -> int | None:
    """The process id of this process's grid child while it lives (benchmarks and the test
    suite count its CPU: it is not a child anyone has waited for yet)."""
    child = _own_child()
    return child.proc.pid if child is not None and child.alive() else None


def _own_child() -> _Child | None:
    """This process's grid child; a forked copy of this process does not share it."""
    if _child and _child[0].owner != os.getpid():
        _child.clear()
    return _child[0] if _child else None


def _forget_child_after_fork() -> None:
    """In a forked copy of this process: the parent's child (and its lock) are not this
    one's."""
    global _child_lock
    _child_lock = threading.Lock()
    _child.clear()


os.register_at_fork(after_in_child=_forget_child_after_fork)


@atexit.register
def _close_child() -> None:
    child = _own_child()
    _child.clear()
    if child is not None:
        child.close()


def _run_in_child(tasks, report, on_result, progress) -> None:
    """Serially in this process's grid child; a task whose child dies is run again in a new
    one (:data:`CHILD_ATTEMPTS` times in all), then failed with how the child died. Not
    re-entrant: a grid started from another's callbacks waits for ever."""
    with _child_lock:
        try:
            for task in tasks:
                for attempt in range(CHILD_ATTEMPTS):
                    child = _own_child()
                    if child is not None and not child.alive():
                        _close_child()
                        child = None
                    if child is None:
                        child = _Child()
                        _child.append(child)
                    try:
                        outcome = child.call(task.fn, task.args)
                        break
                    except _ChildDiedError as died:
                        _child.clear()
                        if attempt == 0:
                            report.retried.append(task.key)
                        why = died
                else:
                    outcome = (False, f"the child process running it died {CHILD_ATTEMPTS} "
                                      f"times ({why}); the other tasks ran")  # fmt: skip
                _record(report, task.key, outcome, on_result, progress)
        finally:
            child = _own_child()
            if child is not None:
                try:
                    child.forget()
                except OSError:  # it died
                    _close_child()


# --- Dask (imported here only) ---------------------------------------------------------------


def _pin_worker(dask_worker) -> int:  # runs on each worker
    """Pin this worker process to one CPU, chosen by its name (0, 1, ...)."""
    cpus = sorted(os.sched_getaffinity(0))
    cpu = cpus[int(dask_worker.name) % len(cpus)]
    for tid in os.listdir("/proc/self/task"):  # every thread: affinity is per thread on Linux
        with contextlib.suppress(ProcessLookupError):
            os.sched_setaffinity(int(tid), {cpu})
    return cpu


def _attempts(dask_scheduler, keys: list[str]) -> dict[str, int]:  # runs on the scheduler
    """How many times each task was sent to a worker (more than once: a worker was lost)."""
    out = {}
    for key in keys:
        out[key] = sum(1 for t in dask_scheduler.story(key) if t[0] == key and t[2] == "processing")
    return out


@contextlib.contextmanager
def _client(cluster: Cluster) -> Iterator[Any]:
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:
        raise StageError(
            "--workers/--scheduler need Dask: pip install 'facelab[cluster]' "
            "(scripts/setup.sh installs it)"
        ) from exc
    if cluster.scheduler is not None:
        try:
            client = Client(cluster.scheduler, timeout=f"{cluster.connect_timeout_s}s")
        except (OSError, TimeoutError) as exc:
            raise StageError(
                f"cannot reach the Dask scheduler at {cluster.scheduler} (is `dask scheduler` "
                "running there and the port open?)"
            ) from exc
        with client:
            yield client
        return
    import dask

    # Dask starts workers with MALLOC_TRIM_THRESHOLD_=65536, which makes glibc hand memory
    # back to the system after every large free: rendering (a few MB of arrays per frame) was
    # 20 % slower per clip with it (facelab bench render-grid). BLAS stays single-threaded.
    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", default={}) or {})
    environ.pop("MALLOC_TRIM_THRESHOLD_", None)
    with (
        dask.config.set({"distributed.nanny.pre-spawn-environ": environ}),
        LocalCluster(
            n_workers=cluster.workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            silence_logs=50,  # CRITICAL only: a lost worker is reported by the grid itself
        ) as local,
        Client(local) as client,
    ):
        if cluster.pin_cores:
            client.run(_pin_worker)
        yield client


def _run_dask(tasks, cluster, report, on_result, progress, window) -> None:
    from distributed import as_completed

    pending = iter(tasks)
    head = list(itertools.islice(pending, 1))
    if not head:  # nothing to run (a render whose clips are all reused): no cluster at all
        return
    pending = itertools.chain(head, pending)
    t0 = time.perf_counter()
    with _client(cluster) as client:
        report.start_s = time.perf_counter() - t0
        if not client.scheduler_info().get("workers"):
            client.wait_for_workers(1, timeout=120)
        n_workers = max(1, len(client.scheduler_info().get("workers", {})))
        window = window or 4 * n_workers
        sent: dict[str, Any] = {}  # every shared input once, by content
        token = os.urandom(4).hex()  # a re-run of the same grid never meets old results
        keys: dict[str, str] = {}  # Dask key -> task key

        def submit(task: GridTask):
            args = []
            for a in task.args:
                if isinstance(a, Shared):
                    if a.sha256 not in sent:
                        sent[a.sha256] = client.scatter(a.value, hash=False, broadcast=True)
                    a = sent[a.sha256]
                args.append(a)
            fut = client.submit(
                task.fn, *args, key=f"facelab-{token}-{task.key}", pure=False, retries=0
            )
            keys[fut.key] = task.key
            return fut

        first = list(itertools.islice(pending, window))
        # workers import the tasks' modules now (pyrender, OpenGL: about a second), so the
        # cost shows as the cluster's start, once per worker, not inside the first tasks
        for module in sorted({t.fn.__module__ for t in first}):
            client.run(importlib.import_module, module)
        report.start_s = time.perf_counter() - t0
        queue = as_completed([submit(t) for t in first])
        for fut in queue:
            key = keys[fut.key]
            if fut.status == "finished":
                outcome = (True, fut.result())
            else:
                exc = fut.exception()
                if not isinstance(exc, FacelabError) and type(exc).__name__ != "KilledWorker":
                    raise exc  # a bug: keep its traceback
                outcome = (False, str(exc) if isinstance(exc, FacelabError) else LOST)
            fut.release()
            _record(report, key, outcome, on_result, progress)
            nxt = next(pending, None)
            if nxt is not None:
                queue.add(submit(nxt))
        attempts = client.run_on_scheduler(_attempts, keys=list(keys))
        report.retried = sorted(keys[k] for k, n in attempts.items() if n > 1)


#: why a task failed when every worker that ran it was lost (Dask's KilledWorker)
LOST = "its worker was lost every time the task ran (the scheduler gave up after 3 tries)"
