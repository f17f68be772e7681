"""The stimulus checks of a protocol's rendered clips (``facelab check``, and the end of every
``facelab render``): measure every clip with an observer that does not share facelab's
assumptions, write ``stimulus_checks.csv`` beside ``clips.csv``, and say which failed.

A failed check (an ``error`` row that did not pass) stops the command with exit 2 unless its
check is accepted by name (``--accept-check NAME`` or the protocol's ``checks.accept``); an
accepted failure is recorded (``accepted`` true in the CSV, listed in the report).
"""

from __future__ import annotations

import csv
import io
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from facelab.durable import replace_file
from facelab.errors import StageError
from facelab.formats import (
    CHECKS_COLUMN,
    CLIP_COLUMNS,
    STIMULUS_CHECKS_NAME,
    read_manifest,
    read_track,
    write_face_tracking,
)
from facelab.protocol import Protocol
from facelab.stimuli.checks.avatar_checks import audit_avatar
from facelab.stimuli.checks.clip_checks import (
    articulation_rows,
    av_sync_rows,
    difference_rows,
    envelope,
    face_visible_rows,
    level_rows,
    mix_lag,
    modality_rows,
    mouth_at_peaks,
    noise_rows,
    not_measured,
    too_few_frames,
    too_small,
)
from facelab.stimuli.checks.face_tracker import ClipTracking, start_tracking
from facelab.stimuli.checks.rows import (
    CHECK_COLUMNS,
    CheckRow,
    accept_checks,
    at_least,
    at_most,
    info,
)
from facelab.stimuli.render.build import vowel_peak_times
from facelab.stimuli.render.clip import decode_audios, padded_audio, shifted_audio
from facelab.stimuli.render.clipspec import ClipJob, plan, unlisted_and_stale
from facelab.stimuli.render.prepare import speech_for, tracks_for
from facelab.stimuli.render.scene import load_avatar
from facelab.stimuli.render.sound import clip_sound
from facelab.stimuli.speech.align import align_phones
from facelab.stimuli.speech.analyser import analyze
from facelab.stimuli.speech.audio import Speech, resample
from facelab.stimuli.speech.natural import aligned_vowels_heard
from facelab.stimuli.speech.track import VisemeTrack

__all__ = [
    "CHECKS_NAME",
    "MANIFEST_COLUMN",
    "CheckReport",
    "check_clips",
    "read_checks",
    "record_in_manifest",
    "track_source_rows",
    "transcript_rows",
    "write_checks",
]

CHECKS_NAME = STIMULUS_CHECKS_NAME
AUDIO_RATE = 16000
#: what the README measured for audio-only analysis on voices it was not trained on
AUDIO_ONLY_ACCURACY = (
    "on voices it was not trained on, audio-only analysis reads about 0.74-0.87 of vowel "
    "frames right in read sentences and as few as 0.30-0.56 in isolated vowels"
)


@dataclass
class CheckReport:
    """The rows, where they were written, how long the checks took, the tracker used."""

    rows: list[CheckRow]
    path: Path | None = None
    seconds: float = 0.0
    tracker: str = ""
    accepted: tuple[str, ...] = ()
    notes: list[str] = field(default_factory=list)

    @property
    def failures(self) -> list[CheckRow]:
        return [r for r in self.rows if r.failed]

    @property
    def warnings(self) -> list[CheckRow]:
        return [r for r in self.rows if r.passed is False and not r.failed]

    def summary(self) -> str:
        judged = [r for r in self.rows if r.passed is not None]
        return (
            f"stimulus checks: {sum(bool(r.passed) for r in judged)} of {len(judged)} passed, "
            f"{len(self.failures)} failed, {len(self.warnings)} warnings or accepted "
            f"({self.seconds:.1f} s{', ' + self.tracker if self.tracker else ''})"
            + (f" -> {self.path}" if self.path else "")
        )

    def error(self) -> StageError:
        """The StageError naming every failure (clip, condition, measure, value, threshold)."""
        lines = [f"{len(self.failures)} stimulus check(s) failed "
                 f"(a participant would see a broken stimulus):"]  # fmt: skip
        lines += [f"  {r.describe()}" for r in self.failures[:30]]
        if len(self.failures) > 30:
            lines.append(f"  … and {len(self.failures) - 30} more in {self.path}")
        names = sorted({r.check for r in self.failures})
        lines.append(
            "fix the avatar, the method or the protocol, or accept a check by name: "
            + " ".join(f"--accept-check {n}" for n in names)
            + (f", or one clip's: --accept-check {first.check}:{first.clip}"
               if (first := next((r for r in self.failures if r.clip), None)) else "")
            + " (recorded in clips.csv and stimulus_checks.csv)"
        )
        return StageError("\n".join(lines))


