// facelab's live 3D and VR view (presentation.display: live3d | webxr). The server sends the
// avatar exactly as the offline renderer deforms it (/avatar/<sha>.glb), the offline camera and
// lights (state.scene.camera), and per clip its animation track (/tracks/<sha>.bin). A clip is
// played by decoding the mp4's sound and, at every display frame, drawing the track frame the
// audio clock has reached: frames follow the sound even when frames are dropped. The animation
// methods never run here.
//
// In VR the same jsPsych screens run, from the instructions to the end; their DOM is mirrored
// on a panel in front of the participant (a canvas texture, its text wrapped and scaled to
// fit) and answered with a controller ray or gaze-and-select, which clicks the very DOM
// buttons a mouse would - one answer path, the same logging. The participant sits in a
// neutral room (vr.room), each screen and clip fades in from black (vr.fade_ms) and out to
// black when an answer is selected or a clip ends, rays are hidden while a clip plays, the
// avatar's eyes are placed where the recentre step measured the participant's (vr.recentre)
// and its voice comes from its mouth (vr.spatial_audio). Every panel carries the page's Stop
// button; its question (stop or continue) is asked on the panel.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";

const WORDS = {
  ja: { enter: "VRを開始", enter_note: "ヘッドセットを着けて、下のボタンを押してください。",
        needs: "この実験にはVRヘッドセットが必要です。WebXRに対応したブラウザーとヘッドセットで、募集ページのリンクから開き直してください。",
        play: "再生",
        recentre_note: "椅子に深く座り、まっすぐ前を向いてください。準備ができたら「ここを正面に」を選んでください。",
        recentre: "ここを正面に", recentre_short: "正面に戻す",
        hint_controller: "コントローラーで指して、トリガーを引いて選びます。",
        hint_gaze: "選びたいものを見つめて、選択ボタンを押します。",
        remove: "ヘッドセットを外して、パソコンの画面をご覧ください。", exit: "VRを終了" },
  en: { enter: "Enter VR", enter_note: "Put on the headset, then press the button below.",
        needs: "This study needs a VR headset. Please open the recruitment link again in a WebXR browser with a headset connected.",
        play: "Play",
        recentre_note: "Sit back in the chair and look straight ahead. When you are ready, select \"This is ahead\".",
        recentre: "This is ahead", recentre_short: "Recentre",
        hint_controller: "Point with the controller and pull the trigger to select.",
        hint_gaze: "Look at what you want to select and press the select button.",
        remove: "Please take off the headset and look at the computer screen.", exit: "Exit VR" },
};
const MAX_FRAMES_LOGGED = 20000; // per clip (a 10-min clip at 30 fps); the API refuses more
const SEATED_EYE_HEIGHT_M = 1.2;  // the floor below the eyes when the runtime gives no floor

