// The session page: send what a closed tab left behind, ask the server for the remaining
// timeline, and walk it with jsPsych (consent, browser check, fullscreen, preload, screens).
"use strict";
const FACELAB_UI = {
  ja: { agree: "同意して始める", next: "次へ", saving: "回答を保存しています…", saved: "すべての回答を保存しました。",
        back: "完了ページへ", fullscreen: "全画面表示で行います。", start: "開始", loading: "読み込み中…",
        missing: "このリンクは無効です。募集ページのリンクから開いてください。", resume: "中断したところから再開します。",
        withdraw: "中止する", withdraw_ask: "研究への参加を中止しますか？ここまでの回答は保存されます。", withdraw_yes: "中止する", withdraw_no: "続ける",
        withdrawn: "参加を中止しました。ここまでの回答は保存されています。ご協力ありがとうございました。募集サイトの案内に従って手続きしてください。",
        withdrawn_unsaved: "参加を中止しました。{n}件の回答をまだ保存できていません。このページを閉じずに、募集サイトのメッセージ機能で研究者にご連絡ください。閉じる場合は、後で同じブラウザで募集ページのリンクを開き直してください。回答はこのブラウザに残っていて、そのときに送られます。",
        stuck: "{n}件の回答をまだ保存できていません。このページを閉じずに、募集サイトのメッセージ機能で研究者にご連絡ください。保存できしだい完了コードを表示します。閉じる場合は、後で同じブラウザで募集ページのリンクを開き直してください。回答はこのブラウザに残っていて、そのときに送られます。" },
  en: { agree: "I agree, start", next: "Next", saving: "Saving your answers…", saved: "All your answers are saved.",
        back: "Back to the recruitment site", fullscreen: "The study runs in full screen.", start: "Start",
        loading: "Loading…", missing: "This link is not valid. Please open the link from the recruitment site.",
        resume: "Continuing where you stopped.",
        withdraw: "Stop the study", withdraw_ask: "Stop taking part in the study? Your answers so far are kept.", withdraw_yes: "Stop", withdraw_no: "Continue",
        withdrawn: "You have stopped the study. Your answers so far are kept. Thank you for taking part; please follow the recruitment site's instructions.",
        withdrawn_unsaved: "You have stopped the study. {n} of your answers could not be saved yet. Please keep this page open and contact the researcher through the recruitment site's messages. If you must close it, open the recruitment link again later in this browser: your answers are kept here and sent then.",
        nolive: "This browser cannot show the study's 3D view. Please open the recruitment link again in a current Chrome, Edge or Firefox.",
        stuck: "{n} of your answers could not be saved yet. Please keep this page open and contact the researcher through the recruitment site's messages. The completion code appears here as soon as they are saved. If you must close it, open the recruitment link again later in this browser: your answers are kept here and sent then." },
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

  if (state.withdrawn) { await facelabWithdrawn(state, ui, app); return; }
  if (!state.complete) facelabWithdrawControl(ui);
  for (const src of state.plugins || []) {  // the plugins of screen kinds added to facelab
    await new Promise((res, rej) => {
      const s = document.createElement("script"); s.src = src; s.onload = res; s.onerror = rej;
      document.head.appendChild(s);
    });
  }
  if (state.display && state.display !== "video") {  // the avatar drawn live (live.js)
    let stage = null;
    try { stage = await (await import("/static/live.js")).createStage(state); }
    catch (e) {
      FacelabOutbox.send("/api/event", { kind: "error", detail: { what: "live view", error: String(e && e.message || e).slice(0, 300) } });
      fail(FACELAB_UI[state.language] ? FACELAB_UI[state.language].nolive : FACELAB_UI.en.nolive); return;
    }
    if (state.display === "webxr" && !(await stage.supported())) {
      const fallback = state.vr && state.vr.fallback === "live3d";
      FacelabOutbox.send("/api/event", { kind: "display", detail: { requested: "webxr", ran: fallback ? "live3d" : "none", reason: "no immersive-vr session in this browser" } });
      if (!fallback) { await FacelabOutbox.flush(); fail(stage.words.needs); return; }
      stage.ran = "live3d"; stage.renderer.xr.enabled = false;
    } else if (state.display === "live3d") {
      FacelabOutbox.send("/api/event", { kind: "display", detail: { requested: "live3d", ran: "live3d" } });
    }
    FacelabSession.stage = stage;
    for (const s of state.timeline) if (s.track) stage.clip(s).catch(() => {});  // fetch ahead
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
  if (state.fullscreen && !(FacelabSession.stage && FacelabSession.stage.ran === "webxr")) {
    timeline.push({ type: jsPsychFullscreen, fullscreen_mode: true, message: `<p>${ui.fullscreen}</p>`, button_label: ui.start });
  }
  if (state.clips.length && !FacelabSession.stage) {
    timeline.push({ type: jsPsychPreload, video: state.clips.map((c) => "/clips/" + c), message: ui.loading, show_progress_bar: true, max_load_time: 600000 });
  }
  for (const s of state.timeline) {
    const type = s.kind === "text" && s.role === "end" ? FacelabComplete : facelabPluginOf(s);
    timeline.push(Object.assign({ type }, s));  // the screen's fields are the plugin's parameters
  }
  document.addEventListener("fullscreenchange", () => {
    if (!document.fullscreenElement && !document.querySelector("[data-facelab=complete]")) {
      FacelabOutbox.send("/api/event", { kind: "fullscreen_exit", detail: {} });
    }
  });
  await jsPsych.run(timeline);
})();

