"""Every file a protocol names, read as ``facelab render`` reads it: the methods' files (Z
matrices, impression models), recorded audio at the protocol's rate, the avatar (loaded and
checked to play every condition's method) and custom behaviour libraries. ``facelab validate``
reports what this finds with the protocol's lines, so "valid" means "will render"."""

from __future__ import annotations

from pathlib import Path

from facelab.errors import FacelabError, Issue, SpeechError, VisemeError
from facelab.protocol import Protocol, Stimulus, load_protocol
from facelab.stimuli.avatar import default_head, load
from facelab.stimuli.behaviour.library import load_library
from facelab.stimuli.methods import check_playable, get
from facelab.stimuli.render.clipspec import plan
from facelab.stimuli.speech.audio import load_audio
from facelab.stimuli.speech.noise import active_level_db
from facelab.stimuli.speech.not_speech import not_speech_reason
from facelab.stimuli.speech.tts import synthesize
from facelab.stimuli.speech.vowel_units import vowel_readings

__all__ = ["audio_only_note", "input_notes", "input_problems", "load_checked_protocol"]


def input_problems(protocol: Protocol, *, base_dir: Path) -> list[Issue]:
    """The problems of the files ``protocol`` names (paths relative to ``base_dir``), each at
    the key that names the file; empty when every file will render."""
    issues: list[Issue] = []
    for i, cond in enumerate(protocol.conditions):
        method = get(cond.method)
        for key_path, message in method.input_problems(cond.settings, base_dir=base_dir):
            issues.append(Issue(("conditions", i, *key_path), message))
        if cond.behaviour.lower().endswith((".json", ".yaml", ".yml")):
            try:
                load_library(base_dir / cond.behaviour)
            except FacelabError as exc:
                issues.append(Issue(("conditions", i, "behaviour"), str(exc)))
    for job in plan(protocol):
        i, cond = next((i, c) for i, c in enumerate(protocol.conditions) if c.id == job.condition)
        for message in get(cond.method).stimulus_problems(
            cond.settings, base_dir=base_dir, stimulus_set=job.stimulus_set,
            stimulus_id=job.stimulus.id,
        ):  # fmt: skip
            issues.append(Issue(("conditions", i, "params"), message))
    rate = protocol.rendering.audio_sample_rate
    for si, sset in enumerate(protocol.stimulus_sets):
        for ti, stim in enumerate(sset.stimuli):
            at = ("stimulus_sets", si, "stimuli", ti)
            said = _words_problems(stim)
            issues += [Issue((*at, key), message) for key, message in said]
            if stim.audio is None:
                continue
            try:
                recorded = load_audio(base_dir / stim.audio, sample_rate=rate)
            except FacelabError as exc:
                issues.append(Issue((*at, "audio"), str(exc)))
                continue
            level = active_level_db(recorded.samples, sample_rate=rate)
            if level < QUIET_SPEECH_DBFS:  # the analysis's level gate closes the mouth
                issues.append(Issue((*at, "audio"), (
                    f"{stim.audio}: the speech is at {level:.1f} dBFS (its active level), "
                    f"quieter than {QUIET_SPEECH_DBFS:g}: the analysis opens the mouth less "
                    "the quieter the voice (one sentence measured: a mean opening of 0.46 at "
                    "-18 dBFS, 0.27 at -38, 0.16 at -43, none at -53): normalise the "
                    "recording to about -20 dBFS "
                    "(e.g. ffmpeg -i IN -af loudnorm OUT.wav)")))
                continue
            reason = not_speech_reason(recorded.samples, sample_rate=rate)
            if reason is not None:  # its clip would move the mouth to a tone
                issues.append(Issue((*at, "audio"), (
                    f"{stim.audio}: this is not speech: {reason}. A clip would move the "
                    "avatar's mouth to it as if it were words: give a recording of speech")))
            elif stim.transcript is not None and not any(k == "transcript" for k, _ in said):
                from facelab.stimuli.speech.align import align_phones  # the signal stack

                try:  # as the render aligns it (kept: the render does not align it again)
                    align_phones(recorded.samples, sample_rate=rate, text=stim.transcript)
                except VisemeError as exc:
                    issues.append(Issue((*at, "transcript"), (
                        f"{stim.audio} and its transcript: {exc} (give the words the "
                        "recording says, or leave the transcript out to analyse the audio "
                        "alone)")))
    spec = protocol.rendering.avatar
    try:
        avatar = default_head() if spec == "default" else load(base_dir / spec)
    except FacelabError as exc:
        issues.append(Issue(("rendering", "avatar"), str(exc)))
        return issues
    for i, cond in enumerate(protocol.conditions):
        if any(issue.path[:2] == ("conditions", i) for issue in issues):
            continue  # its files did not load: whether it plays cannot be told
        try:
            check_playable(avatar, cond.method, cond.settings, base_dir=base_dir)
        except FacelabError as exc:
            issues.append(Issue(("rendering", "avatar"), f"condition {cond.id!r}: {exc}"))
    return issues


