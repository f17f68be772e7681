"""A new animation method is one object registered once (issue 31.1): this file defines a toy
method - the jaw follows the vowel あ, scaled by a parameter - registers it, and a protocol
that names it validates, checks its parameters with the file's line, reports how it plays on
the default head, and renders. Nothing outside this file knows the method's name."""

from __future__ import annotations

import csv
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import pytest
from pydantic import Field

from facelab.errors import ProtocolError
from facelab.methods import METHODS, MethodSpec, Params
from facelab.protocol import load_protocol
from facelab.stimuli.methods import REGISTRY, BlendshapeTrack, DriveInput, Method, register


class JawParams(Params):
    scale: float = Field(0.8, gt=0, le=1, description="jawOpen at full あ")


def _checks(params: JawParams, base_dir: Path) -> Iterator[tuple[tuple[str, ...], str]]:
    if params.scale > 0.95:
        yield ("params", "scale"), "a jaw opened that far looks broken; use at most 0.95"


class ToyJaw(Method[JawParams]):
    spec = MethodSpec("toy_jaw", JawParams, "jawOpen follows the vowel a", checks=_checks)

    def drive(self, inp: DriveInput, params: JawParams) -> BlendshapeTrack:
        jaw = params.scale * inp.track.vowels()[:, :1]
        return BlendshapeTrack(inp.track.times, np.clip(jaw, 0, 1), ("jawOpen",))

    def targets(self, params: JawParams, *, base_dir: Path = Path(".")) -> set[str]:
        return {"jawOpen"}

    def protocol_notes(
        self, settings: Sequence[JawParams], *, base_dir: Path, has_tasks: bool
    ) -> list[str]:
        scales = sorted({p.scale for p in settings})
        return [f"warning: toy_jaw scales {scales} are one level"] if len(scales) == 1 else []


@pytest.fixture
def toy_method() -> Iterator[Method]:
    method = register(ToyJaw())
    yield method
    del REGISTRY["toy_jaw"], METHODS["toy_jaw"]


PROTOCOL = """\
schema_version: 1
study: {id: toy, title: Toy method, participants_planned: 1}
seed: 1
conditions:
  - id: jaw
    label: {en: Jaw only}
    method: toy_jaw
    params: {scale: SCALE}
stimulus_sets:
  - id: words
    stimuli:
      - {id: a, text: あ。}
items:
  - id: natural
    question: {en: "Natural?"}
    left_anchor: {en: "not at all"}
    right_anchor: {en: "very"}
blocks:
  - {id: main, stimulus_set: words, sets: 1, presentations_per_condition: 1}
rendering: {width: 96, height: 64, fps: 15}
presentation: {language: en}
"""


def _protocol(tmp_path: Path, scale: str) -> Path:
    path = tmp_path / "toy.yaml"
    path.write_text(PROTOCOL.replace("SCALE", scale), encoding="utf-8")
    return path


def test_a_registered_method_is_validated_by_its_own_model_and_checks(
    toy_method: Method, tmp_path: Path
) -> None:
    protocol = load_protocol(_protocol(tmp_path, "0.5"))
    assert protocol.conditions[0].settings == JawParams(scale=0.5)
    with pytest.raises(ProtocolError, match=r"toy.yaml:8: conditions\[0\]\.params\.scale.*0\.95"):
        load_protocol(_protocol(tmp_path, "0.99"))
    with pytest.raises(ProtocolError, match=r"conditions\[0\]\.params\.scale"):
        load_protocol(_protocol(tmp_path, "2"))


def test_validate_prints_the_methods_own_notes_on_its_conditions(
    toy_method: Method, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A method sees all the conditions that use it (Method.protocol_notes): validate prints
    what it says, and says nothing when it is content."""
    from facelab.experiment.cli import main

    assert main(["validate", str(_protocol(tmp_path, "0.5"))]) == 0
    assert "warning: toy_jaw scales [0.5] are one level" in capsys.readouterr().out
    two = _protocol(tmp_path, "0.5").read_text(encoding="utf-8").replace(
        "stimulus_sets:",
        "  - {id: jaw2, label: {en: J2}, method: toy_jaw, params: {scale: 0.7}}\nstimulus_sets:",
    )
    (tmp_path / "two.yaml").write_text(two, encoding="utf-8")
    assert main(["validate", str(tmp_path / "two.yaml")]) == 0
    assert "toy_jaw scales" not in capsys.readouterr().out


def test_an_unregistered_method_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ProtocolError, match="unknown method 'toy_jaw'"):
        load_protocol(_protocol(tmp_path, "0.5"))


def test_avatar_inspect_asks_the_registered_method(toy_method: Method) -> None:
    from facelab.stimuli.avatar import default_head
    from facelab.stimuli.render.inspect import playability

    assert playability(default_head())["toy_jaw"] == "yes"


@pytest.mark.slow
def test_a_registered_method_renders(toy_method: Method, tmp_path: Path) -> None:
    from facelab.stimuli.render.build import build_clips

    path = _protocol(tmp_path, "0.9")
    rows = build_clips(load_protocol(path), protocol_path=path, out=tmp_path / "clips")
    assert [r["condition"] for r in rows] == ["jaw"]
    with open(tmp_path / "clips" / "clips.csv", newline="", encoding="utf-8") as fh:
        (row,) = list(csv.DictReader(fh))
    assert (tmp_path / "clips" / row["path"]).stat().st_size > 1000
    assert (int(row["width"]), int(row["height"])) == (96, 64)
