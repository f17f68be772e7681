"""Plugins from installed packages (issue 49, part 1): examples/plugin is pip-installed (into
a folder on PYTHONPATH, as a package installed beside facelab looks to Python) and its method
jaw_only is listed by ``facelab plugins``, validated with its own checks, rendered; a broken
plugin is named in words while the rest of facelab works. The facelab commands run as
subprocesses, so nothing of the plugin leaks into this test process."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.protocol_edits import kato_short, kato_vowels_only

ROOT = Path(__file__).resolve().parents[1]
FACELAB = Path(sys.executable).parent / "facelab"


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """examples/plugin installed with pip into a target folder (no network: the build
    backend, setuptools, is in facelab's environment)."""
    target = tmp_path_factory.mktemp("site")
    source = tmp_path_factory.mktemp("src") / "plugin"  # a copy: the build writes beside it
    shutil.copytree(ROOT / "examples" / "plugin", source)
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
         "--no-index", "--target", str(target), str(source)],
        check=True, capture_output=True,
    )  # fmt: skip
    return target


def _facelab(site: Path | list[Path], *args: str) -> subprocess.CompletedProcess[str]:
    paths = [site] if isinstance(site, Path) else site
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(str(p) for p in paths)}
    return subprocess.run([str(FACELAB), *args], env=env, capture_output=True, text=True,
                          timeout=600)  # fmt: skip


def _protocol(folder: Path, gain: float) -> Path:
    text = (ROOT / "protocols" / "kato2021.yaml").read_text(encoding="utf-8")
    text = kato_vowels_only(text)
    jaw = (f"  - id: jaw\n    label: {{ja: 顎のみ, en: Jaw only}}\n    method: jaw_only\n"
           f"    params: {{gain: {gain}}}\n")  # fmt: skip
    text = text.replace("\nstimulus_sets:", jaw + "\nstimulus_sets:")
    path = folder / "jaw.yaml"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.slow  # it renders (and measures) clips with the installed method
def test_an_installed_method_is_listed_validated_and_rendered(installed: Path,
                                                              tmp_path: Path) -> None:  # fmt: skip
    listed = _facelab(installed, "plugins")
    assert listed.returncode == 0, listed.stderr
    assert "jaw_only" in listed.stdout and "facelab-example-plugin 0.1.0" in listed.stdout
    assert " - ok" in listed.stdout
    bad = _facelab(installed, "validate", str(_protocol(tmp_path, 1.8)))
    assert bad.returncode == 2
    assert "conditions[3].params.gain: a gain above 1.5" in bad.stderr + bad.stdout
    assert "Traceback" not in bad.stderr
    proto = _protocol(tmp_path, 0.9)
    assert _facelab(installed, "validate", str(proto)).returncode == 0
    without = _facelab([], "validate", str(proto))  # not installed: an unknown method
    assert without.returncode == 2 and "unknown method 'jaw_only'" in without.stderr
    out = tmp_path / "clips"
    accept = ["--accept-check", "articulation", "--accept-check", "av_sync"]
    done = _facelab(installed, "render", str(proto), "--out", str(out), "--size", "320x180",
                    "--quiet", *accept)  # fmt: skip
    assert done.returncode == 0, done.stderr
    rows = {r["condition"]: r for r in csv.DictReader((out / "clips.csv").open(encoding="utf-8"))}
    from facelab.formats import read_track

    track = read_track(out / rows["jaw"]["track_file"])
    assert track.names == ["jawOpen"] and track.values.max() > 0.5


@pytest.mark.slow
def test_a_broken_plugin_is_named_and_facelab_still_works(installed: Path, tmp_path: Path) -> None:
    """A package whose entry point names a module that needs one not installed: ``facelab
    plugins`` names the package and what is missing (exit 1); validating kato2021 works."""
    broken = tmp_path / "broken"
    (broken / "broken_plugin").mkdir(parents=True)
    (broken / "broken_plugin" / "__init__.py").write_text("import not_a_real_dependency\n")
    info = broken / "broken_plugin-0.0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: broken-plugin\nVersion: 0.0.1\n")
    (info / "entry_points.txt").write_text("[facelab.methods]\nbroken = broken_plugin:Broken\n")
    listed = _facelab([installed, broken], "plugins")
    assert listed.returncode == 1
    said = ("plugin 'broken' from package 'broken-plugin' (broken_plugin:Broken) could not be "
            "loaded: its code needs the module 'not_a_real_dependency'")  # fmt: skip
    assert said in listed.stdout
    assert "jaw_only" in listed.stdout and "Traceback" not in listed.stderr
    ok = _facelab([installed, broken], "validate", str(ROOT / "protocols" / "kato2021.yaml"))
    assert ok.returncode == 0, ok.stderr


