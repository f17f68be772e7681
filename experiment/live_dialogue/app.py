"""The live-dialogue server (``facelab live``): a talker's audio streams in, the condition's
method drives the avatar as it streams, viewers see and hear it, and each turn is recorded.

Pages and sockets (same origin, one talker at a time, any number of viewers)::

    GET  /            the viewer (three.js, the live-3D avatar and camera of the protocol)
    GET  /talk        the talker: the microphone, captured at 16 kHz, streamed in 10 ms chunks
    GET  /live.json   what both pages need: scene, channel names, rates, playout, language
    GET  /turns       the turns recorded so far (their turn.json)
    WS   /ws/talk     talker -> server: {"sample_rate": 16000}, then float32 chunks, {"end": 1}
    WS   /ws/view     server -> viewer: binary messages (below); viewer -> server at the end of
                      a turn: {"log": [[page_ms, heard_s, frame, wanted], ...],
                      "arrivals": [[first frame, s of audio playing when it arrived], ...]}

A binary message is four little-endian uint32 - kind (1 audio, 2 frames), start (sample or
frame index), count, width (1, or the number of channels) - then count x width float32. A
text message ``{"turn": ...}`` starts a turn, ``{"end": n_samples}`` ends it.

The viewer plays the sound ``playout_ms`` after it arrives (a jitter buffer long enough for the
analysis: a frame waits for :attr:`LiveDriver.latency_s` of audio beyond its time) and draws,
at each display frame, the track frame of the audio it is hearing - or the newest it has,
counted late. With ``--input FILE.wav`` the server is the talker: it streams the file in real
time once a viewer is connected.
"""

from __future__ import annotations

import asyncio
import json
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from fastapi import FastAPI, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response

from facelab.errors import SessionError
from facelab.experiment.live_dialogue.turn import Turn, next_turn_dir
from facelab.experiment.online.middleware import IMPORT_MAP
from facelab.experiment.online.server import THREE_FILES, WEB
from facelab.protocol import Protocol

__all__ = ["LIVE_RATE", "LiveConfig", "LiveHub", "create_live_app"]

LIVE_RATE = 16_000  # the talker page captures at this rate (the analyser's own)
CHUNK = 160  # samples per streamed chunk: 10 ms
AUDIO, FRAMES = 1, 2
VIEWER_LOG_WAIT_S = 15.0  # after a turn ends, how long the viewers' logs are waited for


def pack(kind: int, start: int, values: np.ndarray) -> bytes:
    values = np.ascontiguousarray(values, dtype="<f4")
    width = 1 if values.ndim == 1 else values.shape[1]
    return struct.pack("<4I", kind, start, len(values), width) + values.tobytes()


@dataclass
class LiveConfig:
    """What one ``facelab live`` serves: the protocol's condition on its avatar, where turns
    go, the talker (``"mic"``: a browser page; a Path: that file, streamed by the server)."""

    protocol: Protocol
    protocol_path: Path
    condition: str
    session: Path
    talker: str | Path = "mic"
    display: str = "live3d"
    playout_ms: float = 120.0
    vendor: Path | None = None


