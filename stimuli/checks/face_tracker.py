"""The outside observer of the stimulus checks: MediaPipe face detection and Face Mesh, run in
their own environment (``.venv-mediapipe``, made by ``scripts/setup.sh``) on the clips'
decoded frames. This module is the edge: it starts :mod:`.tracker_worker` there as a child
process and returns what it measured as arrays; nothing here imports MediaPipe.

The tracker's Python is ``$FACELAB_TRACKER_PYTHON`` when set, else ``.venv-mediapipe`` beside
the ``.venv`` facelab runs from (or beside the source tree of an editable install).

Tracker processes are kept: a process that checks clips more than once (a demo, the render of
several stimulus sets, the test suite's workers) starts each of its trackers once. Importing
MediaPipe is most of a small check's work (1.2 CPU-s per process here, two processes a
check). A tracker answers one request (a line of JSON) at a time and goes back to this
process's pool when its answer is read; one that fails or is interrupted is ended, not kept.
"""

from __future__ import annotations

import atexit
import contextlib
import hashlib
import itertools
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import ClassVar

import numpy as np

from facelab.errors import StageError
from facelab.stimuli.render.clip import ffmpeg_each

__all__ = [
    "ANALYSIS_HEIGHT",
    "ClipTracking",
    "PendingTracking",
    "analysis_size",
    "kept_tracker_pids",
    "picture_keys",
    "start_tracking",
    "track_clips",
    "tracker_python",
]

#: every clip is decoded at this height (px) for the tracker, whatever size it was rendered at:
#: MediaPipe reads faces at 128-192 px, and one size keeps the measures comparable
ANALYSIS_HEIGHT = 360
WORKER = Path(__file__).with_name("tracker_worker.py")


@dataclass(frozen=True)
class ClipTracking:
    """Per-frame measures of one clip (n frames): ``detection`` (n,) the best face's confidence
    (0 without a face); ``box`` (n, 4) x0 y0 x1 y1 of the face mesh in fractions of the frame
    (NaN without a mesh); ``aperture``, ``width`` (n,) inner-lip opening and mouth width over
    the face height (10-152); ``face_height`` (n,) in frame heights."""

    path: str
    detection: np.ndarray
    box: np.ndarray
    aperture: np.ndarray
    width: np.ndarray
    face_height: np.ndarray
    tracker: str
    grey: np.ndarray  # (n, h, w) uint8: the frames' grey levels at half the analysis size

    @property
    def frames(self) -> int:
        return len(self.detection)


def tracker_python() -> Path | None:
    """The MediaPipe environment's Python, or None when it is not installed."""
    given = os.environ.get("FACELAB_TRACKER_PYTHON")
    if given:
        return Path(given) if Path(given).is_file() else None
    here = Path(__file__).resolve()
    for root in (Path(sys.prefix).parent, *here.parents):
        candidate = root / ".venv-mediapipe" / "bin" / "python"
        if candidate.is_file():
            return candidate
    return None


def analysis_size(width: int, height: int) -> tuple[int, int]:
    """(width, height) a clip of ``width`` x ``height`` px is decoded at for the tracker."""
    w = 2 * round(width * ANALYSIS_HEIGHT / height / 2)
    return max(w, 2), ANALYSIS_HEIGHT


def _array(values: list, shape: tuple[int, ...] = ()) -> np.ndarray:
    nan = [np.nan] * shape[0] if shape else np.nan
    return np.asarray([nan if v is None else v for v in values], float)


def picture_keys(paths: Sequence[Path], *, batch: int = 24) -> list[str | None]:
    """A key per clip that is equal for clips whose picture streams are the same bytes with
    the same timing (a re-muxed clip and the clip it copied the picture from): the SHA-256
    of ffmpeg's per-packet checksums of the copied video stream (timestamps, sizes, codec
    header and dimensions included). None where it cannot be read (such a clip is tracked
    on its own). In batches (:func:`~facelab.stimuli.render.clip.ffmpeg_each`)."""
    if shutil.which("ffmpeg") is None:
        return [None] * len(paths)
    framehash = ["-c", "copy", "-f", "framehash", "-hash", "sha256"]
    sums = ffmpeg_each(paths, stream="v:0", batch=batch, output_args=framehash)
    return [hashlib.sha256(text).hexdigest() if text else None for text in sums]


