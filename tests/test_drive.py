"""Animation methods: the Z algebra, the viseme path, the text path, Z files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from facelab.errors import StageError
from facelab.methods import METHODS
from facelab.stimuli.arkit import ARKIT_NAMES, VISEME_TARGETS, canonical_arkit_name
from facelab.stimuli.capture.measure_z import write_z
from facelab.stimuli.capture.zmatrix import load_z
from facelab.stimuli.methods import REGISTRY, DriveInput, drive
from facelab.stimuli.speech.audio import Phone
from facelab.stimuli.speech.track import VISEMES, VOWEL_VISEMES, VisemeTrack


def _track_one_hot() -> VisemeTrack:
    """Frame j (0..4) is vowel j alone at intensity 1; frame 5 is silence."""
    w = np.zeros((6, 15))
    for j, v in enumerate(VOWEL_VISEMES):
        w[j, VISEMES.index(v)] = 1.0
    w[5, 0] = 1.0
    return VisemeTrack(times=np.arange(6) / 100, weights=w)


@pytest.mark.parametrize("z_name", ["standard", "emphasized"])
@pytest.mark.parametrize("gain", [0.5, 1.0, 1.7])
def test_one_hot_x_reproduces_z_column_times_g(z_name: str, gain: float) -> None:
    out = drive("vowel_blend", DriveInput(_track_one_hot()), {"z": z_name, "gain": gain})
    z = load_z(z_name)
    assert out.names == ARKIT_NAMES and out.weights.shape == (6, 52)
    for j in range(5):
        np.testing.assert_allclose(out.weights[j], np.clip(gain * z[:, j], 0, 1))
    assert np.all(out.weights[5] == 0)  # silence: neutral face


def test_mixtures_are_linear_until_clipping() -> None:
    w = np.zeros((1, 15))
    w[0, VISEMES.index("aa")], w[0, VISEMES.index("oh")], w[0, 0] = 0.3, 0.5, 0.2
    out = drive("vowel_blend", DriveInput(VisemeTrack(np.zeros(1), w)), {"z": "standard"})
    z = load_z("standard")
    np.testing.assert_allclose(out.weights[0], 0.3 * z[:, 0] + 0.5 * z[:, 4])


def test_shipped_z_matrices_are_sensible() -> None:
    std, emp = load_z("standard"), load_z("emphasized")
    jaw = ARKIT_NAMES.index("jawOpen")
    assert np.argmax(std[jaw]) == 0  # a opens most
    assert (
        std[ARKIT_NAMES.index("mouthStretchLeft"), 1]
        > std[ARKIT_NAMES.index("mouthStretchLeft"), 2]
    )
    assert std[ARKIT_NAMES.index("mouthPucker"), 2] == std[ARKIT_NAMES.index("mouthPucker")].max()
    assert np.all(std[ARKIT_NAMES.index("mouthClose")] == 0)
    mouth = [i for i, n in enumerate(ARKIT_NAMES) if n.startswith(("jaw", "mouth"))]
    other = [i for i in range(52) if i not in mouth]
    assert emp[mouth].sum() > 1.3 * std[mouth].sum()  # larger mouth shapes
    assert emp[other].sum() > 2 * std[other].sum()  # more non-mouth activity


def test_viseme_baseline_and_text_visemes() -> None:
    track = _track_one_hot()
    out = drive("viseme_baseline", DriveInput(track), {"gain": 1.0})
    assert out.names == VISEME_TARGETS
    np.testing.assert_allclose(out.weights, track.weights)
    phones = (Phone("sil", 0, 0.01), Phone("a", 0.01, 0.04), Phone("sil", 0.04, 0.06))
    text = drive("text_visemes", DriveInput(track, phones=phones), {"smoothing_s": 0.0})
    assert text.names == VISEME_TARGETS and text.weights.shape == (6, 15)
    assert text.column("viseme_aa")[2] == 1 and text.column("viseme_aa")[5] == 0
    with pytest.raises(StageError, match="needs a phoneme timeline"):
        drive("text_visemes", DriveInput(track), {})


def test_registry_is_complete_and_params_validated() -> None:
    assert set(REGISTRY) == set(METHODS)
    with pytest.raises(StageError, match="unknown method"):
        drive("nope", DriveInput(_track_one_hot()), {})
    with pytest.raises(ValueError, match="gain"):
        drive("vowel_blend", DriveInput(_track_one_hot()), {"gain": -1})


def test_custom_z_files(tmp_path: Path) -> None:
    z = np.random.default_rng(0).uniform(0, 1, (52, 5))
    write_z(tmp_path / "z.csv", z)
    np.testing.assert_allclose(load_z("z.csv", base_dir=tmp_path), z, atol=1e-6)
    (tmp_path / "bad.csv").write_text("blendshape,a,i,u,e,o\njawOpen,1,2,3,4,5\n")
    with pytest.raises(StageError, match="missing ARKit rows"):
        load_z("bad.csv", base_dir=tmp_path)
    with pytest.raises(StageError, match=r"Z matrix .*none\.csv: file not found"):
        load_z("none.csv", base_dir=tmp_path)
    good = (tmp_path / "z.csv").read_text().splitlines()
    row = next(i for i, line in enumerate(good) if line.startswith("jawOpen,"))
    # each was accepted (NaN, a repeated row, a long row) or a TypeError traceback (short row)
    cases = {
        "nan": ("jawOpen,nan,0.5,0.5,0.5,0.5", "row jawOpen, column a: nan is outside"),
        "short": ("jawOpen,0.5", r"short\.csv:\d+: 2 fields, the header has 6"),
        "long": ("jawOpen,0.5,0.5,0.5,0.5,0.5,0.5", r"long\.csv:\d+: 7 fields, the header has 6"),
        "twice": (good[row] + "\n" + good[row], "rows given twice: jawOpen"),
    }
    for name, (line, message) in cases.items():
        (tmp_path / f"{name}.csv").write_text("\n".join([*good[:row], line, *good[row + 1 :]]))
        with pytest.raises(StageError, match=message):
            load_z(f"{name}.csv", base_dir=tmp_path)


@pytest.mark.parametrize(
    ("given", "canon"),
    [
        ("jawOpen", "jawOpen"),
        ("JawOpen", "jawOpen"),
        ("mouthSmile_L", "mouthSmileLeft"),
        ("MOUTHSMILERIGHT", "mouthSmileRight"),
        ("eyeBlinkL", "eyeBlinkLeft"),
        ("viseme_O", "viseme_oh"),
        ("viseme_aa", "viseme_aa"),
        ("browInnerUp", "browInnerUp"),
        ("nonsense", None),
    ],
)
def test_target_name_matching(given: str, canon: str | None) -> None:
    assert canonical_arkit_name(given) == canon
