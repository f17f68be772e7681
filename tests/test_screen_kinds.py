"""Screen kinds as plugins (issue 31.2).

* The contract between Python and JavaScript: for every screen of every shipped protocol's
  session (staircase trials expanded at each level), the JSON the server sends
  (``Screen.browser``) has exactly the parameters its jsPsych plugin declares in
  ``plugins.js``, with values of the declared types. The plugins are read by Node.
* A toy screen kind added in three places - its Python class (JSON, answer -> log row,
  simulated answer), its jsPsych plugin, and the timeline it is put into (here, after every
  trial's VAS) - runs in the lab walk with a simulated participant (rows in the session log),
  is served and answered through the online study, and meets the contract.
"""

from __future__ import annotations

import csv
import json
import shutil
import subprocess
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any, ClassVar

import numpy as np
import pytest

from facelab.design import build_trials
from facelab.experiment.online.study import OnlineStudy
from facelab.experiment.simulate import ChoiceModel, RatingModel, SimulatedParticipant
from facelab.experiment.timeline import (
    SCREEN_KINDS,
    AdaptiveTrial,
    AnswerError,
    BrowserContext,
    ResponseScreen,
    Screen,
    VasScreen,
    compile_timeline,
    screen_kind,
)
from facelab.experiment.walk import walk
from facelab.protocol import load_protocol
from facelab.protocol_model import Conversation
from facelab.resources import protocol_path, shipped_protocols
from facelab.sessionlog import SessionContext, SessionLog
from tests.protocol_edits import kato_short

ROOT = Path(__file__).resolve().parents[1]
PLUGINS = ROOT / "experiment" / "online" / "web" / "static" / "plugins.js"
NODE = shutil.which("node")

#: reads the plugins' declared parameters: {kind: {parameter: type}} (the end screen: text:end)
READ_INFO = r"""
const fs = require("fs"), vm = require("vm");
const types = {};
for (const t of ["BOOL", "STRING", "INT", "FLOAT", "OBJECT", "COMPLEX"]) types[t] = t;
const ctx = vm.createContext({ jsPsychModule: { ParameterType: types } });
let code = fs.readFileSync(process.argv[1], "utf8");
for (const extra of process.argv.slice(2)) code += "\n" + extra;
const out = vm.runInContext(code + "\n;({ FacelabPlugins, FacelabComplete })", ctx);
const params = (P) =>
  Object.fromEntries(Object.entries(P.info.parameters).map(([k, v]) => [k, v.type]));
const info = { "text:end": params(out.FacelabComplete) };
for (const [kind, P] of Object.entries(out.FacelabPlugins)) info[kind] = params(P);
console.log(JSON.stringify(info));
"""

CHECK = {
    "STRING": lambda v: isinstance(v, str),
    "INT": lambda v: v is None or (isinstance(v, int) and not isinstance(v, bool)),
    "FLOAT": lambda v: v is None or (isinstance(v, int | float) and not isinstance(v, bool)),
    "BOOL": lambda v: isinstance(v, bool),
    "COMPLEX": lambda v: isinstance(v, list | dict),
}