class PendingTracking:
    """Tracker processes started by :func:`start_tracking`; :meth:`collect` waits for them
    (the caller may do its own work meanwhile) and returns {str(path): ClipTracking}. Clips
    with the same picture (:func:`picture_keys`) and size are tracked once."""

    def __init__(self, clips: Sequence[tuple[Path, int, int, float]], processes: int | None):
        python = tracker_python()
        if python is None:
            raise StageError(
                "the face tracker is not installed (MediaPipe's environment .venv-mediapipe); "
                "run bash scripts/setup.sh, or set FACELAB_TRACKER_PYTHON"
            )
        self.python = python
        # one tracking per picture: the others get its measures under their own path
        self._same: dict[str, str] = {}  # str(path) -> str(path) of the clip tracked for it
        first: dict[tuple, str] = {}
        unique = []
        for clip, key in zip(clips, picture_keys([c[0] for c in clips]), strict=True):
            path, w, h, duration = clip
            ident = (key, w, h, duration) if key is not None else (str(path),)
            if ident in first:
                self._same[str(path)] = first[ident]
                continue
            first[ident] = str(path)
            unique.append(clip)
        clips = unique
        n_proc = max(1, min(processes or _max_trackers(), len(clips)))
        groups: list[list[dict]] = [[] for _ in range(n_proc)]
        load = [0.0] * n_proc
        self._trackers: list[_Tracker] = []
        self._tmp = tempfile.TemporaryDirectory(prefix="facelab-track-")
        try:
            tmp = Path(self._tmp.name)
            for i in sorted(range(len(clips)), key=lambda i: -clips[i][3]):  # longest first
                path, w, h, duration = clips[i]
                k = load.index(min(load))
                load[k] += duration
                aw, ah = analysis_size(w, h)
                # absolute: a kept tracker runs in the folder it was started in
                groups[k].append({"path": os.path.abspath(path), "width": aw, "height": ah,
                                  "grey": str(tmp / f"{i}.npy")})  # fmt: skip
            self._given = {os.path.abspath(c[0]): str(c[0]) for c in clips}  # -> caller's name
            self._greys = {c["path"]: c["grey"] for g in groups for c in g}
            for group in groups:
                self._trackers.append(_Tracker.asked(python, {"clips": group}))
        except BaseException:
            self.cancel()
            raise

    def cancel(self) -> None:
        """End the trackers still working for this request (a caller that will not
        :meth:`collect`, after its own error) and remove the temporary folder."""
        trackers, self._trackers = self._trackers, []
        for tracker in trackers:
            tracker.end()
        self._tmp.cleanup()

    def collect(self) -> dict[str, ClipTracking]:
        try:
            answers = [tracker.answer() for tracker in self._trackers]
            out = {}
            for answer in answers:
                for clip in answer["clips"]:
                    name = self._given[clip["path"]]
                    if "error" in clip:
                        raise StageError(
                            f"{name}: the face tracker cannot decode it: {clip['error']}"
                        )
                    out[name] = ClipTracking(
                        path=name,
                        detection=np.asarray(clip["detection"], float),
                        box=_array(clip["box"], (4,)).reshape(-1, 4),
                        aperture=_array(clip["aperture"]),
                        width=_array(clip["width"]),
                        face_height=_array(clip["face_height"]),
                        tracker=answer["tracker"],
                        grey=np.load(self._greys[clip["path"]]),
                    )
            for path, tracked in self._same.items():
                out[path] = replace(out[tracked], path=path)
            trackers, self._trackers = self._trackers, []  # every answer read: to the pool
            _Tracker.give_back(trackers)
            return out
        finally:
            self.cancel()


def _max_trackers() -> int:
    """Tracker processes a check uses (and this process keeps) at most: one per CPU, up to 4."""
    return min(os.cpu_count() or 1, 4)


