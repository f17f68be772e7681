"""Impression stimuli (seed 001): samples, the seed's model and its variants, levels, easing,
clips - checked against the synthetic database's known true direction."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from facelab.errors import StageError
from facelab.experiment.cli import main
from facelab.stimuli.arkit import ARKIT_NAMES
from facelab.stimuli.impression.model import (
    ImpressionModel,
    ease,
    envelope,
    fit_impression,
    read_arkit_samples,
    read_vertex_samples,
    speech_basis,
)
from facelab.stimuli.impression.synth import (
    TRUE_DIRECTION,
    simulate_validation,
    synthetic_samples,
)
from tests.conftest import ROOT


@pytest.fixture(scope="module")
def synth_csv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("imp") / "synth.csv"
    synthetic_samples(people=40, rng=np.random.default_rng(1)).to_csv(path, index=False)
    return path


@pytest.fixture(scope="module")
def samples(synth_csv: Path):
    return read_arkit_samples(synth_csv)


def test_samples_are_displacements_from_each_persons_neutral(samples, synth_csv: Path) -> None:
    raw = pd.read_csv(synth_csv)
    assert samples.s.shape == (40 * 7, 52)
    assert set(samples.labels) == {"friendly", "friendly_rating"}
    row = raw[(raw.person == "synth05") & (raw.expression == "open_smile")][list(ARKIT_NAMES)]
    neutral = raw[(raw.person == "synth05") & (raw.expression == "neutral")][list(ARKIT_NAMES)]
    i = np.nonzero((samples.persons == "synth05") & (samples.expressions == "open_smile"))[0][0]
    np.testing.assert_allclose(samples.s[i], row.to_numpy()[0] - neutral.to_numpy()[0])


def test_without_a_neutral_row_the_rest_pose_is_the_neutral(
    tmp_path: Path, synth_csv: Path
) -> None:
    raw = pd.read_csv(synth_csv)
    raw[raw.expression != "neutral"].to_csv(tmp_path / "s.csv", index=False)
    s = read_arkit_samples(tmp_path / "s.csv")
    first = raw[raw.expression != "neutral"].iloc[0][list(ARKIT_NAMES)].to_numpy(float)
    np.testing.assert_allclose(s.s[0], first)


@pytest.mark.parametrize(
    ("method", "label", "min_cos"),
    [
        ("svm", "friendly", 0.85),
        ("mean_diff", "friendly", 0.85),
        ("ridge", "friendly_rating", 0.85),
    ],
)
def test_fitted_direction_recovers_the_true_one(
    samples, method: str, label: str, min_cos: float
) -> None:
    model = fit_impression(
        samples, label=label, method=method, expressions=["open_smile", "closed_smile"]
    )
    for e, m in model.expressions.items():
        assert np.linalg.norm(m.direction) == pytest.approx(1.0)
        assert m.direction @ TRUE_DIRECTION > min_cos, e
        assert len(m.basis) <= m.n - 1
        np.testing.assert_allclose(m.basis @ m.basis.T, np.eye(len(m.basis)), atol=1e-9)
        # δ: one SD of the training projections on the direction
        proj = (samples.s[samples.expressions == e] - m.mean) @ m.direction
        assert m.delta == pytest.approx(np.std(proj, ddof=1))
        key = "r2" if method == "ridge" else "accuracy"
        assert m.cv["scheme"] == "leave-one-person-out" and m.cv["folds"] == 40
        assert m.cv[key] > (0.2 if method == "ridge" else 0.65)


def test_pca_follows_the_seed_and_k_is_bounded(samples) -> None:
    model = fit_impression(samples, label="friendly", k=7, expressions=["open_smile"])
    m = model.expressions["open_smile"]
    s = samples.s[samples.expressions == "open_smile"]
    np.testing.assert_allclose(m.mean, s.mean(axis=0))  # s̄
    f = m.project(s)  # eq. 1
    np.testing.assert_allclose(f, (s - s.mean(axis=0)) @ m.basis.T)
    assert m.explained[0] >= m.explained[-1] and len(m.basis) == 7
    with pytest.raises(StageError, match="K = 40"):
        fit_impression(samples, label="friendly", k=40, expressions=["open_smile"])


def test_levels_move_along_the_direction_and_clipping_is_reported(samples) -> None:
    model = fit_impression(samples, label="friendly", expressions=["open_smile"])
    m = model.expressions["open_smile"]
    env = np.array([0.0, 1.0])
    faces = {q: model.frames("open_smile", q, env) for q in (0.0, 0.5, 1.0)}
    for q, (fr, info) in faces.items():
        assert info["q_realised"] == pytest.approx(q, abs=1e-6)
        step = fr[-1] - faces[0.0][0][-1]
        np.testing.assert_allclose(step, q * m.delta * m.direction, atol=1e-9)
    dv = [faces[q][1]["decision_value"] for q in (0.0, 0.5, 1.0)]
    assert dv[0] < dv[1] < dv[2]  # the classifier sees more of the impression
    # a huge level clips ARKit coefficients to [0, 1]: the realised level falls short
    fr, info = model.frames("open_smile", 40.0, env)
    assert fr.min() >= 0 and fr.max() <= 1
    assert info["clipped_channels"] > 0 and info["q_realised"] < 40


def test_orthogonal_to_speech_leaves_the_vowel_shapes_alone(samples) -> None:
    model = fit_impression(
        samples, label="friendly", expressions=["open_smile"], orthogonal_to_speech=True
    )
    d = model.expressions["open_smile"].direction
    basis = speech_basis()
    assert np.abs(basis @ d).max() < 1e-9
    from facelab.stimuli.capture.zmatrix import load_z

    assert np.abs(load_z("standard").T @ d).max() < 1e-9  # every vowel column


def test_easing_is_normalised_and_the_envelope_has_its_phases() -> None:
    x = np.linspace(0, 1, 101)
    for kind in ("sigmoid", "linear", "smoothstep"):
        e = ease(x, kind=kind)
        assert e[0] == pytest.approx(0) and e[-1] == pytest.approx(1)
        assert np.all(np.diff(e) >= -1e-12)
    # eq. 4 on [-1, 1], rescaled: the seed's sigmoid with k = 5
    sig = 1 / (1 + np.exp(-5 * (2 * x - 1)))
    np.testing.assert_allclose(ease(x), (sig - sig[0]) / (sig[-1] - sig[0]))
    env = envelope(fps=10, onset_s=1.0, hold_s=0.5, offset_s=1.0, lead_s=0.3)
    assert len(env) == round(2.8 * 10) + 1
    assert env[0] == 0 and env[-1] == pytest.approx(0) and env[13:19].min() == pytest.approx(1)
    with pytest.raises(StageError):
        ease(x, kind="bounce")


def test_model_json_round_trips_with_named_directions(samples, tmp_path: Path) -> None:
    model = fit_impression(samples, label="friendly", expressions=["open_smile", "closed_smile"])
    data = model.to_json()
    assert set(data["directions"]["open_smile"]) == set(ARKIT_NAMES)
    path = tmp_path / "m.json"
    path.write_text(json.dumps(data))
    back = ImpressionModel.load(path)
    env = np.array([0.0, 1.0])
    np.testing.assert_allclose(
        back.frames("closed_smile", 0.7, env)[0],
        model.frames("closed_smile", 0.7, env)[0],
        atol=1e-7,
    )
    assert back.data_sha256 == samples.sha256
    with pytest.raises(StageError, match="no expression"):
        back.model("grimace")


def _first(data: dict, key: str) -> dict:
    return next(iter(data[key].values()))


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: d.pop("space"), "'space' is None; expected 'arkit' or 'vertices'"),
        (lambda d: d["delta"].update({k: float("nan") for k in d["delta"]}), "delta holds non"),
        (lambda d: d["delta"].update({k: 0.0 for k in d["delta"]}), "delta is 0.0; expected > 0"),
        (lambda d: _first(d, "pca")["basis"].pop(), r"explained has shape \(\d+,\); expected"),
        (lambda d: _first(d, "pca").update(w=None), "w has shape"),
        (lambda d: _first(d, "pca").update(coef=[1.0]), "coef has shape"),
        (lambda d: _first(d, "directions").update(jawOpen=5.0), "not a unit vector"),
    ],
)
def test_a_broken_model_file_is_named_not_rendered(tmp_path: Path, mutate, message: str) -> None:
    """Found by mutating the shipped model: NaN or mis-shaped arrays rendered NaN faces or
    failed inside numpy (30 of 500 mutations silent, 5 tracebacks)."""
    data = json.loads((ROOT / "protocols" / "horii_friendly_model.json").read_text())
    mutate(data)
    path = tmp_path / "model.json"
    path.write_text(json.dumps(data, allow_nan=True))
    with pytest.raises(StageError, match=message) as err:
        ImpressionModel.load(path)
    assert str(path) in str(err.value)


def test_simulated_validation_ratings_rise_with_the_level(samples) -> None:
    from facelab.analysis.graded import graded_lmm

    model = fit_impression(samples, label="friendly", expressions=["open_smile"])
    ratings = simulate_validation(
        model, expression="open_smile", levels=[0, 0.5, 1], raters=24, rng=np.random.default_rng(3)
    )
    means = ratings.groupby("q").rating.mean()
    assert means[0] < means[0.5] < means[1]
    fit = graded_lmm(ratings.rename(columns={"rater": "participant", "q": "level"}), dv="rating")
    assert fit["slope"].iloc[0] > 0 and fit["p"].iloc[0] < 0.05


def test_bad_sample_files_are_named_errors(tmp_path: Path, synth_csv: Path) -> None:
    raw = pd.read_csv(synth_csv)
    bad = raw.copy()
    bad.loc[3, "jawOpen"] = 1.7
    bad.to_csv(tmp_path / "range.csv", index=False)
    with pytest.raises(StageError, match=r"range\.csv:5: column 'jawOpen'"):
        read_arkit_samples(tmp_path / "range.csv")
    raw.drop(columns=["tongueOut"]).to_csv(tmp_path / "cols.csv", index=False)
    with pytest.raises(StageError, match="missing ARKit columns tongueOut"):
        read_arkit_samples(tmp_path / "cols.csv")
    s = read_arkit_samples(synth_csv)
    with pytest.raises(StageError, match="no label column 'kindness'"):
        fit_impression(s, label="kindness")
    with pytest.raises(StageError, match="ridge needs numeric"):
        fit_impression(s, label="friendly", method="ridge")


def test_vertex_space_database_of_meshes(tmp_path: Path) -> None:
    """Meshes of one topology per person and expression (OBJ), displacements from each
    person's neutral; the direction is recovered in vertex space."""
    rng = np.random.default_rng(5)
    grid = np.stack(np.meshgrid(np.linspace(-1, 1, 8), np.linspace(-1, 1, 8)), -1).reshape(-1, 2)
    base = np.column_stack([grid * 0.05, np.zeros(len(grid))])
    faces = [[i * 8 + j, i * 8 + j + 1, (i + 1) * 8 + j] for i in range(7) for j in range(7)]
    smile = np.zeros_like(base)
    smile[:, 1] = 0.01 * np.exp(-np.sum(grid**2, axis=1))
    truth = np.zeros_like(base)
    truth[:, 2] = 0.004 * grid[:, 0] ** 2
    truth_unit = truth.reshape(-1) / np.linalg.norm(truth)
    rows = []
    for p in range(12):
        person = base + rng.normal(0, 0.001, base.shape)
        for expr, shape in (("neutral", 0 * smile), ("smile", smile)):
            z = rng.normal()
            v = person + shape * rng.normal(1, 0.1) + (z * truth if expr != "neutral" else 0)
            name = f"p{p}_{expr}.obj"
            lines = [f"v {a:.6f} {b:.6f} {c:.6f}" for a, b, c in v]
            lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
            (tmp_path / name).write_text("\n".join(lines) + "\n")
            rows.append(
                {
                    "person": f"p{p}",
                    "expression": expr,
                    "warm": "high" if z > 0 else "low",
                    "file": name,
                }
            )
    with open(tmp_path / "index.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=["person", "expression", "warm", "file"])
        writer.writeheader()
        writer.writerows(rows)
    s = read_vertex_samples(tmp_path / "index.csv")
    assert s.space == "vertices" and s.s.shape == (12, 64 * 3) and s.faces is not None
    model = fit_impression(s, label="warm", method="mean_diff")
    assert model.expressions["smile"].direction @ truth_unit > 0.9
    with pytest.raises(StageError, match="orthogonal_to_speech needs ARKit"):
        fit_impression(s, label="warm", orthogonal_to_speech=True)


def test_impression_commands(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    samples_csv = tmp_path / "synth.csv"
    assert main(["impression", "synth", "--people", "20", "--out", str(samples_csv)]) == 0
    truth = json.loads(samples_csv.with_suffix(".truth.json").read_text())
    assert truth["synthetic"] is True
    model = tmp_path / "model.json"
    argv = [
        "impression",
        "fit",
        str(samples_csv),
        "--label",
        "friendly",
        "--expression",
        "open_smile",
        "--out",
        str(model),
    ]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "open_smile" in out and "accuracy" in out
    data = json.loads(model.read_text())
    assert set(data["directions"]) == {"open_smile"} and data["delta"]["open_smile"] > 0
    assert main(argv) == 2  # refuses to overwrite without --force
    assert (
        main(
            [
                "impression",
                "fit",
                str(samples_csv),
                "--label",
                "nope",
                "--out",
                str(tmp_path / "x.json"),
            ]
        )
        == 2
    )


@pytest.mark.slow
def test_impression_render_writes_one_clip_per_level(
    tmp_path: Path, synth_csv: Path, capsys: pytest.CaptureFixture
) -> None:
    from facelab.stimuli.render.clip import probe

    model = tmp_path / "model.json"
    assert (
        main(
            [
                "impression",
                "fit",
                str(synth_csv),
                "--label",
                "friendly",
                "--expression",
                "open_smile",
                "--out",
                str(model),
            ]
        )
        == 0
    )
    out = tmp_path / "clips"
    argv = ["impression", "render", str(model), "--expression", "open_smile", "--levels", "0",
            "0.5", "1", "--size", "160x120", "--msaa", "1", "--hold-s", "0.4",
            "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    rows = list(csv.DictReader((out / "clips.csv").read_text().splitlines()))
    assert [r["path"] for r in rows] == [
        "open_smile__q0.mp4",
        "open_smile__q0.5.mp4",
        "open_smile__q1.mp4",
    ]
    assert [float(r["q_realised"]) for r in rows] == pytest.approx([0, 0.5, 1], abs=1e-6)
    dv = [float(r["decision_value"]) for r in rows]
    assert dv == sorted(dv)
    for r in rows:
        video = next(s for s in probe(out / r["path"])["streams"] if s["codec_type"] == "video")
        assert int(video["nb_read_frames"]) == round((0.3 + 0.6 + 0.4 + 0.6) * 30) + 1
    assert (out / "contact_open_smile.png").stat().st_size > 10_000
    assert (out / "channels_open_smile.png").is_file()
    checks = list(csv.DictReader((out / "stimulus_checks.csv").read_text().splitlines()))
    measured = {(r["clip"], r["measure"]): r for r in checks}
    for level in ("0", "0.5", "1"):  # the tracker saw each level's face
        assert measured[f"open_smile__q{level}", "detection_median"]["passed"] == "true"
        assert measured[f"open_smile__q{level}", "realised_level"]["passed"] == "true"
    steps = [r for r in checks if r["measure"].startswith("step_difference:open_smile")]
    assert len(steps) == 2 and all(float(r["value"]) > 0 for r in steps)
    # a second render into the folder keeps the other clips' rows, replaces re-rendered ones
    # and forgets a clip whose file was deleted
    (out / "open_smile__q0.mp4").unlink()
    argv[argv.index("--levels") + 1 : argv.index("--size")] = ["1", "-1"]
    assert main(argv) == 0
    said = capsys.readouterr().out
    assert "kept 1 clip(s) rendered earlier" in said
    assert "whose file is gone: open_smile__q0" in said
    rows = list(csv.DictReader((out / "clips.csv").read_text().splitlines()))
    assert [r["clip_id"] for r in rows] == ["open_smile__q0.5", "open_smile__q1", "open_smile__q-1"]
    assert all((out / r["path"]).is_file() for r in rows)
    assert {r["label"] for r in rows} == {"friendly"} and len(
        {r["model_sha256"] for r in rows}
    ) == 1
    assert "another model_sha256" not in said


# --------------------------------------------------------------------------- in protocols


@pytest.mark.slow
def test_shipped_impression_protocols_simulate_and_analyse(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from facelab.analysis import figures
    from facelab.resources import protocol_path

    drawn: dict[str, list[str]] = {}
    real = figures.rating_figure

    def spy(cells: pd.DataFrame, **kw: object) -> object:
        drawn[str(kw["title"])] = list(kw["conditions"])  # type: ignore[call-overload]
        return real(cells, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(figures, "rating_figure", spy)

    for name, expect in (
        ("horii_impression", ["trend_contrast.csv", "graded_lmm.csv", "rm_anova.csv"]),
        ("horii_impression_2afc", ["psychometric_fits.csv"]),
    ):
        path = protocol_path(name)
        assert main(["validate", str(path)]) == 0
        results, out = tmp_path / name / "results", tmp_path / name / "analysis"
        argv = [
            "simulate",
            str(path),
            "--participants",
            "8",
            "--sim-seed",
            "2",
            "--results",
            str(results),
        ]
        assert main(argv) == 0
        assert (
            main(
                [
                    "analyze",
                    str(path),
                    str(results),
                    "--force",
                    "--out",
                    str(out),
                    "--bootstrap",
                    "30",
                ]
            )
            == 0
        )
        for file in expect:
            assert (out / file).exists(), file
    # each smile's figure shows that smile's three levels, not all six conditions
    closed = [c for t, c in drawn.items() if t.endswith("[closed]")]
    assert closed and all(c == ["closed_q0", "closed_q05", "closed_q1"] for c in closed)
    trend = pd.read_csv(tmp_path / "horii_impression" / "analysis" / "trend_contrast.csv")
    # one trend per item and smile (the blocks keep open and closed smiles apart)
    assert set(zip(trend["item"], trend["stimulus_set"], strict=True)) == {
        ("friendly", "open"), ("friendly", "closed"), ("natural", "open"), ("natural", "closed"),
    }  # fmt: skip
    assert (trend["slope"] > 0).all()


def _horii(tmp_path: Path, edit=lambda s: s) -> Path:
    from facelab.resources import protocol_path

    src = protocol_path("horii_impression")
    (tmp_path / "horii_friendly_model.json").write_bytes(
        (src.parent / "horii_friendly_model.json").read_bytes()
    )
    path = tmp_path / "horii.yaml"
    path.write_text(edit(src.read_text(encoding="utf-8")), encoding="utf-8")
    return path


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            "expression: open_smile, q: 0.5}",
            "expression: grimace, q: 0.5}",
            "no expression 'grimace'",
        ),
        (
            "model: horii_friendly_model.json, expression: open_smile, q: 0.0}",
            "model: nowhere.json, expression: open_smile, q: 0.0}",
            "nowhere.json was not found",
        ),
        ("q: 1.0}, level: 1.0}", "q: 9.0}, level: 1.0}", "less than or equal to 5"),
        ("{id: smile, silence_s: 2.7}", "{id: smile, silence_s: 2.7, text: あ}", "exactly one of"),
    ],
)
def test_impression_conditions_are_checked(
    tmp_path: Path, old: str, new: str, message: str
) -> None:
    from facelab.errors import ProtocolError
    from facelab.protocol import load_protocol

    path = _horii(tmp_path, lambda s: s.replace(old, new, 1))
    with pytest.raises(ProtocolError, match=message):
        load_protocol(path)


def test_impression_method_on_a_speech_track_adds_the_expression(samples, tmp_path: Path) -> None:
    from facelab.methods import ImpressionParams, VowelBlendParams
    from facelab.stimuli.methods import DriveInput, drive
    from facelab.stimuli.speech.track import VISEMES, VisemeTrack

    model = fit_impression(samples, label="friendly", expressions=["open_smile"])
    (tmp_path / "m.json").write_text(json.dumps(model.to_json()))
    times = np.arange(0, 3.0, 0.01)
    weights = np.zeros((len(times), 15))
    weights[:, VISEMES.index("aa")] = 0.5 * (np.sin(times * 9) > 0)
    track = VisemeTrack(times, weights, VISEMES)
    inp = DriveInput(track=track, base_dir=tmp_path)
    silent = drive(
        "impression", inp, ImpressionParams(model="m.json", expression="open_smile", q=1.0)
    )
    t_peak = int(np.argmin(np.abs(times - 1.5)))
    assert silent.notes["q_intended"] == 1.0 and silent.weights[0].max() == 0.0
    assert silent.weights[t_peak].max() > 0.3  # held in the middle (hold fills the stimulus)
    both = drive("impression", inp, ImpressionParams(model="m.json", expression="open_smile", q=1.0,
                                            speech=VowelBlendParams(z="standard")))  # fmt: skip
    speech = drive("vowel_blend", inp, VowelBlendParams(z="standard"))
    jaw = both.names.index("jawOpen")
    expected = np.clip(silent.column("jawOpen") + speech.column("jawOpen"), 0, 1)
    np.testing.assert_allclose(both.weights[:, jaw], expected, atol=1e-9)


@pytest.mark.slow
def test_impression_protocol_renders_with_levels_in_the_clip_metadata(tmp_path: Path) -> None:
    path = _horii(tmp_path)
    out = tmp_path / "clips"
    argv = ["render", str(path), "--out", str(out), "--size", "160x120", "--fps", "10", "--quiet"]
    assert main(argv) == 0
    rows = list(csv.DictReader((out / "clips.csv").read_text(encoding="utf-8").splitlines()))
    assert len(rows) == 6
    notes = {
        r["condition"]: json.loads((out / f"{r['clip_id']}.json").read_text())["track_notes"]
        for r in rows
    }
    for cond in ("open", "closed"):
        q = [notes[f"{cond}_q{s}"]["q_intended"] for s in ("0", "05", "1")]
        dv = [notes[f"{cond}_q{s}"]["decision_value"] for s in ("0", "05", "1")]
        assert q == [0.0, 0.5, 1.0] and dv == sorted(dv)


def test_face_captures_reduce_to_one_sample_row_per_expression(tmp_path: Path) -> None:
    """Live Link Face CSVs (Timecode at 60 fps) -> the samples CSV `impression fit` reads."""
    header = ["Timecode", "BlendShapeCount", *[n[0].upper() + n[1:] for n in ARKIT_NAMES]]
    rows = []
    for f in range(120):  # 2 s; jawOpen 0.2 before 1 s, 0.6 after
        jaw = 0.2 if f < 60 else 0.6
        values = [jaw if n == "jawOpen" else 0.0 for n in ARKIT_NAMES]
        rows.append([f"10:00:{f // 60:02d}:{f % 60:02d}.000", "52", *values])
    with open(tmp_path / "cap.csv", "w", newline="") as fh:
        csv.writer(fh).writerows([header, *rows])
    (tmp_path / "index.csv").write_text(
        "person,expression,warm,capture,time_s\np1,neutral,,cap.csv,0.2\np1,open,high,cap.csv,1.2\n"
    )
    out = tmp_path / "samples.csv"
    assert main(["impression", "samples", str(tmp_path / "index.csv"), "--out", str(out)]) == 0
    s = read_arkit_samples(out)
    assert list(s.expressions) == ["open"] and s.labels["warm"][0] == "high"
    j = ARKIT_NAMES.index("jawOpen")
    assert s.s[0, j] == pytest.approx(0.4)  # 0.6 in the window minus the neutral's 0.2
    (tmp_path / "late.csv").write_text("person,expression,capture,time_s\np1,open,cap.csv,9\n")
    assert (
        main(
            ["impression", "samples", str(tmp_path / "late.csv"), "--out", str(tmp_path / "x.csv")]
        )
        == 2
    )


def test_a_step_gives_delta_a_visible_meaning(samples, tmp_path: Path) -> None:
    """--step: q = 1 moves the channel that moves most by exactly the step; the clip's facts
    report the realised change; levels closer than VISIBLE_CHANGE are named by validate."""
    from facelab.stimuli.impression.model import VISIBLE_CHANGE

    sd = fit_impression(samples, label="friendly", expressions=["open_smile"])
    step = fit_impression(samples, label="friendly", expressions=["open_smile"], step=0.25)
    assert np.allclose(sd.model("open_smile").direction, step.model("open_smile").direction)
    zero = np.zeros(52)
    change, where = step.level_change("open_smile", 1.0, neutral=zero)
    assert change == pytest.approx(0.25, abs=1e-9) and where.startswith("cheekSquint")
    half, _ = step.level_change("open_smile", 1.0, q_from=0.5, neutral=zero)
    assert half == pytest.approx(0.125, abs=1e-9)
    assert sd.level_change("open_smile", 1.0, neutral=zero)[0] < VISIBLE_CHANGE["arkit"]
    _, info = step.frames("open_smile", 1.0, np.ones(3), neutral=zero)
    assert (
        info["change_from_q0"] == pytest.approx(0.25) and info["change_unit"] == "ARKit coefficient"
    )
    back = ImpressionModel.from_json(json.loads(json.dumps(step.to_json())))
    assert (
        back.step == 0.25 and "moves the largest channel by 0.25" in step.to_json()["delta_units"]
    )


def test_validate_names_impression_levels_too_close_to_see(
    samples, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    shipped = (ROOT / "protocols" / "horii_impression.yaml").read_text(encoding="utf-8")
    (tmp_path / "p.yaml").write_text(shipped, encoding="utf-8")
    smiles = ["open_smile", "closed_smile"]
    for name, model in (
        ("sd", fit_impression(samples, label="friendly", expressions=smiles)),
        ("step", fit_impression(samples, label="friendly", expressions=smiles, step=0.25)),
    ):
        (tmp_path / "horii_friendly_model.json").write_text(json.dumps(model.to_json()))
        assert main(["validate", str(tmp_path / "p.yaml")]) == 0
        warnings = [ln for ln in capsys.readouterr().out.splitlines() if "warning:" in ln]
        if name == "sd":  # one SD moves the face by ~0.08 at q = 1: each half step hidden
            assert len(warnings) == 4 and all(
                "below the 0.1 taken as visible" in w for w in warnings
            )
        else:
            assert warnings == []


def test_headroom_and_clipping_eat_levels_are_said(samples) -> None:
    """The headroom is the level where the first (moving) channel reaches 0 or 1; the fit's
    lines say when q = 1 is too small to see or clipped, with a --step range; a clip whose
    realised level falls short of the intended one gets a warning row naming the clipping."""
    from facelab.stimuli.checks.clip_set_checks import impression_rows
    from facelab.stimuli.impression.model import level_visibility

    sd = fit_impression(samples, label="friendly", expressions=["open_smile"])
    big = fit_impression(samples, label="friendly", expressions=["open_smile"], step=0.5)
    room, channel = big.headroom("open_smile")
    assert 0 < room < 1 and channel in ARKIT_NAMES
    _, clipped = big.frames("open_smile", min(room, 1.0) * 0.999, np.ones(2))
    assert clipped["clipped_channels"] == 0  # below the headroom nothing clips
    _, over = big.frames("open_smile", 1.0, np.ones(2))
    assert over["clipped_channels"] > 0 and over["q_realised"] < 1
    assert sd.headroom("open_smile")[0] == pytest.approx(room * 0.5 / np.abs(
        sd.model("open_smile").delta * sd.model("open_smile").direction).max())
    said = "\n".join(level_visibility(sd))
    assert "will look alike; refit with --step S" in said
    said = "\n".join(level_visibility(big))
    assert "clipping eats the levels above q = " in said
    _, far = big.frames("open_smile", 2.0, np.ones(2))  # twice the step: clipping eats it
    assert far["q_realised"] < 1.9
    rows = impression_rows([{"clip_id": "x__q2", **far}])
    realised = next(r for r in rows if r.measure == "realised_level")
    assert realised.passed is False and realised.severity == "warning"
    assert "clipping eats the level" in realised.note
