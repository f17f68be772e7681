// facelab's jsPsych plugins: one per screen kind of the session timeline
// (facelab.experiment.timeline), with the lab runner's rules. Each gets its screen as JSON
// from the server; answers go through FacelabOutbox (stored locally first, then sent).
"use strict";
const FacelabSession = { playback: {}, ui: {}, stage: null };

function facelabEl(tag, cls, text) {
  const e = document.createElement(tag);
  if (cls) e.className = cls;
  if (text !== undefined) e.textContent = text;
  return e;
}
let facelabSeq = 0;
// The root element of one screen: its kind, its place in the session (for drivers and tests).
function facelabBox(cls, kind, screen) {
  const box = facelabEl("div", cls);
  box.dataset.facelab = kind;
  box.dataset.seq = String(++facelabSeq);
  if (screen && screen.trial_index !== null && screen.trial_index !== undefined) box.dataset.trial = String(screen.trial_index);
  return box;
}
function facelabSleep(ms) { return new Promise((res) => setTimeout(res, ms)); }
// Put a screen on the page; in VR (display webxr) its panel mirrors it in front of the
// participant (FacelabSession.stage: the live view, live.js) - answered there or here alike.
function facelabShow(el, box, mirror = true) {
  el.appendChild(box);
  const stage = FacelabSession.stage;
  if (stage) stage.mirror(mirror ? box : null);
}
// A plugin's jsPsych info: one typed parameter per field of its screen's JSON, exactly the
// fields facelab.experiment.timeline's Screen.browser() sends for the kind (a contract test,
// tests/test_screen_kinds.py, reads these and compares them with the Python JSON).
const FacelabFields = {
  screen: { kind: "STRING", trial_index: "INT", practice: "BOOL" },
  clip: { replay: "BOOL", clip: "STRING", fps: "FLOAT", frames: "INT", interval: "INT", announce: "STRING", gap_s: "FLOAT", track: "STRING" },
  task: { item: "STRING", question: "STRING" },
};
function facelabInfo(name, fields) {
  const parameters = {};
  for (const [key, type] of Object.entries(fields)) {
    parameters[key] = { type: jsPsychModule.ParameterType[type], default: null };
  }
  return { name, version: "1.0.0", parameters, data: {} };
}
function facelabAnswer(screen, item, fields, started) {
  const pb = FacelabSession.playback[screen.trial_index] || null;
  // in VR a selected button takes effect after the panel has faded out: the answer's time
  // is the select's (a select on an earlier screen is older than this one's start)
  const stage = FacelabSession.stage;
  const chosen = stage && stage.selectedAt !== null && stage.selectedAt >= started ? stage.selectedAt : performance.now();
  return Object.assign({
    client_key: FacelabOutbox.newKey(),
    trial_index: screen.trial_index,
    item,
    rt_s: Math.max(0, (chosen - started) / 1000),
    timestamp: new Date().toISOString(),
    clip_onset: pb ? pb.onset : null,
    clip_frames_dropped: pb ? pb.dropped : null,
  }, fields);
}
// Buttons also answer to keys (space for "next", 1..9 for choices).
function facelabKeys(map) {
  const handler = (ev) => { const b = map[ev.key]; if (b && !b.disabled) { ev.preventDefault(); b.click(); } };
  document.addEventListener("keydown", handler);
  return () => document.removeEventListener("keydown", handler);
}

class FacelabPlugin {
  constructor(jsPsych) { this.jsPsych = jsPsych; }
  trial(el, trial) {
    el.textContent = "";
    facelabReady(el, trial)
      .then(() => this.run(el, trial))
      .then((data) => { el.textContent = ""; this.jsPsych.finishTrial(data || {}); });
  }
}
// display webxr: every screen runs in the headset, so the immersive session is entered (or
// entered again after the headset was taken off) before the screen is shown - but not for
// the end page alone (its code is read on the screen), nor for the sickness questionnaire
// before the study while the headset is not yet on (its baseline is taken outside VR)
async function facelabReady(el, trial) {
  const stage = FacelabSession.stage;
  if (!stage || stage.ran !== "webxr" || stage.inVR()) return;
  if (trial && trial.kind === "text" && trial.role === "end" && stage.origin) return;
  if (trial && trial.kind === "ssq" && String(trial.item).startsWith("ssq_before_")) return;
  await facelabEnterVR(el);
}