def write_checks(rows: Sequence[CheckRow], path: Path) -> Path:
    """``stimulus_checks.csv`` (:data:`~facelab.stimuli.checks.rows.CHECK_COLUMNS`), atomically."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(CHECK_COLUMNS), lineterminator="\n")
    writer.writeheader()
    writer.writerows(r.as_dict() for r in rows)
    replace_file(path, buf.getvalue())
    return path


def read_checks(path: Path) -> list[dict[str, str]]:
    """The rows of a ``stimulus_checks.csv`` as written (strings)."""
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def _vowel_confidence(weights: np.ndarray) -> float:
    """Mean share of the strongest vowel among the five over frames with a vowel (the
    analyser's confidence in the vowel it reports; 1 = one vowel at a time)."""
    mass = weights.sum(axis=1)
    voiced = mass >= 0.3
    if not voiced.any():
        return math.nan
    return float((weights[voiced].max(axis=1) / mass[voiced]).mean())


#: a recording's transcript is doubted when audio-only analysis hears fewer of its aligned
#: vowels' core frames as those vowels: right transcripts 0.76-1.00 (one short word 0.46),
#: transcripts of other words that the aligner accepts median 0.26-0.35, 95th centile
#: 0.63-0.67 (12 utterances x 3 voices, OpenJTalk at settings not trained on and eSpeak NG)
TRANSCRIPT_HEARD = 0.6
#: ... or when the alignment fits the text's order hardly better than its reverse
#: (:attr:`~facelab.stimuli.speech.align.Alignment.order_fit`, a warning above this)
TRANSCRIPT_ORDER_FIT = 0.85
#: Both at once - fewer than half the vowels heard *and* an order fit near the reverse's, over
#: at least TRANSCRIPT_FRAMES core frames, in a recording the analyser hears clearly (vowel
#: confidence at least TRANSCRIPT_CLEAR) - refuse the stimulus: its mouth would say other
#: words. Set on 16 sentences (not the corpus) x 6 voices (OpenJTalk at two settings, eSpeak
#: NG, Kokoro's three training voices), each recording aligned to its own text, to the two
#: sentences nearest in length, and said twice or cut in half, and on four of those voices
#: with pink noise at +10 dB, white at +15, reverberation and breath noise added. In noise
#: both measures fall for the right words too (a third of right transcripts at +10 dB pink
#: noise met both), while the analyser's confidence falls with them (clean 0.66-0.89,
#: +10 dB pink noise 0.47-0.61): under TRANSCRIPT_CLEAR it only warns. Held-out voices,
#: sentences and recording conditions: the README ("Does the recording say its transcript?").
TRANSCRIPT_REFUSED = (0.5, 0.9)
TRANSCRIPT_FRAMES = 30
TRANSCRIPT_CLEAR = 0.7


def track_source_rows(
    protocol: Protocol, *, clip_of: dict, track_of: Callable[[tuple[str, str]], VisemeTrack],
    speech_of: Callable[[tuple[str, str]], Speech] | None = None,
) -> list[CheckRow]:  # fmt: skip
    """Per stimulus: where its track comes from; a recording analysed audio-only (no
    transcript) is a warning naming the expected accuracy and how to give the words; a
    recording driven by its transcript is a warning when the vowels audio-only analysis hears
    in it are not the transcript's (:data:`TRANSCRIPT_HEARD`: other words, misspelt)."""
    rows = []
    for sset in protocol.stimulus_sets:
        for stim in sset.stimuli:
            clip = clip_of.get((sset.id, stim.id))
            if clip is None:
                continue
            kw = {"clip": clip, "condition": "", "check": "track_source"}
            if stim.track_source == "audio":
                track = track_of((sset.id, stim.id))
                conf = _vowel_confidence(track.vowels())
                words = (
                    f"give the words as 'transcript:' under {sset.id}/{stim.id} (or "
                    "'track_from: words') to drive the mouth from the aligned text"
                    if stim.transcript is None
                    else "its transcript is ignored (track_from: audio)"
                )
                rows.append(CheckRow(
                    **kw, measure="audio_only_vowel_confidence", value=conf, threshold="words",
                    passed=False, severity="warning",
                    note=f"{stim.audio}: the track comes from the audio alone (the analyser's "
                    f"vowel confidence {conf:.2f}, warp {track.warp:g}); {AUDIO_ONLY_ACCURACY}; "
                    + words,
                ))  # fmt: skip
            elif stim.transcript is not None and speech_of is not None:
                rows += transcript_rows(stim, speech_of((sset.id, stim.id)), kw=kw)
            else:
                rows.append(info(None, **kw, measure=f"source:{stim.track_source}",
                                 note="the mouth follows the words' phonemes"
                                 if stim.track_source == "words" else "no speech"))  # fmt: skip
    return rows


def transcript_rows(stim, speech: Speech, *, kw: dict) -> list[CheckRow]:
    """Whether a recording says its transcript (:data:`TRANSCRIPT_REFUSED`): the vowels
    audio-only analysis hears at the aligned vowels, and the alignment's order fit; an error
    row when both say other words in a recording the analyser hears clearly
    (:data:`TRANSCRIPT_CLEAR`), else warnings."""
    track = analyze(speech.samples, sample_rate=speech.sample_rate).compensated()
    heard, frames = aligned_vowels_heard(speech.phones, track)
    if not frames:
        why = f"{stim.audio}: its transcript's vowels are too short to hear (< 40 ms)"
        return [not_measured(**kw, why=why)]
    # kept from the render's own alignment of the recording (no second alignment)
    fit = align_phones(speech.samples, sample_rate=speech.sample_rate,
                       text=stim.transcript).order_fit  # fmt: skip
    clear = _vowel_confidence(track.vowels())
    fit_text = "n/a" if math.isnan(fit) else f"{fit:.2f}"
    said = (f"{stim.audio}: the mouth follows its transcript {stim.transcript!r} aligned to "
            f"it; audio-only analysis hears {heard:.0%} of its vowels' {frames} core frames as "
            f"the transcript's vowels, and its alignment costs {fit_text} times its alignment "
            "to the text reversed (1: the order of the words does not show)")  # fmt: skip
    low_heard, high_fit = TRANSCRIPT_REFUSED
    other_words = frames >= TRANSCRIPT_FRAMES and heard < low_heard and fit > high_fit
    refused = other_words and clear >= TRANSCRIPT_CLEAR
    # the warnings' note: the measures and what to do, or, when refused, where the error is
    lead = f"{stim.audio}: see transcript_matches_recording" if refused else said
    if refused:
        check = ""
    elif other_words:
        clarity = "no voiced frame" if math.isnan(clear) else f"vowel confidence {clear:.2f}"
        check = (f" - both say other words, but the analyser hears this recording unclearly "
                 f"({clarity} < {TRANSCRIPT_CLEAR:g}: noise, reverberation, "
                 "breath or a voice it reads poorly), so it is not refused: listen to it and "
                 "check that the transcript is what it says")  # fmt: skip
    else:
        check = " - check that the transcript is what the recording says"
    rows = [
        at_least(TRANSCRIPT_HEARD, heard, **kw, measure="transcript_vowels_heard",
                 severity="warning", note=lead + ("" if heard >= TRANSCRIPT_HEARD else check)),
        at_most(TRANSCRIPT_ORDER_FIT, fit, **kw, measure="transcript_order_fit",
                severity="warning", note=lead + ("" if fit <= TRANSCRIPT_ORDER_FIT else check)),
    ]  # fmt: skip
    if refused:
        rows.append(CheckRow(
            **kw, measure="transcript_matches_recording", value=heard,
            threshold=f"vowels heard >= {low_heard:g} or order fit <= {high_fit:g}",
            passed=False, severity="error",
            note=f"{said}, in a recording it hears clearly (vowel confidence {clear:.2f}): "
            "the recording does not say its transcript (other words, the words twice, or a "
            "part of them), so the mouth would say other words than the voice - give the "
            "words the recording says, leave the transcript out to analyse the audio alone, "
            "or accept the check if it does say them",
        ))  # fmt: skip
    return rows


def check_clips(
    protocol: Protocol,
    *,
    protocol_path: Path,
    clips_dir: Path,
    accept: Sequence[str] = (),
    log: Callable[[str], None] = print,
) -> CheckReport:
    """Every stimulus check of the clips in ``clips_dir`` (``clips.csv``) against
    ``protocol``; writes ``clips_dir/stimulus_checks.csv`` and returns the report (the caller
    decides what a failure does: :meth:`CheckReport.error`)."""
    t0 = time.perf_counter()
    base_dir = protocol_path.parent
    manifest = _protocols_clips(protocol, read_manifest(clips_dir, need=CLIP_COLUMNS),
                                clips_dir=clips_dir, protocol_path=protocol_path)  # fmt: skip
    names = (*protocol.checks.accept, *accept)
    key = _inputs_key(protocol, manifest)
    earlier = _earlier(clips_dir, key)
    if earlier is not None:  # the same clips, checked by the same rules: measured already
        log("the clips are unchanged since they were checked: stimulus checks reused")
        rows = accept_checks([replace(r, accepted=False) for r in earlier], names)
        report = CheckReport(rows, tracker="reused", accepted=tuple(dict.fromkeys(names)))
        report.path = write_checks(rows, clips_dir / CHECKS_NAME)
        report.seconds = time.perf_counter() - t0
        return report
    missing = [m["path"] for m in manifest if not (clips_dir / m["path"]).is_file()]
    if missing:
        raise StageError(f"{clips_dir}: clips listed in clips.csv are missing: "
                         f"{', '.join(missing[:5])}")  # fmt: skip
    log(f"checking {len(manifest)} clips with the face tracker …")
    pending = start_tracking([
        (clips_dir / m["path"], int(m["width"]), int(m["height"]), float(m["duration_s"] or 0))
        for m in manifest
    ])  # fmt: skip
    try:
        # while the tracker runs: the avatar's geometry, the stimuli's audio
        avatar = load_avatar(protocol, base_dir=base_dir)
        rows = audit_avatar(avatar, protocol, base_dir=base_dir)
        stimuli = {(s.id, st.id): st for s in protocol.stimulus_sets for st in s.stimuli}
        speeches: dict[tuple[str, str], Speech] = {}

        def speech_of(key: tuple[str, str]) -> Speech:
            if key not in speeches:
                rate = protocol.rendering.audio_sample_rate
                speeches[key] = speech_for(stimuli[key], base_dir=base_dir, sample_rate=rate)
            return speeches[key]

        analysed: dict[tuple[str, str], VisemeTrack] = {}

        def track_of(key: tuple[str, str]) -> VisemeTrack:
            """The stimulus' viseme track (audio-only analysis is slow: made once)."""
            if key not in analysed:
                analysed[key] = tracks_for(stimuli[key], speech_of(key))[0]
            return analysed[key]

        decoded = decode_audios([clips_dir / m["path"] for m in manifest], sample_rate=AUDIO_RATE)
        sounds = {m["clip_id"]: sound for m, sound in zip(manifest, decoded, strict=True)}
        for m in manifest:
            if stimuli.get((m["stimulus_set"], m["stimulus"])) is not None:
                speech_of((m["stimulus_set"], m["stimulus"]))
    except BaseException:  # the trackers stop with the check
        pending.cancel()
        raise
    tracked = pending.collect()
    tracking: dict[str, ClipTracking] = {m["clip_id"]: tracked[str(clips_dir / m["path"])]
                                         for m in manifest}  # fmt: skip
    tracker = next(iter(tracked.values())).tracker if tracked else ""
    write_face_tracking(clips_dir, [
        {"clip": m["clip_id"], "frame": k, "time_s": round(k / float(m["fps"]), 6),
         "detection": float(tr.detection[k]), "aperture": float(tr.aperture[k]),
         "width": float(tr.width[k]), "face_height": float(tr.face_height[k])}
        for m in manifest for tr in (tracking[m["clip_id"]],) for k in range(tr.frames)
    ])  # fmt: skip
    by_stimulus: dict[tuple[str, str], list[dict]] = {}
    for m in manifest:
        by_stimulus.setdefault((m["stimulus_set"], m["stimulus"]), []).append(m)
    modality = {c.id: c.modality for c in protocol.conditions}
    offsets = {c.id: c.audio_offset_ms for c in protocol.conditions}
    spectra: dict[str, np.ndarray] = {}  # the noise's spectrum per stimulus set
    heard: dict[str, float] = {}  # clip in noise -> frames its mix follows where it was put
    twins = protocol.offset_twins()
    face = protocol.rendering.audio_only_face
    for m in manifest:
        tr = tracking[m["clip_id"]]
        shown = modality[m["condition"]]
        rows += modality_rows(tr, sounds[m["clip_id"]], modality=shown, face=face,
                              clip=m["clip_id"], condition=m["condition"])  # fmt: skip
        stim = stimuli.get((m["stimulus_set"], m["stimulus"]))
        cond = protocol.condition(m["condition"])
        if cond.noise is not None and stim is not None:  # the mix, measured
            key_stim = (m["stimulus_set"], m["stimulus"])
            padded = padded_audio(speech_of(key_stim), pad_s=protocol.rendering.pad_s)
            mix, _ = clip_sound(protocol, ClipJob(m["clip_id"], m["stimulus_set"], stim,
                                                  m["condition"]),
                                padded, base_dir=base_dir, spectra=spectra,
                                speech_of=lambda sid, st: speech_of((sid, st.id)))  # fmt: skip
            voice = shifted_audio(padded, offset_ms=cond.audio_offset_ms).samples
            ramp = round(cond.noise.ramp_s * padded.sample_rate)
            quiet = voice == 0
            quiet[:ramp], quiet[len(quiet) - ramp:] = False, False

            def at_rate(x: np.ndarray, rate: int = padded.sample_rate) -> np.ndarray:
                return resample(x, rate_in=rate, rate_out=AUDIO_RATE)

            intended = at_rate(mix.samples)
            lag = mix_lag(sounds[m["clip_id"]], intended, sample_rate=AUDIO_RATE)
            heard[m["clip_id"]] = lag / AUDIO_RATE * float(m["fps"])
            rows += noise_rows(sounds[m["clip_id"]], intended, lag=lag,
                               quiet=at_rate(quiet.astype(np.float32)) > 0.999,
                               sample_rate=AUDIO_RATE, snr_db=cond.noise.snr_db,
                               noise_dbfs=cond.noise.speech_level_dbfs - cond.noise.snr_db,
                               fps=float(m["fps"]), clip=m["clip_id"],
                               condition=m["condition"])  # fmt: skip
        if shown == "audio_only" and face == "none":
            continue  # no face to see, track or synchronise
        rows += face_visible_rows(tr, clip=m["clip_id"], condition=m["condition"])
        if shown != "audiovisual":
            continue  # no sound to follow (muted), or no motion to follow it (a still face)
        small = too_small(tr, clip_height=int(m["height"]))
        if stim is not None and stim.track_source != "silence" and small:
            rows.append(not_measured(clip=m["clip_id"], condition=m["condition"],
                                     check="av_sync", why=small))  # fmt: skip
        elif stim is not None and stim.track_source != "silence" and m.get("track_file"):
            fps = float(m["fps"])
            audio = padded_audio(speech_of((m["stimulus_set"], m["stimulus"])),
                                 pad_s=protocol.rendering.pad_s)  # fmt: skip
            sound = envelope(sounds[m["clip_id"]], sample_rate=AUDIO_RATE, fps=fps,
                             n_frames=tr.frames)  # fmt: skip
            want = envelope(audio.samples, sample_rate=audio.sample_rate, fps=fps,
                            n_frames=tr.frames)  # fmt: skip
            values = read_track(clips_dir / m["track_file"]).values
            rows += av_sync_rows(tr, sound, track_values=values, intended_sound=want, fps=fps,
                                 clip=m["clip_id"], condition=m["condition"],
                                 intended_offset_ms=offsets[m["condition"]],
                                 sound_lag_frames=heard.get(m["clip_id"]))  # fmt: skip
    twin = {i for g in twins for i in g}  # one picture: their faces are checked equal instead
    levelled = {c.id: c.level for c in protocol.conditions  # (an SNR is no face's level)
                if c.level is not None and c.id not in twin and c.noise is None}  # fmt: skip
    for (set_id, stim_id), all_clips in by_stimulus.items():
        # the faces of conditions shown alike are compared (a muted clip may look like its
        # audiovisual twin; audio_only faces do not move, by design; to silence, only a
        # behaviour layer moves the face: conditions without one are not compared)
        stim = stimuli.get((set_id, stim_id))
        quiet = stim is not None and stim.silence_s is not None
        for shown in ("audiovisual", "visual_only"):
            plain = {m["condition"]: (m["clip_id"], tracking[m["clip_id"]], m["sha256"])
                     for m in all_clips if m["condition"] not in levelled
                     and modality[m["condition"]] == shown
                     and not (quiet and protocol.condition(m["condition"]).behaviour == "none")
                     }  # fmt: skip
            # one picture's twins are checked equal among themselves; the others see one of
            # them (the first) - not every twin against every other condition
            alike = [[c for c in g if c in plain] for g in twins]
            others = {c for g in alike for c in g[1:]}
            rows += difference_rows({c: v for c, v in plain.items() if c not in others},
                                    equal_groups=protocol.checks.equal_conditions,
                                    explain=_explanations(clips_dir, all_clips))  # fmt: skip
            for group in alike:
                rows += difference_rows({c: plain[c] for c in group}, shared_picture=[group])
        clips = [m for m in all_clips if modality[m["condition"]] != "audio_only"]
        graded: dict[str, list] = {}
        for m in clips:
            if m["condition"] in levelled:
                cond = protocol.condition(m["condition"])
                graded.setdefault(cond.method, []).append(
                    (levelled[cond.id], m["clip_id"], tracking[m["clip_id"]]))
        for method, levels in graded.items():
            if protocol.tasks and len(levels) > 2:  # psychometric designs want close levels:
                ordered = sorted(levels, key=lambda x: x[0])  # only the ends must differ
                levels = [ordered[0], ordered[-1]]
            rows += level_rows(levels, condition_of={m["clip_id"]: m["condition"] for m in clips},
                               group=f"{set_id}/{stim_id} {method}")  # fmt: skip
        if stim is not None and stim.expected_vowels:
            peaks = vowel_peak_times(stim, track_of((set_id, stim_id)),
                                     where=f"{set_id}/{stim_id}",
                                     phones=speech_of((set_id, stim_id)).phones)  # fmt: skip
            readable, peak_times = [], [t for _, t in peaks]
            for m in clips:
                small = too_small(tracking[m["clip_id"]], clip_height=int(m["height"])) or (
                    too_few_frames(peak_times, fps=float(m["fps"])))  # fmt: skip
                if small:
                    rows.append(not_measured(clip=m["clip_id"], condition=m["condition"],
                                             check="articulation", why=small))  # fmt: skip
                else:
                    readable.append(m)
            mouths = {m["condition"]: mouth_at_peaks(tracking[m["clip_id"]], peaks,
                                                      fps=float(m["fps"]),
                                                      offset_s=protocol.rendering.pad_s)
                      for m in readable}  # fmt: skip
            rows += articulation_rows(
                mouths, clips={m["condition"]: m["clip_id"] for m in readable},
                vowel_rules=protocol.checks.vowel_rules, rules=protocol.checks.articulation,
            )  # fmt: skip
    clip_of = {k: v[0]["clip_id"] for k, v in by_stimulus.items()}
    rows += track_source_rows(protocol, clip_of=clip_of, track_of=track_of, speech_of=speech_of)
    rows = accept_checks(rows, names)
    report = CheckReport(rows, seconds=time.perf_counter() - t0, tracker=tracker,
                         accepted=tuple(dict.fromkeys(names)))  # fmt: skip
    report.path = write_checks(rows, clips_dir / CHECKS_NAME)
    report.seconds = time.perf_counter() - t0
    saved = {"inputs": key, "tracker": tracker, "seconds": round(report.seconds, 2)}
    replace_file(clips_dir / CHECKS_KEY_NAME, json.dumps(saved) + "\n")
    return report


#: bump when a check's measure or threshold changes: earlier results are then measured again
CHECKS_VERSION = 10  # (9 was once set back to 8 by mistake: 10 is new)
CHECKS_KEY_NAME = "stimulus_checks.json"


def _inputs_key(protocol: Protocol, manifest: Sequence[dict]) -> str:
    """What the checks' rows depend on: the clips' bytes and inputs, the conditions and the
    protocol's check rules."""
    import hashlib

    data = {
        "version": CHECKS_VERSION,
        "clips": sorted(
            (m["clip_id"], m["sha256"], m["spec_sha256"], m.get("track_sha256", ""))
            for m in manifest
        ),
        "conditions": [c.model_dump(mode="json") for c in protocol.conditions],
        "checks": protocol.checks.model_dump(mode="json", exclude={"accept"}),
        "pad_s": protocol.rendering.pad_s,
    }
    return hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()


def _earlier(clips_dir: Path, key: str) -> list[CheckRow] | None:
    """The rows of an earlier check of the same inputs, or None."""
    try:
        saved = json.loads((clips_dir / CHECKS_KEY_NAME).read_text(encoding="utf-8"))
        if saved.get("inputs") != key:
            return None
        rows = read_checks(clips_dir / CHECKS_NAME)
    except (OSError, ValueError):
        return None
    try:
        return [CheckRow.from_dict(r) for r in rows]
    except (KeyError, ValueError):  # an edited or older file: check again
        return None


def _protocols_clips(
    protocol: Protocol, manifest: list[dict], *, clips_dir: Path, protocol_path: Path
) -> list[dict]:
    """The rows of ``manifest`` that are ``protocol``'s clips, one per clip it plans, each
    rendered from what it declares now (its spec hash); StageError naming the clips missing
    or rendered from something else (another study's clips, an edited protocol or input)."""
    by_key = {(m["stimulus_set"], m["stimulus"], m["condition"]): m for m in manifest}
    keys = [(j.stimulus_set, j.stimulus.id, j.condition) for j in plan(protocol)]
    missing, stale = unlisted_and_stale(protocol, manifest, keys, base_dir=protocol_path.parent)
    render = (f"render them: facelab render {protocol_path} --out {clips_dir} (clips of "
              "recorded turns are checked as facelab render --turn makes them)")
    if missing:
        listed = ", ".join("/".join(k) for k in missing[:5])
        raise StageError(f"{clips_dir / 'clips.csv'} does not list {len(missing)} of the "
                         f"{len(keys)} clips {protocol.study.id!r} needs ({listed}"
                         f"{' …' if len(missing) > 5 else ''}): {render}")  # fmt: skip
    if stale:
        listed = ", ".join("/".join(k) for k in stale[:5])
        raise StageError(f"{len(stale)} clip(s) in {clips_dir} were rendered from another "
                         f"protocol or other input files than {protocol.study.id!r} declares "
                         f"now ({listed}{' …' if len(stale) > 5 else ''}): {render}")  # fmt: skip
    return [by_key[key] for key in keys]


def _explanations(clips_dir: Path, clips: Sequence[dict]) -> dict[tuple[str, str], str]:
    """{(condition a, condition b): why they look alike}, from the clips' JSON (stand-ins) and
    animation tracks (the same weights drawn)."""
    out = {}
    meta = {}
    for m in clips:
        path = clips_dir / f"{m['clip_id']}.json"
        try:
            meta[m["condition"]] = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            meta[m["condition"]] = {}
    tracks = {m["condition"]: m.get("track_sha256") for m in clips}
    for a in meta:
        for b in meta:
            if a >= b:
                continue
            why = []
            if tracks.get(a) and tracks.get(a) == tracks.get(b):
                why.append("both draw the same weights on this avatar")
            for c in (a, b):
                if meta[c].get("stand_in"):
                    why.append(f"{c}: {meta[c]['stand_in']}")
            out[(a, b)] = "; ".join(why)
    return out


#: the column ``facelab check`` adds to ``clips.csv`` (:data:`facelab.formats.CHECKS_COLUMN`)
MANIFEST_COLUMN = CHECKS_COLUMN


def record_in_manifest(clips_dir: Path, report: CheckReport) -> None:
    """Add (or refresh) ``clips.csv``'s :data:`MANIFEST_COLUMN`: per clip ``passed``, or
    ``failed: NAMES`` / ``accepted: NAMES`` for the checks that failed on it (an avatar-audit
    failure counts for every clip of its condition, a pair's for both clips, a
    ``track_source`` failure - about the recording, filed under its first clip - for every
    clip of its stimulus)."""
    path = clips_dir / "clips.csv"
    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        header = [c for c in (reader.fieldnames or []) if c != MANIFEST_COLUMN]
        rows = list(reader)
    stimulus_of = {row["clip_id"]: (row.get("stimulus_set"), row.get("stimulus")) for row in rows}
    for row in rows:
        failed, accepted = set(), set()
        for r in report.rows:
            if r.passed is not False or r.severity != "error":
                continue
            mine = (r.clip == row["clip_id"] or row["clip_id"] in r.clip.split("~")
                    or (not r.clip and r.condition in ("", row["condition"]))
                    or (r.check == "track_source" and r.clip in stimulus_of
                        and stimulus_of[r.clip] == stimulus_of[row["clip_id"]]))  # fmt: skip
            if mine:
                (accepted if r.accepted else failed).add(r.check)
        row[MANIFEST_COLUMN] = "; ".join(
            [f"failed: {', '.join(sorted(failed))}"] * bool(failed)
            + [f"accepted: {', '.join(sorted(accepted))}"] * bool(accepted)
        ) or "passed"
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=[*header, MANIFEST_COLUMN], lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    replace_file(path, buf.getvalue())
