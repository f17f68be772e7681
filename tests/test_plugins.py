"""Plugins from installed packages (issue 49, part 1): examples/plugin is pip-installed (into
a folder on PYTHONPATH, as a package installed beside facelab looks to Python) and its method
jaw_only is listed by ``facelab plugins``, validated with its own checks, rendered; a broken
plugin is named in words while the rest of facelab works. The facelab commands run as
subprocesses, so nothing of the plugin leaks into this test process."""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

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
    text = text[: text.index("  - id: sentences\n    stimulus_set: sentences")] + text[
        text.index("items:"):
    ]  # fmt: skip
    text = text.replace(
        "practice: {stimulus_set: sentences, stimulus: passage, condition: standard}",
        "practice: {stimulus_set: vowels, stimulus: aiueo, condition: standard}",
    )
    jaw = (f"  - id: jaw\n    label: {{ja: 顎のみ, en: Jaw only}}\n    method: jaw_only\n"
           f"    params: {{gain: {gain}}}\n")  # fmt: skip
    text = text.replace("\nstimulus_sets:", jaw + "\nstimulus_sets:")
    path = folder / "jaw.yaml"
    path.write_text(text, encoding="utf-8")
    return path


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


def _with_confidence(folder: Path, *, options: str = "{p_sure: 0.7}", short: bool = False) -> Path:
    """kato2021 with the plugin's confidence screen in every trial (``short``: two vowels,
    one sentence, one set per block - a session of a few minutes)."""
    text = (ROOT / "protocols" / "kato2021.yaml").read_text(encoding="utf-8")
    text = text.replace("presentation:\n", "presentation:\n  added_screens: [{kind: confidence, "
                        f"options: {options}}}]\n", 1)  # fmt: skip
    if short:
        import re

        text = text.replace("        text: あ。い。う。え。お。", "        text: あ。い。")
        text = text.replace("        expected_vowels: aiueo", "        expected_vowels: ai")
        text = re.sub(r"        text: 今日は.*\n", "        text: こんにちは。\n", text)
        text = text.replace("    sets: 2\n", "    sets: 1\n")
    path = folder / "confidence.yaml"
    path.write_text(text, encoding="utf-8")
    return path


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
    results, out = tmp_path / "results", tmp_path / "analysis"
    done = _facelab(installed, "simulate", str(path), "--participants", "3", "--sim-seed", "2",
                    "--results", str(results))  # fmt: skip
    assert done.returncode == 0, done.stderr
    rows = [r for f in sorted(results.rglob("*_beh.tsv"))
            for r in csv.DictReader(f.open(encoding="utf-8"), delimiter="\t")]  # fmt: skip
    confidence = [r for r in rows if r["item"] == "confidence"]
    assert len(confidence) == 3 * 18 and {r["screen"] for r in confidence} == {"confidence"}
    assert {r["response"] for r in confidence} <= {"1", "2", "3"}
    done = _facelab(installed, "analyze", str(path), str(results), "--out", str(out))
    assert done.returncode == 0, done.stderr
    table = list(csv.DictReader((out / "screen_confidence.csv").open(encoding="utf-8")))
    assert {r["condition"] for r in table} == {"baseline", "standard", "emphasized"}
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
                   "--windowed", "--size", "640x360")  # fmt: skip
    assert lab.returncode == 0, lab.stderr
    (tsv,) = (tmp_path / "lab").rglob("*_beh.tsv")
    rows = list(csv.DictReader(tsv.open(encoding="utf-8"), delimiter="\t"))
    trials = {r["trial_index"] for r in rows}
    confidence = [r for r in rows if r["item"] == "confidence"]
    assert {r["trial_index"] for r in confidence} == trials and len(confidence) == len(trials)
    online = tmp_path / "online"
    served = _facelab(installed, "serve", str(path), "--clips", str(clips), "--results",
                      str(online), "--simulate-participants", "1")  # fmt: skip
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
    out = tmp_path / "analysis"
    assert _facelab(installed, "analyze", str(path), str(exported), "--out",
                    str(out)).returncode == 0  # fmt: skip
    assert (out / "screen_confidence.csv").is_file()
