// facelab's live 3D and VR view (presentation.display: live3d | webxr). The server sends the
// avatar exactly as the offline renderer deforms it (/avatar/<sha>.glb), the offline camera and
// lights (state.scene.camera), and per clip its animation track (/tracks/<sha>.bin). A clip is
// played by decoding the mp4's sound and, at every display frame, drawing the track frame the
// audio clock has reached: frames follow the sound even when frames are dropped. The animation
// methods never run here.
//
// In VR the same jsPsych screens run; their DOM is mirrored on a panel in front of the
// participant (a canvas texture) and answered with a controller ray or gaze-and-select, which
// clicks the very DOM buttons a mouse would - one answer path, the same logging.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";

const WORDS = {
  ja: { enter: "VRを開始", enter_note: "ヘッドセットを着けて、下のボタンを押してください。",
        needs: "この実験にはVRヘッドセットが必要です。WebXRに対応したブラウザーとヘッドセットで、募集ページのリンクから開き直してください。",
        play: "再生" },
  en: { enter: "Enter VR", enter_note: "Put on the headset, then press the button below.",
        needs: "This study needs a VR headset. Please open the recruitment link again in a WebXR browser with a headset connected.",
        play: "Play" },
};
const MAX_FRAMES_LOGGED = 20000; // per clip (a 10-min clip at 30 fps); the API refuses more

function deg(rad) { return rad * 180 / Math.PI; }
function median(xs) { if (!xs.length) return null; const s = [...xs].sort((a, b) => a - b); const m = s.length >> 1; return s.length % 2 ? s[m] : 0.5 * (s[m - 1] + s[m]); }
function range(xs) { return xs.length ? Math.max(...xs) - Math.min(...xs) : null; }
function round(x, d = 3) { return x === null || x === undefined ? null : Math.round(x * 10 ** d) / 10 ** d; }

export class Stage {
  constructor(state) {
    this.state = state;
    this.display = state.display;             // what the protocol asks for
    this.ran = state.display;                 // what runs (webxr may fall back to live3d)
    this.camera_json = state.scene.camera;
    this.vr = state.vr || {};
    this.words = WORDS[state.language] || WORDS.en;
    this.cache = new Map();                   // clip -> {track, audio}
    this.session = null;                      // the immersive session, while it runs
    this.panel = null;
    this.onFrame = null;                      // the clip being played, called every frame
  }

  async init() {
    const c = this.camera_json;
    const canvas = document.createElement("canvas");
    canvas.className = "facelab-live";
    canvas.dataset.facelab = "live-canvas";
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
    this.renderer.outputColorSpace = THREE.SRGBColorSpace;
    this.renderer.setPixelRatio(1);
    this.renderer.setSize(c.width, c.height, false);
    this.scene = new THREE.Scene();
    // the offline renderer clears to these values as they are (no colour transform)
    this.scene.background = new THREE.Color().setRGB(...c.background, THREE.SRGBColorSpace);
    // three's Lambert divides by pi; the offline shading does not: lights times pi
    const amb = c.ambient;
    this.scene.add(new THREE.HemisphereLight(new THREE.Color(amb.sky, amb.sky, amb.sky),
      new THREE.Color(amb.ground, amb.ground, amb.ground), Math.PI));
    for (const l of c.lights) {
      const light = new THREE.DirectionalLight(0xffffff, l.intensity * Math.PI);
      light.position.set(...l.direction);
      this.scene.add(light);
    }
    this.camera = new THREE.PerspectiveCamera(c.fov_deg, c.width / c.height, c.near, c.far);
    this.camera.position.set(...c.eye);
    this.camera.lookAt(new THREE.Vector3(...c.target));
    this.scene.add(this.camera);
    const data = await (await fetch(this.state.scene.avatar)).arrayBuffer();
    const gltf = await new GLTFLoader().parseAsync(data, "");
    this.avatar = new THREE.Group();
    this.avatar.add(gltf.scene);
    this.scene.add(this.avatar);
    this.meshes = [];
    gltf.scene.traverse((o) => {
      if (o.isMesh && o.morphTargetDictionary) {
        // the offline shading: (texture x) vertex colour x the lights above, no highlight
        o.material = new THREE.MeshLambertMaterial({ vertexColors: true, side: THREE.DoubleSide, map: o.material.map || null });
        o.frustumCulled = false;  // morphs and skinning move vertices beyond the rest bounds
        this.meshes.push(o);
      }
    });
    // the mesh's extras (on a group when the mesh has one primitive per texture)
    let extras = {};
    gltf.scene.traverse((o) => { if (o.userData && o.userData.facelab) extras = o.userData.facelab; });
    this.bones = {};
    for (const [role, name] of Object.entries(extras.roles || {})) {
      const bone = gltf.scene.getObjectByName(THREE.PropertyBinding.sanitizeNodeName(name));
      if (bone) this.bones[role] = bone;
    }
    this.rest();
    this.audio = new (window.AudioContext || window.webkitAudioContext)();
    this.renderer.xr.enabled = this.display === "webxr";
    this.renderer.xr.setReferenceSpaceType("local");
    this.renderer.setAnimationLoop((t, f) => this.tick(t, f));
    return this;
  }