@pytest.mark.parametrize(
    ("edit", "said"),
    [
        (
            ('placement: ClassVar[str] = "after_clip"', 'placement: ClassVar[str] = "after_clips"'),
            "has placement 'after_clips'; expected after_responses, after_clip",
        ),
        (
            ('Path(__file__).with_name("effort.js")', 'Path(__file__).with_name("missing.js")'),
            "which is not installed (ship it as package data",
        ),
    ],
    ids=["placement", "plugin file"],
)
def test_a_broken_screen_kind_is_never_used(
    installed: Path, tmp_path: Path, edit: tuple[str, str], said: str
) -> None:
    """A kind ``facelab plugins`` calls broken (a placement that does not exist, its jsPsych
    plugin not installed) is not used by any command: validate of a protocol adding it
    fails naming why, instead of running it silently (found by an outside plugin author)."""
    site = tmp_path / "site"
    shutil.copytree(installed, site)
    effort = site / "facelab_example_plugin" / "effort.py"
    text = effort.read_text(encoding="utf-8")
    assert edit[0] in text
    effort.write_text(text.replace(*edit), encoding="utf-8")
    listed = _facelab(site, "plugins")
    assert listed.returncode == 1 and said in listed.stdout, listed.stdout
    done = _facelab(site, "validate", str(_with_confidence(tmp_path)))
    assert done.returncode == 2
    assert "screen kind 'effort' is installed but cannot be used" in done.stderr
    assert said in done.stderr and "Traceback" not in done.stderr


def _with_confidence(folder: Path, *, options: str = "{p_sure: 0.7}", short: bool = False) -> Path:
    """kato2021 with the plugin's confidence screen (buttons, after the ratings) and effort
    screen (its own drawing, right after the clip) in every trial (``short``: two vowels,
    one sentence, one set per block - a session of a few minutes)."""
    text = (ROOT / "protocols" / "kato2021.yaml").read_text(encoding="utf-8")
    text = text.replace("presentation:\n", "presentation:\n  added_screens: [{kind: confidence, "
                        f"options: {options}}}, {{kind: effort, options: {{mean: 4.5}}}}]\n",
                        1)  # fmt: skip
    if short:
        text = kato_short(text)
    path = folder / "confidence.yaml"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.slow
def test_an_installed_screen_kind_is_validated_simulated_and_tabled(
    installed: Path, tmp_path: Path
) -> None:
    bad = _facelab(installed, "validate", str(_with_confidence(tmp_path, options="{p_sure: 2}")))
    assert bad.returncode == 2
    assert "presentation.added_screens[0].options.p_sure: expected a value that is less" in (
        bad.stderr)  # fmt: skip
    missing = _facelab([], "validate", str(_with_confidence(tmp_path)))
    assert missing.returncode == 2 and "unknown screen kind 'confidence'" in missing.stderr
    path = _with_confidence(tmp_path)
    done = _facelab(installed, "validate", str(path))  # says what comes from packages
    assert "from packages: screen kind confidence (facelab-example-plugin), screen kind " \
        "effort (facelab-example-plugin)" in done.stdout, done.stdout
    results, out = tmp_path / "results", tmp_path / "analysis"
    done = _facelab(installed, "simulate", str(path), "--participants", "3", "--sim-seed", "2",
                    "--results", str(results))  # fmt: skip
    assert done.returncode == 0, done.stderr
    rows = [r for f in sorted(results.rglob("*_beh.tsv"))
            for r in csv.DictReader(f.open(encoding="utf-8"), delimiter="\t")]  # fmt: skip
    confidence = [r for r in rows if r["item"] == "confidence"]
    assert len(confidence) == 3 * 18 and {r["screen"] for r in confidence} == {"confidence"}
    assert {r["response"] for r in confidence} <= {"1", "2", "3"}
    effort = [r for r in rows if r["item"] == "effort"]
    assert len(effort) == 3 * 18 and {r["screen"] for r in effort} == {"effort"}
    values = [int(r["response"]) for r in effort]
    assert set(values) <= set(range(1, 8)) and 3.5 < sum(values) / len(values) < 5.5
    # effort is placed right after the clip: before the trial's ratings, confidence after
    first = [r["item"] for r in rows if r["trial_index"] == rows[0]["trial_index"]]
    assert first[0] == "effort" and first[-1] == "confidence", first
    done = _facelab(installed, "analyze", str(path), str(results), "--out", str(out))
    assert done.returncode == 0, done.stderr
    table = list(csv.DictReader((out / "screen_confidence.csv").open(encoding="utf-8")))
    assert {r["condition"] for r in table} == {"baseline", "standard", "emphasized"}
    assert sum(int(r["n"]) for r in table) == 3 * 18
    # the effort kind's own table (its summarise): quartiles per condition
    table = list(csv.DictReader((out / "screen_effort.csv").open(encoding="utf-8")))
    assert [r["condition"] for r in table] == ["baseline", "emphasized", "standard"]
    assert set(table[0]) == {"condition", "n", "median", "q1", "q3", "mean", "share_hard"}
    assert all(float(r["q1"]) <= float(r["median"]) <= float(r["q3"]) for r in table)
    assert sum(int(r["n"]) for r in table) == 3 * 18