function deg(rad) { return rad * 180 / Math.PI; }
function median(xs) { if (!xs.length) return null; const s = [...xs].sort((a, b) => a - b); const m = s.length >> 1; return s.length % 2 ? s[m] : 0.5 * (s[m - 1] + s[m]); }
function range(xs) { return xs.length ? Math.max(...xs) - Math.min(...xs) : null; }
// yaw, pitch, roll (radians; R = Ry Rx Rz, the rig's order) of an XR orientation
function eulerOf(o) { return new THREE.Euler().setFromQuaternion(new THREE.Quaternion(o.x, o.y, o.z, o.w), "YXZ"); }
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
    this.clipHeard = 0;                       // how far (s) into its sound the clip is shown
    this.clipStillWanted = false;             // a still of the next clip in full view, asked
    this.clipStill = null;                    //   for by a driver, and the PNG data URL taken
    this.screenPoses = null;                  // the poses while a VR screen waits (mirror)
    this.yaw = 0;                             // the facing direction the avatar was placed at
    this.lastPose = null;                     // the viewer's pose at the last XR frame
    this.fade = null;                         // {from, to, start, ms}: the fader's course
    this.fades = { in: 0, out: 0 };           // fades begun (drivers and tests read them)
    this.selecting = false;                   // a selected button is taking effect
    this.selectedAt = null;                   // when (page ms) and where the viewer was at
    this.selectedPose = null;                 // the last select of a button
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
    if (this.session && xrFrame) {
      const pose = xrFrame.getViewerPose(this.renderer.xr.getReferenceSpace());
      if (pose) {
        this.lastPose = pose.transform; this.lastPoseFrame = xrFrame;
        if (!this.origin) this.placeAt(pose.transform);
        this.hear(pose.transform);
      }
      this.fading();
    }
    if (this.onFrame) this.onFrame(time, xrFrame);
    else if (this.screenPoses && xrFrame) this.collectScreenPose(time, xrFrame);
    if (this.panel) this.panel.hover(this);
    if (this.onFrame || this.session) this.renderer.render(this.scene, this.camera);
    // a still of a clip faded in and talking, taken in the frame that drew it (a screenshot
    // of a busy headless page lags: it caught the fade from black, or the next screen)
    if (this.clipStillWanted && this.onFrame && this.clipHeard > 0.3 && this.opacity() === 0) {
      this.clipStill = this.renderer.domElement.toDataURL("image/png");
      this.clipStillWanted = false;
    }
  }

  // the audio the participant hears at page time `time` (ms), in context seconds
  heardAt(time) {
    const ts = this.audio.getOutputTimestamp ? this.audio.getOutputTimestamp() : null;
    if (ts && ts.performanceTime > 0) return ts.contextTime + (time - ts.performanceTime) / 1000;
    return this.audio.currentTime - (this.audio.outputLatency || 0);
  }

  // [x, y, z, yaw, pitch, roll] of the viewer at XR frame `xrFrame` (the pose tick read)
  viewer(xrFrame) {
    if (!xrFrame || this.lastPoseFrame !== xrFrame) return null;
    const p = this.lastPose.position, e = eulerOf(this.lastPose.orientation);
    return [p.x, p.y, p.z, deg(e.y), deg(e.x), deg(e.z)];
  }

  // [[hand, x, y, z, yaw, pitch, roll], ...] of each tracked controller at XR frame `xrFrame`
  // (hand 0 left, 1 right, 2 neither; its grip, else its pointer), in the reference space
  // the head's pose is in; [] outside VR or with no controller tracked (a gaze input's ray is
  // the head's: not a controller)
  hands(xrFrame) {
    if (!xrFrame || !this.session) return [];
    const space = this.renderer.xr.getReferenceSpace(), out = [];
    for (const source of this.session.inputSources || []) {
      if (source.targetRayMode === "gaze") continue;
      const where = source.gripSpace || source.targetRaySpace;
      const pose = where && space ? xrFrame.getPose(where, space) : null;
      if (!pose) continue;
      const p = pose.transform.position, e = eulerOf(pose.transform.orientation);
      out.push([{ left: 0, right: 1 }[source.handedness] ?? 2, p.x, p.y, p.z, deg(e.y), deg(e.x), deg(e.z)]);
    }
    return out;
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
    const fps = track.header.fps, n = track.frames, duration = n / fps;
    let frames, source, interruptions = 0;
    // a headset taken off (or the session ended) mid-clip stops the clip; once the
    // participant can see again it plays from the start, and the record counts the stops
    for (;;) {
      this.rest();
      this.avatar.visible = true;
      this.showRays(false);  // nothing drawn over the face while it talks
      this.fadeIn();
      frames = [];
      const src = this.audio.createBufferSource();
      src.buffer = audio;
      source = this.voiceOutput();
      src.connect(source.node);
      // the voice starts once the face has faded in (the frames before show the rest face)
      const lead = this.fade && this.fade.to === 0 ? Math.max(0.15, this.vr.fade_ms / 1000) : 0.15;
      const start = this.audio.currentTime + lead;
      src.start(start);
      const ended = new Promise((res) => { src.onended = res; });
      const outcome = await new Promise((res) => {
        this.playing = { clip: s.clip, trial_index: s.practice ? null : s.trial_index, stop: () => res("interrupted") };
        this.onFrame = (time, xrFrame) => {
          const heard = this.clipHeard = this.heardAt(time) - start;
          const k = heard < 0 ? 0 : Math.min(n - 1, Math.floor(heard * fps + 1e-9));
          this.apply(track, k);
          if (heard >= 0 && frames.length < MAX_FRAMES_LOGGED) frames.push([time, k, heard, this.viewer(xrFrame), this.hands(xrFrame)]);
          if (heard >= duration) res("done");
        };
      });
      this.onFrame = null; this.playing = null; this.clipHeard = 0;
      if (outcome === "done") { await ended; await this.fadeOut(); break; }
      try { src.stop(); } catch (e) { /* not started yet */ }
      if (source.at) source.node.disconnect();
      interruptions += 1;
      await this.untilSeen(box);
    }
    if (source.at) source.node.disconnect();
    this.showRays(true);
    return { ...this.record(s, frames, { fps, n, refused, duration, source }), interruptions };
  }

  // The headset's visibility changed (taken off: hidden; the system's menu: visible-blurred):
  // logged, and a clip playing is stopped (it plays again once seen).
  onVisibility(state) {
    const playing = this.playing;
    FacelabOutbox.send("/api/event", { kind: "headset", detail: {
      state, during: playing ? "clip" : "screen", clip: playing ? playing.clip : null,
      trial_index: playing ? playing.trial_index : null } });
    if (state !== "visible" && playing) playing.stop();
  }

  // Until the participant sees the scene again: the headset's visibility back to visible, or
  // (the session ended) VR entered again.
  async untilSeen(box) {
    for (;;) {
      if (this.session && this.session.visibilityState === "visible") return;
      if (!this.session) { await facelabEnterVR(box); continue; }
      const session = this.session;
      await new Promise((res) => {
        const done = () => { session.removeEventListener("visibilitychange", done); session.removeEventListener("end", done); res(); };
        session.addEventListener("visibilitychange", done); session.addEventListener("end", done);
      });
    }
  }

  // The clip's presentation record: the lab/video keys (onset, frames expected, dropped,
  // flip times, frames shown) and the live ones: the audio clock at each frame, frames late
  // (a frame interval over 1.5x the median), av_offset_ms (median of the shown frame's
  // centre time minus the heard audio time: + picture ahead of sound), and in VR the viewer's
  // head movement and distance to the avatar's face.
  record(s, frames, { fps, n, refused, source }) {
    const shown = frames.map((f) => f[1]);
    const times = frames.map((f) => f[0]);
    const gaps = times.slice(1).map((t, i) => t - times[i]);
    const med = median(gaps);
    // a frame drawn after the track's end (the loop's last, late on a loaded machine) holds
    // the last track frame: it says nothing about sync, so it is not in the offset
    const offsets = frames.filter((f) => f[2] * fps < n).map((f) => 1000 * ((f[1] + 0.5) / fps - f[2]));
    const poses = frames.map((f) => f[3]).filter((p) => p);
    const eyes = this.eyesPosition();
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
      avatar_distance_m: poses.length ? round(median(poses.map((p) => Math.hypot(p[0] - eyes.x, p[1] - eyes.y, p[2] - eyes.z))), 3) : null,
      viewer_poses: poses.length ? frames.filter((f) => f[3]).map((f) => [round(f[0] / 1000, 4), ...f[3].map((v) => round(v, 4))]) : null,
      controller_poses: this.session ? frames.flatMap((f) => (f[4] || []).map((h) => [round(f[0] / 1000, 4), ...h.map((v) => round(v, 4))])).slice(0, 2 * MAX_FRAMES_LOGGED) : null,
      spatial_audio: !!(source && source.at),
      audio_source_m: source && source.at ? source.at.map((v) => round(v, 4)) : null,
    };
    return rec;
  }

  // a point of the avatar at rest ("eyes", "mouth"; its aim point when the file has none),
  // in its own frame, and where it is now
  point(name) { return new THREE.Vector3(...(this.camera_json[name] || this.camera_json.target)); }
  eyesPosition() { return this.point("eyes").applyMatrix4(this.avatar.matrixWorld); }
  mouthPosition() { return this.point("mouth").applyMatrix4(this.avatar.matrixWorld); }

  // Where the voice goes: in VR with vr.spatial_audio an HRTF panner at the avatar's mouth
  // (no distance attenuation where the participant sits at the clip's start; the HRTF
  // filters colour it as a voice from that direction); else the output itself.
  voiceOutput() {
    if (!this.session || this.vr.spatial_audio === false || typeof PannerNode === "undefined") {
      return { node: this.audio.destination, at: null };
    }
    const m = this.mouthPosition();
    const p = this.lastPose ? this.lastPose.position : null;
    const d = p ? Math.hypot(m.x - p.x, m.y - p.y, m.z - p.z) : (this.vr.avatar_distance_m || 1);
    const panner = new PannerNode(this.audio, {
      panningModel: "HRTF", distanceModel: "inverse", refDistance: Math.max(0.1, d),
      rolloffFactor: 1, positionX: m.x, positionY: m.y, positionZ: m.z,
    });
    panner.connect(this.audio.destination);
    return { node: panner, at: [m.x, m.y, m.z] };
  }

  // the listener at the viewer's head, facing where it faces (every XR frame)
  hear(t) {
    const L = this.audio.listener, p = t.position, o = t.orientation;
    const q = new THREE.Quaternion(o.x, o.y, o.z, o.w);
    const f = new THREE.Vector3(0, 0, -1).applyQuaternion(q), u = new THREE.Vector3(0, 1, 0).applyQuaternion(q);
    if (L.positionX) {
      L.positionX.value = p.x; L.positionY.value = p.y; L.positionZ.value = p.z;
      L.forwardX.value = f.x; L.forwardY.value = f.y; L.forwardZ.value = f.z;
      L.upX.value = u.x; L.upY.value = u.y; L.upZ.value = u.z;
    } else { L.setPosition(p.x, p.y, p.z); L.setOrientation(f.x, f.y, f.z, u.x, u.y, u.z); }
  }

  // -- live3d: the canvas inside a clip screen. In VR the runtime keeps the canvas: moved
  // away, a runtime that puts it back when the session ends fails to (IWER's end threw, and
  // the session went on without an end event or frames)

  attach(box) {
    if (this.inVR()) return;
    const canvas = this.renderer.domElement;
    box.appendChild(canvas);
    this.renderer.render(this.scene, this.camera);
  }

  // -- VR

  async supported() {
    try { return !!(navigator.xr && await navigator.xr.isSessionSupported("immersive-vr")); }
    catch (e) { return false; }
  }

  // Enter the immersive session (call from a click). The avatar is placed at the first frame
  // (see placeAt) and again at the recentre step.
  async enterVR() {
    const session = await navigator.xr.requestSession("immersive-vr", { optionalFeatures: ["local-floor"] });
    session.addEventListener("visibilitychange", () => this.onVisibility(session.visibilityState));
    session.addEventListener("end", () => {
      if (this.playing) this.onVisibility("ended");
      this.sendScreenPoses();
      if (this.session === session) this.session = null;
      this.lastPose = null;
      this.fade = null;
      if (this.panel) this.panel.remove();
      this.panel = null;
      if (this.room) { this.scene.remove(this.room); this.room = null; }
    });
    // controllers may connect after the session starts: the panel's hint follows them
    session.addEventListener("inputsourceschange", () => { if (this.panel) this.panel.draw(); });
    // the floor is known when the runtime gives local-floor; else it is put a seated eye
    // height below the eyes
    let space = "local";
    try { await session.requestReferenceSpace("local-floor"); space = "local-floor"; } catch (e) { /* local */ }
    this.renderer.xr.setReferenceSpaceType(space);
    this.referenceSpace = space;
    await this.renderer.xr.setSession(session);
    this.session = session;
    this.origin = null;  // placed at the first frame's head pose (placeAt)
    if (!this.controllers) {
      this.controllers = [0, 1].map((i) => {
        const c = this.renderer.xr.getController(i);
        const ray = new THREE.Line(new THREE.BufferGeometry().setFromPoints([new THREE.Vector3(), new THREE.Vector3(0, 0, -1)]),
          new THREE.LineBasicMaterial({ color: 0xffffff }));
        ray.scale.z = 2; ray.name = "ray"; c.add(ray);
        c.addEventListener("select", () => { if (this.panel) this.panel.select(c); });
        this.scene.add(c);
        return c;
      });
    }
    if (!this.fader) {  // a black sphere around the head: screens fade in from it
      this.fader = new THREE.Mesh(new THREE.SphereGeometry(0.25, 24, 12), new THREE.MeshBasicMaterial({
        color: 0x000000, side: THREE.BackSide, transparent: true, opacity: 0, depthTest: false, depthWrite: false }));
      this.fader.renderOrder = 1e6; this.fader.visible = false; this.fader.frustumCulled = false;
      this.scene.add(this.fader);
    }
    for (let i = 0; i < 200 && this.session && !this.origin; i++) await new Promise((r) => setTimeout(r, 50));
    FacelabOutbox.send("/api/event", { kind: "display", detail: { requested: this.display, ran: "webxr", vr: this.vr, reference_space: space, input: this.device() } });
  }

  // The avatar's eyes vr.avatar_distance_m straight ahead of the viewer's eyes at pose `t`
  // (an XRRigidTransform), vr.avatar_height_m above them, facing the viewer; the room around.
  placeAt(t) {
    const p = t.position;
    this.yaw = eulerOf(t.orientation).y;
    this.origin = new THREE.Vector3(p.x, p.y, p.z);
    const anchor = this.origin.clone().addScaledVector(this.ahead(), this.vr.avatar_distance_m || 1);
    anchor.y += this.vr.avatar_height_m || 0;
    this.avatar.rotation.set(0, this.yaw, 0);
    const eyes = this.point("eyes").applyEuler(this.avatar.rotation);
    this.avatar.position.copy(anchor.sub(eyes));
    this.avatar.updateMatrixWorld(true);
    this.placeRoom();
    if (this.panel) this.panel.place();
  }

  // the horizontal direction the avatar was placed in (the viewer's facing, -z turned by yaw)
  ahead() { return new THREE.Vector3(-Math.sin(this.yaw), 0, -Math.cos(this.yaw)); }

  // The recentre step and button: the avatar (and panel, room) placed again from where the
  // participant's eyes are and face now; logged.
  recentre(why) {
    // the recentre step's button: where the participant was when they selected it (its
    // click comes after the fade-out)
    const pose = why === "start" && this.selectedPose ? this.selectedPose : this.lastPose;
    if (!pose) return false;
    this.placeAt(pose);
    const eyes = this.eyesPosition();
    FacelabOutbox.send("/api/event", { kind: "recentre", detail: {
      why, yaw_deg: round(deg(this.yaw), 2), eye_height_m: round(this.eyeHeight(), 3),
      viewer_m: this.origin.toArray().map((v) => round(v, 4)), avatar_eyes_m: eyes.toArray().map((v) => round(v, 4)) } });
    return true;
  }

  // the floor's height in the reference space, and the eyes' height above it
  floorY() { return this.referenceSpace === "local-floor" ? 0 : (this.origin ? this.origin.y : 0) - SEATED_EYE_HEIGHT_M; }
  eyeHeight() { return this.origin ? this.origin.y - this.floorY() : null; }

  // vr.room: a neutral room (floor, walls, ceiling), a floor, or nothing around the viewer
  placeRoom() {
    const kind = this.vr.room || "room";
    if (kind === "none") return;
    if (!this.room) {  // 4 m around the participant, or 1.5 m beyond a farther avatar
      const R = Math.max(4, (this.vr.avatar_distance_m || 1) + 1.5), H = Math.max(3, R * 0.75);
      const g = new THREE.Group(); g.name = "room";
      const floor = new THREE.Mesh(new THREE.CircleGeometry(R, 64), new THREE.MeshLambertMaterial({ color: 0x8c8984 }));
      floor.rotation.x = -Math.PI / 2; g.add(floor);
      const grid = new THREE.PolarGridHelper(R, 8, Math.round(R * 2), 64, 0x7a7772, 0x7a7772); grid.position.y = 0.003; g.add(grid);
      if (kind === "room") {
        const walls = new THREE.Mesh(new THREE.CylinderGeometry(R, R, H, 64, 1, true),
          new THREE.MeshLambertMaterial({ color: 0xcbc7c0, side: THREE.BackSide }));
        walls.position.y = H / 2; g.add(walls);
        const ceiling = new THREE.Mesh(new THREE.CircleGeometry(R, 64), new THREE.MeshLambertMaterial({ color: 0xe2dfda }));
        ceiling.rotation.x = Math.PI / 2; ceiling.position.y = H; g.add(ceiling);
      }
      // a backdrop: drawn first and writing no depth, so the avatar, the panels and the rays
      // are always in front of it (the room's parts do not overlap in view; the grid after
      // the floor it lies on)
      g.traverse((o) => { o.renderOrder = -10; if (o.material) o.material.depthWrite = false; });
      grid.renderOrder = -9;
      this.room = g; this.scene.add(g);
    }
    this.room.position.set(this.origin.x, this.floorY(), this.origin.z);
    this.room.updateMatrixWorld(true);
  }

  showRays(on) {
    for (const c of this.controllers || []) { const r = c.getObjectByName("ray"); if (r) r.visible = on; }
  }

  // (VR only) the next screen or clip fades in from black over vr.fade_ms; a selected answer
  // and a clip's end fade out to black over half that first (fadeOut resolves then)
  fadable() { return !!this.session && !!this.fader && this.vr.fade_ms > 0; }

  fadeIn() {
    if (!this.fadable()) return;
    this.fade = { from: 1, to: 0, start: performance.now(), ms: this.vr.fade_ms };
    this.fades.in += 1;
    this.fading();
  }

  fadeOut() {
    if (!this.fadable()) return Promise.resolve();
    const ms = this.vr.fade_ms / 2;
    const fade = this.fade = { from: this.opacity(), to: 1, start: performance.now(), ms };
    this.fades.out += 1;
    this.fading();
    // never left in the dark: what follows fades in; if nothing does, this fade undoes itself
    setTimeout(() => { if (this.fade === fade) this.fadeIn(); }, ms + 3000);
    return new Promise((res) => setTimeout(res, ms));
  }

  // the fader's opacity now (0 clear, 1 black)
  opacity() {
    const f = this.fade;
    if (!f) return 0;
    return f.from + (f.to - f.from) * Math.min(1, (performance.now() - f.start) / f.ms);
  }

  fading() {
    if (!this.fader) return;
    if (this.lastPose) { const p = this.lastPose.position; this.fader.position.set(p.x, p.y, p.z); }
    const a = this.opacity();
    if (a <= 0) { if (this.fade && this.fade.to === 0) this.fade = null; this.fader.visible = false; return; }
    this.fader.visible = true; this.fader.material.opacity = a;
  }

  // how the participant selects: "controller" (a tracked pointer) or "gaze"
  device() {
    const modes = this.session ? [...this.session.inputSources].map((s) => s.targetRayMode) : [];
    return modes.includes("tracked-pointer") ? "controller" : "gaze";
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

  // Mirror the DOM screen `box` on a panel (VR only); null out of VR. The poses of the
  // screen it replaces are sent, and this one's are collected while it shows.
  mirror(box) {
    this.sendScreenPoses();
    if (this.panel) { this.panel.remove(); this.panel = null; }
    if (!this.session || !box) return null;
    this.avatar.visible = false;  // a screen to answer: the panel alone
    this.panel = new Panel(this, box);
    this.fadeIn();
    const d = box.dataset;
    this.screenPoses = { trial_index: d.trial !== undefined ? Number(d.trial) : null,
      screen: d.facelab || "screen", item: d.item || null, role: d.role || null,
      shown: round(performance.now() / 1000, 4), viewer_poses: [], controller_poses: [] };
    return this.panel;
  }

  // the head's and controllers' poses at XR frame `xrFrame` while a screen waits (tick)
  collectScreenPose(time, xrFrame) {
    const c = this.screenPoses, head = this.viewer(xrFrame);
    if (!c || !head || c.viewer_poses.length >= MAX_FRAMES_LOGGED) return;
    const t = round(time / 1000, 4);
    c.viewer_poses.push([t, ...head.map((v) => round(v, 4))]);
    for (const h of this.hands(xrFrame)) c.controller_poses.push([t, ...h.map((v) => round(v, 4))]);
  }

  // the poses collected while the last screen showed, to the server (once; none: nothing)
  sendScreenPoses() {
    const c = this.screenPoses;
    this.screenPoses = null;
    if (!c || !c.viewer_poses.length) return;
    FacelabOutbox.send("/api/screen_poses", { client_key: FacelabOutbox.newKey(), ...c });
  }

  // where a DOM element of the panel (a button, or a VAS line at fraction `frac`) is in the
  // world: for drivers and tests that aim an emulated controller
  target(el, frac) {
    return this.panel ? this.panel.target(el, frac) : null;
  }
}

