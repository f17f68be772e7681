"""Checks before a session starts: clips present and unchanged, display, audio, disk.

Every failure is a :class:`~facelab.errors.StageError` saying what is wrong and what to do.
"""

from __future__ import annotations

import csv
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from facelab.design import Trial
from facelab.errors import StageError
from facelab.protocol import Protocol

__all__ = ["ClipRef", "check_audio", "check_clips", "check_disk", "check_display"]

MIN_FREE_MB = 200


@dataclass(frozen=True)
class ClipRef:
    path: Path
    sha256: str
    duration_s: float
    fps: float


def check_clips(
    protocol: Protocol, trials: list[Trial], clips_dir: Path, *, verify_hashes: bool = True
) -> dict[tuple[str, str, str], ClipRef]:
    """Every clip the session shows, from ``clips.csv``, present and matching its hash."""
    from facelab.stimuli.clip import sha256_file

    manifest = clips_dir / "clips.csv"
    if not manifest.is_file():
        raise StageError(
            f"no clip manifest at {manifest}; render the clips first: facelab render "
            f"PROTOCOL --out {clips_dir}"
        )
    with open(manifest, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    by_key = {(r["stimulus_set"], r["stimulus"], r["condition"]): r for r in rows}
    needed = {(t.stimulus_set, t.stimulus, t.condition) for t in trials}
    practice = protocol.presentation.practice
    if practice is not None:
        needed.add((practice.stimulus_set, practice.stimulus, practice.condition))
    missing = sorted(needed - set(by_key))
    if missing:
        listed = ", ".join("/".join(k) for k in missing[:5])
        raise StageError(
            f"{manifest} has no clip for {listed}{' …' if len(missing) > 5 else ''}; "
            "render again with this protocol"
        )
    refs = {}
    for key in sorted(needed):
        row = by_key[key]
        path = clips_dir / row["path"]
        if not path.is_file():
            raise StageError(f"clip file missing: {path} (listed in {manifest})")
        if verify_hashes:
            actual = sha256_file(path)
            if actual != row["sha256"]:
                raise StageError(
                    f"clip {path} does not match its hash in {manifest} "
                    f"(expected {row['sha256'][:12]}…, found {actual[:12]}…); it was "
                    "changed after rendering - render again"
                )
        refs[key] = ClipRef(path, row["sha256"], float(row["duration_s"]), float(row["fps"]))
    return refs


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
