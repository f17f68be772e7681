"""The Simulator Sickness Questionnaire (Kennedy, Lane, Berbaum & Lilienthal, 1993, The
International Journal of Aviation Psychology 3(3):203-220): its 16 symptoms, the four answers
and the standard scoring. Pure.

Each symptom is rated none (0), slight (1), moderate (2) or severe (3). Every symptom loads on
one or two of three subscales - nausea (N), oculomotor (O), disorientation (D), seven
symptoms each - and the scores are the subscale's raw sum times its weight: N x 9.54,
O x 7.58, D x 13.92, and the total score (N + O + D raw sums) x 3.74. Maxima: N 200.34,
O 159.18, D 292.32, total 235.62.

The English wording is the questionnaire's; the Japanese is facelab's own translation (not a
published, validated one - a study that needs one can give its own labels by replacing
:data:`SYMPTOMS`' texts in a fork, and should say which it used).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

__all__ = [
    "ANSWERS",
    "MOMENTS",
    "QUESTION",
    "SUBSCALE_WEIGHTS",
    "SYMPTOMS",
    "Symptom",
    "item_id",
    "parse_item",
    "scores",
]

#: when the questionnaire is given: before the first screen of the study, after its last trial
MOMENTS = ("before", "after")


@dataclass(frozen=True)
class Symptom:
    """One symptom: its id (the log's item is ``ssq_<moment>_<id>``), the subscales it loads
    on and its wording per language."""

    id: str
    subscales: tuple[str, ...]
    text: Mapping[str, str]


# fmt: off
SYMPTOMS: tuple[Symptom, ...] = (
    Symptom("general_discomfort", ("N", "O"), {"en": "General discomfort", "ja": "全体的な不快感"}),
    Symptom("fatigue", ("O",), {"en": "Fatigue", "ja": "疲労感"}),
    Symptom("headache", ("O",), {"en": "Headache", "ja": "頭痛"}),
    Symptom("eyestrain", ("O",), {"en": "Eyestrain", "ja": "目の疲れ"}),
    Symptom("difficulty_focusing", ("O", "D"),
            {"en": "Difficulty focusing", "ja": "目の焦点の合わせにくさ"}),
    Symptom("increased_salivation", ("N",), {"en": "Increased salivation", "ja": "唾液の増加"}),
    Symptom("sweating", ("N",), {"en": "Sweating", "ja": "発汗"}),
    Symptom("nausea", ("N", "D"), {"en": "Nausea", "ja": "吐き気"}),
    Symptom("difficulty_concentrating", ("N", "O"),
            {"en": "Difficulty concentrating", "ja": "集中しにくさ"}),
    Symptom("fullness_of_head", ("D",), {"en": "Fullness of head", "ja": "頭が重い感じ"}),
    Symptom("blurred_vision", ("O", "D"), {"en": "Blurred vision", "ja": "目のかすみ"}),
    Symptom("dizzy_eyes_open", ("D",),
            {"en": "Dizzy (eyes open)", "ja": "めまい（目を開けているとき）"}),
    Symptom("dizzy_eyes_closed", ("D",),
            {"en": "Dizzy (eyes closed)", "ja": "めまい（目を閉じているとき）"}),
    Symptom("vertigo", ("D",), {"en": "Vertigo", "ja": "ぐるぐる回るようなめまい"}),
    Symptom("stomach_awareness", ("N",), {"en": "Stomach awareness", "ja": "胃の違和感"}),
    Symptom("burping", ("N",), {"en": "Burping", "ja": "げっぷ"}),
)
# fmt: on

#: (value, wording per language) of the four answers
ANSWERS: tuple[tuple[int, Mapping[str, str]], ...] = (
    (0, {"en": "None", "ja": "なし"}),
    (1, {"en": "Slight", "ja": "少し"}),
    (2, {"en": "Moderate", "ja": "中程度"}),
    (3, {"en": "Severe", "ja": "強い"}),
)

#: the weight of each subscale's raw sum, and of the three sums together ("total")
SUBSCALE_WEIGHTS = {"N": 9.54, "O": 7.58, "D": 13.92, "total": 3.74}

#: the question above each symptom
QUESTION = {
    "en": "How much is this symptom affecting you right now?",
    "ja": "いまのあなたの状態について、この症状はどのくらいありますか。",
}


def item_id(*, moment: str, symptom: str) -> str:
    """The log item of one answer, e.g. ``ssq_before_nausea``."""
    return f"ssq_{moment}_{symptom}"


def parse_item(item: str) -> tuple[str, str] | None:
    """(moment, symptom id) of an SSQ log item; None for any other item."""
    for moment in MOMENTS:
        prefix = f"ssq_{moment}_"
        if item.startswith(prefix) and item[len(prefix) :] in _BY_ID:
            return moment, item[len(prefix) :]
    return None


_BY_ID = {s.id: s for s in SYMPTOMS}


def scores(answers: Mapping[str, int]) -> dict[str, float]:
    """The subscale and total scores of one questionnaire from ``{symptom id: 0-3}`` (all 16
    symptoms): ``{"N", "O", "D", "total"}`` weighted as Kennedy et al. (1993), and the raw
    sums ``{"N_raw", "O_raw", "D_raw"}``. Raises ValueError naming a symptom missing, unknown
    or rated outside 0-3."""
    unknown = sorted(set(answers) - set(_BY_ID))
    if unknown:
        raise ValueError(f"unknown SSQ symptom {unknown[0]!r}")
    missing = [s.id for s in SYMPTOMS if s.id not in answers]
    if missing:
        raise ValueError(f"SSQ symptom {missing[0]!r} has no answer")
    raw = {"N": 0, "O": 0, "D": 0}
    for symptom in SYMPTOMS:
        value = answers[symptom.id]
        if isinstance(value, bool) or value not in (0, 1, 2, 3):
            raise ValueError(f"SSQ symptom {symptom.id!r}: expected 0-3, got {value!r}")
        for scale in symptom.subscales:
            raw[scale] += int(value)
    out = {scale: round(raw[scale] * SUBSCALE_WEIGHTS[scale], 4) for scale in raw}
    out["total"] = round(sum(raw.values()) * SUBSCALE_WEIGHTS["total"], 4)
    return out | {f"{scale}_raw": float(raw[scale]) for scale in raw}