class _Tracker:
    """One tracker process (:mod:`.tracker_worker` in MediaPipe's environment), kept in this
    process's pool between requests (at most :func:`_max_trackers`). It is started with this
    process's environment: the pool keeps apart trackers whose Python or ffmpeg differ."""

    _idle: ClassVar[list[_Tracker]] = []
    _lock: ClassVar[threading.Lock] = threading.Lock()
    _asked: ClassVar[itertools.count] = itertools.count()

    def __init__(self, python: Path):
        # no display: MediaPipe opens an X connection when it may, and a kept tracker would
        # hold it (an X server resets - keyboard map and all - when its last client leaves)
        env = {k: v for k, v in os.environ.items()
               if k not in ("PYTHONPATH", "PYTHONHOME", "DISPLAY", "WAYLAND_DISPLAY")}  # fmt: skip
        env.setdefault("GLOG_minloglevel", "2")
        env.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
        self.key, self.owner, self.python = _Tracker.key_now(python), os.getpid(), python
        self.reused = False
        # its stderr, read from the end of its last answer when it fails; open while it lives
        self._err = tempfile.TemporaryFile(prefix="facelab-tracker-")  # noqa: SIM115
        self._err_at = 0
        self._id: int | None = None
        self.proc = subprocess.Popen(
            [str(python), str(WORKER)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            stderr=self._err, text=True, env=env,
        )  # fmt: skip

    @staticmethod
    def key_now(python: Path) -> tuple[str, str | None]:
        return str(python), shutil.which("ffmpeg")

    @classmethod
    def asked(cls, python: Path, request: dict) -> _Tracker:
        """A tracker (a kept one if there is one) that has been sent ``request``. A kept
        tracker that died since (its pipe is closed) is replaced by a new one."""
        tracker = cls._take(python)
        try:
            tracker._ask(request)
        except StageError:
            if not tracker.reused:
                raise
            tracker = cls(python)
            tracker._ask(request)
        return tracker

    @classmethod
    def _take(cls, python: Path) -> _Tracker:
        key = cls.key_now(python)
        with cls._lock:
            idle, cls._idle[:] = list(cls._idle), []
            found = None
            for tracker in idle:
                usable = tracker.owner == os.getpid() and tracker.key == key and (
                    tracker.proc.poll() is None)  # fmt: skip
                if found is None and usable:
                    found = tracker
                elif usable:
                    cls._idle.append(tracker)
                else:
                    tracker.end()
        if found is not None:
            found.reused = True
            return found
        return cls(python)

    def _ask(self, request: dict) -> None:
        self._id = next(_Tracker._asked)
        try:
            self.proc.stdin.write(json.dumps({**request, "id": self._id}) + "\n")  # type: ignore[union-attr]
            self.proc.stdin.flush()  # type: ignore[union-attr]
        except OSError:  # it ended
            raise self._failed() from None

    def _failed(self) -> StageError:
        """The tracker stopped: wait for it; its exit and what it wrote since its last answer
        (or its start)."""
        code = self.proc.wait()
        self._err.seek(self._err_at)
        stderr = self._err.read().decode(errors="replace").strip()
        self.end()
        last = stderr.splitlines()[-1] if stderr else "no message"
        return StageError(f"the face tracker ({self.python}) stopped with exit {code}: {last}")

    def answer(self) -> dict:
        line = self.proc.stdout.readline()  # type: ignore[union-attr]
        if not line.endswith("\n"):  # nothing, or a line cut short: it ended
            raise self._failed()
        try:
            answer = json.loads(line)
        except ValueError:
            answer = None
        if not isinstance(answer, dict) or answer.get("id") != self._id:
            self.end()
            raise StageError(f"the face tracker ({self.python}) answered something else than "
                             "the request it was sent")  # fmt: skip
        self._err_at = self._err.seek(0, os.SEEK_END)  # a later failure's message: after this
        return answer

    @classmethod
    def give_back(cls, trackers: list[_Tracker]) -> None:
        """Keep ``trackers`` (every answer read) for later requests, up to the pool's size."""
        with cls._lock:
            room = max(0, _max_trackers() - len(cls._idle))
            cls._idle += trackers[:room]
        for tracker in trackers[room:]:
            tracker.end()

    def end(self) -> None:
        """End the process (interrupted mid-request, failed, or no longer wanted)."""
        if self.owner == os.getpid():
            if self.proc.poll() is None:
                self.proc.kill()
            self.proc.wait()
        for pipe in (self.proc.stdin, self.proc.stdout, self._err):
            with contextlib.suppress(OSError):
                pipe.close()  # type: ignore[union-attr]

    @classmethod
    def end_all(cls) -> None:
        """At exit: the idle trackers' input is closed; each ends when it reads that."""
        with cls._lock:
            idle, cls._idle[:] = list(cls._idle), []
        for tracker in idle:
            if tracker.owner == os.getpid():
                with contextlib.suppress(OSError):
                    tracker.proc.stdin.close()  # type: ignore[union-attr]
                with contextlib.suppress(subprocess.TimeoutExpired):
                    tracker.proc.wait(5)
            tracker.end()

    @classmethod
    def forget_after_fork(cls) -> None:
        """In a forked copy of this process: the parent's trackers are not this one's."""
        cls._lock = threading.Lock()
        cls._idle = []


atexit.register(_Tracker.end_all)
os.register_at_fork(after_in_child=_Tracker.forget_after_fork)


def kept_tracker_pids() -> list[int]:
    """Process ids of this process's idle trackers (the test suite counts their CPU: no one
    has waited for them yet)."""
    with _Tracker._lock:
        return [t.proc.pid for t in _Tracker._idle
                if t.owner == os.getpid() and t.proc.poll() is None]  # fmt: skip


def start_tracking(
    clips: Sequence[tuple[Path, int, int, float]], *, processes: int | None = None
) -> PendingTracking:
    """Start tracking every clip ``(path, width, height, duration_s)``: the clips are shared
    out, longest first, among ``processes`` tracker processes (default: one per CPU, at most
    4). StageError when the tracker is not installed."""
    return PendingTracking(clips, processes)


def track_clips(
    clips: Sequence[tuple[Path, int, int, float]], *, processes: int | None = None
) -> dict[str, ClipTracking]:
    """:func:`start_tracking` and wait: {str(path): ClipTracking}. StageError when the tracker
    is not installed or fails (naming the clip)."""
    return start_tracking(clips, processes=processes).collect()