// Text broken into lines of at most `maxW` pixels for canvas context `g` (its font set):
// Latin words are kept whole where they fit, CJK text breaks between characters (graphemes:
// emoji and combining marks stay whole), closing punctuation never starts a line (it hangs
// into the margin) nor an opening bracket ends one, "\n" breaks (an empty line stays).
// Spaces at a break are dropped.
const CLOSING = "、。，．,.)\\]）」』】〕！？!?ー…・:;";  // never at a line's start
const CLOSERS = new RegExp(`^[${CLOSING}]+$`, "u");
const TRAILING_CLOSERS = new RegExp(`[${CLOSING}]+$`, "u");
const LATIN = /^[A-Za-z0-9\u00C0-\u024F'’.,:;!?%()\-"“”]$/u;
function panelFont(px) { return `${Math.round(px)}px "Noto Sans CJK JP", "Noto Sans JP", sans-serif`; }
function graphemes(text) {
  if (typeof Intl !== "undefined" && Intl.Segmenter) return [...new Intl.Segmenter(undefined, { granularity: "grapheme" }).segment(text)].map((x) => x.segment);
  return [...text];
}
function wrapLines(g, text, maxW) {
  const out = [];
  for (const para of String(text).split("\n")) {
    // tokens: runs of Latin word characters, runs of spaces, single graphemes; closing
    // punctuation joined to the grapheme before it
    const tokens = [];
    for (const ch of graphemes(para)) {
      const last = tokens.length ? tokens[tokens.length - 1] : null;
      if (last !== null && ((LATIN.test(ch) && [...last].every((c) => LATIN.test(c)))
          || (/^\s$/u.test(ch) && /^\s+$/u.test(last)) || CLOSERS.test(ch)
          || (/[「『（【〔“]$/u.test(last) && !/^\s$/u.test(ch)))) tokens[tokens.length - 1] = last + ch;
      else tokens.push(ch);
    }
    const width = (t) => g.measureText(t.replace(TRAILING_CLOSERS, "")).width;  // they hang
    let line = "";
    for (const tok of tokens) {
      if (/^\s+$/u.test(tok)) { if (line) line += tok; continue; }
      if (!line || width(line.trimEnd() + tok) <= maxW) { line += tok; continue; }
      out.push(line.trimEnd()); line = tok;
      // a word longer than the line is broken between graphemes
      while (width(line) > maxW) {
        let cur = "";
        const gs = graphemes(line);
        let i = 0;
        for (; i < gs.length; i++) { if (cur && width(cur + gs[i]) > maxW && !CLOSERS.test(gs[i])) break; cur += gs[i]; }
        if (i >= gs.length) break;
        out.push(cur); line = gs.slice(i).join("");
      }
    }
    out.push(line.trimEnd());
  }
  return out;
}

// A DOM screen drawn on a canvas in front of the participant. Regions map canvas pixels back
// to the DOM element they show; a selection clicks that element (or, on a VAS line, places
// the marker at the fraction hit through the line's facelabPlace hook). The text is laid out
// at the largest scale (1 down to 0.6) at which it fits a 1024 x 640 canvas; taller content
// makes the panel taller (up to 1280, at scales down to 0.4; more is logged as an error).
// `laidOut` says what was drawn where (for tests).
class Panel {
  constructor(stage, box) {
    this.stage = stage; this.box = box;
    this.w = 1024; this.h = 0; this.width_m = 0.8;
    // a panel is drawn over everything, whatever the depth buffer (the avatar is hidden)
    this.mesh = new THREE.Mesh(new THREE.PlaneGeometry(1, 1), new THREE.MeshBasicMaterial({ depthTest: false }));
    this.mesh.renderOrder = 10;
    this.cursor = new THREE.Mesh(new THREE.RingGeometry(0.006, 0.01, 24), new THREE.MeshBasicMaterial({ color: 0x1565c0, depthTest: false }));
    this.cursor.renderOrder = 11;
    this.cursor.visible = false;
    stage.scene.add(this.mesh); stage.scene.add(this.cursor);
    this.regions = [];
    this.draw();  // sizes and places the panel
    this.observer = new MutationObserver(() => this.draw());
    this.observer.observe(box, { subtree: true, attributes: true, childList: true, characterData: true });
    // the page's Stop question is added to (and removed from) the body: drawn on this panel
    this.observer.observe(document.body, { childList: true });
  }

  // below the avatar's eyes, nearer, turned towards the eyes, so the face stays in view
  place() {
    const st = this.stage, o = st.origin || new THREE.Vector3();
    const d = Math.min(0.9, (st.vr.avatar_distance_m || 1) * 0.8);
    const h_m = this.width_m * this.h / this.w;
    this.mesh.position.copy(o).addScaledVector(st.ahead(), d);
    this.mesh.position.y += (st.vr.avatar_height_m || 0) - 0.12 - h_m / 2;
    this.mesh.lookAt(o);
    this.mesh.updateMatrixWorld(true);
  }

  remove() {
    this.observer.disconnect();
    this.stage.scene.remove(this.mesh); this.stage.scene.remove(this.cursor);
    if (this.texture) this.texture.dispose();
  }

  // the drawing of the box at `scale`: operations, regions, lines, height (px)
  layout(scale) {
    const g = this.scratch || (this.scratch = document.createElement("canvas").getContext("2d"));
    const W = this.w, M = 56, st = this.stage, words = st.words;
    const font = panelFont;
    const ops = [], regions = [], lines = [], blocks = [];
    let y = 84 * Math.max(scale, 0.8);
    const text = (str, px, { x = W / 2, align = "center", maxW = W - 2 * M, color = "#111", source = null } = {}) => {
      g.font = font(px);
      const got = wrapLines(g, str, maxW);
      for (const l of got) {
        const w = g.measureText(l).width;
        const x0 = align === "center" ? x - w / 2 : align === "left" ? x : x - w;
        ops.push({ t: "text", s: l, x, y: y + px * 0.5, px, align, color });
        lines.push({ text: l, x0, x1: x0 + w, y0: y, y1: y + px * 1.2 });
        y += px * 1.35;
      }
      if (source !== null) blocks.push({ source, lines: got });
      return got.length;
    };
    // the page's Stop question, while it asks, in place of the screen (its own two buttons)
    const ask = document.querySelector("[data-facelab=withdraw_ask]");
    const src = ask || this.box;
    // the page's Stop button (top left; the study's end removes it)
    const stop = ask ? null : document.querySelector("[data-facelab=withdraw]");
    if (stop) {
      g.font = font(22);
      const bw = Math.max(150, g.measureText(stop.textContent).width + 32), bh = 44;
      const r = { el: stop, kind: "button", x: M, y: 14, w: bw, h: bh };
      ops.push({ t: "rect", x: r.x, y: r.y, w: bw, h: bh, color: "#e0e0e0" });
      ops.push({ t: "text", s: stop.textContent, x: r.x + bw / 2, y: r.y + bh / 2, px: 22, align: "center", color: "#8e2424" });
      regions.push(r);
    }
    // the recentre button (every panel but the recentre step's own)
    if (!ask && st.vr.recentre !== false && !this.box.querySelector("[data-facelab=recentre_ok]")) {
      g.font = font(22);
      const bw = Math.max(150, g.measureText(words.recentre_short).width + 32), bh = 44;
      const r = { el: "recentre", kind: "recentre", x: W - M - bw, y: 14, w: bw, h: bh };
      ops.push({ t: "rect", x: r.x, y: r.y, w: bw, h: bh, color: "#e0e0e0" });
      ops.push({ t: "text", s: words.recentre_short, x: r.x + bw / 2, y: r.y + bh / 2, px: 22, align: "center", color: "#333" });
      regions.push(r);
    }
    // a word matrix: its question, then its columns of words (the screen's own hint names
    // the mouse: the device's hint is drawn at the foot instead)
    const grid = ask ? null : src.querySelector(".facelab-matrix-grid");
    const sources = src.querySelectorAll(grid ? ".facelab-question" : ".facelab-question, :scope > p, .facelab-text > p, .facelab-code");
    const items = src.querySelectorAll(".facelab-vas-item");
    if (!items.length) for (const t of sources) { text(t.textContent, 40 * scale, { source: t.textContent }); y += 14 * scale; }
    for (const item of items) {
      const q = item.querySelector(".facelab-question").textContent;
      text(q, 34 * scale, { source: q });
      const line = item.querySelector("[data-facelab=line]");
      const x0 = M + 40, x1 = W - M - 40, ly = y + 26 * scale;
      ops.push({ t: "rect", x: x0, y: ly - 3, w: x1 - x0, h: 6, color: "#333" });
      for (const [x, y1] of [[x0, ly], [x1, ly]]) ops.push({ t: "rect", x: x - 2, y: y1 - 14, w: 4, h: 28, color: "#333" });
      const marker = line.querySelector(".facelab-marker");
      if (marker && marker.classList.contains("shown")) {
        const frac = parseFloat(marker.style.left) / 100;
        ops.push({ t: "rect", x: x0 + frac * (x1 - x0) - 5, y: ly - 24, w: 10, h: 48, color: "#c62828" });
      }
      regions.push({ el: line, kind: "line", x: x0, y: ly - 30, w: x1 - x0, h: 60 });
      // the end labels under the line's ends, each wrapped within half the line
      const half = (x1 - x0) / 2 - 16, top = ly + 26;
      const left = item.querySelector(".facelab-anchor.left").textContent;
      const right = item.querySelector(".facelab-anchor.right").textContent;
      y = top; text(left, 26 * scale, { x: x0 - 8, align: "left", maxW: half, color: "#333", source: left });
      const yl = y;
      y = top; text(right, 26 * scale, { x: x1 + 8, align: "right", maxW: half, color: "#333", source: right });
      y = Math.max(y, yl) + 26 * scale;
    }
    if (grid) {  // one column per word of the sentence, its pick marked; a select picks
      const cols = [...grid.querySelectorAll(".facelab-matrix-column")];
      const gap = 10, rowGap = 4, n = cols.length;
      const cw = (W - 2 * M - (n - 1) * gap) / n, ch = 40 * Math.max(scale, 0.8), top = y;
      let rows = 0;
      cols.forEach((col, ci) => {
        const x = M + ci * (cw + gap);
        const words = [...col.querySelectorAll("button")];
        rows = Math.max(rows, words.length);
        words.forEach((b, ri) => {
          const by = top + ri * (ch + rowGap), on = b.getAttribute("aria-pressed") === "true";
          ops.push({ t: "rect", x, y: by, w: cw, h: ch, color: on ? "#1b5e20" : "#dcdcdc" });
          let px = 26 * Math.max(scale, 0.8);
          g.font = font(px);
          while (px > 14 && g.measureText(b.textContent).width > cw - 12) { px -= 1; g.font = font(px); }
          const w = g.measureText(b.textContent).width;
          ops.push({ t: "text", s: b.textContent, x: x + cw / 2, y: by + ch / 2, px, align: "center", color: on ? "#fff" : "#111" });
          lines.push({ text: b.textContent, x0: x + cw / 2 - w / 2, x1: x + cw / 2 + w / 2, y0: by, y1: by + ch });
          blocks.push({ source: b.textContent, lines: [b.textContent] });
          regions.push({ el: b, kind: "pick", x, y: by, w: cw, h: ch });
        });
      });
      y = top + rows * (ch + rowGap);
    }
    const buttons = [...src.querySelectorAll("button")].filter((b) => !b.classList.contains("facelab-word"));
    if (buttons.length) {
      y += 10;
      const perRow = buttons.length <= 3 ? buttons.length : Math.ceil(buttons.length / Math.ceil(buttons.length / 3));
      const gap = 20, bw = Math.min(320, (W - 2 * M - (perRow - 1) * gap) / perRow), bh = 78 * Math.max(scale, 0.8);
      for (let r = 0; r * perRow < buttons.length; r++) {
        const row = buttons.slice(r * perRow, (r + 1) * perRow);
        let x = (W - row.length * (bw + gap) + gap) / 2;
        for (const b of row) {
          ops.push({ t: "rect", x, y, w: bw, h: bh, color: b.disabled ? "#bdbdbd" : "#1565c0" });
          let px = 30 * Math.max(scale, 0.8);
          g.font = font(px);
          while (px > 16 && g.measureText(b.textContent).width > bw - 16) { px -= 1; g.font = font(px); }
          const w = g.measureText(b.textContent).width;
          ops.push({ t: "text", s: b.textContent, x: x + bw / 2, y: y + bh / 2, px, align: "center", color: "#fff" });
          lines.push({ text: b.textContent, x0: x + bw / 2 - w / 2, x1: x + bw / 2 + w / 2, y0: y, y1: y + bh });
          blocks.push({ source: b.textContent, lines: [b.textContent] });
          regions.push({ el: b, kind: "button", x, y, w: bw, h: bh });
          x += bw + gap;
        }
        y += bh + gap;
      }
    }
    y += 6;
    text(st.device() === "controller" ? words.hint_controller : words.hint_gaze, 22, { color: "#666" });
    return { ops, regions, lines, blocks, height: Math.ceil(y + 18), scale };
  }

  draw() {
    // the largest scale that fits 640 px; else the smallest scale that fits the tallest panel
    let lay = null;
    for (const scale of [1, 0.9, 0.8, 0.7, 0.6]) { lay = this.layout(scale); if (lay.height <= 640) break; }
    for (const scale of [0.5, 0.45, 0.4]) { if (lay.height <= 1280) break; lay = this.layout(scale); }
    const h = Math.min(1280, Math.max(640, lay.height));
    if (h !== this.h) {  // a new size: a new canvas, texture and plane
      this.h = h;
      this.canvas = document.createElement("canvas"); this.canvas.width = this.w; this.canvas.height = h;
      if (this.texture) this.texture.dispose();
      this.texture = new THREE.CanvasTexture(this.canvas);
      this.texture.colorSpace = THREE.SRGBColorSpace;
      this.mesh.material.map = this.texture; this.mesh.material.needsUpdate = true;
      this.mesh.geometry.dispose();
      this.mesh.geometry = new THREE.PlaneGeometry(this.width_m, this.width_m * h / this.w);
      this.place();
    }
    const g = this.canvas.getContext("2d");
    g.fillStyle = "#f5f5f5"; g.fillRect(0, 0, this.w, h);
    g.textBaseline = "middle";
    for (const op of lay.ops) {
      g.fillStyle = op.color;
      if (op.t === "rect") { g.fillRect(op.x, op.y, op.w, op.h); continue; }
      g.font = panelFont(op.px); g.textAlign = op.align;
      g.fillText(op.s, op.x, op.y);
    }
    this.regions = lay.regions;
    const outside = lay.lines.filter((l) => l.x0 < 0 || l.x1 > this.w || l.y1 > h);
    this.laidOut = { scale: lay.scale, width: this.w, height: h, lines: lay.lines, blocks: lay.blocks,
                     overflow: outside.length > 0 || lay.height > h };
    if (this.laidOut.overflow && !this.reported) {  // too much for one panel: said, once
      this.reported = true;
      FacelabOutbox.send("/api/event", { kind: "error", detail: { what: "VR panel overflow", screen: this.box.dataset.facelab || "", height_px: lay.height } });
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

  async select(controller) {
    const st = this.stage;
    // a selected button is taking effect, or the next screen is still (mostly) dark: a second
    // or blind press answers nothing
    if (st.selecting || st.opacity() > 0.5) return;
    const h = this.hit(controller);
    if (!h) return;
    const r = this.regions.find((q) => h.x >= q.x && h.x <= q.x + q.w && h.y >= q.y && h.y <= q.y + q.h);
    if (!r) return;
    if (r.kind === "button" && !r.el.disabled) {
      // the panel fades to black, then the button takes effect (the answer's time is the
      // select's: facelabAnswer reads selectedAt); a screen that stays (Stop's question, a
      // button that does not end it) fades in again
      st.selecting = true;
      const at = st.selectedAt = performance.now();
      st.selectedPose = st.lastPose;
      let dark = null;
      try {
        await st.fadeOut();
        dark = st.fade;
        if (r.el.isConnected && !r.el.disabled) r.el.click();
      } finally { st.selecting = false; }
      setTimeout(() => {  // the click's answer has been taken (synchronously or just after)
        if (st.selectedAt === at) { st.selectedAt = null; st.selectedPose = null; }
        // the same screen and no other fade since: it fades in again
        if (st.panel === this && dark && st.fade === dark) st.fadeIn();
      }, 100);
    }
    // a word of a matrix: picked at once (no fade: the screen stays until its Confirm)
    if (r.kind === "pick" && r.el.isConnected) r.el.click();
    if (r.kind === "line" && r.el.facelabPlace) r.el.facelabPlace(Math.min(1, Math.max(0, (h.x - r.x) / r.w)));
    if (r.kind === "recentre") this.stage.recentre("button");
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
