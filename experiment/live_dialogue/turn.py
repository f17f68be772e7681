"""One live turn: what the talker said, the frames the viewer was sent, and what the viewer
showed when - kept in a folder, and its latency summarised. Pure but for :meth:`Turn.save`.

A turn's folder (``<session>/turn-001`` …, never overwritten; :meth:`Turn.save_new`)::

    audio.wav    the talker's audio as analysed (32-bit float WAV, the stream's rate)
    track.bin    the frames exactly as sent and shown (facelab-track-1, 100 fps: frame k is
                 the face at k / 100 s of audio.wav)
    frames.csv   per drawn display frame of each viewer: viewer, page_ms, heard_s (the audio
                 time the viewer was hearing), frame (the track frame drawn), wanted (the
                 frame for heard_s), latency_ms (heard_s - frame / 100: mouth behind sound, ms; an
                 on-time frame reads 0-10 ms, the track's own frame step), late
    poses.csv    in VR only: per drawn frame of each viewer in a headset, the head's pose:
                 viewer, page_ms, x, y, z (m), yaw, pitch, roll (deg), in the headset's
                 reference space
    turn.json    protocol, condition, method, avatar, rates, the latency summary, what a
                 browser cannot measure (and in VR the head's yaw and pitch ranges)

Latency is measured where the viewer's page can see it: the audio clock it plays the talker's
sound by and the frame it draws at each display frame. The budget follows ITU-R BT.1359's
detectability limits for sound and picture: the mouth may lag the sound by at most
:data:`BUDGET_BEHIND_MS` (sound 45 ms ahead of the picture is detectable) and may never lead
it by more than :data:`BUDGET_AHEAD_MS`.
"""

from __future__ import annotations

import csv
import errno
import io
import json
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from facelab.durable import fsync_dir, replace_file
from facelab.errors import SessionError
from facelab.formats import encode_track

__all__ = [
    "BUDGET_AHEAD_MS",
    "BUDGET_BEHIND_MS",
    "FRAME_COLUMNS",
    "NOT_MEASURED",
    "Turn",
    "latency_summary",
    "next_turn_dir",
    "turns_protocol",
]

#: mouth behind sound, ms, at the 95th percentile of drawn frames (BT.1359: sound leading the
#: picture by 45 ms is detectable)
BUDGET_BEHIND_MS = 45.0
#: mouth ahead of sound, ms, at any drawn frame
BUDGET_AHEAD_MS = 45.0
FRAME_COLUMNS = ("viewer", "page_ms", "heard_s", "frame", "wanted", "latency_ms", "late")
POSE_COLUMNS = ("viewer", "page_ms", "x", "y", "z", "yaw", "pitch", "roll")
#: what the figures leave out: a page sees its own clocks only
NOT_MEASURED = (
    "the microphone's and the sound card's own delays before the talker's page gets the "
    "samples and after the viewer's page hands them over (AudioContext.outputLatency is "
    "counted where the browser reports it; headless Chromium reports none), and the "
    "display's delay from a drawn frame to light (vsync, scan-out, the panel); "
    "network delay between two machines is inside the playout buffer, not in latency_ms"
)


def next_turn_dir(session: Path) -> Path:
    """The next free ``turn-NNN`` folder in ``session`` (not made)."""
    taken = [int(p.name[5:]) for p in Path(session).glob("turn-*")
             if p.name[5:].isdigit()]  # fmt: skip
    return Path(session) / f"turn-{max(taken, default=0) + 1:03d}"


def latency_summary(
    rows: list[dict[str, Any]],
    *,
    n_frames: int,
    fps: int = 100,
    playout_ms: float = 0.0,
    margins_ms: list[float] | None = None,
) -> dict[str, Any]:
    """The turn's figures from the viewers' frame rows (:data:`FRAME_COLUMNS`): drawn
    frames while the talker's audio was heard (0 <= heard_s < n_frames / fps), how many
    showed an older frame than the sound wanted (late: the frame had not arrived), the mouth's
    lag behind the sound (median, 95th percentile, largest), its largest lead, and whether
    both are within the budget. ``margins_ms``: how long before it was due each frames
    message was handled by the viewer's page (the page's own clock: a page busy drawing
    handles its messages late and in bursts, so this is a bound, not the network's figure)."""
    end = n_frames / fps
    during = [r for r in rows if 0.0 <= float(r["heard_s"]) < end]
    lat = np.array([float(r["latency_ms"]) for r in during])
    out: dict[str, Any] = {
        "frames_shown": len(during),
        "frames_late": int(sum(bool(int(r["late"])) for r in during)),
        "latency_ms_median": None,
        "latency_ms_p95": None,
        "latency_ms_max": None,
        "ahead_ms_max": None,
        "frame_interval_ms_median": None,
        "playout_ms": round(float(playout_ms), 1),
        "frame_margin_ms_min": round(min(margins_ms), 1) if margins_ms else None,
        "frame_margin_ms_median": round(float(np.median(margins_ms)), 1) if margins_ms else None,
        "budget": {
            "behind_ms_p95": BUDGET_BEHIND_MS,
            "ahead_ms_max": BUDGET_AHEAD_MS,
            "after": "ITU-R BT.1359 detectability",
        },
        "within_budget": None,
    }
    if lat.size:
        out.update(
            latency_ms_median=round(float(np.median(lat)), 2),
            latency_ms_p95=round(float(np.percentile(lat, 95)), 2),
            latency_ms_max=round(float(lat.max()), 2),
            ahead_ms_max=round(max(0.0, float(-lat.min())), 2),
        )
        for viewer in sorted({r["viewer"] for r in during}):
            page = np.sort([float(r["page_ms"]) for r in during if r["viewer"] == viewer])
            if len(page) > 1:  # the first viewer's drawing rate (a headless browser's is slow)
                out["frame_interval_ms_median"] = round(float(np.median(np.diff(page))), 1)
                break
        out["within_budget"] = bool(
            out["latency_ms_p95"] <= BUDGET_BEHIND_MS and out["ahead_ms_max"] <= BUDGET_AHEAD_MS
        )
    return out