@dataclass
class LiveHub:
    """The running state: the scene, the viewers' sockets, the turn being recorded."""

    config: LiveConfig
    scene: Any = None  # experiment.online.live.LiveScene-like: avatar_glb, avatar_name, camera
    avatar: Any = None
    viewers: dict[int, Any] = field(default_factory=dict)
    turn: Turn | None = None
    driver: Any = None
    turns: list[dict[str, Any]] = field(default_factory=list)
    logs: dict[int, list] = field(default_factory=dict)
    arrivals: dict[int, list] = field(default_factory=dict)
    _next_viewer: int = 1
    busy: bool = False

    @classmethod
    def open(cls, config: LiveConfig) -> LiveHub:
        """Load the avatar and check that the condition's method can run live (SessionError
        naming it otherwise)."""
        from facelab.errors import FacelabError
        from facelab.stimuli.avatar.gltf import live_glb
        from facelab.stimuli.methods.live_drive import live_problem
        from facelab.stimuli.render.scene import camera_json, load_avatar, settings_for

        protocol, base = config.protocol, config.protocol_path.parent
        cond = protocol.condition(config.condition)
        avatar = load_avatar(protocol, base_dir=base)
        problem = live_problem(cond.method, cond.settings, avatar=avatar, base_dir=base)
        if problem is not None:
            raise SessionError(f"condition {config.condition!r}: {problem}")
        glb = live_glb(avatar)
        import hashlib

        hub = cls(config=config, avatar=avatar)
        hub.scene = {
            "glb": glb,
            "name": hashlib.sha256(glb).hexdigest() + ".glb",
            "camera": camera_json(avatar, settings_for(protocol)),
            "avatar_sha256": avatar.content_hash(),
        }
        try:
            hub.new_driver()
        except FacelabError as exc:
            raise SessionError(f"condition {config.condition!r}: {exc}") from None
        return hub

    def new_driver(self):
        from facelab.stimuli.methods.live_drive import LiveDriver

        cond = self.config.protocol.condition(self.config.condition)
        self.driver = LiveDriver(
            method_name=cond.method, params=cond.settings, avatar=self.avatar,
            sample_rate=LIVE_RATE, base_dir=self.config.protocol_path.parent,
        )  # fmt: skip
        return self.driver

    def live_json(self) -> dict[str, Any]:
        p = self.config.protocol
        return {
            "scene": {"avatar": "/avatar/" + self.scene["name"], "camera": self.scene["camera"]},
            "names": list(self.driver.names),
            "fps": 100,
            "sample_rate": LIVE_RATE,
            "chunk": CHUNK,
            "playout_ms": self.config.playout_ms,
            "display": self.config.display,
            "language": p.presentation.language,
            "condition": self.config.condition,
            "talker": "mic" if self.config.talker == "mic" else "file",
            "vr": p.presentation.vr.model_dump(),
        }

    # -- a turn

    async def broadcast(self, message: bytes | str) -> None:
        for vid, ws in list(self.viewers.items()):
            try:
                if isinstance(message, bytes):
                    await ws.send_bytes(message)
                else:
                    await ws.send_text(message)
            except Exception:  # a viewer gone mid-turn: the others go on
                self.viewers.pop(vid, None)

    async def start_turn(self) -> None:
        if self.busy:
            raise SessionError("a turn is being recorded already (one talker at a time)")
        self.busy = True
        driver = self.new_driver()
        self.turn = Turn(sample_rate=LIVE_RATE, names=driver.names)
        self.logs, self.arrivals = {}, {}
        self.turn_started = time.time()
        await self.broadcast(json.dumps({"turn": len(self.turns) + 1}))

    async def audio(self, chunk: np.ndarray) -> None:
        turn, driver = self.turn, self.driver
        start = driver.samples_in
        frames = driver.feed(chunk)
        turn.add_audio(chunk)
        await self.broadcast(pack(AUDIO, start, chunk))
        if len(frames):
            turn.add_frames(frames.weights)
            await self.broadcast(pack(FRAMES, frames.start, frames.weights))

    async def end_turn(self) -> dict[str, Any] | None:
        turn, driver = self.turn, self.driver
        if turn is None:
            return None
        frames = driver.flush()
        if len(frames):
            turn.add_frames(frames.weights)
            await self.broadcast(pack(FRAMES, frames.start, frames.weights))
        waiting = set(self.viewers)
        await self.broadcast(json.dumps({"end": driver.samples_in}))
        deadline = time.monotonic() + VIEWER_LOG_WAIT_S
        while waiting - set(self.logs) and time.monotonic() < deadline:
            waiting &= set(self.viewers) | set(self.logs)
            await asyncio.sleep(0.05)
        for vid, log in sorted(self.logs.items()):
            turn.add_viewer_log(vid, log, arrivals=self.arrivals.get(vid, []))
        self.turn = None
        self.busy = False
        if not len(turn.samples):
            return None
        cond = self.config.protocol.condition(self.config.condition)
        folder = next_turn_dir(self.config.session)
        record = await asyncio.to_thread(
            turn.save, folder, clip_id=f"live__{folder.name}__{self.config.condition}",
            avatar_sha256=self.scene["avatar_sha256"], playout_ms=self.config.playout_ms,
            info={
                "protocol": str(self.config.protocol_path),
                "study": self.config.protocol.study.id,
                "condition": self.config.condition,
                "method": cond.method,
                "started": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(self.turn_started)),
                "talker": "microphone (browser page)" if self.config.talker == "mic"
                else str(self.config.talker),
                "analysis_latency_ms": round(driver.latency_s * 1000, 1),
                "behaviour": "not run live (the mouth only: the condition's method)",
            },
        )  # fmt: skip
        record["folder"] = str(folder)
        self.turns.append(record)
        return record

    async def stream_file(self, path: Path) -> None:
        """Be the talker: stream ``path`` in real time, 10 ms a chunk."""
        from facelab.stimuli.speech.audio import load_audio

        x = (await asyncio.to_thread(load_audio, path, sample_rate=LIVE_RATE)).samples
        await self.start_turn()
        t0 = time.monotonic()
        for k in range(0, len(x), CHUNK):
            await self.audio(x[k : k + CHUNK])
            delay = t0 + (k + CHUNK) / LIVE_RATE - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
        await self.end_turn()


