"""Simulated online participants: headless Chromium (Debian's ``chromium`` and
``chromium-driver`` through Selenium) clicking through the real pages.

Each simulated participant ``k`` (1..N) joins with the recruitment id ``sim-k``; its token is
an HMAC of the study and ``k`` under the server's key, so starting again against the same
database gives the same ids and tokens and resumes them. Before every answer it gives, it
writes the answer to the ``actions`` table (``{"t", "trial_index", "item", "value"}`` - the
lab's ``_actions.jsonl`` record), then clicks: the VAS line at the rating its
:class:`~facelab.experiment.simulate.RatingModel` gives, then confirm; the option a
:class:`~facelab.experiment.simulate.ChoiceModel` picks; "next" on text screens.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import re
import shutil
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from facelab.design import participant_seed
from facelab.errors import SessionError
from facelab.experiment.online.db import Action, Participant
from facelab.experiment.online.server import StudyServer
from facelab.experiment.simulate import ChoiceModel, RatingModel, SimulatedParticipant
from facelab.experiment.timeline import (
    AdaptiveTrial,
    ResponseScreen,
)

__all__ = [
    "WINDOW", "SimulatedBrowser", "chromium", "emulator_js", "run_simulated", "simulated_token"
]

CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"


def simulated_token(server: StudyServer, k: int) -> str:
    """The stable token of simulated participant ``k`` (256 bits, URL-safe hex)."""
    return hmac.new(
        server.hmac_key, f"simulated:{server.study.study}:{k}".encode(), hashlib.sha256
    ).hexdigest()


#: the simulated participants' browser window (width, height; pixels) unless asked otherwise
WINDOW = (1280, 800)


def chromium(*, size: tuple[int, int] = WINDOW, extra_args: Sequence[str] = ()) -> Any:
    """A headless Chromium under Selenium, sound muted, autoplay allowed (no person to click);
    ``extra_args``: more command-line switches (e.g. a fake microphone)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    exe = shutil.which("chromium") or CHROMIUM
    driver_exe = shutil.which("chromedriver") or CHROMEDRIVER
    if not Path(exe).exists() or not Path(driver_exe).exists():
        raise SessionError(
            "simulated online participants need Debian's chromium and chromium-driver "
            "(apt-get install chromium chromium-driver)"
        )
    opts = webdriver.ChromeOptions()
    opts.binary_location = exe
    for arg in (
        "--headless=new",
        f"--window-size={size[0]},{size[1]}",
        "--no-sandbox",
        "--disable-dev-shm-usage",
        "--mute-audio",
        "--autoplay-policy=no-user-gesture-required",
        "--disable-gpu",
        # WebGL for the live 3D and VR views: SwiftShader, which recent Chromium uses only
        # when asked (no GPU here; frame times measured this way are not device figures)
        "--enable-unsafe-swiftshader",
        "--use-angle=swiftshader",
        *extra_args,
    ):
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(executable_path=driver_exe), options=opts)
    driver.set_script_timeout(90)  # a VR select waits for XR frames (up to 60 s on a load)
    return driver


