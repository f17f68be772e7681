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
import hashlib
import json
import math
import struct
import sys
import time
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from fastapi import FastAPI, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response

from facelab.errors import FacelabError, SessionError
from facelab.experiment.live_dialogue.turn import Turn
from facelab.experiment.online.middleware import IMPORT_MAP
from facelab.experiment.online.server import THREE_FILES, WEB
from facelab.protocol import Protocol
from facelab.stimuli.methods.live_drive import LIVE_FPS, LiveDriver

__all__ = ["LIVE_RATE", "LiveConfig", "LiveHub", "create_live_app", "talk_socket", "view_socket"]

LIVE_RATE = 16_000  # the talker page captures at this rate (the analyser's own)
CHUNK = 160  # samples per streamed chunk: 10 ms
AUDIO, FRAMES = 1, 2
VIEWER_LOG_WAIT_S = 15.0  # after a turn ends, how long the viewers' logs are waited for
SEND_TIMEOUT_S = 2.0  # a viewer that takes no message for this long is dropped


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
    #: an online study's conversation: whose it is (participant id, session, the SHA-256 of
    #: the protocol version their session runs), written into each turn.json
    owner: dict[str, Any] | None = None


@dataclass
class LiveHub:
    """The running state: the scene, the viewers' sockets, the turn being recorded. One
    event loop drives it (the server's); a turn's save runs in a thread, one at a time."""

    config: LiveConfig
    scene: dict[str, Any]  # glb (bytes), name, camera, avatar_sha256
    driver: LiveDriver
    viewers: dict[int, WebSocket] = field(default_factory=dict)
    turn: Turn | None = None
    turns: list[dict[str, Any]] = field(default_factory=list)
    #: the viewers that were sent this turn's start: the end of the turn waits for their logs
    turn_viewers: set[int] = field(default_factory=set)
    logs: dict[int, list] = field(default_factory=dict)
    arrivals: dict[int, list] = field(default_factory=dict)
    poses: dict[int, list] = field(default_factory=dict)  # in VR: a viewer's head per frame
    late_audio: dict[int, int] = field(default_factory=dict)  # chunks a viewer got too late
    displays: dict[int, str] = field(default_factory=dict)  # how each viewer showed the turn
    turn_started: float = 0.0
    busy: bool = False
    #: the warp the last turn's analysis settled on: the same talker's next turn starts there
    last_warp: float = 1.0
    talker_audio: np.ndarray | None = None  # a file talker's samples at LIVE_RATE
    stream_task: asyncio.Task | None = None
    problems: list[str] = field(default_factory=list)  # what went wrong, said to the operator
    next_viewer: int = 1
    feeding: asyncio.Future | None = None  # the analysis of the latest chunk
    ending: bool = False  # the turn is ending: its viewers' logs are awaited
    #: the server's event loop, once it runs (a viewer in another thread joins through it)
    loop: asyncio.AbstractEventLoop | None = None

    @classmethod
    def open(cls, config: LiveConfig) -> LiveHub:
        """Load the avatar (and a file talker's audio) and check that the condition's method
        can run live: SessionError naming what cannot."""
        from facelab.stimuli.avatar.gltf import live_glb
        from facelab.stimuli.render.scene import camera_json, load_avatar, settings_for
        from facelab.stimuli.speech.audio import load_audio

        protocol, base = config.protocol, config.protocol_path.parent
        cond = protocol.condition(config.condition)
        avatar = load_avatar(protocol, base_dir=base)
        try:  # the method checked (it must run live on this avatar) and prepared, once
            driver = LiveDriver(method_name=cond.method, params=cond.settings, avatar=avatar,
                                sample_rate=LIVE_RATE, base_dir=base)  # fmt: skip
            talker_audio = None
            if config.talker != "mic":
                talker_audio = load_audio(Path(config.talker), sample_rate=LIVE_RATE).samples
        except FacelabError as exc:
            raise SessionError(f"condition {config.condition!r}: {exc}") from None
        glb = live_glb(avatar)
        scene = {
            "glb": glb,
            "name": hashlib.sha256(glb).hexdigest() + ".glb",
            "camera": camera_json(avatar, settings_for(protocol)),
            "avatar_sha256": avatar.content_hash(),
        }
        return cls(config=config, scene=scene, driver=driver,
                   talker_audio=talker_audio)  # fmt: skip

    def running_loop(self, *, timeout_s: float = 20.0) -> asyncio.AbstractEventLoop:
        """The server's event loop once the app serving this hub runs (another thread joins
        the hub through it); SessionError when it does not start within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while self.loop is None:
            if time.monotonic() > deadline:
                raise SessionError("the live server did not start")
            time.sleep(0.02)
        return self.loop

    def live_json(self) -> dict[str, Any]:
        p = self.config.protocol
        return {
            "scene": {"avatar": "/avatar/" + self.scene["name"], "camera": self.scene["camera"]},
            "names": list(self.driver.names),
            "fps": LIVE_FPS,
            "sample_rate": LIVE_RATE,
            "chunk": CHUNK,
            "playout_ms": self.config.playout_ms,
            "display": self.config.display,
            "language": p.presentation.language,
            "condition": self.config.condition,
            "talker": "mic" if self.config.talker == "mic" else "file",
            "vr": p.presentation.vr.model_dump(),
        }

    # -- viewers

    def add_viewer(self, ws: WebSocket) -> int:
        vid = self.next_viewer
        self.next_viewer += 1
        self.viewers[vid] = ws
        return vid

    def viewer_log(self, vid: int, msg: Any) -> None:
        """A viewer's end-of-turn message: its drawn frames and frame arrivals, kept only as
        finite numbers (anything else in them is dropped)."""
        if not isinstance(msg, dict) or vid not in self.turn_viewers:
            return
        self.logs[vid] = _numeric_rows(msg.get("log"), width=4)
        self.arrivals[vid] = _numeric_rows(msg.get("arrivals"), width=2)
        self.poses[vid] = _numeric_rows(msg.get("poses"), width=7)
        late = msg.get("late_audio")
        self.late_audio[vid] = int(late) if isinstance(late, int) and late >= 0 else 0
        shown = msg.get("display")
        self.displays[vid] = shown if shown in ("live3d", "webxr", "window") else "unknown"

    async def broadcast(self, message: bytes | str, *, to: set[int] | None = None) -> None:
        for vid, ws in list(self.viewers.items()):
            if to is not None and vid not in to:
                continue
            try:
                if isinstance(message, bytes):
                    await asyncio.wait_for(ws.send_bytes(message), SEND_TIMEOUT_S)
                else:
                    await asyncio.wait_for(ws.send_text(message), SEND_TIMEOUT_S)
            except Exception:  # a viewer gone or not reading: the others go on without it
                self.viewers.pop(vid, None)

    async def join_turn(self, vid: int) -> None:
        """A viewer connecting while a turn runs: it gets the turn's start (and is waited for
        at its end); it hears the talker from the next chunk on."""
        if self.turn is not None and not self.ending and vid not in self.turn_viewers:
            await self.broadcast(json.dumps({"turn": len(self.turns) + 1}), to={vid})
            self.turn_viewers.add(vid)  # after its start: no chunk overtakes it

    # -- a turn

    async def start_turn(self) -> None:
        """SessionError when a turn is being recorded already (one talker at a time)."""
        if self.busy:
            raise SessionError("another talker is speaking (one talker at a time)")
        self.driver.restart(start_warp=self.last_warp)
        self.busy = True
        self.turn = Turn(sample_rate=LIVE_RATE, names=self.driver.names)
        self.logs, self.arrivals, self.late_audio, self.displays = {}, {}, {}, {}
        self.poses = {}
        self.turn_started = time.time()
        self.turn_viewers = set(self.viewers)
        await self.broadcast(json.dumps({"turn": len(self.turns) + 1}))

    async def audio(self, chunk: np.ndarray) -> None:
        """Relay a talker's chunk to the viewers at once, then analyse it (in a thread, so the
        server keeps relaying while the analysis runs) and send the frames it completes. The
        analysis records its frames itself and is shielded: a talker's handler cancelled
        meanwhile loses nothing, and the end of the turn waits for it."""
        turn, driver = self.turn, self.driver
        start = driver.samples_in
        turn.add_audio(chunk)
        await self.broadcast(pack(AUDIO, start, chunk), to=self.turn_viewers)
        self.feeding = asyncio.ensure_future(asyncio.to_thread(self._feed, turn, driver, chunk))
        frames = await asyncio.shield(self.feeding)
        if len(frames):
            await self.broadcast(pack(FRAMES, frames.start, frames.weights), to=self.turn_viewers)

    @staticmethod
    def _feed(turn: Turn, driver: LiveDriver, chunk: np.ndarray):
        frames = driver.feed(chunk)
        turn.add_frames(frames.start, frames.weights)
        return frames

    async def end_turn(self) -> dict[str, Any] | None:
        """Flush the analysis, collect the viewers' logs and save the turn (None when it had
        no audio). The hub is free for the next talker whatever happens; a turn that cannot
        be saved is said in ``problems`` and raised."""
        turn, driver = self.turn, self.driver
        if turn is None:
            return None
        self.ending = True  # a viewer connecting now is not waited for
        try:
            if self.feeding is not None:  # the last chunk's analysis, if still running
                await asyncio.wait({self.feeding})
            frames = driver.flush()
            self.last_warp = driver.stream.warp
            if not len(turn.samples):
                return None
            if len(frames):
                turn.add_frames(frames.start, frames.weights)
                await self.broadcast(pack(FRAMES, frames.start, frames.weights),
                                     to=self.turn_viewers)  # fmt: skip
            await self.broadcast(json.dumps({"end": driver.samples_in}), to=self.turn_viewers)
            deadline = time.monotonic() + VIEWER_LOG_WAIT_S
            while time.monotonic() < deadline and (
                (self.turn_viewers & set(self.viewers)) - set(self.logs)
            ):
                await asyncio.sleep(0.05)
            for vid, log in sorted(self.logs.items()):
                turn.add_viewer_log(vid, log, arrivals=self.arrivals.get(vid, []),
                                    poses=self.poses.get(vid, []))  # fmt: skip
            cond = self.config.protocol.condition(self.config.condition)
            info = {
                "protocol": str(self.config.protocol_path),
                "study": self.config.protocol.study.id,
                "condition": self.config.condition,
                "method": cond.method,
                "started": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(self.turn_started)),
                "talker": "microphone (browser page)" if self.config.talker == "mic"
                else str(self.config.talker),
                "analysis_latency_ms": round(driver.latency_s * 1000, 1),
                "analysis_warps": [[round(n / LIVE_RATE, 3), w]
                                   for n, w in getattr(driver.stream, "warps", ())],
                "behaviour": "not run live (the mouth only: the condition's method)",
                "audio_chunks_late": sum(self.late_audio.values()),
                "viewer_displays": {str(v): d for v, d in sorted(self.displays.items())},
                **(self.config.owner or {}),
            }  # fmt: skip
            try:
                record = await asyncio.to_thread(
                    turn.save_new, self.config.session, condition=self.config.condition,
                    avatar_sha256=self.scene["avatar_sha256"],
                    playout_ms=self.config.playout_ms, info=info,
                )  # fmt: skip
            except (OSError, FacelabError) as exc:
                why = exc if isinstance(exc, FacelabError) else exc.strerror or "write error"
                self.problems.append(f"a turn could not be saved in "
                                     f"{self.config.session}: {why}")  # fmt: skip
                raise SessionError(self.problems[-1]) from None
            self.turns.append(record)
            return record
        finally:
            self.turn, self.feeding = None, None
            self.turn_viewers = set()
            self.busy = self.ending = False

    def start_file_talker(self) -> None:
        """Be the talker (``--input FILE``): the first time a viewer connects, stream the
        file in real time, 10 ms a chunk."""
        if self.stream_task is None and self.talker_audio is not None:
            self.stream_task = asyncio.create_task(self._stream_file())

    async def _stream_file(self) -> None:
        x = self.talker_audio
        try:
            await self.start_turn()
        except FacelabError as exc:
            self.problems.append(str(exc))
            print(f"facelab live: {exc}", file=sys.stderr)
            return
        try:
            t0 = time.monotonic()
            for k in range(0, len(x), CHUNK):
                await self.audio(x[k : k + CHUNK])
                delay = t0 + (k + CHUNK) / LIVE_RATE - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
        finally:  # the turn is saved (or said to have failed) however the stream ended
            try:
                await asyncio.shield(self.end_turn())
            except FacelabError as exc:
                self.problems.append(str(exc))
                print(f"facelab live: {exc}", file=sys.stderr)


def _numeric_rows(rows: Any, *, width: int, limit: int = 200_000) -> list[list[float]]:
    """The rows of ``width`` finite numbers among ``rows`` (a client's JSON), at most
    ``limit``."""
    out: list[list[float]] = []
    for row in rows[:limit] if isinstance(rows, list) else ():
        if not isinstance(row, list) or len(row) != width:
            continue
        try:
            values = [float(v) for v in row if isinstance(v, (int, float))
                      and not isinstance(v, bool)]  # fmt: skip
        except OverflowError:  # an integer too large for a float
            continue
        if len(values) == width and all(math.isfinite(v) for v in values):
            out.append(values)
    return out


def create_live_app(hub: LiveHub):
    """The FastAPI app over ``hub`` (see the module docstring)."""

    @asynccontextmanager
    async def lifespan(_app: FastAPI):
        hub.loop = asyncio.get_running_loop()
        yield

    app = FastAPI(openapi_url=None, docs_url=None, redoc_url=None, lifespan=lifespan)
    assets = {n: WEB / "static" / n
              for n in ("live.js", "dialogue.js", "conversation.js", "capture.js", "facelab.css")}
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
        await view_socket(hub, ws)

    @app.websocket("/ws/talk")
    async def talk(ws: WebSocket) -> None:
        await ws.accept()
        await talk_socket(hub, ws)

    return app


async def view_socket(hub: LiveHub, ws: WebSocket) -> None:
    """A viewer's socket (accepted): joined to the hub (and to a turn running now) until it
    closes; its end-of-turn logs go to the hub. A file talker starts with the first viewer."""
    vid = hub.add_viewer(ws)
    await hub.join_turn(vid)
    hub.start_file_talker()
    try:
        while True:
            msg = await ws.receive()
            if msg.get("type") == "websocket.disconnect":
                break
            try:
                hub.viewer_log(vid, json.loads(msg.get("text") or ""))
            except (ValueError, RecursionError):  # not JSON, or nested beyond reason
                continue
    except WebSocketDisconnect:
        pass
    finally:
        hub.viewers.pop(vid, None)


async def talk_socket(hub: LiveHub, ws: WebSocket) -> None:
    """A talker's socket (accepted): ``{"sample_rate": 16000}`` starts a turn, float32 chunks
    follow, ``{"end": 1}`` (or the socket closing) ends and saves it; the reply names the
    saved folder or the error."""

    async def refuse(why: str) -> None:
        await ws.send_text(json.dumps({"error": why}))
        await ws.close()

    if hub.config.talker != "mic":
        await refuse("this session's talker is a file")
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
                # a sample that is not a number becomes silence: the timing is kept
                chunk = np.nan_to_num(np.frombuffer(data, dtype="<f4").astype(np.float64),
                                      nan=0.0, posinf=0.0, neginf=0.0)  # fmt: skip
                await hub.audio(np.clip(chunk, -1.0, 1.0))
                continue
            try:
                control = json.loads(msg.get("text") or "")
            except (ValueError, RecursionError):
                continue
            if not isinstance(control, dict):
                continue
            if not started and control.get("sample_rate") == LIVE_RATE:
                try:
                    await hub.start_turn()
                except SessionError as exc:
                    await refuse(str(exc))
                    return
                started = True
                await ws.send_text(json.dumps({"started": True}))
            elif started and control.get("end"):
                break
            elif not started:
                await ws.send_text(json.dumps({"error": f"capture at {LIVE_RATE} Hz"}))
    except WebSocketDisconnect:
        pass
    finally:
        if started:  # a talker gone without saying so ends its turn too (shielded: a
            try:  # handler cancelled on a lost connection still saves the turn)
                record = await asyncio.shield(hub.end_turn())
                reply = {"saved": record and record["folder"]}
            except SessionError as exc:
                reply = {"error": str(exc)}
            try:
                await ws.send_text(json.dumps(reply))
                await ws.close()
            except Exception:  # the talker's page is gone: the turn is saved anyway
                pass
