// A live talker heard and seen (facelab live's viewer, and the conversation screen of an online
// study): the talker's sound is played `playout_ms` after it arrives, and at every display frame
// the face frame of the audio being heard is drawn (frame k is the face at k / 100 s of the
// talker's audio; the server's method made it as the audio streamed). Every drawn frame is
// logged (page time, audio time heard, frame drawn, frame wanted) and sent to the server when
// the turn ends (or when the viewer stops mid-turn), which records it beside the turn's audio
// and track (experiment/live_dialogue/).
import { Stage } from "/static/live.js";

const AUDIO = 1, FRAMES = 2, MAX_LOG = 200000;
export const wsUrl = (path) => (location.protocol === "https:" ? "wss://" : "ws://") + location.host + path;

// Follow the turns a socket brings: `api` (the page's state for drivers and tests) gets
// state, turns, shown, lateAudio and snapshots; `onMessage(msg)` sees every text message.
// Returns stop(): the turn being heard is logged to the server now, the stage let go.
export function followTurns({ stage, cfg, ws, api, status, onMessage, output = null }) {
  const K = cfg.names.length, ctx = stage.audio;
  const channels = cfg.names.map((name) => ({ name, kind: "blendshape" }));
  let values = new Float32Array(K * 1024), have = -1, t0 = null, endS = null, log = [], sent = true;
  let arrivals = [];  // [first frame, audio context time it arrived] per frames message
  let poses = [];  // in VR: [page ms, x, y, z, yaw, pitch, roll] of the head per drawn frame
  api.lateAudio = 0; api.turns = 0;
  const frameTrack = { header: { channels }, channels: K, values: null };
  const sendLog = () => {
    sent = true;
    if (ws.readyState === 1) ws.send(JSON.stringify({ log, arrivals, poses, late_audio: api.lateAudio, display: stage.inVR() ? "webxr" : "live3d" }));
    api.lastLog = log.length;
  };

  ws.binaryType = "arraybuffer";
  ws.onmessage = (e) => {
    if (typeof e.data === "string") {
      const msg = JSON.parse(e.data);
      if ("turn" in msg) {  // a new turn: forget the last one's frames and clock
        have = -1; t0 = null; endS = null; log = []; arrivals = []; poses = []; sent = false; api.lateAudio = 0;
        api.state = "turn"; api.turns += 1;
        if (status) status.textContent = "";
      }
      if ("end" in msg) endS = msg.end / cfg.sample_rate;
      if (onMessage) onMessage(msg);
      return;
    }
    const head = new Uint32Array(e.data, 0, 4);
    const [kind, start, count, width] = head;
    const data = new Float32Array(e.data, 16, count * width);
    if (kind === AUDIO) {
      if (t0 === null) t0 = ctx.currentTime + cfg.playout_ms / 1000 - start / cfg.sample_rate;
      const buffer = ctx.createBuffer(1, count, cfg.sample_rate);
      buffer.copyToChannel(data, 0);
      const src = ctx.createBufferSource();
      src.buffer = buffer; src.connect(output || ctx.destination);  // in VR: from the mouth
      const when = t0 + start / cfg.sample_rate;
      if (when < ctx.currentTime) api.lateAudio += 1;  // arrived after its time: played now
      src.start(Math.max(when, ctx.currentTime));
    } else if (kind === FRAMES) {
      const need = (start + count) * K;
      if (need > values.length) { const v = new Float32Array(Math.max(need, 2 * values.length)); v.set(values); values = v; }
      values.set(data, start * K);
      have = Math.max(have, start + count - 1);
      if (t0 !== null && arrivals.length < MAX_LOG) arrivals.push([start, ctx.currentTime - t0]);
    }
  };

  stage.onFrame = (time, xrFrame) => {
    // a requested still (api.snap = {after_s, peak}): the canvas as last drawn, once it drew a
    // frame past after_s whose largest weight reached peak
    if (api.snapDue) { api.snapshot = stage.renderer.domElement.toDataURL("image/png"); api.snapDue = false; }
    if (api.bestDue) { api.bestShot = stage.renderer.domElement.toDataURL("image/png"); api.bestDue = false; }
    if (t0 === null || have < 0) return;
    const heard = stage.heardAt(time) - t0;  // s of the talker's audio being heard now
    if (heard < 0) return;
    const wanted = Math.floor(heard * cfg.fps + 1e-9);
    const k = Math.min(wanted, have);
    frameTrack.values = values.subarray(k * K, (k + 1) * K);
    stage.apply(frameTrack, 0);
    api.shown = { frame: k, heard, peak: Math.max(...frameTrack.values) };
    if (api.snap && !api.snapshot && heard > api.snap.after_s && api.shown.peak >= api.snap.peak) {
      api.snapDue = true; api.snap = null; api.snapped = api.shown;
    } else if (api.snap && !api.snapshot && heard >= 0 && (!api.best || api.shown.peak > api.best.peak)) {
      // the most moved face drawn so far, kept in case no frame reaches the wanted one (a short
      // turn on a page that draws a few frames a second)
      api.bestDue = true; api.best = api.shown;
    }
    if (!sent && log.length < MAX_LOG) {
      log.push([time, heard, k, wanted]);
      const head = stage.inVR() ? stage.viewer(xrFrame) : null;  // where the participant looked
      if (head) poses.push([time, ...head]);
    }
    if (!sent && endS !== null && heard > endS + 0.2) { sendLog(); api.state = "done"; }
  };

  return function stop() {
    if (!sent) sendLog();  // the viewer leaves mid-turn: what it drew so far is kept
    stage.onFrame = null;
    stage.rest();
  };
}