@dataclass
class Turn:
    """A turn being recorded: audio chunks and sent frames appended as they come."""

    sample_rate: int
    names: tuple[str, ...]
    fps: int = 100
    audio: list[np.ndarray] = field(default_factory=list)
    frames: list[np.ndarray] = field(default_factory=list)
    rows: list[dict[str, Any]] = field(default_factory=list)
    n_frames: int = 0
    #: per frames message a viewer got: how long before its first frame was due it arrived, ms
    margins_ms: list[float] = field(default_factory=list)
    #: in VR: per drawn frame, the viewer's head pose (see the module docstring)
    poses: list[dict[str, Any]] = field(default_factory=list)

    def add_audio(self, chunk: np.ndarray) -> None:
        self.audio.append(np.asarray(chunk, np.float32).ravel())

    def add_frames(self, start: int, weights: np.ndarray) -> None:
        """Frames ``start`` .. ``start + len(weights) - 1``; they must follow the last ones."""
        if start != self.n_frames:
            raise SessionError(f"live frames from {start} after {self.n_frames} frames: the "
                               "track would not line up with the audio")  # fmt: skip
        if len(weights):
            self.frames.append(np.asarray(weights, np.float32))
            self.n_frames += len(weights)

    def add_viewer_log(
        self,
        viewer: int,
        log: list[list[float]],
        *,
        arrivals: list[list[float]] | None = None,
        poses: list[list[float]] | None = None,
    ) -> None:
        """A viewer's drawn frames, each ``[page_ms, heard_s, frame, _]`` (finite numbers),
        and when its frame messages arrived, each ``[first frame, audio time then playing
        (s)]``. The frame the sound wanted (``wanted``) and ``late`` are computed here from
        ``heard_s``, not taken from the page. In VR, ``poses``: per drawn frame
        ``[page_ms, x, y, z, yaw, pitch, roll]`` of the viewer's head."""
        for page_ms, *pose in poses or ():
            head = {k: round(float(v), 4) for k, v in zip(POSE_COLUMNS[2:], pose, strict=True)}
            self.poses.append({"viewer": viewer, "page_ms": round(float(page_ms), 2), **head})
        for frame, at in arrivals or ():
            self.margins_ms.append(round((int(frame) / self.fps - float(at)) * 1000, 2))
        for page_ms, heard_s, frame, _ in log:
            wanted = math.floor(float(heard_s) * self.fps + 1e-9)
            self.rows.append({
                "viewer": viewer, "page_ms": round(float(page_ms), 2),
                "heard_s": round(float(heard_s), 5), "frame": int(frame), "wanted": wanted,
                "latency_ms": round((float(heard_s) - int(frame) / self.fps) * 1000, 2),
                "late": int(int(frame) < wanted),
            })  # fmt: skip

    def _pose_summary(self) -> dict[str, Any]:
        """In VR: the head poses logged, and the head's yaw and pitch ranges (deg) over them."""
        if not self.poses:
            return {}
        yaw = np.degrees(np.unwrap(np.radians([p["yaw"] for p in self.poses])))
        pitch = np.array([p["pitch"] for p in self.poses])
        return {"head_poses": len(self.poses),
                "head_yaw_range_deg": round(float(np.ptp(yaw)), 2),
                "head_pitch_range_deg": round(float(np.ptp(pitch)), 2)}  # fmt: skip

    @property
    def samples(self) -> np.ndarray:
        return np.concatenate(self.audio) if self.audio else np.zeros(0, np.float32)

    @property
    def weights(self) -> np.ndarray:
        return (np.vstack(self.frames) if self.frames
                else np.zeros((0, len(self.names)), np.float32))  # fmt: skip

    def save_new(
        self,
        session: Path,
        *,
        condition: str,
        avatar_sha256: str,
        info: dict[str, Any],
        playout_ms: float,
    ) -> dict[str, Any]:
        """Write the turn as the next free ``turn-NNN`` of ``session`` (made if missing) and
        return turn.json's content with ``folder``. The four files are written (and synced)
        into a scratch folder ``.turn-*`` beside it, which is then renamed to the first free
        name - a rename never replaces a turn, so two savers cannot overwrite each other, and a
        crash leaves a hidden scratch folder, never a turn that looks whole."""
        import soundfile as sf

        session = Path(session)
        session.mkdir(parents=True, exist_ok=True)
        weights = self.weights
        summary = latency_summary(self.rows, n_frames=len(weights), fps=self.fps,
                                  playout_ms=playout_ms, margins_ms=self.margins_ms)  # fmt: skip
        record = {
            **info,
            "sample_rate": self.sample_rate,
            "duration_s": round(len(self.samples) / self.sample_rate, 3),
            "fps": self.fps,
            "n_frames": len(weights),
            "viewers": sorted({int(r["viewer"]) for r in self.rows}),
            **summary,
            **self._pose_summary(),
            "not_measured": NOT_MEASURED,
        }
        stamp = str(info.get("started", "")).replace("-", "").replace(":", "")
        scratch = Path(tempfile.mkdtemp(prefix=".turn-", dir=session))
        wav = io.BytesIO()
        sf.write(wav, self.samples, self.sample_rate, format="WAV", subtype="FLOAT")
        replace_file(scratch / "audio.wav", wav.getvalue())
        replace_file(scratch / "track.bin", encode_track(
            clip_id=f"live__{condition}__{stamp or 'turn'}", fps=self.fps,
            blendshapes=list(self.names), weights=weights, poses=None,
            sample_rate=self.sample_rate, speech_start_s=0.0, avatar_sha256=avatar_sha256,
        ))  # fmt: skip
        text = io.StringIO()
        writer = csv.DictWriter(text, fieldnames=FRAME_COLUMNS, lineterminator="\n")
        writer.writeheader()
        writer.writerows(self.rows)
        replace_file(scratch / "frames.csv", text.getvalue())
        if self.poses:  # a viewer in a headset
            text = io.StringIO()
            writer = csv.DictWriter(text, fieldnames=POSE_COLUMNS, lineterminator="\n")
            writer.writeheader()
            writer.writerows(self.poses)
            replace_file(scratch / "poses.csv", text.getvalue())
        for _ in range(10_000):
            folder = next_turn_dir(session)
            record["turn"] = folder.name
            replace_file(scratch / "turn.json",
                         json.dumps(record, ensure_ascii=False, indent=2) + "\n")  # fmt: skip
            try:
                os.rename(scratch, folder)  # fails when another saver took the name
            except OSError as exc:
                if exc.errno not in (errno.EEXIST, errno.ENOTEMPTY, errno.ENOTDIR):
                    raise
                continue
            os.chmod(folder, 0o755)  # mkdtemp made it private
            fsync_dir(session)
            record["folder"] = str(folder)
            return record
        raise SessionError(f"{session}: no free turn-NNN name")