#: the emulated headset (Meta's IWER from npm, never served to participants): installed in the
#: page before its scripts run; while a clip plays it moves the head as a seated participant
#: watching might - turns (yaw +-HEAD_TURN_DEG, one cycle every 2 s), nods (pitch +-0.4 of
#: that), tilts (roll +-0.2), sways 2 cm and leans in up to 4 cm - and sits back facing
#: ahead for the panels. The
#: head moves inside the session's own frame loop (after each XR frame's callbacks, for the
#: next frame), not on a page timer: a busy page starves its timers while it draws, and the
#: head then stood still. A sparse frame advances the turn by at most an eighth of a cycle, and
#: the turn goes on from clip to clip, so the logged poses sample the whole turn however slowly
#: a loaded machine draws (headless XR frames come every 150-500 ms idle; with the machine
#: busy a short clip gets two frames, and a 2-s cycle sampled every second would alias).
HEAD_TURN_DEG = 20.0
#: the emulated headset's most frames a second (Hz). It draws both eyes in software
#: (SwiftShader): run as fast as the page draws, its frame loop took the machine's two cores
#: from everything else (an 18-rating kato2021 session with the default head, alone on the
#: machine: 140 CPU-s uncapped, 98 at 10 Hz; a frame with the default head takes ~360 ms, a
#: panel's ~18 ms). A real headset's 72-90 Hz is its own.
EMULATED_HEADSET_HZ = 10
_EMULATOR_JS = """
(function () {
  const gazeOnly = %(gaze)s;
  // a gaze-only headset (no controllers: the head's ray and one select button, as a
  // phone-in-a-viewer or a headset used without its controllers) or a Quest 3 with both
  const config = gazeOnly ? { ...IWER.metaQuest3, name: "gaze-only headset",
    controllerConfig: undefined,
    supportedFeatures: [...IWER.metaQuest3.supportedFeatures.filter((f) => f !== "hand-tracking"),
                        "gaze-tracking"] } : IWER.metaQuest3;
  const device = new IWER.XRDevice(config, { stereoEnabled: %(stereo)s });
  device.installRuntime({ forceInstall: true });
  window.facelabXRDevice = device;
  window.facelabGazeOnly = gazeOnly;
  let pressed = 0;  // gaze-only: XR frames left of a select button held (2: press, 1: release)
  window.facelabGazeSelect = () => { pressed = 2; window.facelabGazeMissed = null; };
  window.facelabGazeSelects = 0;  // selects sent (a driver checks its own arrived)
  // The headset's own clock: while its session runs, its frames come from a timer, at most
  // %(hz)s a second (IWER would run them on the page's rAF, as fast as the page draws)
  const pageFrame = window.requestAnimationFrame.bind(window);
  const pageCancel = window.cancelAnimationFrame.bind(window);
  const gap = 1000 / %(hz)s;
  let inSession = false, lastFrame = -Infinity, nextHandle = 1;
  const timers = new Map();  // a frame asked for in the session: our handle -> its timer
  window.requestAnimationFrame = (callback) => {
    if (!inSession) return pageFrame(callback);
    const handle = -(nextHandle++);  // never a page rAF's (positive) handle
    const wait = Math.max(0, lastFrame + gap - performance.now());
    timers.set(handle, setTimeout(() => {
      timers.delete(handle);
      const now = performance.now();
      if (now - lastFrame >= gap - 1) lastFrame = now;  // one frame time for all due at once
      callback(lastFrame);
    }, wait));
    return handle;
  };
  window.cancelAnimationFrame = (handle) => {
    if (!timers.has(handle)) { pageCancel(handle); return; }
    clearTimeout(timers.get(handle)); timers.delete(handle);
  };
  const request = navigator.xr.requestSession.bind(navigator.xr);
  navigator.xr.requestSession = async (mode, init = {}) => {
    // IWER gives its gaze input only to sessions asking for it
    const asked = gazeOnly ? { ...init,
      optionalFeatures: [...(init.optionalFeatures || []), "gaze-tracking"] } : init;
    const session = await request(mode, asked);
    inSession = true;
    session.addEventListener("end", () => { inSession = false; });
    return session;
  };
  const turn = %(turn)s;
  const rest = { x: device.position.x, y: device.position.y, z: device.position.z };
  let phase = 0, last = null;
  // the head at (yaw, pitch, roll) degrees (R = Ry Rx Rz, the rig's order) leaning
  // (dx, dy, dz) metres from where it sat
  const pose = (yaw, pitch, roll, dx, dy, dz) => {
    const r = Math.PI / 360, [cy, sy] = [Math.cos(yaw * r), Math.sin(yaw * r)];
    const [cx, sx] = [Math.cos(pitch * r), Math.sin(pitch * r)];
    const [cz, sz] = [Math.cos(roll * r), Math.sin(roll * r)];
    device.quaternion.set(cy * sx * cz + sy * cx * sz, sy * cx * cz - cy * sx * sz,
                          cy * cx * sz - sy * sx * cz, cy * cx * cz + sy * sx * sz);
    device.position.set(rest.x + dx, rest.y + dy, rest.z + dz);
  };
  window.facelabFace = (yaw) => pose(yaw, 0, 0, 0, 0, 0);
  let offAt = %(off)s;  // the trial whose clip sees the headset taken off (once)
  let off = null;  // taken off: {since: when the page saw it hidden}
  const frameLoop = IWER.XRSession.prototype.requestAnimationFrame;
  window.facelabXRFrames = 0;  // XR frames run: a driver's trigger waits for them
  IWER.XRSession.prototype.requestAnimationFrame = function (callback) {
    const session = this;
    return frameLoop.call(this, function (time, frame) {
      window.facelabXRFrames += 1;
      const gaze = gazeOnly && pressed
        ? [...session.inputSources].find((s) => s.targetRayMode === "gaze") : null;
      if (gaze) {  // the select button, pressed on one XR frame and released on the next
        // (as the WebXR spec orders them: selectstart; then select and selectend)
        const at = { frame, inputSource: gaze };
        if (pressed === 2) session.dispatchEvent(new IWER.XRInputSourceEvent("selectstart", at));
        else {
          session.dispatchEvent(new IWER.XRInputSourceEvent("select", at));
          session.dispatchEvent(new IWER.XRInputSourceEvent("selectend", at));
          window.facelabGazeSelects += 1;
        }
        pressed -= 1;
      } else if (gazeOnly && pressed) {  // no gaze input (the headset off): nothing selected
        window.facelabGazeMissed = "the headset has no gaze input on this frame";
        pressed = 0;
      }
      const result = callback(time, frame);
      const live = window.FacelabLive;
      if (offAt !== null && live && live.playing && live.playing.trial_index === offAt) {
        offAt = null;  // off for a second, then on again
        device.updateVisibilityState("hidden");
        off = { since: null };
      } else if (off && device.visibilityState === "hidden") {
        // IWER applies a visibility change at its next frame and drops a change back to the
        // state still in force: "visible" is asked for only once "hidden" took effect (a
        // loaded machine may draw no XR frame for over a second)
        const now = performance.now();
        if (off.since === null) off.since = now;
        else if (now - off.since >= 1000) { device.updateVisibilityState("visible"); off = null; }
      }
      if (live && live.onFrame && live.session) {
        const now = performance.now();
        phase += last === null ? 1 / 8 : Math.min((now - last) / 2000, 1 / 8);
        last = now;
        const w = 2 * Math.PI * phase;  // a person watching: turns, nods, tilts and leans in
        pose(turn * Math.sin(w), 0.4 * turn * Math.sin(1.7 * w + 1),
             0.2 * turn * Math.sin(0.6 * w + 2), 0.02 * Math.sin(0.8 * w),
             0.01 * Math.sin(1.3 * w), -0.02 * (1 - Math.cos(0.5 * w)));
      } else if (last !== null) {  // a panel: sit back, face ahead (the motion goes on later)
        last = null; pose(0, 0, 0, 0, 0, 0);
      }
      return result;
    });
  };
})();
"""
#: a screen the simulated participant answered that is still on show this long after (s):
#: the answer was lost - said, rather than waited out to the session's timeout
STUCK_S = 180.0
#: how an emulated headset's participant selects (emulator_js)
VR_INPUTS = ("controller", "gaze")
#: the yaw (deg, + to the left) the emulated participant faces when they recentre
RECENTRE_YAW_DEG = 15.0
_FACE_JS = "window.facelabFace(arguments[0]);"

