// facelab's animation track reader (format facelab-track-1, written by `facelab render` beside
// each clip as <clip_id>.track.bin; see facelab/formats.py encode_track). The browser plays the
// same per-frame values the offline renderer drew: frame k is shown from k / fps s after the
// clip's audio starts, so a player looks the frame up from the audio clock.
"use strict";
const FacelabTrack = (function () {
  const MAGIC = "FLTRACK1";

  function parse(buffer) {
    const bytes = new Uint8Array(buffer);
    const magic = String.fromCharCode(...bytes.subarray(0, 8));
    if (bytes.length < 12 || magic !== MAGIC) throw new Error("not a facelab animation track");
    const length = new DataView(buffer, 8, 4).getUint32(0, true);
    const header = JSON.parse(new TextDecoder("utf-8").decode(bytes.subarray(12, 12 + length)));
    const n = header.n_frames;
    const c = header.channels.length;
    const start = 12 + length; // a multiple of 4: the header is padded
    if (header.format !== "facelab-track-1" || buffer.byteLength - start !== 4 * n * c) {
      throw new Error("the track's size does not match its header");
    }
    // little-endian float32 values; copy through a DataView so any host byte order reads them
    const view = new DataView(buffer, start);
    const values = new Float32Array(n * c);
    for (let i = 0; i < n * c; i++) values[i] = view.getFloat32(4 * i, true);
    const names = header.channels.map((ch) => ch.name);
    return {
      header,
      names,
      frames: n,
      channels: c,
      values,
      // the frame shown at audio time t (s from the clip's start): floor(t * fps), clamped
      frameAt(t) { return Math.min(n - 1, Math.max(0, Math.floor(t * header.fps + 1e-9))); },
      // { name: value } of frame k
      frame(k) {
        const out = {};
        for (let j = 0; j < c; j++) out[names[j]] = values[k * c + j];
        return out;
      },
    };
  }

  return { parse };
})();
if (typeof module !== "undefined") module.exports = FacelabTrack;
