// facelab live dialogue (`facelab live`): the talker page streams its microphone to the server
// (16 kHz, 10 ms chunks); the viewer page hears the talker `playout_ms` after the sound arrives
// and draws, at every display frame, the face frame of the audio it is hearing now (frame k is
// the face at k / 100 s of the talker's audio; the server's method made it as the audio
// streamed). The viewer logs every drawn frame (page time, audio time heard, frame drawn, frame
// wanted) and sends the log to the server when the turn ends: the server records it beside the
// turn's audio and track (experiment/live_dialogue/).
import { Stage } from "/static/live.js";

const WORDS = {
  ja: { start: "話し始める", stop: "話し終える", listen: "音声をオンにする", waiting: "話し手を待っています…",
        talking: "話しています…", saved: "録音しました", enter: "VRを開始" },
  en: { start: "Start talking", stop: "Stop", listen: "Turn the sound on", waiting: "Waiting for the talker…",
        talking: "Talking…", saved: "Turn recorded", enter: "Enter VR" },
};
const AUDIO = 1, FRAMES = 2, MAX_LOG = 200000;
const wsUrl = (path) => (location.protocol === "https:" ? "wss://" : "ws://") + location.host + path;
const el = (tag, cls, text) => { const e = document.createElement(tag); if (cls) e.className = cls; if (text) e.textContent = text; return e; };
window.FacelabOutbox = window.FacelabOutbox || { send() {} };  // the study server's event log: none here

const cfg = await (await fetch("/live.json")).json();
const words = WORDS[cfg.language] || WORDS.en;
const main = document.getElementById("facelab-live");
const status = el("p", "facelab-announce");
status.dataset.facelab = "live-status";
window.FacelabDialogue = { cfg, state: "loading" };

if (document.body.dataset.role === "talk") await talker(); else await viewer();

// -- the talker: microphone -> 16 kHz float32 chunks of 10 ms over a socket

async function talker() {
  main.className = "facelab-page";
  main.append(status);
  const params = new URLSearchParams(location.search);
  const button = el("button", "facelab-button", words.start);
  button.dataset.facelab = "talk";
  main.append(button);
  const api = window.FacelabDialogue;
  let ws = null, ctx = null, stream = null, pending = [], have = 0;

  async function start() {
    button.disabled = true;
    ctx = new AudioContext({ sampleRate: cfg.sample_rate });
    stream = await navigator.mediaDevices.getUserMedia({ audio: { echoCancellation: false, noiseSuppression: false, autoGainControl: false } });
    const source = ctx.createMediaStreamSource(stream);
    const url = URL.createObjectURL(new Blob([`
      class Capture extends AudioWorkletProcessor {
        process(inputs) { const x = inputs[0][0]; if (x) this.port.postMessage(x.slice(0)); return true; }
      }
      registerProcessor("facelab-capture", Capture);`], { type: "text/javascript" }));
    await ctx.audioWorklet.addModule(url);
    const node = new AudioWorkletNode(ctx, "facelab-capture");
    ws = new WebSocket(wsUrl("/ws/talk"));
    ws.binaryType = "arraybuffer";
    await new Promise((res, rej) => { ws.onopen = res; ws.onerror = () => rej(new Error("socket")); });
    ws.onmessage = (e) => {
      const msg = JSON.parse(e.data);
      if (msg.started) { api.state = "talking"; status.textContent = words.talking; }
      if (msg.error) { api.state = "refused"; status.textContent = msg.error; }
      if ("saved" in msg) { api.state = "saved"; api.saved = msg.saved; status.textContent = words.saved; }
    };
    ws.send(JSON.stringify({ sample_rate: ctx.sampleRate }));
    node.port.onmessage = (e) => {
      pending.push(e.data); have += e.data.length;
      while (have >= cfg.chunk) {  // 10 ms chunks
        const out = new Float32Array(cfg.chunk);
        let k = 0;
        while (k < cfg.chunk) {
          const head = pending[0], take = Math.min(head.length, cfg.chunk - k);
          out.set(head.subarray(0, take), k); k += take;
          if (take === head.length) pending.shift(); else pending[0] = head.subarray(take);
        }
        have -= cfg.chunk;
        if (ws.readyState === 1) ws.send(out.buffer);
      }
    };
    source.connect(node);
    button.textContent = words.stop; button.disabled = false;
    button.onclick = stop;
  }

  function stop() {
    button.disabled = true;
    if (stream) for (const t of stream.getTracks()) t.stop();
    if (ws && ws.readyState === 1) ws.send(JSON.stringify({ end: 1 }));
    api.state = "stopping";
  }

  button.onclick = start;
  api.start = start; api.stop = stop;
  const seconds = parseFloat(params.get("seconds") || "0");
  if (params.get("auto") === "1") {  // a simulated talker: speak now, stop after `seconds`
    await start();
    if (seconds > 0) setTimeout(stop, seconds * 1000);
  }
}

// -- the viewer: the talker's sound after the playout delay, the face frame of what is heard

async function viewer() {
  const stage = await new Stage({ display: cfg.display, scene: cfg.scene, language: cfg.language, vr: cfg.vr }).init();
  window.FacelabLive = stage;
  main.className = "facelab-clip";
  stage.attach(main);
  main.append(status);
  status.textContent = words.waiting;
  const api = window.FacelabDialogue;
  api.state = "waiting";
  const K = cfg.names.length, ctx = stage.audio;
  const channels = cfg.names.map((name) => ({ name, kind: "blendshape" }));
  let values = new Float32Array(K * 1024), have = -1, t0 = null, endS = null, log = [], sent = true;
  let arrivals = [];  // [first frame, audio context time it arrived] per frames message
  api.lateAudio = 0; api.turns = 0;
  const frameTrack = { header: { channels }, channels: K, values: null };

  if (ctx.state !== "running") {
    await Promise.race([ctx.resume(), new Promise((r) => setTimeout(r, 1000))]);
  }
  if (ctx.state !== "running") {  // a gesture turns the sound on
    const b = el("button", "facelab-button", words.listen); b.dataset.facelab = "listen";
    main.append(b);
    b.onclick = async () => { await ctx.resume(); b.remove(); };
  }
  if (cfg.display === "webxr" && await stage.supported()) {
    const b = el("button", "facelab-button", words.enter); b.dataset.facelab = "enter_vr";
    main.append(b);
    b.onclick = async () => {
      b.remove();
      await stage.enterVR();
      for (const c of stage.controllers || []) c.visible = false;  // no panel to point at here
    };
  }

  const ws = new WebSocket(wsUrl("/ws/view"));
  ws.binaryType = "arraybuffer";
  ws.onmessage = (e) => {
    if (typeof e.data === "string") {
      const msg = JSON.parse(e.data);
      if ("turn" in msg) {  // a new turn: forget the last one's frames and clock
        have = -1; t0 = null; endS = null; log = []; arrivals = []; sent = false; api.lateAudio = 0;
        api.state = "turn"; api.turns += 1;
        status.textContent = "";
      }
      if ("end" in msg) endS = msg.end / cfg.sample_rate;
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
      src.buffer = buffer; src.connect(ctx.destination);
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

  stage.onFrame = (time) => {
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
    if (!sent && log.length < MAX_LOG) log.push([time, heard, k, wanted]);
    if (!sent && endS !== null && heard > endS + 0.2) {
      sent = true;
      ws.send(JSON.stringify({ log, arrivals, late_audio: api.lateAudio, display: stage.inVR() ? "webxr" : "live3d" }));
      api.state = "done"; api.lastLog = log.length;
    }
  };
}