// a text screen's words: in the headset its VR wording when the protocol (or facelab) has one
function facelabTextOf(s) {
  const stage = FacelabSession.stage;
  return stage && stage.inVR() && s.vr_text ? s.vr_text : s.text;
}

class FacelabText extends FacelabPlugin {
  async run(el, s) {
    const box = facelabBox("facelab-text", "text", s); box.dataset.role = s.role;
    box.appendChild(facelabEl("p", "", facelabTextOf(s)));
    const next = facelabEl("button", "facelab-button", FacelabSession.ui.next);
    next.dataset.facelab = "next";
    box.appendChild(next); facelabShow(el, box);
    await new Promise((res) => { const off = facelabKeys({ " ": next }); next.addEventListener("click", () => { off(); res(); }, { once: true }); });
    return { role: s.role };
  }
}
FacelabText.info = facelabInfo("facelab-text", { kind: "STRING", role: "STRING", text: "STRING", vr_text: "STRING" });

// One <video> of a clip screen, with the frames requestVideoFrameCallback reports.
function facelabVideo(clip, muted) {
  const video = document.createElement("video");
  video.playsInline = true; video.preload = "auto"; video.controls = false; video.muted = !!muted;
  const frames = [];
  const onFrame = (now, meta) => {
    frames.push([meta.expectedDisplayTime, meta.mediaTime, meta.presentedFrames]);
    video.requestVideoFrameCallback(onFrame);
  };
  if ("requestVideoFrameCallback" in video) video.requestVideoFrameCallback(onFrame);
  const ended = new Promise((res) => video.addEventListener("ended", res, { once: true }));
  return { video, frames, ended, clip };
}
// Start the videos together (every play() awaited; a refusal logged, then a click starts
// them) and wait until all have ended. Returns the refusal, or null.
async function facelabPlayAll(plugin, box, s, videos) {
  for (const v of videos) v.video.src = plugin.jsPsych.pluginAPI.getVideoBuffer("/clips/" + v.clip.clip);
  const playAll = () => Promise.all(videos.map((v) => v.video.play()));
  let refused = null;
  try { await playAll(); }
  catch (e) {
    refused = (e.name || "Error") + ": " + (e.message || "");
    FacelabOutbox.send("/api/event", { kind: "play_refused", detail: { clip: videos.map((v) => v.clip.clip).join(" "), trial_index: s.trial_index, error: refused } });
    const play = facelabEl("button", "facelab-button", "▶"); play.dataset.facelab = "play";
    box.appendChild(play);
    await new Promise((res) => play.addEventListener("click", res, { once: true }));
    play.remove();
    await playAll();
  }
  await Promise.all(videos.map((v) => v.ended));
  return refused;
}
// The _playback.jsonl record of one video (sent unless practice); returns onset and drops.
function facelabPlayback(s, v, refused) {
  const fps = v.clip.fps;
  const shown = v.frames.map((f) => Math.round(f[1] * fps));
  const expected = v.clip.frames || Math.round(v.video.duration * fps);
  const dropped = Math.max(0, expected - new Set(shown).size);
  const onset = v.frames.length ? v.frames[0][0] / 1000 : null;
  const record = {
    client_key: FacelabOutbox.newKey(), trial_index: s.practice ? null : s.trial_index,
    clip: v.clip.clip, replay: !!s.replay, onset, frames_expected: expected, dropped,
    flip_times: v.frames.map((f) => f[0] / 1000), frames_shown: shown,
    presented_frames: v.frames.length ? v.frames[v.frames.length - 1][2] : 0,
    media_time_end: v.video.currentTime, play_refused: refused,
  };
  if (!s.practice) FacelabOutbox.send("/api/playback", record);
  return { onset, dropped };
}