#: The screen kinds that store a participant's answer (a stop or a withdrawal is taken
#: there, after the answers counted).
_ANSWER_KINDS = ("vas", "choice_2afc", "identify", "typed", "matrix")
#: the fades the VR page has begun, {in, out} (out: a selected answer, a clip's end)
_FADES_JS = "return window.FacelabLive ? {...window.FacelabLive.fades} : null;"
#: in VR, what the page's stage was doing (for a message when a session runs out of time)
_VR_STATE_JS = """
const s = window.FacelabLive;
if (!s || !s.inVR || !s.inVR()) return null;
const n = window.facelabXRFrames;  // the emulated headset's count (emulator_js)
const frames = n === undefined ? '' : `, XR frames run: ${n}`;
const clip = s.playing ? `, clip ${s.playing.clip} playing` : '';
const seen = s.session ? `, headset ${s.session.visibilityState}` : '';
return `in VR, panel opacity ${s.opacity().toFixed(2)}, selecting: ${!!s.selecting}` + clip
  + seen + frames;
"""
_ON_PANEL_JS = """
const el = document.querySelector(arguments[0]);
return !!(el && window.FacelabLive && window.FacelabLive.target(el));
"""

# Point the emulated right controller at a DOM element's place on the VR panel (a VAS line at
# fraction arguments[1]) and pull the trigger (a select), as a participant would; on a
# gaze-only headset look at it and press the select button.
_XR_SELECT_JS = """
const [selector, frac, done] = arguments;
const stage = window.FacelabLive, device = window.facelabXRDevice;
const el = document.querySelector(selector);
const target = el && stage.target(el, frac);
if (!target) { done('no panel target for ' + selector); return; }
const seen = () => new Promise((resolve, reject) => {  // as a participant: once it shows
  const until = performance.now() + 30000;
  const poll = () => {
    if (stage.opacity() <= 0.5 && !stage.selecting) resolve();
    else if (performance.now() > until) reject(new Error(
      `the panel still dark (opacity ${stage.opacity().toFixed(2)}) after 30 s`));
    else setTimeout(poll, 20);
  };
  poll();
});
// a controller's ray (the right one), or on a gaze-only headset the head turned to look
const gazeOnly = !!window.facelabGazeOnly, c = device.controllers.right;
const aim = () => {
  const q = stage.aim(gazeOnly ? 0 : 1, target);
  (gazeOnly ? device : c).quaternion.set(q[0], q[1], q[2], q[3]);
};
if (!gazeOnly) aim();
// IWER reads a button once per XR frame (the last value set wins), and a loaded machine
// draws a headless XR frame only every few hundred ms: each step waits for two XR frames,
// so the press is seen, aimed, and the release after it (a timer alone can miss the press);
// a select that ends the session (Exit) has no frames after it
const give_up = performance.now() + 60000;  // the whole select (the driver waits 90 s)
const frames = (n) => new Promise((resolve, reject) => {
  const until = window.facelabXRFrames + n;
  const poll = () => {
    if (window.facelabXRFrames >= until || !stage.session) resolve();
    else if (performance.now() > give_up) reject(new Error('too few XR frames in 60 s'));
    else setTimeout(poll, 20);
  };
  poll();
});
(async () => {
  await seen();
  if (gazeOnly) {  // look at it (once the panel is drawn), then the select button
    await frames(1);
    aim();
    await frames(2);
    const sent = window.facelabGazeSelects;
    window.facelabGazeSelect();
    await frames(3);
    if (window.facelabGazeSelects > sent) done(null);
    else done('the gaze select on ' + selector + ' was not sent: '
              + (window.facelabGazeMissed || 'too few XR frames'));
    return;
  }
  await frames(2);
  c.updateButtonValue('trigger', 1);
  await frames(2);
  c.updateButtonValue('trigger', 0);
  await frames(2);
  done(null);
})().catch((e) => done('the select on ' + selector + ': ' + e.message));
"""


