// The talker page's microphone capture (an AudioWorklet): each block of samples to the page,
// which sends them in 10 ms chunks (dialogue.js). A file, not a blob: the pages' policy runs
// scripts of this origin only.
class Capture extends AudioWorkletProcessor {
  process(inputs) { const x = inputs[0][0]; if (x) this.port.postMessage(x.slice(0)); return true; }
}
registerProcessor("facelab-capture", Capture);
