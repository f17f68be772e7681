"""Typed answers scored as pronounced (issue 52.2): the tricky inputs of
``tests/reference/typed_answers.csv`` - kana and kanji variants, long vowels, typos, extra and
missing words, keywords inside other words, spaced words, keywords out of order - and
``facelab score-typed``."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from facelab.analysis.typed_scoring import score_table, score_typed
from facelab.experiment.cli import main
from facelab.japanese_reading import morae, pronunciation

TRICKY = Path(__file__).parent / "reference" / "typed_answers.csv"
#: (mora score, keyword score, exact) each case must get - worked out by hand
EXPECTED = {
    "hiragana for kanji": (1.0, 1.0, 1),
    "katakana for kanji": (1.0, 1.0, 1),
    "kanji for hiragana": (1.0, 1.0, 1),
    "long vowel spelled out": (1.0, 1.0, 1),
    "long vowel as a bar": (1.0, 1.0, 1),
    "long vowel missing": (0.8, 0.0, 0),
    "an extra word": (1.0, 1.0, 0),
    "one mora wrong": (0.5, 0.0, 0),
    "a sentence in kana": (1.0, 1.0, 1),
    "a particle left out": (5 / 6, 1.0, 0),
    "a typo in a keyword": (5 / 6, 1.0, 0),
    "other words": (2 / 6, 0.0, 0),
    "a homophone (鹿 and しか read alike)": (1.0, 1.0, 1),
    "full-width katakana": (1.0, 1.0, 1),
    "half-width katakana": (1.0, 1.0, 1),
    "e+i in kana for a long e in kanji": (1.0, 1.0, 1),
    "e+i in kana for a long e in kanji (2)": (1.0, 1.0, 1),
    # オーキナハコオハコンダ (11) against オーキナハコンダ: オーキナ + ハコンダ in order; the
    # keywords 大きな and 運んだ each on morae of their own (箱 only inside 運んだ)
    "a keyword inside another's reading (箱 ハコ in 運んだ ハコンダ)": (8 / 11, 2 / 3, 0),
    # アシタノアサワアメ (9) against アサアメ: アサ, アメ
    "words apart read apart (朝 雨 not as one word)": (4 / 9, 2 / 3, 0),
    # ネコガハシル (6) against ハシルネコ: ハシル; keywords in the order said: one of two
    "keywords out of the order said": (3 / 6, 1 / 2, 0),
}


def test_tricky_inputs_are_scored_as_pronounced() -> None:
    table = score_table(pd.read_csv(TRICKY, dtype=str, keep_default_na=False),
                        reader=pronunciation, split=morae)  # fmt: skip
    assert set(table["case"]) == set(EXPECTED)
    for r in table.itertuples():
        want = EXPECTED[r.case]
        assert (r.mora_score, r.keyword_score, r.exact) == pytest.approx(want), r


def test_a_keyword_typo_counts_only_when_tolerated() -> None:
    kw = {"reader": pronunciation, "split": morae, "keywords": ["走る"]}
    assert score_typed("猫が走る", "ねこがはしろ", tolerant=True, **kw).keyword_score == 1.0
    assert score_typed("猫が走る", "ねこがはしろ", tolerant=False, **kw).keyword_score == 0.0
    assert morae("キャット") == ["キャ", "ッ", "ト"]


def test_score_typed_command_writes_the_table(tmp_path, capsys) -> None:
    out = tmp_path / "scored.csv"
    assert main(["score-typed", str(TRICKY), "--out", str(out)]) == 0
    scored = pd.read_csv(out)
    assert len(scored) == len(EXPECTED) and {"mora_score", "keywords"} <= set(scored.columns)
    bad = tmp_path / "bad.csv"
    bad.write_text("said,typed\nx,y\n", encoding="utf-8")
    assert main(["score-typed", str(bad)]) == 2
    assert "missing column(s) target, response" in capsys.readouterr().err
    # a comma inside an unquoted answer was read as a shifted row (the target taken from the
    # answer, the next row's answer empty) and scored, exit 0; quoted, it is one answer
    bad.write_text("target,response\n今日は晴れです,今日は,晴れです\nあさ,あさ\n", encoding="utf-8")
    assert main(["score-typed", str(bad), "--out", str(tmp_path / "no.csv")]) == 2
    assert "bad.csv:2: 3 fields, the header has 2" in capsys.readouterr().err
    assert not (tmp_path / "no.csv").exists()
    bad.write_text('target,response\n今日は晴れです,"今日は,晴れです"\n', encoding="utf-8")
    assert main(["score-typed", str(bad), "--out", str(out), "--force"]) == 0
    row = pd.read_csv(out).iloc[0]
    assert row["response"] == "今日は,晴れです" and row["mora_score"] == 1.0
    bad.write_text("target,response\nあさ,あさ\n ,あさ\n", encoding="utf-8")  # was scored 0
    assert main(["score-typed", str(bad)]) == 2
    assert "bad.csv:3: the target (what was said) is empty" in capsys.readouterr().err
    # a keyword the target does not say scored 0 even for a word-for-word answer (exact 1);
    # a target of punctuation only left a blank score
    head = "target,response,keywords\n"
    for text, said in ((head + "今日は晴れです,きょうははれ,今日 晴れ\n猫,ねこ,犬\n",
                        "bad.csv:3: keyword '犬' is not said in the target '猫'"),
                       ("target,response,keywords\n晴れです,はれ,です 晴れ\n",
                        "bad.csv:2: keyword '晴れ' is not said in the target '晴れです' after"),
                       ("target,response\nあさ,あさ\n。,。\n",
                        "bad.csv:3: the target '。' has nothing to pronounce")):  # fmt: skip
        bad.write_text(text, encoding="utf-8")
        assert main(["score-typed", str(bad)]) == 2
        assert said in capsys.readouterr().err
    bad.write_text(head + "今日は晴れです,きょうははれ,今日 晴れ\n", encoding="utf-8")
    assert main(["score-typed", str(bad)]) == 0  # keywords as written or as read, in order
    assert capsys.readouterr().out.splitlines()[1].endswith(",2,2,1.0,0")
