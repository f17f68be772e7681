"""Checks before a session starts: clips present and unchanged, display, audio, disk.

Every failure is a :class:`~facelab.errors.StageError` saying what is wrong and what to do.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from facelab.errors import FormatError, SessionError, StageError
from facelab.experiment.timeline import ClipKey
from facelab.formats import CLIP_COLUMNS, checks_failed, read_manifest
from facelab.hashing import sha256_file
from facelab.protocol import Protocol
from facelab.stimuli.render.clipspec import unlisted_and_stale

__all__ = [
    "ClipRef",
    "check_audio",
    "check_clips",
    "check_disk",
    "check_display",
    "compare_with_session",
]

MIN_FREE_MB = 200


@dataclass(frozen=True)
class ClipRef:
    path: Path
    sha256: str
    duration_s: float
    fps: float
    size: tuple[int, int] = (0, 0)
    track: Path | None = None  # the clip's animation track (clips.csv track_file), if any
    track_sha256: str | None = None


def check_clips(
    protocol: Protocol,
    needed: Iterable[ClipKey],
    clips_dir: Path,
    *,
    base_dir: Path,
    verify_hashes: bool = True,
) -> dict[ClipKey, ClipRef]:
    """Every clip the session shows, from ``clips.csv``: present, unchanged since rendering
    (its SHA-256), rendered from the protocol as it is now (its spec hash) and not failed by
    its stimulus checks (``stimulus_checks`` ``failed: ...``; accepted checks pass)."""
    manifest = clips_dir / "clips.csv"
    if not manifest.is_file():
        raise SessionError(
            f"no clip manifest at {manifest}; render the clips first: facelab render "
            f"PROTOCOL --out {clips_dir}"
        )
    try:
        rows = read_manifest(clips_dir, need=CLIP_COLUMNS)
    except FormatError as exc:
        raise SessionError(
            f"{exc}: without every column (spec_sha256 among them) the clips cannot be checked "
            "against the protocol"
        ) from None
    by_key = {(r["stimulus_set"], r["stimulus"], r["condition"]): r for r in rows}
    needed = set(needed)
    missing, stale = unlisted_and_stale(protocol, rows, needed, base_dir=base_dir)
    if missing:
        listed = ", ".join("/".join(k) for k in missing[:5])
        raise SessionError(
            f"{manifest} has no clip for {listed}{' …' if len(missing) > 5 else ''}; "
            "render again with this protocol"
        )
    if stale:
        listed = ", ".join("/".join(k) for k in stale[:5])
        raise SessionError(
            f"{len(stale)} clip(s) in {clips_dir} were rendered from a different protocol or "
            f"different input files than {protocol.study.id!r} now declares ({listed}"
            f"{' …' if len(stale) > 5 else ''}): the protocol, an audio or avatar file changed "
            f"after rendering. Render again: facelab render PROTOCOL --out {clips_dir}"
        )
    failed = [(k, checks_failed(by_key[k])) for k in sorted(needed) if checks_failed(by_key[k])]
    if failed:  # a participant would see a stimulus its checks found broken
        listed = "; ".join(f"{'/'.join(k)} ({why})" for k, why in failed[:5])
        raise SessionError(
            f"{len(failed)} clip(s) in {manifest} failed their stimulus checks: {listed}"
            f"{' …' if len(failed) > 5 else ''}. Fix the cause and render again (the checks' "
            "report says what each found), or, when the failure is what the study intends, "
            "accept the check by name, or one clip's with NAME:CLIP: facelab render "
            "PROTOCOL --accept-check NAME[:CLIP]"
        )
    refs = {}
    for key in sorted(needed):
        row = by_key[key]
        path = clips_dir / row["path"]
        if not path.is_file():
            raise SessionError(f"clip file missing: {path} (listed in {manifest})")
        if verify_hashes:
            actual = sha256_file(path)
            if actual != row["sha256"]:
                raise SessionError(
                    f"clip {path} does not match its hash in {manifest} "
                    f"(expected {row['sha256'][:12]}…, found {actual[:12]}…); it was "
                    "changed after rendering - render again"
                )
        refs[key] = ClipRef(
            path,
            row["sha256"],
            float(row["duration_s"]),
            float(row["fps"]),
            (int(row["width"]), int(row["height"])),
            track=clips_dir / row["track_file"] if row.get("track_file") else None,
            track_sha256=row.get("track_sha256") or None,
        )
    return refs


def compare_with_session(
    clips: dict[ClipKey, ClipRef], recorded: dict[str, str]
) -> dict[str, dict[str, str]]:
    """Clips whose bytes differ from those the session started with: {clip: {was, now}}."""
    changed = {}
    for key, ref in clips.items():
        name = "/".join(key)
        if name in recorded and recorded[name] != ref.sha256:
            changed[name] = {"was": recorded[name], "now": ref.sha256}
    return changed


def check_disk(results: Path, *, min_mb: int = MIN_FREE_MB) -> None:
    target = results
    while not target.exists():
        target = target.parent
    free_mb = shutil.disk_usage(target).free / 2**20
    if free_mb < min_mb:
        raise StageError(
            f"only {free_mb:.0f} MB free under {target}; a session needs at least {min_mb} MB"
        )


def check_display() -> None:
    if (
        os.name == "posix"
        and not os.environ.get("DISPLAY")
        and not os.environ.get("WAYLAND_DISPLAY")
    ):
        raise StageError(
            "no display: DISPLAY is not set. Run on the lab computer's screen, or for a "
            "test run under a virtual screen: xvfb-run -a facelab run … --simulate"
        )


def check_audio(*, allow_dummy: bool) -> str:
    """The audio output clips will play on. Without a device, a dummy output is used only
    when ``allow_dummy`` (simulated runs); otherwise the session cannot start."""
    if os.environ.get("SDL_AUDIODRIVER") == "dummy":
        if not allow_dummy:
            raise StageError("SDL_AUDIODRIVER=dummy: participants would hear nothing; unset it")
        return "dummy (SDL_AUDIODRIVER=dummy)"
    try:
        import sounddevice

        outputs = [d for d in sounddevice.query_devices() if d.get("max_output_channels", 0) > 0]
    except Exception as exc:  # PortAudio missing or broken
        outputs = []
        reason = f" ({exc})"
    else:
        reason = ""
    if outputs:
        return (
            f"{outputs[0]['name']} (+{len(outputs) - 1} more)"
            if len(outputs) > 1
            else outputs[0]["name"]
        )
    if allow_dummy:
        os.environ["SDL_AUDIODRIVER"] = "dummy"
        return "dummy (no audio device; simulated run)"
    raise StageError(
        f"no audio output device found{reason}: connect headphones or speakers and check "
        "the system's sound settings (a simulated run may use --simulate)"
    )
