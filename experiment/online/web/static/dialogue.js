// facelab live dialogue (`facelab live`, and the talker page of an online study's live
// conversation, `facelab serve` /talk): the talker page streams its microphone to the server
// (16 kHz, 10 ms chunks); the viewer page hears the talker `playout_ms` after the sound arrives
// and draws, at every display frame, the face frame of the audio it is hearing now
// (conversation.js). The server records each turn's audio, track and the viewers' logs
// (experiment/live_dialogue/).
import { Stage } from "/static/live.js";
import { followTurns, soundOn, wsUrl } from "/static/conversation.js";

const WORDS = {
  ja: { start: "話し始める", stop: "話し終える", listen: "音声をオンにする", waiting: "話し手を待っています…",
        talking: "話しています…", saved: "録音しました", enter: "VRを開始", secret: "実験者の秘密鍵",
        participant: "参加者ID（例 P0001）", join: "接続", end: "会話を終える", ended: "会話を終えました",
        viewers: "参加者の画面: {n}", room: "参加者の画面: {n} · 残り {left} 秒 · 録音した発話: {turns}" },
  en: { start: "Start talking", stop: "Stop", listen: "Turn the sound on", waiting: "Waiting for the talker…",
        talking: "Talking…", saved: "Turn recorded", enter: "Enter VR", secret: "Experimenter secret",
        participant: "Participant id (e.g. P0001)", join: "Connect", end: "End the conversation",
        ended: "Conversation ended", viewers: "Participant's page: {n}",
        room: "Participant's page: {n} · {left} s left · turns recorded: {turns}" },
};
const el = (tag, cls, text) => { const e = document.createElement(tag); if (cls) e.className = cls; if (text) e.textContent = text; return e; };
window.FacelabOutbox = window.FacelabOutbox || { send() {} };  // the study server's event log: none here

const online = document.body.dataset.online === "1";  // an online study's conversation talker
const cfg = online ? { language: document.documentElement.lang || "en", sample_rate: 16000, chunk: 160 }
                   : await (await fetch("/live.json")).json();
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
  const api = window.FacelabDialogue;
  const login = {}, viewers = el("p", "facelab-note");
  if (online) {  // whom to talk to: the experimenter's secret and the participant's id
    for (const [key, type] of [["secret", "password"], ["participant", "text"]]) {
      const label = el("label", "facelab-field", words[key]);
      const input = el("input"); input.type = type; input.dataset.facelab = key;
      input.value = key === "participant" ? params.get("participant") || "" : sessionStorage.getItem("facelab-admin") || "";
      label.append(input); main.append(label); login[key] = input;
    }
    const end = el("button", "facelab-button", words.end); end.dataset.facelab = "end_conversation";
    end.onclick = async () => {  // the participant's conversation screen ends now
      const r = await fetch("/api/conversation/end", { method: "POST", headers: { "content-type": "application/json", "x-facelab-admin": login.secret.value },
                                                       body: JSON.stringify({ participant: login.participant.value.trim() }) });
      const body = await r.json().catch(() => ({}));
      status.textContent = r.ok ? words.ended : body.error || String(r.status);
      api.state = r.ok ? "ended" : "refused";
    };
    login.secret.onchange = () => sessionStorage.setItem("facelab-admin", login.secret.value);
    login.end = end;
    main.append(viewers);
    // where the participant is: their page in the conversation, the time left, the turns
    setInterval(async () => {
      const who = login.participant.value.trim(), secret = login.secret.value;
      if (!who || !secret) return;
      const r = await fetch("/api/conversation/status?participant=" + encodeURIComponent(who),
                            { headers: { "x-facelab-admin": secret } }).catch(() => null);
      const b = r ? await r.json().catch(() => ({})) : {};
      api.participant = r && r.ok ? b : null;
      viewers.textContent = !r ? "" : r.ok
        ? words.room.replace("{n}", b.viewers).replace("{left}", Math.round(b.remaining_s)).replace("{turns}", b.turns) + (b.ended ? " · " + words.ended : "")
        : b.error || String(r.status);
    }, 2000);
  }
  const button = el("button", "facelab-button", words.start);
  button.dataset.facelab = "talk";
  main.append(button);
  if (login.end) main.append(login.end);
  let ws = null, ctx = null, stream = null, pending = [], have = 0;

  async function start() {
    button.disabled = true;
    ctx = new AudioContext({ sampleRate: cfg.sample_rate });
    stream = await navigator.mediaDevices.getUserMedia({ audio: { echoCancellation: false, noiseSuppression: false, autoGainControl: false } });
    const source = ctx.createMediaStreamSource(stream);
    await ctx.audioWorklet.addModule("/static/capture.js");
    const node = new AudioWorkletNode(ctx, "facelab-capture");
    ws = new WebSocket(wsUrl(online ? "/ws/conversation/talk" : "/ws/talk"));
    ws.binaryType = "arraybuffer";
    await new Promise((res, rej) => { ws.onopen = res; ws.onerror = () => rej(new Error("socket")); });
    if (online) ws.send(JSON.stringify({ admin: login.secret.value, participant: login.participant.value.trim() }));
    ws.onmessage = (e) => {
      const msg = JSON.parse(e.data);
      if ("joined" in msg) { api.viewers = msg.viewers; viewers.textContent = words.viewers.replace("{n}", msg.viewers); }
      if (msg.started) { api.state = "talking"; status.textContent = words.talking; }
      if (msg.error) { api.state = "refused"; status.textContent = msg.error; ready(); }
      if ("saved" in msg) { api.state = "saved"; api.saved = msg.saved; status.textContent = words.saved; ready(); }
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

  function ready() {  // this turn's capture let go; the button starts the next turn
    if (stream) for (const t of stream.getTracks()) t.stop();
    if (ctx) { ctx.close().catch(() => {}); ctx = null; pending = []; have = 0; }
    button.textContent = words.start; button.disabled = false; button.onclick = start;
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
  await soundOn(stage.audio, main, words.listen);
  if (cfg.display === "webxr" && await stage.supported()) {
    const b = el("button", "facelab-button", words.enter); b.dataset.facelab = "enter_vr";
    main.append(b);
    b.onclick = async () => {
      b.remove();
      await stage.enterVR();
      for (const c of stage.controllers || []) c.visible = false;  // no panel to point at here
    };
  }
  followTurns({ stage, cfg, ws: new WebSocket(wsUrl("/ws/view")), api, status });
}
