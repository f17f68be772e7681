"""``method: external_track``: play an animation made elsewhere - a captured human (Live Link
Face), a neural audio-to-face model (Audio2Face-3D), a viseme stream (Oculus LipSync,
uLipSync), a DCC tool's glTF animation - as a condition beside facelab's own methods.

``params: {tracks: DIR, format: auto, offset_ms: 0, fps: null}``: one file per stimulus,
``DIR/<stimulus_set>/<stimulus_id>.<csv|json|glb|gltf>`` (formats:
:mod:`facelab.stimuli.capture.external_tracks`). The capture is resampled to the clip's frame
times. ``offset_ms`` shifts it (positive: the animation starts later); ``auto`` aligns it by a
WAV recorded with it (``DIR/<stimulus_set>/<stimulus_id>.wav``): the lag that best matches the
recording's loudness envelope to the stimulus audio's (cross-correlation), recorded in the
clip's JSON (``offset_ms_found``, with the correlation). Each file's bytes are part of its
clip's spec hash.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

from facelab.errors import FacelabError, StageError
from facelab.methods import METHODS, ExternalTrackParams
from facelab.stimuli.arkit import VISEME_TARGETS
from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.capture.external_tracks import CapturedTrack, read_capture, resample
from facelab.stimuli.methods.registry import Method, Playback, register
from facelab.stimuli.methods.types import BlendshapeTrack, DriveInput

__all__ = ["ExternalTrack", "align_offset_s", "capture_poses", "track_file"]

#: a capture's angle columns (lower case) -> HeadPose field (eye angles: both eyes' mean)
_POSE_COLUMNS = {"headyaw": 0, "headpitch": 1, "headroll": 2, "lefteyeyaw": 3,
                 "righteyeyaw": 3, "lefteyepitch": 4, "righteyepitch": 4}  # fmt: skip


def capture_poses(
    track: CapturedTrack, times: np.ndarray, *, offset_s: float, unit: str
) -> np.ndarray:
    """(len(times), 5) head yaw, pitch, roll and eye yaw, pitch in degrees from a capture's
    angle columns at ``times`` (the capture shifted by ``offset_s``, held at its ends); eye
    angles are the two eyes' mean. The capture's signs are taken as facelab's (see
    :mod:`facelab.stimuli.avatar.rig`)."""
    t = np.asarray(times, float) - offset_s
    out = np.zeros((len(t), 5))
    counts = np.zeros(5)
    for name, values in track.angles.items():
        j = _POSE_COLUMNS.get(name.lower())
        if j is None:
            continue
        col = np.interp(t, track.times, np.asarray(values, float))
        out[:, j] += np.degrees(col) if unit == "radians" else col
        counts[j] += 1
    return out / np.maximum(counts, 1)

_SUFFIXES = (".csv", ".json", ".glb", ".gltf")
#: the loudness envelope's rate for alignment (Hz) and the largest lag searched (s)
_ENV_RATE, _MAX_LAG_S = 100.0, 2.0


def track_file(params: ExternalTrackParams, *, base_dir: Path, stimulus_set: str,
               stimulus_id: str) -> Path | None:  # fmt: skip
    """The stimulus' track file in ``params.tracks``, or None when there is none."""
    folder = base_dir / params.tracks / stimulus_set
    for suffix in _SUFFIXES:
        path = folder / f"{stimulus_id}{suffix}"
        if path.is_file():
            return path
    return None


def _envelope(samples: np.ndarray, rate: int) -> np.ndarray:
    hop = max(1, round(rate / _ENV_RATE))
    n = len(samples) // hop
    x = np.asarray(samples[: n * hop], np.float64).reshape(n, hop)
    db = 10 * np.log10((x**2).mean(axis=1) + 1e-10)
    db = np.maximum(db, db.max() - 40.0)
    return db - db.mean()


def align_offset_s(
    recording: np.ndarray, recording_rate: int, stimulus: np.ndarray, stimulus_rate: int
) -> tuple[float, float]:
    """(offset s, correlation): how much later the recording's sound starts than the
    stimulus audio's (the capture made with the recording is shifted by it), from the
    cross-correlation of their loudness envelopes (10 ms hops, lags up to 2 s)."""
    a, b = _envelope(recording, recording_rate), _envelope(stimulus, stimulus_rate)
    max_lag = int(_MAX_LAG_S * _ENV_RATE)
    best, best_r = 0, -np.inf
    for lag in range(-max_lag, max_lag + 1):
        # recording frame i + lag against stimulus frame i
        lo, hi = max(0, -lag), min(len(b), len(a) - lag)
        if hi - lo < _ENV_RATE * 0.2:
            continue
        x, y = a[lo + lag : hi + lag], b[lo:hi]
        den = np.sqrt((x**2).sum() * (y**2).sum())
        r = float((x * y).sum() / den) if den > 0 else -np.inf
        if r > best_r:
            best, best_r = lag, r
    return best / _ENV_RATE, best_r


