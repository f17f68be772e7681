"""What the live 3D and VR views (``presentation.display: live3d | webxr``) need from the server:
the avatar as the offline renderer deforms it (one glTF binary, :func:`~facelab.stimuli.avatar.
gltf.live_glb`), the offline camera and lights (:func:`~facelab.stimuli.render.scene.
camera_json`), and each clip's animation track - checked here before a session starts, so a
browser never gets a track drawn on another avatar or changed since rendering.

The browser plays a clip by decoding the mp4's sound (the same file the ``video`` display
plays) and drawing, at every display frame, the track frame the audio clock has reached: the
animation methods never run in the browser, and the offline clip and the live view show the
same values at every instant.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from facelab.errors import FormatError, SessionError
from facelab.formats import read_track
from facelab.hashing import sha256_file
from facelab.protocol import Protocol

__all__ = ["LiveScene", "checked_tracks", "live_scene"]


@dataclass(frozen=True)
class LiveScene:
    """The avatar file (``avatar_name`` = ``<sha256>.glb``), the camera JSON and the tracks
    by the name the browser fetches (``<track sha256>.bin``)."""

    avatar_glb: bytes
    avatar_name: str
    avatar_sha256: str  # the avatar's content hash, as each track's header names it
    camera: dict[str, Any]
    tracks: dict[str, Path]

    def scene_json(self) -> dict[str, Any]:
        return {"avatar": "/avatar/" + self.avatar_name, "camera": self.camera}


def live_scene(protocol: Protocol, *, base_dir: Path, clips: Mapping[Any, Any]) -> LiveScene:
    """The live scene of ``protocol`` for the checked ``clips`` ({key: ClipRef}); SessionError
    naming the clip when one has no track, a changed track or a track of another avatar."""
    from facelab.stimuli.avatar.gltf import live_glb
    from facelab.stimuli.render.scene import camera_json, load_avatar, settings_for

    avatar = load_avatar(protocol, base_dir=base_dir)
    avatar_sha = avatar.content_hash()
    tracks = checked_tracks(protocol, clips=clips, avatar_sha256=avatar_sha)
    glb = live_glb(avatar)
    return LiveScene(
        avatar_glb=glb,
        avatar_name=hashlib.sha256(glb).hexdigest() + ".glb",
        avatar_sha256=avatar_sha,
        camera=camera_json(avatar, settings_for(protocol)),
        tracks=tracks,
    )


def checked_tracks(
    protocol: Protocol, *, clips: Mapping[Any, Any], avatar_sha256: str
) -> dict[str, Path]:
    """The animation track of every clip ({key: ClipRef}) by the name the browser fetches,
    each checked: listed in clips.csv, unchanged since rendering, drawn on the avatar whose
    content hash is ``avatar_sha256``; SessionError naming the clip otherwise."""
    tracks: dict[str, Path] = {}
    for key, ref in sorted(clips.items()):
        name = "/".join(key)
        if ref.track is None or ref.track_sha256 is None:
            raise SessionError(
                f"presentation.display {protocol.presentation.display!r} draws each clip from "
                f"its animation track, and clip {name} has none in clips.csv (rendered before "
                "tracks existed): render again with facelab render PROTOCOL --out CLIPS"
            )
        if not ref.track.is_file() or sha256_file(ref.track) != ref.track_sha256:
            raise SessionError(
                f"the animation track of clip {name} ({ref.track}) is missing or changed since "
                "rendering: render again with facelab render PROTOCOL --out CLIPS"
            )
        try:
            header = read_track(ref.track).header
        except FormatError as exc:
            raise SessionError(str(exc)) from None
        if header.get("avatar_sha256") != avatar_sha256:
            raise SessionError(
                f"the animation track of clip {name} was drawn on another avatar than "
                f"rendering.avatar ({protocol.rendering.avatar}) gives now: render again"
            )
        tracks[ref.track_sha256 + ".bin"] = ref.track
    return tracks