def turns_protocol(protocol_path: Path, turns: list[Path]):
    """``protocol_path``'s study with the recorded ``turns`` as its stimuli: one stimulus set
    ``live`` (each turn's audio.wav, its viseme track by audio-only analysis, as offline), every
    block showing it; no practice trial, no reported results or simulated effects of the
    protocol's own stimulus sets. ``facelab render --turn`` renders it, so a live turn can be
    rated later under any condition."""
    import yaml

    from facelab.protocol import load_protocol_text

    protocol_path = Path(protocol_path)
    stimuli, seen = [], set()
    for folder in turns:
        folder = Path(folder)
        audio = folder / "audio.wav"
        if not (folder / "turn.json").is_file() or not audio.is_file():
            raise SessionError(f"--turn {folder}: not a recorded live turn (expected turn.json "
                               "and audio.wav, written by facelab live)")  # fmt: skip
        sid = folder.name if folder.name not in seen else f"{folder.parent.name}-{folder.name}"
        if sid in seen:
            raise SessionError(f"--turn {folder}: given twice")
        seen.add(sid)
        stimuli.append({"id": sid, "audio": str(audio.resolve()), "track_from": "audio"})
    data = yaml.safe_load(protocol_path.read_text(encoding="utf-8"))
    data["stimulus_sets"] = [{"id": "live", "description": "recorded live turns",
                              "stimuli": stimuli}]  # fmt: skip
    for block in data.get("blocks") or []:
        block["stimulus_set"] = "live"
    (data.get("presentation") or {}).pop("practice", None)
    data.pop("reported_results", None)  # the paper's tests name the protocol's own stimuli
    simulation = data.get("simulation") or {}
    simulation["overrides"] = [o for o in simulation.get("overrides") or []
                               if not (isinstance(o, dict) and o.get("stimulus_set"))]
    return load_protocol_text(yaml.safe_dump(data, allow_unicode=True, sort_keys=False),
                              path=protocol_path, base_dir=protocol_path.parent)  # fmt: skip