// The sound on: resumed now if the page may, else a button the participant presses.
export async function soundOn(ctx, parent, label) {
  if (ctx.state !== "running") await Promise.race([ctx.resume(), new Promise((r) => setTimeout(r, 1000))]);
  if (ctx.state === "running") return;
  const b = document.createElement("button");
  b.className = "facelab-button"; b.textContent = label; b.dataset.facelab = "listen";
  parent.append(b);
  b.onclick = async () => { await ctx.resume(); b.remove(); };
}

const WORDS = {
  ja: { listen: "音声をオンにする", waiting: "相手を待っています…", failed: "会話を始められませんでした。研究者に連絡してください。" },
  en: { listen: "Turn the sound on", waiting: "Waiting for your partner…", failed: "The conversation could not start. Please contact the researcher." },
};

// The conversation screen of an online study (presentation.conversation): the partner's avatar
// drawn live from the talker's voice until the conversation's time has run out (the server
// keeps its clock: a reloaded page rejoins it with the time left) or the talker ends it.
// Resolves {ended: "time" | "talker", turns}. A conversation that cannot run here (the server
// refuses it, the 3D view cannot start, the connection is lost) is said to the participant
// and reported as an event; the page reloads to rejoin it - nothing is answered for it.
export async function converse({ box, screen, language, token, show }) {
  const words = WORDS[language] || WORDS.en;
  // a driver's standing request for a still of the partner mid-turn (see followTurns' snap)
  const snap = window.FacelabSnapRequest ? { ...window.FacelabSnapRequest } : null;
  const api = window.FacelabDialogue = { state: "loading", turns: 0, snap };
  const fail = async (what, error) => {
    api.state = "failed"; api.error = String(error).slice(0, 300);
    box.textContent = "";
    const p = document.createElement("p"); p.className = "facelab-note"; p.dataset.facelab = "error";
    p.textContent = words.failed; box.append(p); show();
    FacelabOutbox.send("/api/event", { kind: "error", detail: { what, error: api.error } });
    await new Promise((res) => setTimeout(res, 8000));
    location.reload();  // rejoins the conversation where it is (the session resumes here)
    await new Promise(() => {});
  };
  let cfg, stage, own;
  try {
    const r = await FacelabOutbox.request("GET", "/api/conversation");
    if (!r.ok) return await fail("conversation", (await r.json().catch(() => ({}))).error || r.status);
    cfg = await r.json();
    // the session's own stage when it has one (live3d / webxr: the same avatar), else one here
    own = !FacelabSession.stage;
    stage = FacelabSession.stage || await new Stage({ display: "live3d", scene: cfg.scene, language, vr: cfg.vr }).init();
  } catch (e) {
    return await fail("conversation view", e && e.message || e);
  }
  api.cfg = cfg;
  window.FacelabLive = stage;
  const text = document.createElement("p"); text.className = "facelab-question"; text.textContent = screen.text;
  const status = document.createElement("p"); status.className = "facelab-announce"; status.dataset.facelab = "live-status";
  status.textContent = words.waiting;
  box.append(text);
  stage.attach(box);
  box.append(status);
  show();
  const inVR = stage.inVR();
  let voice = null;
  if (inVR) {  // the partner in the room, no panel and no rays over them, the voice from the mouth
    stage.avatar.visible = true; stage.showRays(false); stage.fadeIn();
    voice = stage.voiceOutput();
  } else {
    await soundOn(stage.audio, box, words.listen);
  }
  const ws = new WebSocket(wsUrl("/ws/conversation/view"));
  let finished = false, lost = null;
  const done = new Promise((res) => {
    if (cfg.ended) { res("talker"); return; }  // the talker ended it while this page was away
    ws.onopen = () => { ws.send(JSON.stringify({ token })); api.state = "waiting"; };
    const left = Number.isFinite(cfg.remaining_s) ? cfg.remaining_s : screen.seconds;
    setTimeout(() => res("time"), Math.max(0, left) * 1000);
    ws.onclose = () => { if (!finished) { lost = lost || "the connection to the server was lost"; res("lost"); } };
    const stop = followTurns({ stage, cfg, ws, api, status, output: voice && voice.node, onMessage: (msg) => {
      if (msg.conversation_end) res("talker");
      if (msg.error) { lost = msg.error; res("lost"); }
    } });
    api.stop = stop;
  });
  const ended = await done;
  finished = true;
  if (api.stop) api.stop();
  await new Promise((res) => setTimeout(res, 200));  // the log's message leaves before the close
  ws.close();
  if (voice && voice.at) voice.node.disconnect();
  if (inVR) stage.showRays(true);
  if (own) { stage.renderer.setAnimationLoop(null); stage.audio.close().catch(() => {}); }
  if (ended === "lost") return await fail("conversation connection", lost);
  api.state = "ended"; api.ended = ended;
  return { ended, turns: (cfg.turns || 0) + api.turns };
}
