"""Shared fixtures: the repository paths, the paper's protocol, and a fixed-seed generator.

Parallel workers (pytest-xdist, ``scripts/test.sh`` runs ``-n``): each worker gets an X display
of its own (an Xvfb started here), because the scripted participant of ``facelab run
--simulate`` moves the one pointer of its display and two sessions on one screen would click
into each other's windows. Ports, databases and folders are per test already (port 0 or a free
port, temporary folders). Slow tests are collected first so that the long ones start early and
the short ones fill the gaps at the end.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import subprocess
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
KATO = ROOT / "protocols" / "kato2021.yaml"

_XVFB: subprocess.Popen | None = None


def _own_display() -> None:
    """Start an Xvfb for this worker and point DISPLAY (and every child) at it."""
    global _XVFB
    exe = shutil.which("Xvfb")
    if exe is None:
        return  # the display tests say so themselves
    read, write = os.pipe()
    _XVFB = subprocess.Popen(
        [exe, "-displayfd", str(write), "-screen", "0", "1280x1024x24", "-nolisten", "tcp"],
        pass_fds=(write,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    os.close(write)
    with os.fdopen(read) as fh:
        number = fh.readline().strip()
    if not number:
        raise RuntimeError("Xvfb did not start for this test worker")
    os.environ["DISPLAY"] = f":{number}"
    os.environ.pop("XAUTHORITY", None)  # no cookie: the worker's own server admits local clients


#: every test's wall and CPU seconds (its own process, the children it waited for - ffmpeg,
#: Dask workers - and the grid child and face trackers, which live on between tests; not
#: Chromium's processes, which chromedriver does not wait for), one
#: JSON line each, appended by whichever worker ran it (named: "gw0".., "main" without xdist);
#: the run's summary adds them up by file.
TIMES = ROOT / ".pytest_cache" / "facelab-test-times.jsonl"


def _cpu() -> tuple[float, float]:
    me = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime, kids.ru_utime + kids.ru_stime


def _kept_processes_cpu() -> float:
    """CPU seconds so far of the child processes facelab keeps between tests - its grid child
    (facelab.grid) and its idle face trackers - with their own waited-for children (ffmpeg):
    /proc/PID/stat's utime, stime, cutime, cstime."""
    from facelab.grid import grid_child_pid
    from facelab.stimuli.checks.face_tracker import kept_tracker_pids

    total = 0.0
    for pid in [grid_child_pid(), *kept_tracker_pids()]:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        total += sum(int(v) for v in fields[11:15]) / os.sysconf("SC_CLK_TCK")
    return total


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None):
    wall, kept, (me, kids) = time.perf_counter(), _kept_processes_cpu(), _cpu()
    yield
    kept_after, after = _kept_processes_cpu(), _cpu()
    # the kept processes' CPU since the test began; one that ended in the test (replaced
    # after a crash, a tracker that failed) was waited for, so its whole life is in the
    # children's CPU: less what earlier tests counted of it
    kept_s = kept_after - kept
    line = {"test": item.nodeid, "wall_s": round(time.perf_counter() - wall, 3),
            "cpu_s": round(after[0] - me, 3),
            "children_cpu_s": round(after[1] - kids + kept_s, 3),
            "worker": os.environ.get("PYTEST_XDIST_WORKER", "main")}
    with TIMES.open("a", encoding="utf-8") as fh:  # one short line a write: whole lines interleave
        fh.write(json.dumps(line) + "\n")


def pytest_terminal_summary(terminalreporter, exitstatus: int, config: pytest.Config) -> None:
    if os.environ.get("PYTEST_XDIST_WORKER") or not TIMES.is_file():
        return
    by_file: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0])
    for raw in TIMES.read_text(encoding="utf-8").splitlines():
        try:
            t = json.loads(raw)
        except ValueError:  # a worker killed mid-line
            continue
        spent = by_file[t["test"].split("::")[0]]
        spent[0] += t["cpu_s"] + t["children_cpu_s"]
        spent[1] += t["wall_s"]
    if not by_file:
        return
    total = sum(cpu for cpu, _ in by_file.values())
    terminalreporter.section(
        f"test files by CPU seconds (all: {total:.0f} s, browsers not counted; {TIMES.name})"
    )
    for name, (cpu, wall) in sorted(by_file.items(), key=lambda kv: -kv[1][0])[:15]:
        terminalreporter.write_line(f"{cpu:8.1f} s CPU {wall:8.1f} s wall  {name}")


_CACHE: str | None = None  # the OpenJTalk cache this run made, removed at its end


def pytest_configure(config: pytest.Config) -> None:
    if not os.environ.get("PYTEST_XDIST_WORKER"):  # the run's first process starts the record
        TIMES.parent.mkdir(exist_ok=True)
        TIMES.write_text("", encoding="utf-8")
        # OpenJTalk's outputs are kept for the run's processes (workers and the commands they
        # start inherit it), in a new folder: every run starts without, as a fresh machine does
        if "FACELAB_CACHE_DIR" not in os.environ:
            global _CACHE
            _CACHE = tempfile.mkdtemp(prefix="facelab-test-cache-")
            os.environ["FACELAB_CACHE_DIR"] = _CACHE
    # a facelab child that dies in native code (a signal, not an error) prints where it was
    os.environ.setdefault("PYTHONFAULTHANDLER", "1")
    if os.environ.get("PYTEST_XDIST_WORKER") and os.environ.get("DISPLAY"):
        _own_display()


def pytest_unconfigure(config: pytest.Config) -> None:
    if _CACHE is not None:  # the run's own cache (made by its first process)
        shutil.rmtree(_CACHE, ignore_errors=True)
    if _XVFB is not None:
        _XVFB.terminate()
        _XVFB.wait(timeout=10)


@pytest.hookimpl(trylast=True)  # after -m / -k deselection: the split is of the tests run
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Slow tests first. Under scripts/test.sh's work stealing each of n workers starts on one
    of n equal consecutive runs of the collection, so the slowest measured tests
    (tests/slowest_tests.json) are dealt out to the runs' starts, longest first to the run
    with the least so far: each starts at once on its own worker, not queued behind another."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)  # stable: slow first
    known = json.loads((ROOT / "tests" / "slowest_tests.json").read_text("utf-8"))["seconds"]
    heavy = sorted((i for i in items if i.nodeid in known), key=lambda i: -known[i.nodeid])
    rest = [i for i in items if i.nodeid not in known]
    n = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
    runs: list[list[pytest.Item]] = [[] for _ in range(n)]
    loads = [0.0] * n
    for item in heavy:
        k = loads.index(min(loads))
        runs[k].append(item)
        loads[k] += known[item.nodeid]
    ordered, left = [], len(items)
    for k in range(n):  # the scheduler's first split: left // (workers still to serve)
        size = max(left // (n - k), len(runs[k]))
        take = size - len(runs[k])
        ordered += runs[k] + rest[:take]
        rest, left = rest[take:], left - size
    items[:] = ordered + rest


@pytest.fixture(autouse=True, scope="session")
def _shared_renders_factory(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Helpers without a fixture of their own (tests/task_protocols.py) share renders too."""
    from tests.shared_renders import remember_factory

    remember_factory(tmp_path_factory)


@pytest.fixture
def kato_path() -> Path:
    return KATO


@pytest.fixture
def kato_text() -> str:
    return KATO.read_text(encoding="utf-8")


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20260101)