class FacelabClip extends FacelabPlugin {
  async run(el, s) {
    const box = facelabBox("facelab-clip", "clip", s);
    const announce = facelabEl("div", "facelab-announce", s.announce || "");
    box.appendChild(announce);
    const stage = FacelabSession.stage;
    let onset, dropped;
    if (stage) {  // display live3d / webxr: the avatar drawn here from the clip's track
      facelabShow(el, box, false);
      if (stage.ran === "webxr" && !stage.inVR()) await facelabEnterVR(box);
      stage.attach(box);
      if (s.gap_s) await facelabSleep(s.gap_s * 1000);
      const record = await stage.play(s, box);
      if (!s.practice) FacelabOutbox.send("/api/playback", record);
      ({ onset, dropped } = record);
    } else {
      const v = facelabVideo(s, false);
      box.appendChild(v.video); el.appendChild(box);
      if (s.gap_s) { v.video.hidden = true; await facelabSleep(s.gap_s * 1000); v.video.hidden = false; }
      const refused = await facelabPlayAll(this, box, s, [v]);
      ({ onset, dropped } = facelabPlayback(s, v, refused));
    }
    const prev = FacelabSession.playback[s.trial_index];
    FacelabSession.playback[s.trial_index] = (s.interval === 2 && prev)
      ? { onset: prev.onset, dropped: prev.dropped + dropped } : { onset, dropped };
    return { clip: s.clip, dropped };
  }
}
FacelabClip.info = facelabInfo("facelab-clip", { ...FacelabFields.screen, ...FacelabFields.clip });

// The button that starts (or, after the headset was taken off, restarts) the immersive
// session: entering VR needs a click. Then, with vr.recentre, the recentre step: the
// participant looks straight ahead and selects; the avatar is placed from there.
async function facelabEnterVR(parent) {
  const stage = FacelabSession.stage;
  const box = facelabEl("div", "facelab-text"); box.dataset.facelab = "enter_vr";
  box.appendChild(facelabEl("p", "", stage.words.enter_note));
  const b = facelabEl("button", "facelab-button", stage.words.enter); b.dataset.facelab = "enter";
  box.appendChild(b); parent.appendChild(box);
  for (;;) {
    await new Promise((res) => b.addEventListener("click", res, { once: true }));
    try { await stage.enterVR(); break; }
    catch (e) { FacelabOutbox.send("/api/event", { kind: "error", detail: { what: "enter VR", error: String(e.name || e) } }); }
  }
  box.remove();
  if (stage.vr.recentre === false || !stage.inVR()) return;
  const step = facelabEl("div", "facelab-text"); step.dataset.facelab = "recentre";
  step.appendChild(facelabEl("p", "", stage.words.recentre_note));
  const ok = facelabEl("button", "facelab-button", stage.words.recentre); ok.dataset.facelab = "recentre_ok";
  step.appendChild(ok); facelabShow(parent, step);
  await new Promise((res) => ok.addEventListener("click", res, { once: true }));
  stage.recentre("start");
  stage.mirror(null);
  step.remove();
}

// The end in VR: once every answer is stored the panel asks the participant to take off the
// headset (the completion code is on the page) and VR ends when they select Exit (or after a
// minute, or when they take it off).
async function facelabLeaveVR(box) {
  const stage = FacelabSession.stage;
  if (!stage || !stage.session) return;
  const note = facelabEl("p", "", stage.words.remove); note.dataset.facelab = "remove_headset";
  const exit = facelabEl("button", "facelab-button", stage.words.exit); exit.dataset.facelab = "exit_vr";
  box.appendChild(note); box.appendChild(exit);
  const ended = new Promise((res) => stage.session.addEventListener("end", res, { once: true }));
  await Promise.race([new Promise((res) => exit.addEventListener("click", res, { once: true })), ended, facelabSleep(60000)]);
  if (stage.session) await stage.session.end().catch(() => {});
  exit.remove();
}