  // -- the avatar

  rest() {
    for (const m of this.meshes) m.morphTargetInfluences.fill(0);
    for (const b of Object.values(this.bones)) b.quaternion.identity();
  }

  // the values of track frame k: morph weights by name, head/neck/eye rotations (the rig's
  // world-axis angles, R = Ry(yaw) Rx(pitch) Rz(roll), degrees; facelab.stimuli.avatar.rig)
  apply(track, k) {
    const pose = {};
    const base = k * track.channels;
    for (let j = 0; j < track.channels; j++) {
      const ch = track.header.channels[j];
      const v = track.values[base + j];
      if (ch.kind === "pose") { pose[ch.name] = v; continue; }
      for (const m of this.meshes) {
        const i = m.morphTargetDictionary[ch.name];
        if (i !== undefined) m.morphTargetInfluences[i] = v;
      }
    }
    if ("head_yaw" in pose) {
      const r = (s, p) => new THREE.Quaternion().setFromEuler(new THREE.Euler(
        THREE.MathUtils.degToRad(p.head_pitch * s), THREE.MathUtils.degToRad(p.head_yaw * s),
        THREE.MathUtils.degToRad(p.head_roll * s), "YXZ"));
      const share = this.bones.neck ? pose.neck_share : 0;
      if (this.bones.neck) this.bones.neck.quaternion.copy(r(share, pose));
      if (this.bones.head) this.bones.head.quaternion.copy(r(1 - share, pose));
      const eye = new THREE.Quaternion().setFromEuler(new THREE.Euler(
        THREE.MathUtils.degToRad(pose.eye_pitch), THREE.MathUtils.degToRad(pose.eye_yaw), 0, "YXZ"));
      for (const role of ["eye_left", "eye_right"]) if (this.bones[role]) this.bones[role].quaternion.copy(eye);
    }
  }

  // one frame of a track drawn offscreen-style at the offline frame size: a data URL (the
  // fidelity check compares it with the offline clip's frame k)
  still(track, k) {
    this.rest();
    this.apply(track, k);
    this.renderer.render(this.scene, this.camera);
    return this.renderer.domElement.toDataURL("image/png");
  }

  async clip(c) {
    if (!this.cache.has(c.clip)) {
      const [tb, ab] = await Promise.all([
        fetch("/tracks/" + c.track).then((r) => { if (!r.ok) throw new Error("track " + r.status); return r.arrayBuffer(); }),
        fetch("/clips/" + c.clip).then((r) => { if (!r.ok) throw new Error("clip " + r.status); return r.arrayBuffer(); }),
      ]);
      const track = FacelabTrack.parse(tb);
      const audio = await this.audio.decodeAudioData(ab);
      this.cache.set(c.clip, { track, audio });
    }
    return this.cache.get(c.clip);
  }

  // -- the frame loop: live3d draws while a clip plays; VR draws every frame of the session

