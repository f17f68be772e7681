"""The files participants' browsers fetch, made so that nothing in them tells a clip's
condition (issue: condition stays hidden):

* every clip is served as a copy whose name is the copy's own SHA-256, padded with an mp4
  ``free`` box (which players skip) to the same size as every other condition of its
  stimulus - a file's size no longer tells conditions apart;
* the practice trial's clip is a copy of its own: the same picture and sound, other padding
  bytes (derived from the server's secret key), so no byte, name or size ties it to the main
  trial that shows the same stimulus and condition;
* animation tracks (display live3d / webxr) are served with the clip id - which names the
  stimulus set, stimulus and condition - blanked from their header, the practice's copy again
  of its own. (What a track animates - its channel names - is what the browser must draw,
  so a method's family of shapes, visemes or ARKit, stays visible to a curious participant
  of a live display; the README says so.)

Copies are written once into a folder (``<results>/<study>/served``), named by their hash,
and checked by it; the rendered clips are never changed. Pure but for that folder.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import struct
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from facelab.durable import replace_file
from facelab.formats import TRACK_MAGIC

__all__ = ["ServedFiles", "served_files"]

_ALIGN = 4096  # a stimulus' copies are padded to a multiple of this many bytes


@dataclass(frozen=True)
class ServedClip:
    clip: str  # "<sha256>.mp4" of the served copy
    track: str  # "<sha256>.bin" of the served track copy, "" without a track


@dataclass
class ServedFiles:
    """The served copies: by clip key (main trials and the practice trial), every served
    name's file, and the rendered clip's SHA-256 each served mp4 stands for."""

    main: dict[Any, ServedClip] = field(default_factory=dict)
    practice: dict[Any, ServedClip] = field(default_factory=dict)
    paths: dict[str, Path] = field(default_factory=dict)
    original: dict[str, str] = field(default_factory=dict)

    def merge(self, other: ServedFiles) -> None:
        """Add another protocol version's copies (names are content hashes: no clash)."""
        self.main.update(other.main)
        self.practice.update(other.practice)
        self.paths.update(other.paths)
        self.original.update(other.original)


def _free_box(size: int, fill: bytes) -> bytes:
    """An mp4 ``free`` box of ``size`` bytes (>= 8) whose payload repeats ``fill``."""
    payload = (fill * (size // max(1, len(fill)) + 1))[: size - 8] if fill else bytes(size - 8)
    return struct.pack(">I", size) + b"free" + payload


def _write(folder: Path, data: bytes, suffix: str) -> tuple[str, Path]:
    name = hashlib.sha256(data).hexdigest() + suffix
    path = folder / name
    if not path.is_file() or path.stat().st_size != len(data):
        replace_file(path, data)
    return name, path


def _blank_track(data: bytes, *, nonce: str) -> bytes:
    """A track with its ``clip_id`` blanked (and a nonce that makes copies differ); the
    float32 frames are kept byte for byte."""
    length = struct.unpack_from("<I", data, 8)[0]
    header = json.loads(data[12 : 12 + length])
    body = data[12 + length :]
    header["clip_id"] = ""
    header["copy"] = nonce
    text = json.dumps(header, ensure_ascii=False, sort_keys=True).encode("utf-8")
    text += b" " * (-(12 + len(text)) % 4)
    return TRACK_MAGIC + struct.pack("<I", len(text)) + text + body


def served_files(
    clips: Mapping[Any, Any],
    *,
    folder: Path,
    key: bytes,
    practice: Any | None = None,
    tracks: bool = False,
) -> ServedFiles:
    """Copies of the checked ``clips`` ({(set, stimulus, condition): ClipRef}) in
    ``folder``; ``practice`` the practice trial's clip key (it gets copies of its own);
    ``key`` the server's secret (the practice copy's padding bytes come from it); ``tracks``:
    copy the animation tracks too (a live display; checked by the server before)."""
    folder.mkdir(parents=True, exist_ok=True)
    sizes: dict[tuple[str, str], int] = {}
    for (sset, stim, _cond), ref in clips.items():
        sizes[(sset, stim)] = max(sizes.get((sset, stim), 0), ref.path.stat().st_size)
    out = ServedFiles()
    for k, ref in sorted(clips.items()):
        data = ref.path.read_bytes()
        group = sizes[(k[0], k[1])]
        target = -(-(group + 8) // _ALIGN) * _ALIGN  # room for the smallest free box
        track = ref.track.read_bytes() if tracks and ref.track is not None else None
        roles = [("main", b"")]
        if practice is not None and tuple(practice) == tuple(k):
            roles.append(("practice", hmac.new(key, b"practice:" + bytes.fromhex(ref.sha256),
                                               hashlib.sha256).digest()))  # fmt: skip
        for role, fill in roles:
            name, path = _write(folder, data + _free_box(target - len(data), fill), ".mp4")
            out.paths[name] = path
            out.original[name] = ref.sha256
            track_name = ""
            if track is not None:
                nonce = hmac.new(key, f"{role}:{ref.sha256}".encode(), hashlib.sha256).hexdigest()
                track_name, track_path = _write(folder, _blank_track(track, nonce=nonce[:16]),
                                                ".bin")  # fmt: skip
                out.paths[track_name] = track_path
            getattr(out, role)[k] = ServedClip(clip=name, track=track_name)
    return out
