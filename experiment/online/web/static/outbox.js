// facelab's outbox: every answer is written to localStorage before it is sent, sent at once,
// and retried (with back-off) until the server has stored it. Survives a closed tab: the
// next page load sends what is left before asking the server where the session stands.
"use strict";
const FacelabOutbox = (function () {
  const TOKEN_KEY = "facelab.token";
  let token = null;
  let flushing = null;
  let delay = 500;
  const listeners = [];

  function key() { return "facelab.outbox." + token; }
  function load() {
    try { return JSON.parse(localStorage.getItem(key()) || "[]"); } catch (e) { return []; }
  }
  function save(items) { localStorage.setItem(key(), JSON.stringify(items)); }
  function notify() { const n = load().length; listeners.forEach((f) => f(n)); }

  function readToken() {
    const m = location.hash.match(/(?:^#|&)t=([A-Za-z0-9_-]{20,128})/);
    if (m) {
      localStorage.setItem(TOKEN_KEY, m[1]);
      history.replaceState(null, "", location.pathname); // the token leaves the address bar
    }
    token = localStorage.getItem(TOKEN_KEY);
    if (token) adoptEarlier();
    return token;
  }

  // Answers this browser saved under an earlier token (the session's token before a rejoin
  // rotated it, or another session's on a shared computer) go first, each carrying that
  // token: the server stores them only if it was this session's, else they are held and
  // reported like any refused answer - nothing the participant gave is dropped.
  function adoptEarlier() {
    const earlier = [];
    for (let i = 0; i < localStorage.length; i++) {
      const k = localStorage.key(i);
      const m = k && k.match(/^facelab\.(outbox|held)\.([A-Za-z0-9_-]{20,128})$/);
      if (m && m[2] !== token) earlier.push([k, m[2]]);
    }
    if (!earlier.length) return;
    const moved = [];
    for (const [k, old] of earlier) {
      let items = [];
      try { items = JSON.parse(localStorage.getItem(k) || "[]"); } catch (e) { items = []; }
      for (const it of items) {
        if (it.url === "/api/event") continue;  // the earlier session's page events stay there
        moved.push({ url: it.url, body: it.body, earlier: it.earlier || old });
      }
    }
    save(moved.concat(load()));     // saved under this token first, then the old keys go
    for (const [k] of earlier) localStorage.removeItem(k);
  }

  function newKey() {
    const b = new Uint8Array(16);
    crypto.getRandomValues(b);
    return Array.from(b, (x) => x.toString(16).padStart(2, "0")).join("");
  }

  async function request(method, url, body, earlier) {
    const headers = { "X-Facelab-Token": token };
    if (earlier) headers["X-Facelab-Earlier-Token"] = earlier;
    if (body !== undefined) headers["Content-Type"] = "application/json";
    // a server that accepts the connection but never answers must not hold the page: 15 s
    return fetch(url, { method, headers, body: body === undefined ? undefined : JSON.stringify(body), cache: "no-store",
                        signal: typeof AbortSignal.timeout === "function" ? AbortSignal.timeout(15000) : undefined });
  }

  // Answers the server refused (409, 413, 422) are never thrown away: they are held under
  // facelab.held.<token> with the reason, reported once as an event (the experimenter sees
  // it), and put back in the queue after HOLD_MS - so a refusal whose reason goes away (a
  // protocol edited and restored under a running session) is stored in the end.
  const HOLD_MS = 20000;
  function heldKey() { return "facelab.held." + token; }
  function loadHeld() {
    try { return JSON.parse(localStorage.getItem(heldKey()) || "[]"); } catch (e) { return []; }
  }
  function saveHeld(items) { localStorage.setItem(heldKey(), JSON.stringify(items)); }
  function requeueHeld() {
    const now = Date.now();
    const held = loadHeld();
    const due = held.filter((h) => now - h.at >= HOLD_MS);
    if (!due.length) return;
    saveHeld(held.filter((h) => now - h.at < HOLD_MS));  // queued first, then released
    save(load().concat(due.map((h) => ({ url: h.url, body: h.body, tries: h.tries, earlier: h.earlier }))));
  }

  // Send everything in order; resolves when the queue is empty (retries until then; held
  // answers are not waited for - see held()).
  function flush() {
    if (flushing) return flushing;
    flushing = (async () => {
      requeueHeld();
      for (;;) {
        const items = load();
        if (!items.length) break;
        const item = items[0];
        let drop = false;
        try {
          const r = await request("POST", item.url, item.body, item.earlier);
          if (r.ok) { drop = true; delay = 500; }
          else if (r.status === 409 || r.status === 413 || r.status === 422) {
            const why = ((await r.json().catch(() => ({}))).error || String(r.status)).slice(0, 300);
            const tries = (item.tries || 0) + 1;
            saveHeld(loadHeld().concat([{ url: item.url, body: item.body, why, tries, at: Date.now(), earlier: item.earlier }]));
            if (tries === 1 && item.url !== "/api/event") {  // reported once, through the queue
              const q = load();
              q.push({ url: "/api/event", body: { kind: "error", detail: { held: item.url, why,
                trial_index: item.body.trial_index || null, item: item.body.item || null } } });
              save(q);
            }
            console.warn("facelab: held back", item.url, why);
            drop = true;
          } else if (r.status === 401) {
            throw new Error("token refused");
          }
        } catch (e) { /* network down or server restarting: retry below */ }
        if (drop) { const rest = load(); rest.shift(); save(rest); notify(); continue; }
        await new Promise((res) => setTimeout(res, delay));
        delay = Math.min(delay * 2, 8000);
      }
    })().finally(() => { flushing = null; });  // (set after the assignment, even when empty)
    return flushing;
  }

  function send(url, body) {
    const items = load();
    items.push({ url, body });
    save(items);             // on disk (localStorage) before the first attempt
    notify();
    return flush();
  }

  return { readToken, send, flush, request, newKey, held: () => loadHeld().length,
           pending: () => load().length,
           onChange: (f) => listeners.push(f), token: () => token };
})();