  tick(time, xrFrame) {
    if (this.session && !this.origin && xrFrame) this.place(xrFrame);
    if (this.onFrame) this.onFrame(time, xrFrame);
    if (this.panel) this.panel.hover(this);
    if (this.onFrame || this.session) this.renderer.render(this.scene, this.camera);
  }

  // the audio the participant hears at page time `time` (ms), in context seconds
  heardAt(time) {
    const ts = this.audio.getOutputTimestamp ? this.audio.getOutputTimestamp() : null;
    if (ts && ts.performanceTime > 0) return ts.contextTime + (time - ts.performanceTime) / 1000;
    return this.audio.currentTime - (this.audio.outputLatency || 0);
  }

  viewer(xrFrame) {
    if (!xrFrame) return null;
    const pose = xrFrame.getViewerPose(this.renderer.xr.getReferenceSpace());
    if (!pose) return null;
    const p = pose.transform.position, o = pose.transform.orientation;
    const e = new THREE.Euler().setFromQuaternion(new THREE.Quaternion(o.x, o.y, o.z, o.w), "YXZ");
    return [p.x, p.y, p.z, deg(e.y), deg(e.x), deg(e.z)];
  }

  // Play clip screen `s` (its clip JSON): resolves with the _playback.jsonl record.
  async play(s, box) {
    const { track, audio } = await this.clip(s);
    if (this.audio.state !== "running") {
      await Promise.race([this.audio.resume(), new Promise((r) => setTimeout(r, 1500))]);
    }
    let refused = null;
    if (this.audio.state !== "running") {  // no gesture yet: a click starts the sound
      refused = "audio context " + this.audio.state;
      FacelabOutbox.send("/api/event", { kind: "play_refused", detail: { clip: s.clip, trial_index: s.trial_index, error: refused } });
      const play = facelabEl("button", "facelab-button", "▶"); play.dataset.facelab = "play";
      box.appendChild(play);
      await new Promise((res) => play.addEventListener("click", res, { once: true }));
      play.remove();
      await this.audio.resume();
    }
    this.rest();
    this.avatar.visible = true;
    const fps = track.header.fps, n = track.frames, duration = n / fps;
    const frames = [];
    const src = this.audio.createBufferSource();
    src.buffer = audio; src.connect(this.audio.destination);
    const start = this.audio.currentTime + 0.15;
    src.start(start);
    const ended = new Promise((res) => { src.onended = res; });
    await new Promise((res) => {
      this.onFrame = (time, xrFrame) => {
        const heard = this.heardAt(time) - start;
        const k = heard < 0 ? 0 : Math.min(n - 1, Math.floor(heard * fps + 1e-9));
        this.apply(track, k);
        if (heard >= 0 && frames.length < MAX_FRAMES_LOGGED) frames.push([time, k, heard, this.viewer(xrFrame)]);
        if (heard >= duration) { this.onFrame = null; res(); }
      };
    });
    await ended;
    return this.record(s, frames, { fps, n, refused, duration });
  }