@functools.lru_cache(maxsize=512)
def _read_once(
    path: str, mtime_ns: int, size: int, fmt: str, fps: float | None
) -> CapturedTrack | None:
    """A track file read once per version of its bytes (the avatar audit and playability ask
    for every file of the folder per condition); None when it does not read."""
    try:
        return read_capture(Path(path), format=fmt, fps=fps)
    except FacelabError:
        return None


class ExternalTrack(Method[ExternalTrackParams]):
    """A track made elsewhere, one file per stimulus (see the module docstring)."""

    spec = METHODS["external_track"]
    live_problem = "it plays an animation made beforehand, one file per stimulus"

    def drive(self, inp: DriveInput, params: ExternalTrackParams) -> BlendshapeTrack:
        path = track_file(params, base_dir=inp.base_dir, stimulus_set=inp.stimulus_set,
                          stimulus_id=inp.stimulus_id)  # fmt: skip
        if path is None:
            raise StageError(
                f"method external_track: no track for stimulus {inp.stimulus_set}/"
                f"{inp.stimulus_id} in {inp.base_dir / params.tracks / inp.stimulus_set} "
                f"(expected {inp.stimulus_id}.csv, .json, .glb or .gltf)"
            )
        track = read_capture(path, format=params.format, fps=params.fps)
        notes: dict = {"track_file": str(path.relative_to(inp.base_dir)), "format": track.format,
                       **track.notes}  # fmt: skip
        offset = self._offset_s(params, path, inp, notes)
        times = inp.track.times
        weights = resample(track, times, offset_s=offset)
        end = float(track.times[-1]) + offset
        if end < float(times[-1]) - 0.1:
            notes["held_last_frame_s"] = round(float(times[-1]) - end, 3)
        poses = None
        if track.angles and params.head:
            poses = capture_poses(track, times, offset_s=offset, unit=params.angle_unit)
            notes["angles_played"] = sorted(n for n in track.angles if n.lower() in _POSE_COLUMNS)
            notes["angle_unit"] = params.angle_unit
        elif track.angles:
            notes["angles_not_played"] = "head: false"
        return BlendshapeTrack(times, weights, track.names, notes, poses)

    def drive_on(self, avatar: Avatar, inp: DriveInput, params: ExternalTrackParams
                 ) -> BlendshapeTrack:  # fmt: skip
        """The capture on ``avatar``: its angles turn the head only where the avatar has a
        skeleton, and the eyes only where the capture's eyeLook shapes do not (both say where
        the eyes look: played twice they would turn twice as far)."""
        bs = self.drive(inp, params)
        if bs.poses is None:
            return bs
        notes = dict(bs.notes)
        if avatar.skeleton is None:
            notes.pop("angles_played", None)
            notes["angles_not_played"] = "the avatar has no skeleton"
            return replace(bs, notes=notes, poses=None)
        looks = [k for k, n in enumerate(bs.names) if n.startswith("eyeLook")
                 and n in avatar.targets and np.ptp(bs.weights[:, k]) > 0.02]  # fmt: skip
        if not looks:
            return bs
        poses = bs.poses.copy()
        poses[:, 3:] = 0.0
        notes["eye_angles"] = "not played: the capture's eyeLook shapes move the eyes"
        return replace(bs, notes=notes, poses=poses)

    def _offset_s(self, params: ExternalTrackParams, path: Path, inp: DriveInput,
                  notes: dict) -> float:  # fmt: skip
        if params.offset_ms != "auto":
            notes["offset_ms"] = float(params.offset_ms)
            return float(params.offset_ms) / 1000.0
        from facelab.stimuli.speech.audio import load_audio

        wav = path.with_suffix(".wav")
        if not wav.is_file():
            raise StageError(f"{path}: offset_ms auto needs the recording made with the "
                             f"capture at {wav}")  # fmt: skip
        if inp.audio is None:
            raise StageError(f"{path}: offset_ms auto needs the stimulus audio")
        rec = load_audio(wav, sample_rate=inp.audio.sample_rate)
        offset, r = align_offset_s(rec.samples, rec.sample_rate, inp.audio.samples,
                                   inp.audio.sample_rate)  # fmt: skip
        notes.update(offset_ms="auto", offset_ms_found=round(offset * 1000, 1),
                     alignment_correlation=round(r, 3))  # fmt: skip
        return -offset  # the capture started with its recording: move it back by the lag

    def stimulus_files(self, params: ExternalTrackParams, *, base_dir: Path, stimulus_set: str,
                       stimulus_id: str) -> dict[str, str]:  # fmt: skip
        path = track_file(params, base_dir=base_dir, stimulus_set=stimulus_set,
                          stimulus_id=stimulus_id)  # fmt: skip
        if path is None:
            return {"track": f"{params.tracks}/{stimulus_set}/{stimulus_id}"}
        files = {"track": str(path.relative_to(base_dir))}
        if params.offset_ms == "auto":
            files["track_audio"] = str(path.with_suffix(".wav").relative_to(base_dir))
        return files

    def stimulus_problems(self, params: ExternalTrackParams, *, base_dir: Path,
                          stimulus_set: str, stimulus_id: str) -> Iterator[str]:  # fmt: skip
        path = track_file(params, base_dir=base_dir, stimulus_set=stimulus_set,
                          stimulus_id=stimulus_id)  # fmt: skip
        if path is None:
            yield (f"no track for stimulus {stimulus_set}/{stimulus_id}: expected "
                   f"{base_dir / params.tracks / stimulus_set / stimulus_id}.csv (or .json, "
                   ".glb, .gltf)")  # fmt: skip
            return
        try:
            read_capture(path, format=params.format, fps=params.fps)
        except FacelabError as exc:
            yield str(exc)
            return
        if params.offset_ms == "auto" and not path.with_suffix(".wav").is_file():
            wav = path.with_suffix(".wav")
            yield f"offset_ms auto needs the recording made with the capture: {wav}"

    def input_problems(self, params: ExternalTrackParams, *, base_dir: Path
                       ) -> Iterator[tuple[tuple[str, ...], str]]:  # fmt: skip
        if not (base_dir / params.tracks).is_dir():
            yield ("params", "tracks"), f"the track folder {base_dir / params.tracks} was not found"

    def captures(self, params: ExternalTrackParams, *, base_dir: Path) -> list[CapturedTrack]:
        """Every track file in the folder that reads (for the audit and playability)."""
        folder = base_dir / params.tracks
        out = []
        if folder.is_dir():
            for path in sorted(folder.glob("*/*")):
                if path.suffix.lower() in _SUFFIXES:
                    stat = path.stat()
                    track = _read_once(str(path), stat.st_mtime_ns, stat.st_size,
                                       params.format, params.fps)  # fmt: skip
                    if track is not None:
                        out.append(track)
        return out

    def driven_targets(self, avatar: Avatar, params: ExternalTrackParams, *,
                       base_dir: Path = Path(".")) -> set[str]:  # fmt: skip
        moving = {n for c in self.captures(params, base_dir=base_dir)
                  for k, n in enumerate(c.names) if np.ptp(c.weights[:, k]) > 0.05}  # fmt: skip
        return moving & set(avatar.targets)

    def playback(self, avatar: Avatar, params: ExternalTrackParams, *,
                 base_dir: Path = Path(".")) -> Playback:  # fmt: skip
        if params is None:  # avatar inspect: no folder named yet
            return Playback(True, "plays tracks made elsewhere (needs the targets their "
                            "channels name: ARKit or viseme_*)")  # fmt: skip
        names = {n for c in self.captures(params, base_dir=base_dir) for n in c.names}
        missing = sorted(names - set(avatar.targets))
        if not names:
            return Playback(True, "plays the tracks in its folder (none read yet)")
        if missing:
            visemes = [n for n in missing if n in VISEME_TARGETS]
            hint = " (viseme tracks: the avatar's viseme_* targets)" if visemes else ""
            problem = (f"avatar {avatar.name!r} lacks {len(missing)} target(s) the tracks in "
                       f"{params.tracks} drive{hint}: {', '.join(missing)}")  # fmt: skip
            return Playback(False, f"no: lacks {', '.join(missing[:4])}", problem=problem)
        return Playback(True, f"yes ({len(names)} channels of the tracks in {params.tracks})")

    def examples(self) -> tuple[ExternalTrackParams | None, ...]:
        return (None,)


register(ExternalTrack())