def plugin_parameters(*extra_js: str) -> dict[str, dict[str, str]]:
    if NODE is None:
        pytest.fail("node is not installed (scripts/setup.sh installs it)")
    done = subprocess.run(
        [NODE, "-e", READ_INFO, str(PLUGINS), *extra_js],
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(done.stdout)


def _context(protocol: Any) -> BrowserContext:
    def clip_json(key: tuple[str, str, str]) -> dict[str, Any]:
        return {"clip": "0" * 64 + ".mp4", "fps": 30, "frames": 150, "track": ""}

    return BrowserContext(lang=protocol.presentation.language, clip_json=clip_json)


def _every_screen(protocol: Any, participant: str) -> Iterator[Screen]:
    trials = build_trials(protocol, participant=participant)
    for s in compile_timeline(protocol, trials, participant=participant, session=1):
        yield s
        if isinstance(s, AdaptiveTrial):
            block = next(b for b in protocol.blocks if b.id == s.trial.block)
            for condition in protocol.block_conditions(block):
                yield from s.expand(condition)


def _meets(info: dict[str, dict[str, str]], payload: dict[str, Any]) -> list[str]:
    """What is wrong with one screen's JSON against its plugin's declared parameters."""
    kind = payload["kind"]
    declared = info.get("text:end" if kind == "text" and payload.get("role") == "end" else kind)
    if declared is None:
        return [f"{kind}: no jsPsych plugin"]
    problems = []
    if set(payload) != set(declared):
        problems.append(f"{kind}: JSON {sorted(payload)} but plugin declares {sorted(declared)}")
    for key, value in payload.items():
        if key in declared and not CHECK[declared[key]](value):
            problems.append(f"{kind}.{key}: {value!r} is not {declared[key]}")
    return problems


def test_every_screen_kind_has_a_plugin_and_each_json_is_what_it_declares() -> None:
    info = plugin_parameters()
    assert set(SCREEN_KINDS) <= set(info), set(SCREEN_KINDS) - set(info)
    seen: set[str] = set()
    problems: list[str] = []
    for name, protocol in _protocols_with_every_kind():
        ctx = _context(protocol)
        for s in _every_screen(protocol, "P0007"):
            payload = s.browser(ctx)
            seen.add(payload["kind"])
            problems += [f"{name}: {p}" for p in _meets(info, payload)]
    assert not problems, "\n".join(sorted(set(problems))[:20])
    assert seen == set(SCREEN_KINDS)  # the shipped protocols (and the SSQ) use every kind


def _protocols_with_every_kind() -> Iterator[tuple[str, Any]]:
    """The shipped protocols, and kato2021 with the sickness questionnaire and with a live
    conversation (no shipped protocol asks for them)."""
    for name in shipped_protocols():
        yield name, load_protocol(protocol_path(name))
    kato = load_protocol(protocol_path("kato2021"))
    yield "kato2021+ssq", kato.model_copy(update={
        "presentation": kato.presentation.model_copy(update={"ssq": ["before", "after"]})})
    conversation = Conversation(condition="emphasized", minutes=2.0)
    yield "kato2021+conversation", kato.model_copy(update={
        "presentation": kato.presentation.model_copy(update={"conversation": conversation})})


def test_a_plugin_that_drifts_from_its_screen_is_caught() -> None:
    info = plugin_parameters('FacelabVas.info.parameters.scale = { type: "FLOAT" };')
    protocol = load_protocol(protocol_path("kato2021"))
    vas = next(s for s in _every_screen(protocol, "P01") if isinstance(s, VasScreen))
    assert _meets(info, vas.browser(_context(protocol)))


# --------------------------------------------------------------------------- a toy kind
# Place 1 of 3: the screen kind (registered once, by the fixture below: in a study, the
# @screen_kind decorator on the class).


@dataclass(frozen=True)
class ConfidenceAnswer:
    level: int
    rt_s: float
    timestamp: str


@dataclass(frozen=True)
class ConfidenceScreen(ResponseScreen):
    """How sure was the rating? 1 (guess) .. 3 (sure); logged as item ``confidence``."""

    kind: ClassVar[str] = "toy_confidence"

    def response_keys(self) -> tuple[tuple[int, str], ...]:
        if self.practice or self.trial is None:
            return ()
        return ((self.trial.trial_index, "confidence"),)

    def browser(self, ctx: BrowserContext) -> dict[str, Any]:
        return {"kind": self.kind, "trial_index": self.trial_index, "item": "confidence",
                "levels": [1, 2, 3]}  # fmt: skip

    def answer(
        self, item: str, posted: Mapping[str, Any], *, rt_s: float, timestamp: str
    ) -> ConfidenceAnswer:
        level = posted.get("value")  # a kind added to facelab posts its answer as "value"
        if level not in (1, 2, 3) or isinstance(level, bool):
            raise AnswerError(f"value: expected 1, 2 or 3, got {level!r}")
        return ConfidenceAnswer(int(level), rt_s, timestamp)

    def posted(self, answer: ConfidenceAnswer) -> dict[str, Any]:
        return {"value": answer.level}

    def row(
        self, item: str, answer: ConfidenceAnswer, *, context: SessionContext, playback: Any
    ) -> dict[str, Any]:
        return self._row(
            context=context, playback=playback, item=item, rt_s=answer.rt_s,
            timestamp=answer.timestamp, response=str(answer.level),
        )  # fmt: skip

    def present(self, presenter: Any) -> list[ConfidenceAnswer]:
        """The lab window would show three buttons; a simulated participant is sure when its
        rating model's noise is small (here: always level 3 on odd trials, else 2)."""
        level = 3 if (self.trial_index or 0) % 2 else 2
        return [ConfidenceAnswer(level, 0.8, presenter._stamp())]


# Place 2 of 3: its jsPsych plugin (in a study: added to plugins.js).
TOY_PLUGIN = """
class FacelabConfidence extends FacelabChoice {
  async run(el, s) {
    const { value, started } = await this.buttons(el, s, "toy_confidence",
      s.levels.map((n) => ({ text: String(n), value: n })));
    FacelabOutbox.send("/api/response", facelabAnswer(s, "confidence", { value }, started));
    return { level: value };
  }
}
FacelabConfidence.info = facelabInfo("facelab-confidence",
  { kind: "STRING", trial_index: "INT", item: "STRING", levels: "COMPLEX" });
FacelabPlugins.toy_confidence = FacelabConfidence;
"""


# Place 3 of 3: the timeline it appears in (after each trial's last response screen).
def _with_confidence(screens: list[Screen]) -> list[Screen]:
    out: list[Screen] = []
    for i, s in enumerate(screens):
        out.append(s)
        nxt = screens[i + 1] if i + 1 < len(screens) else None
        last = not (isinstance(nxt, VasScreen) and nxt.trial_index == s.trial_index)
        if isinstance(s, VasScreen) and s.trial is not None and last:
            out.append(ConfidenceScreen(trial=s.trial))
    return out


@pytest.fixture
def toy_kind(tmp_path: Path) -> Iterator[type[Screen]]:
    plugin = tmp_path / "toy_confidence.js"
    plugin.write_text(TOY_PLUGIN, encoding="utf-8")
    ConfidenceScreen.plugin_js = plugin  # place 2: the kind names its plugin file
    yield screen_kind(ConfidenceScreen)
    del SCREEN_KINDS[ConfidenceScreen.kind]
    ConfidenceScreen.plugin_js = None


def test_a_toy_screen_kind_runs_in_the_lab_walk_online_and_meets_its_plugin(
    toy_kind: type[Screen], tmp_path: Path
) -> None:
    path = protocol_path("kato2021")
    protocol = load_protocol(path)
    trials = build_trials(protocol, participant="P01")
    screens = _with_confidence(compile_timeline(protocol, trials, participant="P01", session=1))

    # the lab walk with a simulated participant: one confidence row per trial in the log
    rng = np.random.default_rng(5)
    log = SessionLog.create(
        tmp_path, study=protocol.study.id, participant="P01", session=1, provenance={}
    )
    context = SessionContext(study=protocol.study.id, participant="P01", session=1,
                             simulated=True, protocol_sha256="0" * 64)  # fmt: skip
    presenter = SimulatedParticipant(RatingModel(protocol, rng=rng), ChoiceModel(protocol, rng=rng))
    walk(screens, presenter=presenter, log=log, context=context, record_playback=False)
    with open(log.paths.tsv, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh, delimiter="\t"))
    confidence = [r for r in rows if r["item"] == "confidence"]
    assert len(confidence) == len(trials)
    assert {r["screen"] for r in confidence} == {"toy_confidence"}
    assert {r["response"] for r in confidence} == {"2", "3"}

    # online: served to the browser and a posted answer becomes the same row
    clips = {key: SimpleNamespace(sha256="a" * 64, fps=30, duration_s=5.0)
             for key in {(t.stimulus_set, t.stimulus, t.condition) for t in trials}}  # fmt: skip
    study = OnlineStudy(protocol=protocol, protocol_sha256="0" * 64, clips=clips)
    study._screens["P01/1"] = screens
    timeline, _ = study.timeline_json("P01", set())
    served = [s for s in timeline if s["kind"] == "toy_confidence"]
    assert len(served) == len(trials)
    first = trials[0].trial_index
    posted = {"trial_index": first, "item": "confidence", "rt_s": 0.5, "value": 3}
    row = study.row(participant="P01", session=1, simulated=True, answer=posted,
                    playback=None, timestamp="2026-11-25T00:00:00+00:00")  # fmt: skip
    assert (row["item"], row["response"], row["screen"]) == ("confidence", "3", "toy_confidence")
    with pytest.raises(AnswerError, match="value: expected 1, 2 or 3"):
        study.row(participant="P01", session=1, simulated=True, answer={**posted, "value": 7},
                  playback=None, timestamp="2026-11-25T00:00:00+00:00")  # fmt: skip

    # the contract with its jsPsych plugin
    info = plugin_parameters(TOY_PLUGIN)
    assert all(not _meets(info, s) for s in served)