def create_live_app(hub: LiveHub):
    """The FastAPI app over ``hub`` (see the module docstring)."""
    app = FastAPI(openapi_url=None, docs_url=None, redoc_url=None)
    assets = {n: WEB / "static" / n for n in ("live.js", "dialogue.js", "facelab.css")}
    three = {rel: (hub.config.vendor or WEB / "node_modules") / "three" / rel
             for rel in THREE_FILES}  # fmt: skip

    def page(role: str) -> HTMLResponse:
        title = {"view": "facelab live", "talk": "facelab live: talker"}[role]
        return HTMLResponse(
            "<!doctype html><html><head><meta charset='utf-8'>"
            f"<title>{title}</title><link rel='stylesheet' href='/static/facelab.css'>"
            f"<script type='importmap'>{IMPORT_MAP}</script></head>"
            f"<body data-role='{role}'><main id='facelab-live'></main>"
            "<script type='module' src='/static/dialogue.js'></script></body></html>",
            headers={"cache-control": "no-store"},
        )

    @app.get("/")
    def viewer_page() -> HTMLResponse:
        return page("view")

    @app.get("/talk")
    def talker_page() -> HTMLResponse:
        return page("talk")

    @app.get("/live.json")
    def live_json() -> JSONResponse:
        return JSONResponse(hub.live_json())

    @app.get("/turns")
    def turns() -> JSONResponse:
        return JSONResponse({"turns": hub.turns, "busy": hub.busy})

    @app.get("/avatar/{name}")
    def avatar(name: str) -> Response:
        if name != hub.scene["name"]:
            return JSONResponse({"error": "not found"}, status_code=404)
        return Response(hub.scene["glb"], media_type="model/gltf-binary")

    @app.get("/static/{name}")
    def static(name: str) -> Response:
        if name not in assets:
            return JSONResponse({"error": "not found"}, status_code=404)
        return FileResponse(assets[name])

    @app.get("/vendor/three/{rel:path}")
    def vendor_three(rel: str) -> Response:
        if rel not in three or not three[rel].is_file():
            return JSONResponse({"error": "not found"}, status_code=404)
        return FileResponse(three[rel], media_type="text/javascript")

    @app.websocket("/ws/view")
    async def view(ws: WebSocket) -> None:
        await ws.accept()
        vid = hub._next_viewer
        hub._next_viewer += 1
        hub.viewers[vid] = ws
        if hub.config.talker != "mic" and not hub.busy and not hub.turns:
            hub.stream_task = asyncio.create_task(hub.stream_file(Path(hub.config.talker)))
        try:
            while True:
                text = await ws.receive_text()
                try:
                    msg = json.loads(text)
                except ValueError:
                    continue
                if isinstance(msg, dict) and isinstance(msg.get("log"), list):
                    arrivals = msg.get("arrivals") if isinstance(msg.get("arrivals"), list) else []
                    hub.arrivals[vid] = [row for row in arrivals[:200_000]
                                         if isinstance(row, list) and len(row) == 2]  # fmt: skip
                    hub.logs[vid] = [row for row in msg["log"][:200_000]
                                     if isinstance(row, list) and len(row) == 4]  # fmt: skip
        except WebSocketDisconnect:
            pass
        finally:
            hub.viewers.pop(vid, None)

    @app.websocket("/ws/talk")
    async def talk(ws: WebSocket) -> None:
        await ws.accept()
        if hub.busy or hub.config.talker != "mic":
            await ws.send_text(json.dumps({"error": "another talker is speaking"
                                           if hub.busy else "this session's talker is a file"}))
            await ws.close()
            return
        started = False
        try:
            while True:
                msg = await ws.receive()
                if msg.get("type") == "websocket.disconnect":
                    break
                if msg.get("bytes") is not None:
                    data = msg["bytes"]
                    if not started or len(data) % 4 or len(data) > 4 * LIVE_RATE:
                        continue
                    chunk = np.frombuffer(data, dtype="<f4").astype(np.float64)
                    if np.all(np.isfinite(chunk)):
                        await hub.audio(np.clip(chunk, -1.0, 1.0))
                    continue
                try:
                    control = json.loads(msg.get("text") or "")
                except ValueError:
                    continue
                if not started and control.get("sample_rate") == LIVE_RATE:
                    await hub.start_turn()
                    started = True
                    await ws.send_text(json.dumps({"started": True}))
                elif started and control.get("end"):
                    break
                elif not started:
                    await ws.send_text(json.dumps({"error": f"capture at {LIVE_RATE} Hz"}))
        finally:
            if started:
                record = await hub.end_turn()
                try:
                    await ws.send_text(json.dumps({"saved": record and record["folder"]}))
                    await ws.close()
                except Exception:
                    pass

    return app


def free_port() -> int:
    from facelab.experiment.online.serve import free_port as _free

    return _free()
