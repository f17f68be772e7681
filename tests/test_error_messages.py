"""Every reader's refusal names the file (and the line or key) and says in words what was
expected - never an exception class name, a library's message or a traceback (issue 34.6).
Each reader is fed what people feed it by mistake: a binary file renamed, a truncated file,
a cell of the wrong type."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import pytest

from facelab.experiment.cli import main
from facelab.resources import package_file, protocol_path

JPEG = b"\xff\xd8\xff\xe0\x00\x10JFIF\x00\x01\x01" + bytes(600)
#: what a message may not contain: a Python exception class, a traceback, errno-speak
LEAKS = re.compile(r"\b[A-Z][A-Za-z]*(Error|Exception)\b|Traceback|Errno|codec can't")


def _study_with_z(tmp: Path) -> list[str]:
    text = protocol_path("kato2021").read_text(encoding="utf-8")
    text = text.replace("params: {z: standard, gain: 1.0}", "params: {z: z.csv, gain: 1.0}", 1)
    (tmp / "study.yaml").write_text(text, encoding="utf-8")
    return ["validate", str(tmp / "study.yaml")]


def _study_with_audio(tmp: Path) -> list[str]:
    text = protocol_path("kato2021").read_text(encoding="utf-8")
    text = text.replace("text: あ。い。う。え。お。", "audio: vowels.wav", 1)
    (tmp / "study.yaml").write_text(text, encoding="utf-8")
    return ["validate", str(tmp / "study.yaml")]


def _good_z(tmp: Path) -> str:
    return package_file("facelab.stimuli", "data", "z_standard.csv").read_text(encoding="utf-8")


def _good_wav(tmp: Path) -> bytes:
    import soundfile as sf

    from facelab.stimuli.speech.tts import synthesize

    speech = synthesize("あ。い。う。え。お。", sample_rate=16_000)  # a tone is refused: not speech
    sf.write(tmp / "tmp.wav", speech.samples, 16_000)
    return (tmp / "tmp.wav").read_bytes()


def _good_annotations(tmp: Path) -> str:
    rows = ["emotion,layer,behaviour,start_s,end_s"]
    for emotion in ("joy", "anger"):
        rows += [f"{emotion},posture,upright,0.0,4.0", f"{emotion},gesture,nod,1.0,1.5"]
    return "\n".join(rows) + "\n"


def _glb(tmp: Path) -> bytes:
    out = tmp / "sample.glb"
    assert main(["avatar", "sample", "--kind", "rpm", "--out", str(out)]) == 0
    return out.read_bytes()


def _good_samples(tmp: Path) -> str:
    assert main(["impression", "synth", "--people", "6", "--out", str(tmp / "s0.csv")]) == 0
    return (tmp / "s0.csv").read_text(encoding="utf-8")


def _good_gltf(tmp: Path) -> str:
    assert main(["avatar", "sample", "--kind", "rpm", "--out", str(tmp / "s.gltf")]) == 0
    return (tmp / "s.gltf").read_text(encoding="utf-8")


def _good_protocol(tmp: Path) -> str:
    return protocol_path("kato2021").read_text(encoding="utf-8")


def _fit_annotations(tmp: Path) -> list[str]:
    return ["behaviour", "fit", str(tmp / "ann.csv"), "--out", str(tmp / "lib.json")]


def _fit_samples(tmp: Path) -> list[str]:
    out = str(tmp / "m.json")
    return ["impression", "fit", str(tmp / "samples.csv"), "--label", "friendly", "--out", out]


def _validate(name: str) -> Callable[[Path], list[str]]:
    return lambda tmp: ["validate", str(tmp / name)]


def _inspect(name: str) -> Callable[[Path], list[str]]:
    return lambda tmp: ["avatar", "inspect", str(tmp / name)]


# reader -> (file it reads, argv that reads it, a good file's bytes or text)
READERS: dict[str, tuple[str, Callable[[Path], list[str]], Callable[[Path], bytes | str]]] = {
    "z matrix (validate)": ("z.csv", _study_with_z, _good_z),
    "audio (validate)": ("vowels.wav", _study_with_audio, _good_wav),
    "annotations (behaviour fit)": ("ann.csv", _fit_annotations, _good_annotations),
    "samples (impression fit)": ("samples.csv", _fit_samples, _good_samples),
    "glb avatar (avatar inspect)": ("a.glb", _inspect("a.glb"), _glb),
    "gltf avatar (avatar inspect)": ("a.gltf", _inspect("a.gltf"), _good_gltf),
    "protocol (validate)": ("p.yaml", _validate("p.yaml"), _good_protocol),
}
#: binary formats have no cells to give a wrong type
BINARY = {"audio (validate)", "glb avatar (avatar inspect)"}
CASES = [
    (reader, damage)
    for reader in sorted(READERS)
    for damage in ("renamed binary", "truncated", "wrong-typed cell")
    if not (damage == "wrong-typed cell" and reader in BINARY)
]


def _truncate(good: bytes | str) -> bytes | str:
    return good[: max(1, len(good) // 3)]


def _wrong_cell(name: str, good: bytes | str) -> bytes | str | None:
    """The good file with one value of the wrong type (None: the format has no cells)."""
    if isinstance(good, bytes):
        return None
    if name.startswith("z matrix"):
        return good.replace("\njawOpen,", "\njawOpen,abc,", 1).replace("abc,0", "abc", 1)
    if name.startswith("annotations"):
        return good.replace(",1.0,1.5", ",soon,1.5", 1)
    if name.startswith("samples"):
        lines = good.splitlines()
        cells = lines[1].split(",")
        cells[-1] = "lots"
        return "\n".join([lines[0], ",".join(cells), *lines[2:]]) + "\n"
    if name.startswith("protocol"):
        return good.replace("gain: 1.0", "gain: loud", 1)
    if name.startswith("gltf"):  # an accessor's count as a word: valid JSON, wrong type
        return re.sub(r'"count"\s*:\s*\d+', '"count": "many"', good, count=1)
    return None


@pytest.mark.parametrize(("reader", "damage"), CASES)
def test_a_damaged_file_is_named_in_words(
    reader: str, damage: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    name, argv_of, good_of = READERS[reader]
    good = good_of(tmp_path)
    bad = {"renamed binary": JPEG, "truncated": _truncate(good)}.get(damage)
    if damage == "wrong-typed cell":
        bad = _wrong_cell(reader, good)
        assert bad is not None and bad != good
    target = tmp_path / name
    target.write_bytes(bad) if isinstance(bad, bytes) else target.write_text(bad, "utf-8")
    capsys.readouterr()
    try:
        code = main(argv_of(tmp_path))
    except SystemExit as exc:  # argparse-level refusals
        code = int(exc.code or 0)
    err = capsys.readouterr().err
    assert code == 2, (code, err)
    assert name in err, err  # the file is named
    assert not LEAKS.search(err), err
