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