// Two clips at once, left and right; only the clip on side s.sound has its sound.
class FacelabClipPair extends FacelabPlugin {
  async run(el, s) {
    const box = facelabBox("facelab-clip facelab-pair", "clip_pair", s);
    const videos = s.clips.map((c, i) => facelabVideo(c, i + 1 !== s.sound));
    const row = facelabEl("div", "facelab-pair-row");
    for (const v of videos) row.appendChild(v.video);
    box.appendChild(row); el.appendChild(box);
    const refused = await facelabPlayAll(this, box, s, videos);
    const both = videos.map((v) => facelabPlayback(s, v, refused));
    const onsets = both.map((b) => b.onset).filter((x) => x !== null);
    FacelabSession.playback[s.trial_index] = {
      onset: onsets.length ? Math.min(...onsets) : null,
      dropped: both.reduce((n, b) => n + b.dropped, 0),
    };
    return { clips: s.clips.map((c) => c.clip), dropped: FacelabSession.playback[s.trial_index].dropped };
  }
}
FacelabClipPair.info = facelabInfo("facelab-clip-pair", { ...FacelabFields.screen, replay: "BOOL", clips: "COMPLEX", sound: "INT" });

class FacelabVas extends FacelabPlugin {
  async run(el, s) {
    const started = performance.now();
    const box = facelabBox("facelab-vas", "vas", s); box.dataset.item = s.items.map((it) => it.id).join(",");
    const values = {};
    const confirm = facelabEl("button", "facelab-button", s.confirm);
    confirm.disabled = true; confirm.dataset.facelab = "confirm";
    for (const item of s.items) {
      const wrap = facelabEl("div", "facelab-vas-item"); wrap.dataset.item = item.id;
      wrap.appendChild(facelabEl("div", "facelab-question", item.question));
      const scale = facelabEl("div", "facelab-scale");
      const line = facelabEl("div", "facelab-line"); line.dataset.facelab = "line";
      const marker = facelabEl("div", "facelab-marker"); line.appendChild(marker);
      scale.appendChild(facelabEl("div", "facelab-anchor left", item.left));
      scale.appendChild(line);
      scale.appendChild(facelabEl("div", "facelab-anchor right", item.right));
      wrap.appendChild(scale); box.appendChild(wrap);
      const [lo, hi] = item.range;
      // a VR panel's ray places the marker through the same hook (line.facelabPlace)
      line.facelabPlace = (frac) => {
        values[item.id] = Math.round((lo + frac * (hi - lo)) * 100) / 100;
        marker.style.left = (frac * 100) + "%";
        marker.classList.add("shown");  // no marker until the first touch
        confirm.disabled = s.items.some((it) => values[it.id] === undefined);
      };
      const place = (ev) => {
        const r = line.getBoundingClientRect();
        line.facelabPlace(Math.min(1, Math.max(0, (ev.clientX - r.left) / r.width)));
      };
      line.addEventListener("pointerdown", (ev) => { line.setPointerCapture(ev.pointerId); place(ev); });
      line.addEventListener("pointermove", (ev) => { if (line.hasPointerCapture(ev.pointerId)) place(ev); });
    }
    box.appendChild(confirm); facelabShow(el, box);
    await new Promise((res) => confirm.addEventListener("click", res, { once: true }));
    if (!s.practice) {
      for (const item of s.items) {
        FacelabOutbox.send("/api/response", facelabAnswer(s, item.id, { rating: values[item.id] }, started));
      }
    }
    return { ratings: values };
  }
}
FacelabVas.info = facelabInfo("facelab-vas", { ...FacelabFields.screen, confirm: "STRING", items: "COMPLEX" });