  // The clip's presentation record: the lab/video keys (onset, frames expected, dropped,
  // flip times, frames shown) and the live ones: the audio clock at each frame, frames late
  // (a frame interval over 1.5x the median), av_offset_ms (median of the shown frame's
  // centre time minus the heard audio time: + picture ahead of sound), and in VR the viewer's
  // head movement and distance to the avatar's face.
  record(s, frames, { fps, n, refused }) {
    const shown = frames.map((f) => f[1]);
    const times = frames.map((f) => f[0]);
    const gaps = times.slice(1).map((t, i) => t - times[i]);
    const med = median(gaps);
    // a frame drawn after the track's end (the loop's last, late on a loaded machine) holds
    // the last track frame: it says nothing about sync, so it is not in the offset
    const offsets = frames.filter((f) => f[2] * fps < n).map((f) => 1000 * ((f[1] + 0.5) / fps - f[2]));
    const poses = frames.map((f) => f[3]).filter((p) => p);
    const face = this.facePosition();
    const rec = {
      client_key: FacelabOutbox.newKey(), trial_index: s.practice ? null : s.trial_index,
      clip: s.clip, replay: !!s.replay,
      onset: frames.length ? frames[0][0] / 1000 : null,
      frames_expected: n, dropped: Math.max(0, n - new Set(shown).size),
      flip_times: times.map((t) => round(t / 1000, 4)),
      frames_shown: shown, presented_frames: frames.length, media_time_end: round(frames.length ? frames[frames.length - 1][2] : 0, 4),
      play_refused: refused,
      display: this.session ? "webxr" : "live3d",
      audio_times: frames.map((f) => round(f[2], 4)),
      frames_late: med === null ? 0 : gaps.filter((g) => g > 1.5 * med).length,
      av_offset_ms: offsets.length ? round(median(offsets), 2) : null,
      head_yaw_range_deg: poses.length ? round(range(poses.map((p) => p[3])), 2) : null,
      head_pitch_range_deg: poses.length ? round(range(poses.map((p) => p[4])), 2) : null,
      avatar_distance_m: poses.length ? round(median(poses.map((p) => Math.hypot(p[0] - face.x, p[1] - face.y, p[2] - face.z))), 3) : null,
      viewer_poses: poses.length ? frames.filter((f) => f[3]).map((f) => [round(f[0] / 1000, 4), ...f[3].map((v) => round(v, 4))]) : null,
    };
    return rec;
  }

  facePosition() { return new THREE.Vector3(...this.camera_json.target).applyMatrix4(this.avatar.matrixWorld); }

  // -- live3d: the canvas inside a clip screen

  attach(box) {
    const canvas = this.renderer.domElement;
    box.appendChild(canvas);
    this.renderer.render(this.scene, this.camera);
  }

  // -- VR

  async supported() {
    try { return !!(navigator.xr && await navigator.xr.isSessionSupported("immersive-vr")); }
    catch (e) { return false; }
  }

  // Enter the immersive session (call from a click). The avatar's face stands
  // vr.avatar_distance_m in front of the participant's eyes, vr.avatar_height_m above them.
  async enterVR() {
    const session = await navigator.xr.requestSession("immersive-vr", { optionalFeatures: ["local-floor"] });
    await this.renderer.xr.setSession(session);
    this.session = session;
    session.addEventListener("end", () => { this.session = null; if (this.panel) this.panel.remove(); this.panel = null; });
    this.origin = null;  // placed at the first frame's head position (place)
    this.controllers = [0, 1].map((i) => {
      const c = this.renderer.xr.getController(i);
      const ray = new THREE.Line(new THREE.BufferGeometry().setFromPoints([new THREE.Vector3(), new THREE.Vector3(0, 0, -1)]),
        new THREE.LineBasicMaterial({ color: 0xffffff }));
      ray.scale.z = 2; c.add(ray);
      c.addEventListener("select", () => { if (this.panel) this.panel.select(c); });
      this.scene.add(c);
      return c;
    });
    for (let i = 0; i < 200 && this.session && !this.origin; i++) await new Promise((r) => setTimeout(r, 50));
    FacelabOutbox.send("/api/event", { kind: "display", detail: { requested: this.display, ran: "webxr", vr: this.vr } });
  }

  // The avatar's face vr.avatar_distance_m straight ahead of where the participant's eyes
  // are at the session's first frame, vr.avatar_height_m above them, facing them.
  place(xrFrame) {
    const pose = xrFrame.getViewerPose(this.renderer.xr.getReferenceSpace());
    if (!pose) return;
    const p = pose.transform.position;
    this.origin = new THREE.Vector3(p.x, p.y, p.z);
    const t = this.camera_json.target;
    this.avatar.position.set(p.x - t[0], p.y + (this.vr.avatar_height_m || 0) - t[1],
      p.z - (this.vr.avatar_distance_m || 1) - t[2]);
    this.avatar.updateMatrixWorld(true);
    if (this.panel) this.panel.place();
  }

  inVR() { return !!this.session && !!this.origin; }

