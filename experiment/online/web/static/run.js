// The session page: send what a closed tab left behind, ask the server for the remaining
// timeline, and walk it with jsPsych (consent, browser check, fullscreen, preload, screens).
"use strict";
const FACELAB_UI = {
  ja: { agree: "同意して始める", next: "次へ", saving: "回答を保存しています…", saved: "すべての回答を保存しました。",
        back: "完了ページへ", fullscreen: "全画面表示で行います。", start: "開始", loading: "読み込み中…",
        missing: "このリンクは無効です。募集ページのリンクから開いてください。", resume: "中断したところから再開します。",
        stuck: "{n}件の回答をまだ保存できていません。このページを閉じずに、募集サイトのメッセージ機能で研究者にご連絡ください。保存できしだい完了コードを表示します。" },
  en: { agree: "I agree, start", next: "Next", saving: "Saving your answers…", saved: "All your answers are saved.",
        back: "Back to the recruitment site", fullscreen: "The study runs in full screen.", start: "Start",
        loading: "Loading…", missing: "This link is not valid. Please open the link from the recruitment site.",
        resume: "Continuing where you stopped.",
        stuck: "{n} of your answers could not be saved yet. Please keep this page open and contact the researcher through the recruitment site's messages. The completion code appears here as soon as they are saved." },
};

(async function main() {
  const app = document.getElementById("app");
  const token = FacelabOutbox.readToken();
  const fail = (text) => { app.textContent = ""; const p = facelabEl("p", "facelab-note", text); p.dataset.facelab = "error"; app.appendChild(p); };
  if (!token) { fail(FACELAB_UI.en.missing); return; }
  await FacelabOutbox.flush();             // answers a closed tab did not get to send
  let state = null;
  for (let attempt = 0; !state; attempt++) {
    try {
      const r = await FacelabOutbox.request("GET", "/api/session");
      if (r.status === 401 || r.status === 409) { fail((await r.json()).error || FACELAB_UI.en.missing); return; }
      if (r.ok) state = await r.json();
    } catch (e) { /* server restarting */ }
    if (!state) await facelabSleep(Math.min(8000, 500 * 2 ** attempt));
  }
  const ui = FACELAB_UI[state.language] || FACELAB_UI.en;
  FacelabSession.ui = ui;
  document.documentElement.lang = state.language;
  const status = facelabEl("div", "facelab-status"); document.body.appendChild(status);
  FacelabOutbox.onChange((n) => { status.textContent = n ? `${n} …` : ""; });

  for (const src of state.plugins || []) {  // the plugins of screen kinds added to facelab
    await new Promise((res, rej) => {
      const s = document.createElement("script"); s.src = src; s.onload = res; s.onerror = rej;
      document.head.appendChild(s);
    });
  }
  app.textContent = "";
  const jsPsych = initJsPsych({ display_element: "app" });
  const timeline = [];
  if (state.resumed) {
    timeline.push({ type: FacelabText, kind: "text", role: "resume", text: ui.resume });
  } else if (state.consent) {
    timeline.push({ type: jsPsychHtmlButtonResponse, stimulus: "", choices: [ui.agree],
      on_load: () => {
        const el = document.querySelector("#jspsych-html-button-response-stimulus");
        const p = facelabEl("div", "facelab-text", state.consent); p.dataset.facelab = "consent"; el.appendChild(p);
      } });
  }
  timeline.push({
    type: jsPsychBrowserCheck, skip_features: ["webcam", "microphone"],
    on_finish: (data) => {
      const keep = ["width", "height", "browser", "browser_version", "mobile", "os", "fullscreen", "vsync_rate"];
      const detail = {}; keep.forEach((k) => { if (k in data) detail[k] = data[k]; });
      detail.device_pixel_ratio = window.devicePixelRatio;
      FacelabOutbox.send("/api/event", { kind: "browser", detail });
    },
  });
  if (state.fullscreen) {
    timeline.push({ type: jsPsychFullscreen, fullscreen_mode: true, message: `<p>${ui.fullscreen}</p>`, button_label: ui.start });
  }
  if (state.clips.length) {
    timeline.push({ type: jsPsychPreload, video: state.clips.map((c) => "/clips/" + c), message: ui.loading, show_progress_bar: true, max_load_time: 600000 });
  }
  for (const s of state.timeline) {
    const type = s.kind === "text" && s.role === "end" ? FacelabComplete : FacelabPlugins[s.kind];
    timeline.push(Object.assign({ type }, s));  // the screen's fields are the plugin's parameters
  }
  document.addEventListener("fullscreenchange", () => {
    if (!document.fullscreenElement && !document.querySelector("[data-facelab=complete]")) {
      FacelabOutbox.send("/api/event", { kind: "fullscreen_exit", detail: {} });
    }
  });
  await jsPsych.run(timeline);
})();