class FacelabChoice extends FacelabPlugin {
  async buttons(el, s, kind, options) {
    const started = performance.now();
    const box = facelabBox("facelab-choice", kind, s); box.dataset.item = s.item;
    box.appendChild(facelabEl("div", "facelab-question", s.question));
    const row = facelabEl("div", "facelab-choices");
    const keys = {};
    const picked = new Promise((res) => {
      options.forEach((opt, i) => {
        const b = facelabEl("button", "facelab-button", opt.text);
        b.dataset.facelab = "option"; b.dataset.value = String(opt.value);
        b.addEventListener("click", () => res(opt.value), { once: true });
        keys[String(i + 1)] = b; row.appendChild(b);
      });
    });
    box.appendChild(row); facelabShow(el, box);
    const off = facelabKeys(keys);
    const value = await picked;
    off();
    return { value, started };
  }
  async run(el, s) {
    const { value, started } = await this.buttons(el, s, "choice_2afc",
      s.options.map((text, i) => ({ text, value: i + 1 })));
    if (!s.practice) FacelabOutbox.send("/api/response", facelabAnswer(s, s.item, { choice: value }, started));
    return { choice: value };
  }
}
FacelabChoice.info = facelabInfo("facelab-choice", { ...FacelabFields.screen, ...FacelabFields.task, options: "COMPLEX" });

class FacelabIdentify extends FacelabChoice {
  async run(el, s) {
    const { value, started } = await this.buttons(el, s, "identify",
      s.labels.map((lb) => ({ text: lb.text, value: lb.id })));
    if (!s.practice) FacelabOutbox.send("/api/response", facelabAnswer(s, s.item, { label: value }, started));
    return { label: value };
  }
}
FacelabIdentify.info = facelabInfo("facelab-identify", { ...FacelabFields.screen, ...FacelabFields.task, labels: "COMPLEX" });

// Type what was said: a text field (the participant's input method composes into it; Enter
// while composing finishes the composition, not the answer), Enter or Confirm answers.
class FacelabTyped extends FacelabPlugin {
  async run(el, s) {
    const started = performance.now();
    const box = facelabBox("facelab-choice facelab-typed", "typed", s); box.dataset.item = s.item;
    box.appendChild(facelabEl("div", "facelab-question", s.question));
    const field = facelabEl("input", "facelab-field"); field.type = "text";
    field.maxLength = s.max_length; field.lang = document.documentElement.lang || "";
    field.autocomplete = "off"; field.spellcheck = false; field.dataset.facelab = "answer";
    const confirm = facelabEl("button", "facelab-button", s.confirm); confirm.dataset.facelab = "confirm";
    box.appendChild(field); box.appendChild(confirm);
    box.appendChild(facelabEl("p", "facelab-note", s.hint));
    facelabShow(el, box); field.focus();
    await new Promise((res) => {
      confirm.addEventListener("click", res, { once: true });
      field.addEventListener("keydown", (ev) => {
        if (ev.key === "Enter" && !ev.isComposing && ev.keyCode !== 229) { ev.preventDefault(); res(); }
      });
    });
    const text = field.value.replace(/\s+/g, " ").trim().slice(0, s.max_length);
    if (!s.practice) FacelabOutbox.send("/api/response", facelabAnswer(s, s.item, { text }, started));
    return { text };
  }
}
FacelabTyped.info = facelabInfo("facelab-typed", { ...FacelabFields.screen, ...FacelabFields.task, max_length: "INT", confirm: "STRING", hint: "STRING" });

