// The jsPsych plugin of the screen kind "effort" (facelab_example_plugin.effort): a row of
// numbered circles between two anchors; keys 1-7 or a click. facelab serves this file at
// /plugins/effort.js and loads it when a session shows the kind. Its parameters are the
// fields EffortScreen.browser sends: kind, trial_index, item, practice and browser_params.
"use strict";
class FacelabEffort extends FacelabPlugin {
  async run(el, s) {
    const started = performance.now();
    const box = facelabBox("facelab-choice", s.kind, s); box.dataset.item = s.item;
    box.appendChild(facelabEl("div", "facelab-question", s.question));
    // its own layout (inline styles: nothing of facelab's stylesheet is assumed but the button)
    const row = facelabEl("div");
    Object.assign(row.style, { display: "flex", flexWrap: "nowrap", alignItems: "center",
      justifyContent: "center", gap: "0.6em", margin: "1.5em auto" });
    const keys = {};
    const picked = new Promise((res) => {
      const anchor = (text) => { const a = facelabEl("span", null, text); a.style.maxWidth = "7em"; return a; };
      row.appendChild(anchor(s.anchors[0]));
      for (let k = 1; k <= s.points; k++) {
        const b = facelabEl("button", "facelab-button", String(k));
        Object.assign(b.style, { borderRadius: "50%", width: "3em", height: "3em", minWidth: "0",
          padding: "0", margin: "0", flex: "0 0 auto" });
        b.dataset.facelab = "option"; b.dataset.value = String(k);
        b.addEventListener("click", () => res(k), { once: true });
        keys[String(k)] = b; row.appendChild(b);
      }
      row.appendChild(anchor(s.anchors[1]));
    });
    box.appendChild(row); facelabShow(el, box);
    const off = facelabKeys(keys);
    const value = await picked;
    off();
    if (!s.practice) FacelabOutbox.send("/api/response", facelabAnswer(s, s.item, { value }, started));
    return { value };
  }
}
FacelabEffort.info = facelabInfo("facelab-effort", {
  kind: "STRING", trial_index: "INT", item: "STRING", practice: "BOOL",
  question: "STRING", anchors: "COMPLEX", points: "INT",
});
FacelabPlugins.effort = FacelabEffort;