// Stopping the study (a participant may, at any time): a small button in the corner asks
// again, logs a "withdrawn" event (kept in this browser until the server has it) and reloads
// the page, which the server then serves as a stopped session.
function facelabWithdrawControl(ui) {
  const stop = facelabEl("button", "facelab-withdraw", ui.withdraw); stop.dataset.facelab = "withdraw";
  document.body.appendChild(stop);
  stop.addEventListener("click", () => {
    if (document.querySelector("[data-facelab=withdraw_ask]")) return;
    const ask = facelabEl("div", "facelab-withdraw-ask"); ask.dataset.facelab = "withdraw_ask";
    ask.appendChild(facelabEl("p", "", ui.withdraw_ask));
    const yes = facelabEl("button", "facelab-button", ui.withdraw_yes); yes.dataset.facelab = "withdraw_confirm";
    const no = facelabEl("button", "facelab-button", ui.withdraw_no); no.dataset.facelab = "withdraw_cancel";
    ask.appendChild(yes); ask.appendChild(no); document.body.appendChild(ask);
    // while it asks, keys do not reach the screen behind it (a space would go on)
    const hold = (e) => {  // keys on the question's own buttons still work
      if (document.body.contains(ask) && !ask.contains(e.target)) { e.stopImmediatePropagation(); e.preventDefault(); }
    };
    yes.focus();
    window.addEventListener("keydown", hold, true); window.addEventListener("keyup", hold, true);
    no.addEventListener("click", () => {
      ask.remove(); window.removeEventListener("keydown", hold, true); window.removeEventListener("keyup", hold, true);
      stop.blur();  // Enter or space go to the screen again, not to Stop
      const on = document.querySelector("#app [data-facelab]");
      FacelabOutbox.send("/api/event", { kind: "withdraw_cancelled", detail: { trial_index: on && on.dataset.trial ? Number(on.dataset.trial) : null } });
    });
    yes.addEventListener("click", async () => {
      yes.disabled = true; no.disabled = true;
      const on = document.querySelector("#app [data-facelab]");
      const detail = { screen: on ? on.dataset.facelab : null, trial_index: on && on.dataset.trial ? Number(on.dataset.trial) : null };
      FacelabOutbox.send("/api/event", { kind: "withdrawn", detail });
      const stage = FacelabSession.stage;
      if (stage && stage.session) await stage.session.end().catch(() => {});
      await Promise.race([FacelabOutbox.flush(), facelabSleep(20000)]);
      location.reload();  // an unsent event goes first on the next load
    });
  });
}

// A stopped session: the sickness questionnaire after (when the protocol asks for it), on the
// plain page, then the note that the answers are kept.
async function facelabWithdrawn(state, ui, app) {
  app.textContent = "";
  const timeline = state.timeline.map((s) => Object.assign({ type: facelabPluginOf(s) }, s));
  if (timeline.length) await initJsPsych({ display_element: "app" }).run(timeline);
  await Promise.race([FacelabOutbox.flush(), facelabSleep(30000)]);
  app.textContent = "";
  const box = facelabEl("div", "facelab-text"); box.dataset.facelab = "withdrawn";
  const unsaved = FacelabOutbox.held() + FacelabOutbox.pending();
  // answers not yet stored are not called kept: what to do instead (they stay in the browser)
  box.appendChild(facelabEl("p", "", unsaved ? ui.withdrawn_unsaved.replace("{n}", String(unsaved)) : ui.withdrawn));
  app.appendChild(box);
}