  // For drivers and tests with an emulated headset: the orientation [x, y, z, w] (reference
  // space axes) that points controller `i`'s ray at `target` ([x, y, z]), from where it is.
  aim(i, target) {
    const c = this.controllers[i];
    c.updateMatrixWorld(true);
    const from = new THREE.Vector3().setFromMatrixPosition(c.matrixWorld);
    const dir = new THREE.Vector3(...target).sub(from).normalize();
    return new THREE.Quaternion().setFromUnitVectors(new THREE.Vector3(0, 0, -1), dir).toArray();
  }

  // Mirror the DOM screen `box` on a panel (VR only); null out of VR.
  mirror(box) {
    if (this.panel) { this.panel.remove(); this.panel = null; }
    if (!this.session || !box) return null;
    this.avatar.visible = false;  // a screen to answer: the panel alone
    this.panel = new Panel(this, box);
    return this.panel;
  }

  // where a DOM element of the panel (a button, or a VAS line at fraction `frac`) is in the
  // world: for drivers and tests that aim an emulated controller
  target(el, frac) {
    return this.panel ? this.panel.target(el, frac) : null;
  }
}

// A DOM screen drawn on a canvas in front of the participant. Regions map canvas pixels back
// to the DOM element they show; a selection clicks that element (or, on a VAS line, places
// the marker at the fraction hit through the line's facelabPlace hook).
class Panel {
  constructor(stage, box) {
    this.stage = stage; this.box = box;
    this.w = 1024; this.h = 640;
    this.canvas = document.createElement("canvas"); this.canvas.width = this.w; this.canvas.height = this.h;
    this.texture = new THREE.CanvasTexture(this.canvas);
    this.texture.colorSpace = THREE.SRGBColorSpace;
    const width_m = 0.8, height_m = width_m * this.h / this.w;
    this.mesh = new THREE.Mesh(new THREE.PlaneGeometry(width_m, height_m), new THREE.MeshBasicMaterial({ map: this.texture }));
    this.place();
    this.cursor = new THREE.Mesh(new THREE.RingGeometry(0.006, 0.01, 24), new THREE.MeshBasicMaterial({ color: 0x1565c0 }));
    this.cursor.visible = false;
    stage.scene.add(this.mesh); stage.scene.add(this.cursor);
    this.regions = [];
    this.draw();
    this.observer = new MutationObserver(() => this.draw());
    this.observer.observe(box, { subtree: true, attributes: true, childList: true, characterData: true });
  }

  // below the avatar's face, nearer, turned towards the eyes, so the face stays in view
  place() {
    const o = this.stage.origin || new THREE.Vector3();
    const d = Math.min(0.9, (this.stage.vr.avatar_distance_m || 1) * 0.8);
    this.mesh.position.set(o.x, o.y + (this.stage.vr.avatar_height_m || 0) - 0.32, o.z - d);
    this.mesh.lookAt(o);
    this.mesh.updateMatrixWorld(true);
  }

  remove() {
    this.observer.disconnect();
    this.stage.scene.remove(this.mesh); this.stage.scene.remove(this.cursor);
    this.texture.dispose();
  }