def emulator_js(
    *, turn_deg: float = HEAD_TURN_DEG, headset_off_at: int | None = None,
    input: str = "controller", stereo: bool = True,
) -> str:  # fmt: skip
    """The script that installs the emulated headset (IWER, from experiment/online/web);
    with ``headset_off_at`` the participant takes it off for a second once that trial's clip
    plays (checked in the XR frame loop: a driver polling between frames misses short
    clips). ``input``: ``"controller"`` (a Quest 3 and its two controllers) or ``"gaze"`` (no
    controllers: the head's ray and a select button). ``stereo`` False: one view, not one per
    eye (a test of a session's flow, not of what each eye sees: the avatar is drawn once a
    frame in software instead of twice)."""
    if input not in VR_INPUTS:
        raise SessionError(
            f"an emulated headset's input {input!r}: expected one of {', '.join(VR_INPUTS)}"
        )
    from facelab.experiment.online.serve import vendor_dir

    iwer = vendor_dir() / "iwer" / "build" / "iwer.min.js"
    if not iwer.is_file():
        raise SessionError(f"the emulated headset needs {iwer}; run scripts/setup.sh (npm ci)")
    off = "null" if headset_off_at is None else str(int(headset_off_at))
    gaze = "true" if input == "gaze" else "false"
    return iwer.read_text(encoding="utf-8") + _EMULATOR_JS % {
        "turn": float(turn_deg), "off": off, "gaze": gaze,
        "stereo": "true" if stereo else "false", "hz": float(EMULATED_HEADSET_HZ)}  # fmt: skip


_STATE_JS = """
if (document.querySelector('[data-facelab=enter_vr]')) return {kind: 'enter_vr'};
const el = document.querySelector('#app [data-facelab]');
const fs = document.querySelector('#jspsych-fullscreen-btn');
const consent = document.querySelector('#jspsych-html-button-response-btngroup button');
if (fs) return {kind: 'fullscreen'};
if (document.querySelector('#app [data-facelab=play]')) return {kind: 'play'};
if (document.querySelector('#app [data-facelab=complete]')) return {kind: 'complete'};
if (el) return {kind: el.dataset.facelab, seq: el.dataset.seq || null,
                role: el.dataset.role || null,
                trial: el.dataset.trial ? Number(el.dataset.trial) : null,
                item: el.dataset.item || null};
if (consent) return {kind: 'consent'};
return {kind: 'wait'};
"""

#: a live conversation: ask the page (conversation.js) to keep the first frame it draws with
#: a weight of 0.3 or more, and return it once kept
_CONVERSATION_SNAP_JS = """
window.FacelabSnapRequest = window.FacelabSnapRequest || {after_s: 0.0, peak: 0.3};
const a = window.FacelabDialogue;
return (a && a.snapshot) || null;
"""


#: in VR: the page's still of a clip in full view once it has one (live.js), else ask for one
_VR_CLIP_STILL_JS = """
const s = window.FacelabLive;
if (!s.clipStill) s.clipStillWanted = true;
return s.clipStill || "";
"""