// Pick what was said from a word matrix (a matrix sentence test): one word in each column
// (a click picks, another click in the column moves the pick); Confirm answers once every
// column has a pick. The picks are posted as "words", in the columns' order.
class FacelabMatrix extends FacelabPlugin {
  async run(el, s) {
    const started = performance.now();
    const box = facelabBox("facelab-choice facelab-matrix", "matrix", s); box.dataset.item = s.item;
    box.appendChild(facelabEl("div", "facelab-question", s.question));
    const grid = facelabEl("div", "facelab-matrix-grid");
    grid.style.gridTemplateColumns = `repeat(${s.columns.length}, minmax(0, 1fr))`;
    const picked = new Array(s.columns.length).fill(null);
    const confirm = facelabEl("button", "facelab-button", s.confirm); confirm.dataset.facelab = "confirm";
    confirm.disabled = true;
    s.columns.forEach((column, ci) => {
      const col = facelabEl("div", "facelab-matrix-column"); col.dataset.column = String(ci);
      col.setAttribute("role", "group");  // a screen reader names the column before its words
      col.setAttribute("aria-label", (s.column_labels || [])[ci] || String(ci + 1));
      const buttons = column.map((word) => {
        const b = facelabEl("button", "facelab-button facelab-word", word);
        b.dataset.facelab = "word"; b.dataset.column = String(ci); b.dataset.value = word;
        b.setAttribute("aria-pressed", "false");
        b.addEventListener("click", () => {
          picked[ci] = word;
          for (const o of buttons) o.setAttribute("aria-pressed", String(o === b));
          confirm.disabled = picked.some((w) => w === null);
        });
        col.appendChild(b);
        return b;
      });
      grid.appendChild(col);
    });
    box.appendChild(grid); box.appendChild(confirm);
    box.appendChild(facelabEl("p", "facelab-note", s.hint));
    facelabShow(el, box);
    await new Promise((res) => confirm.addEventListener("click", () => { if (!picked.includes(null)) res(); }));
    const words = picked.slice();
    if (!s.practice) FacelabOutbox.send("/api/response", facelabAnswer(s, s.item, { words }, started));
    return { words };
  }
}
FacelabMatrix.info = facelabInfo("facelab-matrix", { ...FacelabFields.screen, ...FacelabFields.task, columns: "COMPLEX", column_labels: "COMPLEX", confirm: "STRING", hint: "STRING" });

// A screen kind of buttons from an installed package (facelab.experiment.screen_kinds.
// ButtonScreen, widget "buttons"): its question and choices; the answer posted as "value".
class FacelabButtons extends FacelabChoice {
  async run(el, s) {
    const { value, started } = await this.buttons(el, s, s.kind,
      s.choices.map((c) => ({ text: c.label, value: c.value })));
    if (!s.practice) FacelabOutbox.send("/api/response", facelabAnswer(s, s.item, { value }, started));
    return { value };
  }
}
FacelabButtons.info = facelabInfo("facelab-buttons", { ...FacelabFields.screen, ...FacelabFields.task, widget: "STRING", choices: "COMPLEX" });
// the plugin of a screen: its kind's own, or the generic buttons plugin of a buttons kind
function facelabPluginOf(s) {
  return FacelabPlugins[s.kind] || (s.widget === "buttons" ? FacelabButtons : undefined);
}

// A staircase trial: once every answer before it is stored, the server says which level it
// shows (the rule runs there, as in the lab); its screens then run like any others.
class FacelabAdaptive extends FacelabPlugin {
  async run(el, s) {
    let screens = null;
    for (let attempt = 0; !screens; attempt++) {
      await FacelabOutbox.flush();
      try {
        const r = await FacelabOutbox.request("GET", "/api/adaptive/" + s.trial_index);
        if (r.ok) screens = (await r.json()).screens;
      } catch (e) { /* server restarting: retry */ }
      if (!screens) {
        if (!el.firstChild) { const w = facelabEl("p", "facelab-note", FacelabSession.ui.loading); w.dataset.facelab = "wait"; el.appendChild(w); }
        await facelabSleep(Math.min(8000, 300 * 2 ** attempt));
      }
    }
    const shown = [];
    for (const x of screens) {
      el.textContent = "";
      shown.push(await new (facelabPluginOf(x))(this.jsPsych).run(el, x));
    }
    return { adaptive: s.trial_index, screens: shown };
  }
}
FacelabAdaptive.info = facelabInfo("facelab-adaptive", { kind: "STRING", trial_index: "INT", block: "STRING" });

