"""The clips a protocol needs, and each clip's spec hash. Pure: no audio, no rendering.

:func:`plan` lists every (stimulus set, stimulus, condition) clip the blocks and the practice
trial show. ``clips.csv`` (DESIGN.md) has :data:`CLIP_COLUMNS`.

:func:`clip_spec_hash` hashes what the protocol declares for one clip - the stimulus text or
the recording's bytes, TTS options, vowel isolation, the condition's method and parameters
(and a custom Z file's bytes), the avatar file's bytes, camera, padding, background, MSAA and
audio rate. It is cheap to recompute without synthesising or rendering anything, so
``facelab run`` checks before a session that every clip was rendered from the protocol as it
is now. Size and frame rate are left out: ``--size``/``--fps`` overrides give the same clips
at another resolution (``clips.csv`` records them).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

from facelab.formats import CLIP_COLUMNS
from facelab.hashing import sha256_file
from facelab.protocol import Protocol, Stimulus
from facelab.stimuli.methods import get
from facelab.stimuli.speech.noise import NOISE_SYNTHESIS

__all__ = [
    "CLIP_COLUMNS",
    "RENDER_VERSION",
    "ClipJob",
    "clip_spec_hash",
    "plan",
    "unlisted_and_stale",
]

#: 2: the default head with lids, ears, hair; new lighting. 3: the sound with ffmpeg's "fast"
#: AAC coder (clips of 2 keep their old sound, so their spec must not match)
RENDER_VERSION = "facelab-render-3"


@dataclass(frozen=True)
class ClipJob:
    clip_id: str
    stimulus_set: str
    stimulus: Stimulus
    condition: str


def plan(protocol: Protocol) -> list[ClipJob]:
    """Every (stimulus, condition) the blocks and the practice trial show, in protocol order."""
    wanted: dict[tuple[str, str, str], None] = {}
    for block in protocol.blocks:
        for stim in protocol.stimulus_set(block.stimulus_set).stimuli:
            task = protocol.block_task(block)
            standard = [task.standard] if task is not None and task.type == "choice_2afc" else []
            for cond in [*protocol.block_conditions(block), *standard]:
                wanted[(block.stimulus_set, stim.id, cond)] = None
    practice = protocol.presentation.practice
    if practice is not None:
        wanted[(practice.stimulus_set, practice.stimulus, practice.condition)] = None
    jobs = []
    for set_id, stim_id, cond in wanted:
        stim = next(s for s in protocol.stimulus_set(set_id).stimuli if s.id == stim_id)
        jobs.append(ClipJob(f"{set_id}__{stim_id}__{cond}", set_id, stim, cond))
    return jobs


def _file_sha256(path: Path) -> str:
    return sha256_file(path) if path.is_file() else "missing"


def clip_spec_hash(protocol: Protocol, job: ClipJob, *, base_dir: Path) -> str:
    """SHA-256 of what the protocol declares for one clip (see the module docstring)."""
    stim = job.stimulus
    cond = protocol.condition(job.condition)
    r = protocol.rendering
    files = {}
    if stim.audio is not None:
        files["audio"] = _file_sha256(base_dir / stim.audio)
    method = get(cond.method)
    for role, name in method.input_files(cond.settings).items():
        files[role] = _file_sha256(base_dir / name)  # a Z matrix, an impression model, …
    for role, name in method.stimulus_files(cond.settings, base_dir=base_dir,
                                            stimulus_set=job.stimulus_set,
                                            stimulus_id=stim.id).items():  # fmt: skip
        files[role] = _file_sha256(base_dir / name)  # one track file per stimulus
    if r.avatar != "default":
        files["avatar"] = _file_sha256(base_dir / r.avatar)
    if cond.behaviour.lower().endswith((".json", ".yaml", ".yml")):
        files["behaviour"] = _file_sha256(base_dir / cond.behaviour)
    spec = {
        "version": RENDER_VERSION,
        "stimulus": {
            "text": stim.text,
            "audio": stim.audio,
            "transcript": stim.transcript,
            "silence_s": stim.silence_s,
            "tts": stim.tts.model_dump(),
            "expected_vowels": stim.expected_vowels,
            "isolated": job.condition in stim.vowel_isolation,
        },
        "method": cond.method,
        "params": cond.params,
        "files": files,
        **(
            {
                "behaviour": cond.behaviour,
                "emotion": cond.emotion if cond.emotion is not None else stim.emotion,
                "behaviour_seed": r.behaviour_seed,
            }
            if cond.behaviour != "none"
            else {}
        ),
        "avatar": r.avatar,
        "camera": r.camera.model_dump(),
        "pad_s": r.pad_s,
        "msaa": r.msaa,
        "background": list(r.background),
        "audio_sample_rate": r.audio_sample_rate,
    }
    if cond.audio_offset_ms:  # (absent when 0: earlier hashes still hold)
        spec["audio_offset_ms"] = cond.audio_offset_ms
    if cond.noise is not None:  # the mix, its noise file's bytes, the set's spectrum's texts
        spec["noise"] = cond.noise.model_dump()
        spec["noise_token_of"] = protocol.study.id  # (seeds the noise with set, word, SNR)
        if cond.noise.source != "speech_shaped":
            files["noise"] = _file_sha256(base_dir / cond.noise.source)
        else:
            spec["noise_synthesis"] = NOISE_SYNTHESIS
            spec["noise_spectrum_of"] = [
                [st.text, _file_sha256(base_dir / st.audio) if st.audio else None,
                 st.tts.model_dump()]
                for st in protocol.stimulus_set(job.stimulus_set).stimuli
            ]  # fmt: skip
    if cond.modality != "audiovisual":  # (absent for audiovisual: earlier hashes still hold)
        spec["modality"] = cond.modality
        if cond.modality == "audio_only":
            spec["audio_only_face"] = r.audio_only_face
    text = json.dumps(spec, sort_keys=True, ensure_ascii=False, default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def unlisted_and_stale(
    protocol: Protocol, rows: Iterable[Mapping[str, str]], keys: Iterable[tuple[str, str, str]],
    *, base_dir: Path,
) -> tuple[list[tuple[str, str, str]], list[tuple[str, str, str]]]:  # fmt: skip
    """Of the clips ``keys`` (stimulus set, stimulus, condition) of ``protocol``: those the
    ``rows`` of a clips.csv do not list, and those listed but rendered from something other
    than what the protocol declares now (another spec hash: an edited protocol or input file,
    another study's clips). Both sorted."""
    by_key = {(r["stimulus_set"], r["stimulus"], r["condition"]): r for r in rows}
    jobs = {(j.stimulus_set, j.stimulus.id, j.condition): j for j in plan(protocol)}
    keys = sorted(set(keys))
    missing = [k for k in keys if k not in by_key]
    stale = [k for k in keys if k in by_key and k in jobs
             and by_key[k]["spec_sha256"] != clip_spec_hash(protocol, jobs[k], base_dir=base_dir)]
    return missing, stale