@dataclass
class SimulatedBrowser:
    """One simulated participant driving one Chromium through the session."""

    server: StudyServer
    base_url: str
    k: int
    seed: int = 1
    screenshots: Path | None = None
    stop_after: int | None = None  # logged answers to give, then stop (a closed tab)
    # logged answers to give, then stop the study from the page (its Stop button, confirmed),
    # answer what the stopped session still asks (the sickness questionnaire after)
    withdraw_after: int | None = None
    withdrew: bool = False
    exit_missed: bool = False  # the end panel's Exit select saw no XR frames (VR ended itself)
    vr_fades: dict[str, int] | None = None  # the VR page's fades begun, before Exit or Stop
    driver: Any = None
    given: int = 0
    shots: set[str] = field(default_factory=set)
    texts: dict[str, str] = field(default_factory=dict)  # role -> the text screen's words
    headset: bool = True  # display webxr: an emulated headset (False: a browser without one)
    # display webxr: the participant takes the headset off for a second during the clip of
    # this trial (and puts it back on), once
    headset_off_at: int | None = None
    vr_input: str = "controller"  # display webxr: the emulated headset's input (VR_INPUTS)
    vr_stereo: bool = True  # display webxr: the emulated headset draws a view per eye
    # the browser window (pixels) when it opens its own; an emulated headset draws both eyes
    # into it, so a smaller one draws faster without a GPU (1280x800 -> 640x400: the same
    # session in about 58 % of the time)
    window: tuple[int, int] = WINDOW
    _emulator: Any = None

    def participant(self) -> tuple[Participant, str]:
        token = simulated_token(self.server, self.k)
        p, _ = self.server.join(
            recruitment=f"sim-{self.k}", source="simulated", simulated=True, token=token
        )
        return p, token

    def _record(self, p: Participant, *, trial_index: int, item: str, value: Any) -> None:
        with Session(self.server.engine) as db:
            db.add(
                Action(
                    participant_pk=p.pk,
                    record={
                        "t": time.time(),
                        "trial_index": trial_index,
                        "item": item,
                        "value": value,
                    },
                )
            )
            db.commit()

    def _shot(self, name: str) -> None:
        """A screenshot of the page as ``name``.png, once per name; in VR also the panel's
        layout as ``name``.panel.json (each text line drawn and where, whether any fell
        outside the panel)."""
        if self.screenshots is not None and name not in self.shots:
            self.shots.add(name)
            self.screenshots.mkdir(parents=True, exist_ok=True)
            self.driver.save_screenshot(str(self.screenshots / f"{name}.png"))
            layout = self.driver.execute_script(
                "const s = window.FacelabLive;"
                "return s && s.inVR() && s.panel ? s.panel.laidOut : null"
            )
            if layout:
                (self.screenshots / f"{name}.panel.json").write_text(
                    json.dumps(layout, ensure_ascii=False), encoding="utf-8"
                )

    def _stuck_on(self, state: dict[str, Any] | None, for_s: float) -> str:
        """What the page showed when the session ran out of time, for the message; its
        screenshot as ``timeout.png`` (with ``screenshots``)."""
        from selenium.common.exceptions import WebDriverException

        where = "nothing" if state is None else f"the {state.get('kind')} screen"
        if state and state.get("trial") is not None:
            where += f" of trial {state['trial']}"
        try:  # what the page says, as far as it still answers
            self._shot("timeout")
            vr = self.driver.execute_script(_VR_STATE_JS) if self.driver is not None else None
        except WebDriverException:
            vr = "the page no longer answers"
        except OSError as exc:  # the screenshot could not be written: the timeout still said
            vr = f"no screenshot: {exc.strerror or exc}"
        return f"{where} on show for {for_s:.0f} s" + (f" ({vr})" if vr else "")

    def _save_data_url(self, name: str, url: str) -> None:
        """A PNG data URL the page made (a canvas) as ``name``.png, once per name."""
        if self.screenshots is not None and name not in self.shots and "," in url:
            self.shots.add(name)
            self.screenshots.mkdir(parents=True, exist_ok=True)
            (self.screenshots / f"{name}.png").write_bytes(base64.b64decode(url.split(",", 1)[1]))

    def run(self, *, timeout_s: float = 900.0) -> str:
        """Walk the session; returns "complete", "stopped" (``stop_after`` reached) or
        "withdrawn" (stopped from the page, ``withdraw_after``)."""
        from selenium.webdriver.common.action_chains import ActionChains
        from selenium.webdriver.common.by import By

        p, token = self.participant()
        if p.completed is not None:
            return "complete"
        with Session(self.server.engine) as db:
            runs = db.scalar(select(func.count()).where(Action.participant_pk == p.pk)) or 0
        rng = np.random.default_rng(
            [self.seed, participant_seed(0, p.participant) % 2**32, int(runs)]
        )
        rater = RatingModel(self.server.study.protocol, rng=rng)
        chooser = ChoiceModel(self.server.study.protocol, rng=rng)
        sim = SimulatedParticipant(rater, chooser)
        study = self.server.study
        screens: dict[tuple[int | None, str, str | None], ResponseScreen] = {}
        for s in study.screens(p.participant):
            if isinstance(s, ResponseScreen) and not s.practice:
                keys = s.response_keys()
                # a screen of one item is also found by it (the questionnaire's screens share
                # their trial and kind); the first of a trial and kind by (trial, kind) alone
                if len(keys) == 1:
                    screens[(s.trial_index, s.kind, keys[0][1])] = s
                screens.setdefault((s.trial_index, s.kind, None), s)

        def screen_for(
            trial: int | None, kind: str, item: str | None = None
        ) -> ResponseScreen | None:
            """The response screen on show; a staircase trial's at the level the server
            chose from the answers stored so far (the page stored them before asking)."""
            adaptive = screens.get((trial, "adaptive", None))
            if isinstance(adaptive, AdaptiveTrial):
                expanded = study.expand_adaptive(
                    p.participant, p.session, adaptive, self.server.logged(p)
                )
                return next(s for s in expanded if isinstance(s, ResponseScreen))
            return screens.get((trial, kind, item)) or screens.get((trial, kind, None))

        own = self.driver is None
        if own:
            self.driver = chromium(size=self.window)
        d = self.driver
        vr = study.protocol.presentation.display == "webxr" and self.headset
        if vr:  # an emulated headset in this page (and on every reload)
            self._emulator = self._emulator or d.execute_cdp_cmd(
                "Page.addScriptToEvaluateOnNewDocument",
                {"source": emulator_js(headset_off_at=self.headset_off_at, input=self.vr_input,
                                       stereo=self.vr_stereo)},
            )

        def in_vr() -> bool:
            return bool(vr and d.execute_script(
                "return !!(window.FacelabLive && window.FacelabLive.inVR())"))  # fmt: skip

        def xr_select(selector: str, frac: float | None = None) -> None:
            """A click on the page, or in VR the controller's ray and trigger."""
            problem = d.execute_async_script(_XR_SELECT_JS, selector, frac)
            if problem:
                raise SessionError(f"simulated participant {self.k}: {problem}")

        def wait_for(selector: str, timeout_s: float = 10.0) -> None:
            """Until the VR panel shows the element ``selector`` (it is drawn as it appears)."""
            until = time.monotonic() + timeout_s
            while not d.execute_script(_ON_PANEL_JS, selector) and time.monotonic() < until:
                time.sleep(0.1)

        try:
            d.get(f"{self.base_url}/run#t={token}")
            deadline = time.monotonic() + timeout_s
            done_screens: dict[Any, float] = {}  # screen answered -> when
            showing: tuple[Any, float] = (None, time.monotonic())  # the state on show, since
            while time.monotonic() < deadline:
                state = d.execute_script(_STATE_JS)
                kind = state["kind"]
                key = (kind, state.get("seq"))
                if state != showing[0]:
                    showing = (state, time.monotonic())
                if key in done_screens and time.monotonic() - done_screens[key] > STUCK_S:
                    raise SessionError(
                        f"simulated participant {self.k}: the {kind} screen answered "
                        f"{STUCK_S:.0f} s ago is still on show"
                    )
                if (
                    kind in ("wait", "loading", "clip", "clip_pair", "saving")
                    or key in done_screens
                ):
                    if kind in ("clip", "clip_pair"):
                        if in_vr() and self.screenshots is not None and "vr-clip" not in self.shots:
                            # the avatar talking, in the room: a still the page takes in the
                            # frame that drew it, asked for until a clip gives one
                            self._save_data_url("vr-clip", d.execute_script(_VR_CLIP_STILL_JS))
                        self._shot(kind)
                    time.sleep(0.1)
                    continue
                if self.screenshots is not None and "conversation" not in self.shots:
                    # a live conversation's page keeps its first drawn frame with the mouth
                    # well open (a busy page answers a driver's call only every few seconds,
                    # so the request stands from the start and the still is fetched later)
                    shot = d.execute_script(_CONVERSATION_SNAP_JS)
                    if shot:
                        self._save_data_url("conversation", shot)
                if kind == "conversation":  # the partner talks; the participant watches
                    self._shot("conversation-page")
                    time.sleep(0.1)
                    continue
                if kind == "error":
                    raise SessionError(
                        f"simulated participant {self.k}: the page says "
                        f"{d.find_element(By.CSS_SELECTOR, '[data-facelab=error]').text!r}"
                    )
                if kind == "complete":
                    if in_vr():  # the end panel: take off the headset, then Exit
                        if self.screenshots is not None and "vr-clip" not in self.shots:
                            # a still asked for in one clip may be taken in a later one that
                            # a busy page's driver never saw on show: the page keeps it
                            self._save_data_url("vr-clip", d.execute_script(_VR_CLIP_STILL_JS))
                        wait_for("[data-facelab=exit_vr]")
                        self.vr_fades = d.execute_script(_FADES_JS)
                        self._shot("vr-end")
                        wait_s = 10.0
                        try:
                            xr_select("[data-facelab=exit_vr]")
                        except SessionError:
                            # the end panel's XR frames stopped (seen after a live
                            # conversation in VR, CI at fb52dcd): the page ends VR itself
                            # within a minute, as it does for a participant who never selects
                            self.exit_missed = True
                            wait_s = 75.0
                        until = time.monotonic() + wait_s
                        while in_vr() and time.monotonic() < until:
                            time.sleep(0.1)
                    self._shot("complete")
                    return "complete"
                if (
                    self.stop_after is not None
                    and self.given >= self.stop_after
                    and kind in _ANSWER_KINDS
                ):
                    return "stopped"
                if kind == "withdrawn":  # the stopped session's last page
                    self._shot("withdrawn")
                    return "withdrawn"
                if (
                    self.withdraw_after is not None
                    and not self.withdrew
                    and self.given >= self.withdraw_after
                    and kind in _ANSWER_KINDS
                ):
                    if in_vr():  # with the headset on: the panel's Stop, its question there
                        wait_for("[data-facelab=withdraw]")
                        xr_select("[data-facelab=withdraw]")
                        wait_for("[data-facelab=withdraw_confirm]")
                        self._shot("vr-withdraw-ask")
                        self.vr_fades = d.execute_script(_FADES_JS)
                        xr_select("[data-facelab=withdraw_confirm]")
                    else:
                        d.find_element(By.CSS_SELECTOR, "[data-facelab=withdraw]").click()
                        self._shot("withdraw-ask")
                        d.find_element(By.CSS_SELECTOR, "[data-facelab=withdraw_confirm]").click()
                    self.withdrew = True
                    until = time.monotonic() + 60  # until the page has reloaded
                    while time.monotonic() < until and d.execute_script(
                        "return !!document.querySelector('[data-facelab=withdraw_ask]')"
                    ):
                        time.sleep(0.2)
                    done_screens.clear()  # the reloaded page numbers its screens anew
                    continue
                if kind == "enter_vr":
                    self._shot("enter_vr")
                    d.find_element(By.CSS_SELECTOR, "[data-facelab=enter_vr] button").click()
                    time.sleep(0.5)
                    continue
                if kind == "recentre" and in_vr():
                    # a participant sitting a little turned: "ahead" is where they look (on a
                    # gaze-only headset they then look at the OK button to select it: its
                    # direction is the one the recentre takes)
                    d.execute_script(_FACE_JS, RECENTRE_YAW_DEG)
                    wait_for("[data-facelab=recentre_ok]")
                    self._shot("vr-recentre")
                    xr_select("[data-facelab=recentre_ok]")
                    time.sleep(0.2)
                    continue
                if kind == "consent":
                    self._shot("consent")
                    d.find_element(
                        By.CSS_SELECTOR, "#jspsych-html-button-response-btngroup button"
                    ).click()
                elif kind == "play":  # play() was refused: click, as a person would
                    d.find_element(By.CSS_SELECTOR, "[data-facelab=play]").click()
                    time.sleep(0.3)
                    continue
                elif kind == "fullscreen":
                    d.find_element(By.ID, "jspsych-fullscreen-btn").click()
                elif kind == "text":
                    self._shot(f"text-{state.get('role')}")
                    shown = d.find_element(By.CSS_SELECTOR, "#app [data-facelab=text]")
                    self.texts[str(state.get("role"))] = shown.get_attribute("textContent")
                    if in_vr():
                        self._shot(f"vr-text-{state.get('role')}")
                        xr_select("[data-facelab=next]")
                    else:
                        d.find_element(By.CSS_SELECTOR, "[data-facelab=next]").click()
                elif kind == "vas":
                    trial = state["trial"]  # None on the practice trial (never logged)
                    screen = screens.get((trial, "vas", None))
                    for wrap in d.find_elements(By.CSS_SELECTOR, ".facelab-vas-item"):
                        item = wrap.get_attribute("data-item")
                        vas = next(i for i in self.server.study.protocol.items if i.id == item)
                        lo, hi = vas.range
                        if screen is None or screen.trial is None:
                            value = round(float(rng.uniform(lo, hi)), 2)
                        else:
                            value, _rt = rater.rate(
                                item=item,
                                stimulus_set=screen.trial.stimulus_set,
                                condition=screen.trial.condition,
                            )
                            self._record(p, trial_index=trial, item=item, value=value)
                        if in_vr():  # the ray at the value's place on the panel's line
                            xr_select(
                                f".facelab-vas-item[data-item='{item}'] [data-facelab=line]",
                                (value - lo) / (hi - lo),
                            )
                            continue
                        line = wrap.find_element(By.CSS_SELECTOR, "[data-facelab=line]")
                        width = line.size["width"]
                        dx = round((value - lo) / (hi - lo) * (width - 1) - (width - 1) / 2)
                        ActionChains(d).move_to_element_with_offset(line, dx, 0).click().perform()
                    if in_vr():  # one shot per item (or set of items shown together)
                        self._shot(f"vr-vas-{state.get('item')}")
                        xr_select("[data-facelab=confirm]")
                    else:
                        self._shot("vas")
                        d.find_element(By.CSS_SELECTOR, "[data-facelab=confirm]").click()
                    self.given += screen is not None  # practice answers are not counted
                elif kind == "typed":  # type the answer into the field, then Enter
                    trial = state["trial"]
                    screen = screen_for(trial, kind)
                    if screen is None:  # the practice trial: what was said
                        text = "れんしゅう"
                    else:
                        (answer,) = screen.present(sim)
                        text = screen.posted(answer)["text"]
                        self._record(p, trial_index=trial, item=state.get("item") or "",
                                     value=text)  # fmt: skip
                    field = d.find_element(By.CSS_SELECTOR, "[data-facelab=answer]")
                    if text:
                        field.send_keys(text)
                    self._shot(kind)
                    field.send_keys("\n")
                    self.given += screen is not None
                elif kind == "matrix":  # a word in each column, then Confirm
                    trial = state["trial"]
                    screen = screen_for(trial, kind)
                    if screen is None:  # the practice trial: the first word of each column
                        cols = d.find_elements(By.CSS_SELECTOR, ".facelab-matrix-column")
                        words = [c.find_element(By.CSS_SELECTOR, "[data-facelab=word]")
                                 .get_attribute("data-value") for c in cols]  # fmt: skip
                    else:
                        (answer,) = screen.present(sim)
                        words = screen.posted(answer)["words"]
                        self._record(p, trial_index=trial, item=state.get("item") or "",
                                     value=" ".join(words))  # fmt: skip
                    vr = in_vr()
                    groups = [] if vr else d.find_elements(
                        By.CSS_SELECTOR, ".facelab-matrix [role=group][aria-label]")  # fmt: skip
                    for ci, word in enumerate(words):
                        if vr:  # the controller's ray (or the gaze) on the panel's word
                            xr_select(f"[data-facelab=word][data-column='{ci}']"
                                      f"[data-value={json.dumps(word, ensure_ascii=False)}]")
                            continue
                        # as a screen reader finds it: the column group named by its
                        # number, then the button that says the word
                        number = re.compile(rf"(?<!\d){ci + 1}(?!\d)")
                        (group,) = [g for g in groups
                                    if number.search(g.get_attribute("aria-label") or "")]
                        (button,) = [b for b in group.find_elements(By.TAG_NAME, "button")
                                     if b.text == word]  # fmt: skip
                        button.click()
                    if vr:
                        self._shot(f"vr-{kind}")
                        xr_select("[data-facelab=confirm]")
                    else:
                        self._shot(kind)
                        d.find_element(By.CSS_SELECTOR, "[data-facelab=confirm]").click()
                    self.given += screen is not None
                elif d.find_elements(By.CSS_SELECTOR, "[data-facelab=option]"):
                    # a screen answered by one of its option buttons: 2AFC, identification
                    # and any kind added to facelab that draws them
                    trial = state["trial"]
                    screen = screen_for(trial, kind, state.get("item"))
                    if screen is None:  # the practice trial: any answer
                        options = d.find_elements(By.CSS_SELECTOR, "[data-facelab=option]")
                        value = options[int(rng.integers(len(options)))].get_attribute("data-value")
                    else:  # the simulated participant's answer, as the page posts it
                        (answer,) = screen.present(sim)
                        (value,) = screen.posted(answer).values()
                    if screen is not None:
                        self._record(
                            p, trial_index=trial, item=state.get("item") or "", value=value
                        )
                    vr_now = in_vr()
                    self._shot(f"vr-{kind}" if vr_now else kind)
                    option = f"[data-facelab=option][data-value='{value}']"
                    if vr_now:
                        xr_select(option)
                    else:
                        d.find_element(By.CSS_SELECTOR, option).click()
                    self.given += screen is not None
                done_screens[key] = time.monotonic()
                time.sleep(0.05)
            raise SessionError(
                f"simulated participant {self.k} did not finish in {timeout_s} s: "
                + self._stuck_on(showing[0], time.monotonic() - showing[1])
            )
        finally:
            if own:
                d.quit()
                self.driver = None


def run_simulated(
    server: StudyServer,
    base_url: str,
    n: int,
    *,
    seed: int = 1,
    parallel: int = 2,
    screenshots: Path | None = None,
    progress: Callable[[int, str], None] | None = None,
    headset_off_at: int | None = None,
    vr_input: str = "controller",
    window: tuple[int, int] = WINDOW,
) -> dict[int, str]:
    """Drive simulated participants 1..n through the study; returns {k: outcome}. The first
    takes screenshots and, in VR, the headset off during trial ``headset_off_at``'s clip;
    ``vr_input``: their emulated headset's input (:data:`VR_INPUTS`); ``window``: each
    browser's window (width, height) in pixels."""

    def one(k: int) -> str:
        outcome = SimulatedBrowser(
            server, base_url, k, seed=seed, screenshots=screenshots if k == 1 else None,
            headset_off_at=headset_off_at if k == 1 else None, vr_input=vr_input, window=window,
        ).run()  # fmt: skip
        if progress is not None:
            progress(k, outcome)
        return outcome

    with ThreadPoolExecutor(max_workers=max(1, parallel)) as pool:
        return dict(zip(range(1, n + 1), pool.map(one, range(1, n + 1)), strict=True))