@pytest.mark.slow
def test_an_installed_screen_kind_runs_in_the_lab_window_and_online(
    installed: Path, tmp_path: Path
) -> None:
    """The same kind in a lab session (PsychoPy under Xvfb, the scripted participant
    clicking) and an online one (headless Chromium, generic buttons plugin), exported and
    analysed: one confidence answer per trial in both."""
    path = _with_confidence(tmp_path, short=True)
    clips = tmp_path / "clips"
    accept = ["--accept-check", "face_visible", "--accept-check", "articulation",
              "--accept-check", "av_sync"]  # fmt: skip
    done = _facelab(installed, "render", str(path), "--out", str(clips), "--size", "160x90",
                    "--fps", "10", "--quiet", *accept)  # fmt: skip
    assert done.returncode == 0, done.stderr
    lab = _facelab(installed, "run", str(path), "--participant", "P01", "--simulate",
                   "--sim-seed", "1", "--clips", str(clips), "--results", str(tmp_path / "lab"),
                   "--windowed", "--size", "640x360", "--screenshots",
                   str(tmp_path / "shots"))  # fmt: skip
    assert lab.returncode == 0, lab.stderr
    (tsv,) = (tmp_path / "lab").rglob("*_beh.tsv")
    rows = list(csv.DictReader(tsv.open(encoding="utf-8"), delimiter="\t"))
    trials = {r["trial_index"] for r in rows}
    for kind in ("confidence", "effort"):
        answers = [r for r in rows if r["item"] == kind]
        assert {r["trial_index"] for r in answers} == trials and len(answers) == len(trials)
    shots = {p.name for p in (tmp_path / "shots").rglob("*.png")}
    assert any("effort" in name for name in shots), shots  # the kind's own lab drawing
    online = tmp_path / "online"
    served = _facelab(installed, "serve", str(path), "--clips", str(clips), "--results",
                      str(online), "--simulate-participants", "1", "--screenshots",
                      str(tmp_path / "web"))  # fmt: skip
    assert served.returncode == 0, served.stderr
    (db,) = online.rglob("online.sqlite")
    exported = tmp_path / "exported"
    assert _facelab(installed, "export", "--db", f"sqlite:///{db}", "--results",
                    str(exported)).returncode == 0  # fmt: skip
    (tsv,) = exported.rglob("*_beh.tsv")
    rows = list(csv.DictReader(tsv.open(encoding="utf-8"), delimiter="\t"))
    confidence = [r for r in rows if r["item"] == "confidence"]
    assert len(confidence) == len({r["trial_index"] for r in rows})
    assert {r["response"] for r in confidence} <= {"1", "2", "3"}  # the choice's own value
    effort = [r for r in rows if r["item"] == "effort"]  # through the kind's own plugin
    assert len(effort) == len(confidence) and {r["response"] for r in effort} <= set("1234567")
    out = tmp_path / "analysis"
    assert _facelab(installed, "analyze", str(path), str(exported), "--out",
                    str(out)).returncode == 0  # fmt: skip
    assert (out / "screen_confidence.csv").is_file() and (out / "screen_effort.csv").is_file()


PAYLOAD = """
import json, sys
from facelab.design import build_trials
from facelab.experiment.timeline import BrowserContext, compile_timeline
from facelab.protocol import load_protocol
protocol = load_protocol(sys.argv[1])
trials = build_trials(protocol, participant="P01")
ctx = BrowserContext(lang="ja", clip_json=lambda key: {})
added = [s.browser(ctx) for s in compile_timeline(protocol, trials, participant="P01", session=1)
         if s.kind in ("confidence", "effort")]
print(json.dumps(added))
"""


def test_the_kinds_own_plugin_declares_what_its_screen_sends(
    installed: Path, tmp_path: Path
) -> None:
    """effort.js (shipped as package data) declares exactly the parameters EffortScreen sends,
    with their types; confidence uses facelab's generic buttons plugin."""
    from tests.test_screen_kinds import _meets, plugin_parameters

    env = {**os.environ, "PYTHONPATH": str(installed)}
    done = subprocess.run([sys.executable, "-c", PAYLOAD, str(_with_confidence(tmp_path))],
                          env=env, capture_output=True, text=True, check=True)  # fmt: skip
    payloads = json.loads(done.stdout)
    assert {p["kind"] for p in payloads} == {"confidence", "effort"}
    plugin = installed / "facelab_example_plugin" / "effort.js"
    # a buttons kind is shown by the generic plugin (facelabPluginOf), read under its kind
    info = plugin_parameters(plugin.read_text(encoding="utf-8"),
                             "FacelabPlugins.confidence = FacelabButtons;")  # fmt: skip
    problems = [p for payload in payloads for p in _meets(info, payload)]
    assert not problems, problems[:5]