  draw() {
    const g = this.canvas.getContext("2d"), W = this.w;
    g.fillStyle = "#f5f5f5"; g.fillRect(0, 0, W, this.h);
    g.fillStyle = "#111"; g.textAlign = "center"; g.textBaseline = "middle";
    const font = (px) => `${px}px "Noto Sans CJK JP", "Noto Sans JP", sans-serif`;
    this.regions = [];
    let y = 70;
    const wrap = (text, px, maxW) => {
      g.font = font(px);
      const lines = []; let line = "";
      for (const ch of text) {
        if (ch === "\n" || g.measureText(line + ch).width > maxW) { lines.push(line); line = ch === "\n" ? "" : ch; }
        else line += ch;
      }
      if (line) lines.push(line);
      for (const l of lines) { g.fillText(l, W / 2, y); y += px * 1.35; }
    };
    const texts = this.box.querySelectorAll(".facelab-question, :scope > p, .facelab-text > p, .facelab-code");
    const items = this.box.querySelectorAll(".facelab-vas-item");
    if (!items.length) for (const t of texts) { wrap(t.textContent, 40, W - 120); y += 14; }
    for (const item of items) {
      wrap(item.querySelector(".facelab-question").textContent, 34, W - 120);
      const line = item.querySelector("[data-facelab=line]");
      const x0 = 200, x1 = W - 200, ly = y + 20;
      g.font = font(24); g.textAlign = "right"; g.fillText(item.querySelector(".facelab-anchor.left").textContent, x0 - 16, ly);
      g.textAlign = "left"; g.fillText(item.querySelector(".facelab-anchor.right").textContent, x1 + 16, ly);
      g.textAlign = "center";
      g.fillStyle = "#333"; g.fillRect(x0, ly - 3, x1 - x0, 6);
      const marker = line.querySelector(".facelab-marker");
      if (marker && marker.classList.contains("shown")) {
        const frac = parseFloat(marker.style.left) / 100;
        g.fillStyle = "#c62828"; g.fillRect(x0 + frac * (x1 - x0) - 5, ly - 24, 10, 48);
      }
      g.fillStyle = "#111";
      this.regions.push({ el: line, kind: "line", x: x0, y: ly - 30, w: x1 - x0, h: 60 });
      y = ly + 60;
    }
    const buttons = [...this.box.querySelectorAll("button")];
    if (buttons.length) {
      y = Math.max(y + 10, this.h - 130);
      const bw = Math.min(300, (W - 80) / buttons.length - 20), bh = 80;
      let x = (W - buttons.length * (bw + 20) + 20) / 2;
      for (const b of buttons) {
        g.fillStyle = b.disabled ? "#bdbdbd" : "#1565c0"; g.fillRect(x, y, bw, bh);
        g.fillStyle = "#fff"; g.font = font(30); g.fillText(b.textContent, x + bw / 2, y + bh / 2);
        this.regions.push({ el: b, kind: "button", x, y, w: bw, h: bh });
        x += bw + 20;
      }
    }
    this.texture.needsUpdate = true;
  }

  hit(controller) {
    const ray = new THREE.Raycaster();
    const m = controller.matrixWorld;
    ray.ray.origin.setFromMatrixPosition(m);
    ray.ray.direction.set(0, 0, -1).transformDirection(m);
    const hits = ray.intersectObject(this.mesh);
    if (!hits.length) return null;
    const { uv, point } = hits[0];
    return { point, x: uv.x * this.w, y: (1 - uv.y) * this.h };
  }

  hover(stage) {
    let shown = false;
    for (const c of stage.controllers || []) {
      const h = this.hit(c);
      if (h) { this.cursor.position.copy(h.point); this.cursor.quaternion.copy(this.mesh.quaternion); shown = true; }
    }
    this.cursor.visible = shown;
  }

  select(controller) {
    const h = this.hit(controller);
    if (!h) return;
    const r = this.regions.find((q) => h.x >= q.x && h.x <= q.x + q.w && h.y >= q.y && h.y <= q.y + q.h);
    if (!r) return;
    if (r.kind === "button" && !r.el.disabled) r.el.click();
    if (r.kind === "line" && r.el.facelabPlace) r.el.facelabPlace(Math.min(1, Math.max(0, (h.x - r.x) / r.w)));
  }

  target(el, frac) {
    const r = this.regions.find((q) => q.el === el);
    if (!r) return null;
    const x = r.kind === "line" ? r.x + (frac ?? 0.5) * r.w : r.x + r.w / 2;
    const y = r.y + r.h / 2;
    const p = this.mesh.geometry.parameters;
    const local = new THREE.Vector3((x / this.w - 0.5) * p.width, (0.5 - y / this.h) * p.height, 0);
    this.mesh.updateMatrixWorld(true);
    return local.applyMatrix4(this.mesh.matrixWorld).toArray();
  }
}

export async function createStage(state) {
  const stage = await new Stage(state).init();
  window.FacelabLive = stage;   // drivers and tests reach the stage here
  return stage;
}
export { WORDS };