#: a recording's active speech level (dBFS) below which validate refuses it: the analyser's
#: absolute level gate (-50..-30 dBFS, as uLipSync) closes the mouth on quiet speech
QUIET_SPEECH_DBFS = -40.0


def load_checked_protocol(path: Path | str) -> Protocol:
    """The protocol at ``path``, or the ProtocolError ``facelab validate`` gives: every
    problem of the file and of the files and texts it names (:func:`input_problems`) in one
    report, each at its line - raised before a render writes anything."""
    return load_protocol(path, file_checks=lambda p, base: input_problems(p, base_dir=base))


def _words_problems(stim: Stimulus) -> list[tuple[str, str]]:
    """(key, message) for a text or transcript OpenJTalk reads as no speech (punctuation,
    symbols, a lone っ: a clip whose mouth never moves), and for ``expected_vowels`` that are
    not the vowels it reads there (the vowels the clip's checks and isolation look for). Read
    by the synthesiser itself (kept per process: the render reuses it), which also times a
    transcript for alignment."""
    key, words = ("text", stim.text) if stim.text is not None else ("transcript", stim.transcript)
    if words is None:
        return []
    try:
        phones = synthesize(words).phones
    except SpeechError:
        phones = ()
    sounded = [p.phoneme for p in phones if p.phoneme not in ("sil", "pau", "cl")]
    if not sounded:
        read = "only a pause or a closure (っ)" if phones else "nothing"
        return [(key, f"OpenJTalk reads {read} in {words!r}: no speech to synthesise or "
                 "align (write words it can pronounce, in kana or kanji)")]  # fmt: skip
    readings = vowel_readings(phones)
    if stim.expected_vowels is not None and stim.expected_vowels not in readings:
        said = " ".join(p.phoneme for p in phones if p.phoneme != "sil")
        return [("expected_vowels", f"{stim.expected_vowels!r}, but OpenJTalk reads {words!r} "
                 f"as {said!r}: give its vowels in order, "
                 + " or ".join(repr(r) for r in readings))]  # fmt: skip
    return []


def audio_only_note(protocol: Protocol) -> str | None:
    """One line naming the recordings analysed audio-only (no transcript), or None."""
    found = [
        f"{s.id} ({s.audio})"
        for ss in protocol.stimulus_sets
        for s in ss.stimuli
        if s.audio is not None and s.transcript is None
    ]
    if not found:
        return None
    return (
        f"note: {len(found)} recording(s) without a transcript get their tracks from "
        f"audio-only analysis: {', '.join(found)} (give each a 'transcript' to drive the "
        "mouth from the aligned words)"
    )


def input_notes(protocol: Protocol, *, base_dir: Path) -> list[str]:
    """What ``validate`` and ``render`` say about the protocol's inputs besides problems:
    recordings analysed audio-only, and each method's own notes on the conditions that use
    it (:meth:`Method.protocol_notes`, e.g. impression levels too close to see)."""
    note = audio_only_note(protocol)
    notes = [note] if note else []
    by_method: dict[str, list[object]] = {}
    for cond in protocol.conditions:
        by_method.setdefault(cond.method, []).append(cond.settings)
    for name, settings in by_method.items():
        notes += get(name).protocol_notes(
            settings, base_dir=base_dir, has_tasks=bool(protocol.tasks)
        )
    return notes