@pytest.mark.slow
def test_a_toy_screen_kind_is_answered_in_chromium(toy_kind: type[Screen], tmp_path: Path) -> None:
    """The browser part: the session page loads the kind's plugin, a simulated participant in
    headless Chromium clicks its buttons, and every answer is stored as the lab would log it."""

    from sqlalchemy import select
    from sqlalchemy.orm import Session

    from facelab.experiment.cli import main
    from facelab.experiment.online.browser import SimulatedBrowser
    from facelab.experiment.online.db import Action, Participant, Response
    from facelab.experiment.online.serve import BackgroundServer, prepare_server

    text = protocol_path("kato2021").read_text(encoding="utf-8")
    text = kato_short(text)
    path = tmp_path / "short.yaml"
    path.write_text(text, encoding="utf-8")
    argv = ["render", str(path), "--out", str(tmp_path / "clips"), "--size", "160x90"]
    assert main([*argv, "--fps", "10", "--quiet"]) == 0
    server, _ = prepare_server(
        load_protocol(path), protocol_path=path, clips_dir=tmp_path / "clips",
        db_url=f"sqlite:///{tmp_path / 'db.sqlite'}", results=tmp_path, admin_secret="s" * 20,
    )  # fmt: skip
    # place 3: the timeline it appears in (the first participant's, after each trial's VAS)
    server.study._screens["P0001/1"] = _with_confidence(server.study.screens("P0001"))
    shots = tmp_path / "shots"
    with BackgroundServer(server) as bg:
        browser = SimulatedBrowser(server, bg.url, 1, screenshots=shots)
        assert browser.run(timeout_s=300) == "complete"
    assert (shots / "toy_confidence.png").stat().st_size > 1000  # the page drew its buttons
    with Session(server.engine) as db:
        p = db.scalars(select(Participant).where(Participant.participant == "P0001")).one()
        rows = [r.row for r in db.scalars(select(Response).where(Response.participant_pk == p.pk))]
        clicked = {(a.record["trial_index"], a.record["item"]): a.record["value"]
                   for a in db.scalars(select(Action))}  # fmt: skip
    confidence = [r for r in rows if r["item"] == "confidence"]
    trials = {r["trial_index"] for r in rows if r["item"] != "confidence"}
    assert {r["trial_index"] for r in confidence} == trials and len(confidence) == len(trials)
    assert {r["screen"] for r in confidence} == {"toy_confidence"}
    for r in confidence:  # the button clicked is the answer stored
        assert r["response"] == str(clicked[(r["trial_index"], "confidence")])
