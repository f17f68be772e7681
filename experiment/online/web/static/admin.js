// The experimenter's progress page: the secret stays in this tab's memory only.
"use strict";
(function () {
  const form = document.getElementById("login");
  const status = document.getElementById("status");
  const table = document.getElementById("progress");
  let secret = "";
  function cell(row, text) {
    const td = document.createElement("td");
    td.textContent = text === null || text === undefined ? "" : String(text);
    row.appendChild(td);
  }
  async function refresh() {
    const r = await fetch("/api/admin/progress", { headers: { "X-Facelab-Admin": secret } });
    if (!r.ok) { status.textContent = (await r.json()).error; return; }
    const data = await r.json();
    const done = data.participants.filter((p) => p.completed).length;
    const held = data.participants.reduce((n, p) => n + (p.held || 0), 0);
    const stuck = data.participants.filter((p) => p.stuck).length;
    const capped = data.participants.filter((p) => p.at_cap).length;
    status.textContent = `${data.study}: ${data.participants.length} participants, ${done} complete` +
      (held ? `; ${held} answers held back in browsers (see held_why)` : "") +
      (stuck ? `; ${stuck} waiting at the end page with unsaved answers` : "") +
      (capped ? `; ${capped} reached a storage cap (further records refused, see at_cap)` : "");
    table.textContent = "";
    const head = table.insertRow();
    const columns = ["participant", "responses", "planned", "held", "held_why", "stuck", "at_cap", "stored_kb", "protocol", "source", "simulated", "started", "completed"];
    for (const h of columns) {
      const th = document.createElement("th"); th.textContent = h; head.appendChild(th);
    }
    for (const p of data.participants) {
      const row = table.insertRow();
      for (const k of columns) cell(row, p[k]);
      if (p.held || p.stuck || p.at_cap) row.className = "facelab-attention";
    }
  }
  form.addEventListener("submit", (ev) => {
    ev.preventDefault();
    secret = document.getElementById("secret").value;
    refresh();
    setInterval(refresh, 5000);
  });
})();
