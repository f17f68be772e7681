"""Does the stimulus check see a recording that does not say its transcript? Prints the
README's table ("Does the recording say its transcript?").

    .venv/bin/python scripts/measure_transcript_checks.py --set held-out [--json OUT.jsonl]

Needs the natural voices (``pip install 'facelab[training]'``) and espeak-ng. Each
recording is aligned to its own words, to the two sentences nearest in length, said twice
(transcript once) and cut in half; the outcome is what ``track_source`` makes of it
(:func:`facelab.stimuli.checks.run_checks.transcript_rows`, the shipped rule) or the
aligner's own refusal. ``--set tune`` is the material the thresholds were set on;
``--set held-out`` (other sentences, held-out voices) was only measured.
"""

from __future__ import annotations

import argparse
import io
import json
import subprocess
import sys
import wave
from collections import Counter

import numpy as np

from facelab.errors import VisemeError
from facelab.protocol_model import Stimulus
from facelab.stimuli.checks.run_checks import transcript_rows
from facelab.stimuli.speech.align import align_phones
from facelab.stimuli.speech.audio import Speech, resample
from facelab.stimuli.speech.natural import NATURAL_HELDOUT, NATURAL_TRAIN, _kokoro, _speak
from facelab.stimuli.speech.tts import synthesize

RATE = 48_000
TUNE = (
    "はい。", "ありがとうございます。", "少々お待ちください。", "駅まで歩いて十分ほどです。",
    "その本は机の上に置いてあります。", "今朝は電車がとても混んでいました。",
    "来週の会議は木曜日に変更になりました。", "冷たい飲み物をお願いします。",
    "窓を開けてもいいですか。", "先生は図書館にいらっしゃいます。",
    "この道をまっすぐ行ってください。", "昨日の夜は雨が強く降りました。",
    "すみません、もう一度言ってください。", "夏休みには海へ行く予定です。",
    "新しい靴を買いに行きました。", "お昼ご飯は何にしますか。",
)  # fmt: skip
HELD_OUT = (
    "いいえ。", "おはようございます。", "はい、わかりました。すぐに行きます。",
    "明日は晴れるといいですね。", "駐車場は建物の裏にあります。",
    "この荷物を二階まで運んでください。", "彼女は毎朝公園を走っています。",
    "お茶とコーヒー、どちらがいいですか。", "その映画はとても面白かったです。",
    "会議室の鍵を忘れてしまいました。", "ここに名前を書いてください。", "弟は来年大学に入ります。",
    "そろそろ帰りましょうか。", "今日は少し寒いですね。", "電話番号を教えていただけますか。",
    "春になると桜がきれいに咲きます。",
)  # fmt: skip
ENGLISH = (
    "Good morning, how are you today?", "The meeting was moved to Thursday afternoon.",
    "Please close the window before you leave.", "I think it will rain tomorrow.",
)  # fmt: skip
#: OpenJTalk settings (speed, half-tones) standing in for voices
OPENJTALK = {"ojt": (1.0, 0.0), "ojt_fast": (1.3, 3.0), "ojt_low": (0.85, -4.0)}
SETS = {
    "tune": (TUNE, ("ojt", "ojt_fast", "espeak", *NATURAL_TRAIN)),
    "held-out": (HELD_OUT, (*NATURAL_HELDOUT, "ojt_low")),
}


def _espeak(text: str, voice: str) -> np.ndarray:
    out = subprocess.run(["espeak-ng", "-v", voice, "--stdout", text], capture_output=True,
                         check=True).stdout  # fmt: skip
    with wave.open(io.BytesIO(out)) as f:
        rate = f.getframerate()
        x = np.frombuffer(f.readframes(f.getnframes()), "<i2") / 32768.0
    return resample(np.asarray(0.7 * x / np.abs(x).max(), np.float32), rate_in=rate,
                    rate_out=RATE)  # fmt: skip


def _say(voice: str, text: str) -> np.ndarray:
    if voice in OPENJTALK:
        speed, tones = OPENJTALK[voice]
        return synthesize(text, speed=speed, pitch_halftones=tones, sample_rate=RATE).samples
    if voice == "espeak":
        return _espeak(text, "ja")
    x, rate = _speak(_kokoro(), text, voice, 1.0)
    return resample(x, rate_in=rate, rate_out=RATE)


def outcome(samples: np.ndarray, transcript: str) -> dict:
    """What ``track_source`` says of ``samples`` given ``transcript``."""
    try:
        aligned = align_phones(samples, sample_rate=RATE, text=transcript)
    except VisemeError:
        return {"outcome": "refused by the aligner"}
    stim = Stimulus(id="r", audio="r.wav", transcript=transcript)
    rows = transcript_rows(stim, Speech(samples, RATE, phones=aligned.phones),
                           kw={"clip": "r", "condition": "", "check": "track_source"})  # fmt: skip
    by = {r.measure: r for r in rows}
    verdict = ("error" if any(r.failed for r in rows)
               else "warning" if any(r.passed is False for r in rows) else "passed")  # fmt: skip
    return {"outcome": verdict, "heard": by.get("transcript_vowels_heard").value
            if "transcript_vowels_heard" in by else None,
            "order_fit": aligned.order_fit}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", choices=sorted(SETS), default="held-out")
    ap.add_argument("--json", help="write every case as a JSON line here")
    args = ap.parse_args(argv)
    sentences, voices = SETS[args.set]
    sink = open(args.json, "w", encoding="utf-8") if args.json else None  # noqa: SIM115
    counts: dict[str, Counter] = {}
    for voice in voices:
        said = {s: _say(voice, s) for s in sentences}
        for s in sentences:
            x = said[s]
            near = sorted((t for t in sentences if t != s),
                          key=lambda t: abs(len(said[t]) - len(x)))  # fmt: skip
            cases = {
                "its own words": (x, s),
                "other words, nearest in length": (x, near[0]),
                "other words, next nearest": (x, near[1]),
                "the words said twice, transcript once": (
                    np.concatenate([x, np.zeros(RATE // 2, np.float32), x]), s),
                "the first half of the words": (x[: len(x) // 2], s),
            }  # fmt: skip
            for kind, (samples, text) in cases.items():
                got = outcome(samples, text)
                counts.setdefault(kind, Counter())[got["outcome"]] += 1
                if sink:
                    line = {"voice": voice, "said": s, "case": kind, "transcript": text, **got}
                    sink.write(json.dumps(line, ensure_ascii=False) + "\n")
    for e in ENGLISH if args.set == "held-out" else ():
        x = _espeak(e, "en")
        text = min(sentences, key=lambda t: abs(len(_say("ojt", t)) - len(x)))
        got = outcome(x, text)
        counts.setdefault("English, a Japanese transcript", Counter())[got["outcome"]] += 1
    cols = ("error", "refused by the aligner", "warning", "passed")
    print("| recording and transcript | " + " | ".join(cols) + " |")
    for kind, c in counts.items():
        print(f"| {kind} ({sum(c.values())}) | " + " | ".join(str(c[k]) for k in cols) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