// The end: the text, then the completion code once the server has every response.
// This screen never finishes: it stays as the session's last page.
class FacelabComplete extends FacelabPlugin {
  async run(el, s) {
    const box = facelabBox("facelab-text", "end", s);
    const stop = document.querySelector("[data-facelab=withdraw]"); if (stop) stop.remove();  // done: nothing to stop
    box.appendChild(facelabEl("p", "", facelabTextOf(s)));
    const status = facelabEl("p", "facelab-note", FacelabSession.ui.saving); status.dataset.facelab = "saving";
    box.appendChild(status); facelabShow(el, box);
    const started = Date.now();
    const LIMIT_MS = FacelabSession.endLimitMs || 90000;
    for (;;) {
      // the bound holds while the server is down or the browser offline: flush() retries
      // until its queue is empty, so it is raced against the time left (then every 2 s)
      const left = LIMIT_MS - (Date.now() - started);
      await Promise.race([FacelabOutbox.flush(), facelabSleep(Math.max(2000, left))]);
      if (Date.now() - started > LIMIT_MS && status.dataset.facelab === "saving") {
        // bounded wait: say what is wrong and what to do, and keep trying in the background;
        // the answers stay in this browser's outbox (sent on the next visit of the link)
        const unsaved = FacelabOutbox.held() + FacelabOutbox.pending();
        status.textContent = FacelabSession.ui.stuck.replace("{n}", String(unsaved));
        status.dataset.facelab = "stuck";
        // the experimenter's progress page lists this participant (sent when it can be)
        FacelabOutbox.send("/api/event", { kind: "error", detail: { what: "end page", unsaved } });
      }
      try {
        const r = await FacelabOutbox.request("GET", "/api/complete");
        if (r.ok) {
          const c = await r.json();
          status.textContent = FacelabSession.ui.saved;
          status.dataset.facelab = "complete";
          if (c.code) box.appendChild(facelabEl("p", "facelab-code", c.code));
          await facelabLeaveVR(box);  // in VR: take off the headset, then VR ends
          if (c.redirect) {
            const a = facelabEl("a", "facelab-button", FacelabSession.ui.back);
            a.href = c.redirect; a.dataset.facelab = "redirect"; box.appendChild(a);
          }
          if (document.fullscreenElement) document.exitFullscreen().catch(() => {});
          return new Promise(() => {});  // the last page stays (jsPsych would clear it)
        }
      } catch (e) { /* retry */ }
      await facelabSleep(2000);
    }
  }
}
FacelabComplete.info = facelabInfo("facelab-complete", { kind: "STRING", role: "STRING", text: "STRING", vr_text: "STRING" });

// A live conversation (presentation.conversation): the partner's avatar, driven by the
// talker's streamed voice, for the screen's seconds or until the talker ends it
// (conversation.js); answered with how it ended and the turns heard. In VR no panel covers
// the partner.
class FacelabConversation extends FacelabPlugin {
  async run(el, s) {
    const started = performance.now();
    const box = facelabBox("facelab-conversation", "conversation", s); box.dataset.item = s.item;
    const stage = FacelabSession.stage;
    const { converse } = await import("/static/conversation.js");
    const out = await converse({ box, screen: s, language: document.documentElement.lang, token: FacelabOutbox.readToken(),
                                 show: () => facelabShow(el, box, !(stage && stage.inVR())) });
    FacelabOutbox.send("/api/response", facelabAnswer(s, s.item, { ended: out.ended, turns: out.turns }, started));
    return { ended: out.ended, turns: out.turns };
  }
}
FacelabConversation.info = facelabInfo("facelab-conversation", { ...FacelabFields.screen, item: "STRING", condition: "STRING", seconds: "FLOAT", text: "STRING" });

// The plugin of each screen kind the server sends (facelab.experiment.online.study).
const FacelabPlugins = { text: FacelabText, clip: FacelabClip, clip_pair: FacelabClipPair, vas: FacelabVas,
                         choice_2afc: FacelabChoice, identify: FacelabIdentify, typed: FacelabTyped, matrix: FacelabMatrix,
                         adaptive: FacelabAdaptive, ssq: FacelabButtons,  // ssq: the sickness questionnaire's buttons
                         conversation: FacelabConversation };
