"""Edits of the shipped kato2021 protocol's text that many tests make: a study cut down to
what a test needs, so each test file does not carry its own copy of the same replacements;
and the error an edited protocol is refused with (:func:`protocol_problems`)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from facelab.errors import ProtocolError
from facelab.protocol import load_protocol_text


def kato_vowels_only(text: str) -> str:
    """kato2021 without the sentences block (the practice trial on the vowels): a render of
    the vowel stimulus in every condition only."""
    text = text[: text.index("  - id: sentences\n    stimulus_set: sentences")] + text[
        text.index("items:"):
    ]  # fmt: skip
    return text.replace(
        "practice: {stimulus_set: sentences, stimulus: passage, condition: standard}",
        "practice: {stimulus_set: vowels, stimulus: aiueo, condition: standard}",
    )


def kato_short(text: str, *, one_set: bool = True) -> str:
    """kato2021 with short stimuli (two vowels, one short sentence) and, with ``one_set``,
    one set per block: a session of a few minutes."""
    text = text.replace("        text: あ。い。う。え。お。", "        text: あ。い。")
    text = text.replace("        expected_vowels: aiueo", "        expected_vowels: ai")
    text = re.sub(r"        text: 今日は.*\n", "        text: こんにちは。\n", text)
    return text.replace("    sets: 2\n", "    sets: 1\n") if one_set else text


def protocol_problems(text: str, root: Path, name: str = "p.yaml") -> str:
    """The error a protocol's ``text`` (written to ``root/name``) is refused with."""
    path = root / name
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ProtocolError) as info:
        load_protocol_text(text, path=path, base_dir=root)
    return str(info.value)


#: a study of one condition (a pilot of one method) on vowels spoken without pauses
ONE_CONDITION = """\
schema_version: 1
study: {id: one_condition, title: One method, participants_planned: 3}
seed: 1
conditions:
  - {id: standard, label: {ja: 標準, en: standard}, method: vowel_blend,
     params: {z: standard, gain: 1.0}}
stimulus_sets:
  - id: short
    stimuli:
      - {id: aiueo, text: あいうえお, expected_vowels: aiueo}
      - {id: hai, text: はい, expected_vowels: ai}
blocks:
  - {id: short, stimulus_set: short, sets: 1, presentations_per_condition: 1,
     order: random_within_set}
items:
  - id: naturalness
    question: {ja: 自然さ, en: naturalness}
    left_anchor: {ja: 不自然, en: unnatural}
    right_anchor: {ja: 自然, en: natural}
    range: [0, 100]
    marker_start: hidden
    confirm: true
presentation:
  language: ja
  items_layout: sequential
  fullscreen: false
  instructions: {ja: 見てください, en: Watch}
  end_text: {ja: 終了, en: End}
rendering: {width: 160, height: 90, fps: 10, avatar: default, pad_s: 0.3}
simulation:
  model: {mean: 45, participant_sd: 10, interaction_sd: 4, noise_sd: 12, rt_median_s: 3.0}
  effects: {standard: 10}
"""
