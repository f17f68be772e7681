"""Words and accent phrases of an OpenJTalk utterance, timed from its label trace.

``open_jtalk -ot`` writes the front end's word analysis (``[Text analysis result]``: one
line per word with its surface form, part of speech, reading, pronunciation and
``accent-type/morae``) and the full-context labels (``[Output label]``) the audio was
synthesised from. The labels carry the prosody:

* ``/A:a1+a2+a3`` - a2 is the mora's position in its accent phrase (1-based);
* ``/F:f1_f2#…@f5_…`` - f1 morae in the accent phrase, f2 its accent type (0 = flat, k > 0 =
  the pitch falls after mora k), f5 the phrase's position in its breath group;
* ``/I:…@i3+…`` - i3 the breath group's position in the utterance.

Words get times by counting morae: every vowel (``a i u e o`` and devoiced ``A I U E O``),
``N`` and ``cl`` closes a mora; word k covers the morae its pronunciation counts. The
behaviour planner uses these to time trigger words and to put head nods and brow raises on
accent peaks (the accented mora, or mora 2 of a flat phrase, where the pitch rises) rather than
at random.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from facelab.errors import SpeechError

__all__ = [
    "AccentPhrase",
    "Word",
    "accent_phrases",
    "label_rows",
    "parse_words",
    "words_with_times",
]

_MORA_END = frozenset(["a", "i", "u", "e", "o", "A", "I", "U", "E", "O", "N", "cl"])
_LABEL = re.compile(r"^(\d+) (\d+) \S*?\^\S*?-(\S+?)\+")
_A = re.compile(r"/A:(-?\d+|xx)\+(\d+|xx)\+")
_F = re.compile(r"/F:(\d+|xx)_(\d+|xx)#\S*?@(\d+|xx)_")
_I = re.compile(r"/I:\S*?@(\d+|xx)\+")


@dataclass(frozen=True)
class Word:
    """One word of the front end: ``surface`` as written, ``reading`` its pronunciation in
    katakana, ``pos`` the part of speech, ``morae`` its mora count; ``start``/``end`` in seconds
    from the start of the audio (NaN for punctuation, which has no morae)."""

    surface: str
    reading: str
    pos: str
    morae: int
    start: float = float("nan")
    end: float = float("nan")


@dataclass(frozen=True)
class AccentPhrase:
    """One accent phrase: ``start``/``end`` s, ``morae``, ``accent_type`` (0 = flat), ``peak``
    the start of the prominent mora (the accent nucleus, or mora 2 of a flat phrase) in s,
    ``breath_group`` and ``position`` (1-based) and ``final`` when it ends its breath group."""

    start: float
    end: float
    morae: int
    accent_type: int
    peak: float
    breath_group: int
    position: int
    final: bool


def parse_words(trace: str) -> list[Word]:
    """The ``[Text analysis result]`` section of an ``open_jtalk -ot`` trace as words
    (untimed)."""
    words: list[Word] = []
    inside = False
    for line in trace.splitlines():
        if line.startswith("[Text analysis result]"):
            inside = True
            continue
        if inside:
            if not line.strip():
                break
            fields = line.split(",")
            if len(fields) < 11:
                raise SpeechError(f"unexpected OpenJTalk word line: {line[:60]!r}")
            acc = fields[10].split("/")
            morae = int(acc[1]) if len(acc) == 2 and acc[1].isdigit() else 0
            words.append(Word(fields[0], fields[9], fields[1], morae))
    return words


def label_rows(trace: str) -> list[tuple[float, float, str, str]]:
    """(start s, end s, phoneme, label line) of each ``[Output label]`` line."""
    rows = []
    inside = False
    for line in trace.splitlines():
        if line.startswith("[Output label]"):
            inside = True
            continue
        if inside:
            if not line.strip():
                break
            m = _LABEL.match(line)
            if m is None:
                raise SpeechError(f"unexpected OpenJTalk label line: {line[:60]!r}")
            rows.append((int(m.group(1)) * 1e-7, int(m.group(2)) * 1e-7, m.group(3), line))
    return rows


def _morae(trace: str) -> list[tuple[float, float, str]]:
    """(start, end, label line of the mora's last phone) per mora, in order."""
    out = []
    start = None
    for t0, t1, ph, line in label_rows(trace):
        if ph in ("sil", "pau"):
            start = None
            continue
        if start is None:
            start = t0
        if ph in _MORA_END:
            out.append((start, t1, line))
            start = None
    return out


def words_with_times(trace: str) -> list[Word]:
    """Words with their start and end times, by walking the morae of the labels.

    Raises :class:`SpeechError` when the word analysis and the labels disagree on the number
    of morae (the timing would be wrong)."""
    words = parse_words(trace)
    morae = _morae(trace)
    if sum(w.morae for w in words) != len(morae):
        raise SpeechError(
            f"OpenJTalk's words count {sum(w.morae for w in words)} morae but its labels "
            f"{len(morae)}: cannot time the words"
        )
    out, k = [], 0
    for w in words:
        if w.morae == 0:
            out.append(w)
            continue
        span = morae[k : k + w.morae]
        out.append(Word(w.surface, w.reading, w.pos, w.morae, span[0][0], span[-1][1]))
        k += w.morae
    return out


def accent_phrases(trace: str) -> list[AccentPhrase]:
    """The accent phrases of the labels, in order, with their prominent mora's time."""
    groups: dict[tuple[int, int], list[tuple[float, float, int, int, int]]] = {}
    for t0, t1, ph, line in label_rows(trace):
        if ph in ("sil", "pau"):
            continue
        a, f, i = _A.search(line), _F.search(line), _I.search(line)
        if not (a and f and i) or "xx" in (a.group(2), f.group(1), f.group(2), f.group(3)):
            continue
        key = (int(i.group(1)) if i.group(1) != "xx" else 0, int(f.group(3)))
        groups.setdefault(key, []).append(
            (t0, t1, int(a.group(2)), int(f.group(1)), int(f.group(2)))
        )
    phrases = []
    keys = list(groups)
    for n, key in enumerate(keys):
        rows = groups[key]
        morae, accent = rows[0][3], rows[0][4]
        target = accent if accent > 0 else min(2, morae)
        peak = next((r[0] for r in rows if r[2] == target), rows[0][0])
        final = n + 1 == len(keys) or keys[n + 1][0] != key[0]
        phrases.append(
            AccentPhrase(rows[0][0], rows[-1][1], morae, accent, peak, key[0], key[1], final)
        )
    return phrases
