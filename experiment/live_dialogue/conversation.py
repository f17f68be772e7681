"""A live conversation inside an online study (``presentation.conversation``, issue 53.4).

A participant's timeline reaches its conversation screen; their page becomes a viewer of
their own live hub (:class:`~facelab.experiment.live_dialogue.app.LiveHub`: the
conversation's condition on the protocol's avatar), and the talker - the experimenter or a
confederate on ``/talk``, or the server itself streaming ``--conversation-input FILE.wav`` -
speaks to them; each turn is recorded in ``<folder>/<participant>/turn-NNN`` as ``facelab
live`` records it. The screen ends when its minutes have run out or the talker ends it; its
answer and the questions about the partner after it are logged like any screen's.

Routes it adds to ``facelab serve``'s app (:func:`conversation_routes`):

===============================  ==========================================================
``GET /api/conversation``        (participant token) the participant's conversation, opened
                                 on first ask: what the viewer needs (scene, channel names,
                                 rates, playout)
``GET /conversation/avatar/N``   the avatar an open conversation draws (by its hash)
``WS /ws/conversation/view``     the participant's page; its first message ``{"token": T}``;
                                 then as ``facelab live``'s ``/ws/view``, and
                                 ``{"conversation_end": 1}`` when the talker ends it
``GET /talk``                    the talker's page (experimenter secret, participant id)
``WS /ws/conversation/talk``     first message ``{"admin": SECRET, "participant": ID}``;
                                 then one turn as ``facelab live``'s ``/ws/talk``
``POST /api/conversation/end``   (experimenter secret) ``{"participant": ID}``: end it now
``GET /api/conversation/status`` (experimenter secret) ``?participant=ID``: viewers, turns
===============================  ==========================================================

The sockets refuse a page of another origin (the browser's ``Origin`` header), an unknown
token or a wrong secret; the token travels in the socket's first message, never in its URL.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request, WebSocket
from fastapi.responses import HTMLResponse, Response

from facelab.errors import FacelabError, SessionError
from facelab.experiment.live_dialogue.app import (
    LiveConfig,
    LiveHub,
    talk_socket,
    view_socket,
)
from facelab.experiment.online.middleware import IMPORT_MAP
from facelab.experiment.online.server import (
    ADMIN_HEADER,
    TOKEN_HEADER,
    RefusedError,
    StudyServer,
)
from facelab.protocol import Protocol

__all__ = ["Conversations", "conversation_routes"]

FIRST_MESSAGE_S = 10.0  # a socket that does not say who it is within this long is closed


@dataclass
class Conversations:
    """The live conversations of one study's participants: a hub each, opened when their
    conversation screen first asks for it (and kept while the server runs, so a page that
    reloads joins the same one)."""

    protocol_path: Path
    folder: Path  # turns go to <folder>/<participant>/turn-NNN
    talker: str | Path = "mic"  # "mic": the talker's page; a WAV: the server talks
    playout_ms: float = 120.0
    vendor: Path | None = None
    hubs: dict[str, LiveHub] = field(default_factory=dict)
    locks: dict[str, asyncio.Lock] = field(default_factory=dict)

    def config(self, protocol: Protocol, participant: str) -> LiveConfig:
        conv = protocol.presentation.conversation
        if conv is None:
            raise SessionError(f"{self.protocol_path}: the protocol has no "
                               "presentation.conversation")  # fmt: skip
        display = "webxr" if protocol.presentation.display == "webxr" else "live3d"
        return LiveConfig(protocol=protocol, protocol_path=self.protocol_path,
                          condition=conv.condition, session=self.folder / participant,
                          talker=self.talker, display=display, playout_ms=self.playout_ms,
                          vendor=self.vendor)  # fmt: skip

    def check(self, protocol: Protocol) -> None:
        """Open the conversation once (SessionError naming what cannot run live): a
        condition whose method cannot run on streaming audio is refused before anyone
        joins."""
        LiveHub.open(self.config(protocol, "check"))

    async def hub(self, server: StudyServer, participant: Any) -> LiveHub:
        pid = participant.participant
        lock = self.locks.setdefault(pid, asyncio.Lock())
        async with lock:
            if pid not in self.hubs:
                protocol = server.study_of(participant).protocol
                config = self.config(protocol, pid)
                self.hubs[pid] = await asyncio.to_thread(LiveHub.open, config)
            return self.hubs[pid]

    def viewer_json(self, hub: LiveHub) -> dict[str, Any]:
        out = hub.live_json()
        out["scene"]["avatar"] = "/conversation/avatar/" + hub.scene["name"]
        out["turns"] = len(hub.turns)
        return out

    def add_routes(self, app: FastAPI, server: StudyServer) -> None:
        """The routes of the module docstring, on ``app`` over ``server``."""
        conversations = self

        async def participant_of(token: Any) -> Any:
            return await asyncio.to_thread(server.participant, token if isinstance(token, str)
                                           else None)  # fmt: skip

        async def open_hub(token: Any) -> LiveHub:
            p = await participant_of(token)
            try:
                return await conversations.hub(server, p)
            except FacelabError as exc:
                raise RefusedError(503, f"the conversation cannot start: {exc}") from None

        @app.get("/api/conversation")
        async def conversation(request: Request) -> dict[str, Any]:
            hub = await open_hub(request.headers.get(TOKEN_HEADER))
            return conversations.viewer_json(hub)

        @app.get("/conversation/avatar/{name}")
        def avatar(name: str) -> Response:
            for hub in list(conversations.hubs.values()):
                if hub.scene["name"] == name:
                    return Response(hub.scene["glb"], media_type="model/gltf-binary")
            raise RefusedError(404, "not found")

        @app.get("/talk")
        def talk_page() -> HTMLResponse:
            return HTMLResponse(
                "<!doctype html><html><head><meta charset='utf-8'>"
                "<title>facelab: talker</title><link rel='stylesheet' "
                "href='/static/facelab.css'>"
                f"<script type='importmap'>{IMPORT_MAP}</script></head>"
                "<body data-role='talk' data-online='1'><main id='facelab-live'></main>"
                "<script type='module' src='/static/dialogue.js'></script></body></html>",
                headers={"cache-control": "no-store"},
            )

        async def talker_hub(request_or_ws: Any, secret: Any, participant: Any) -> LiveHub:
            address = request_or_ws.client.host if request_or_ws.client else "?"
            await asyncio.to_thread(server.check_admin, secret if isinstance(secret, str)
                                    else None, address=address)  # fmt: skip
            if not isinstance(participant, str) or len(participant) > 32:
                raise RefusedError(422, "participant: expected a participant id, e.g. P0001")
            p = await asyncio.to_thread(server.participant_by_id, participant)
            try:
                return await conversations.hub(server, p)
            except FacelabError as exc:
                raise RefusedError(503, f"the conversation cannot start: {exc}") from None

        @app.post("/api/conversation/end")
        async def end(request: Request) -> dict[str, Any]:
            try:
                body = await request.json()
            except ValueError:
                body = None
            who = body.get("participant") if isinstance(body, dict) else None
            hub = await talker_hub(request, request.headers.get(ADMIN_HEADER), who)
            await hub.broadcast(json.dumps({"conversation_end": 1}))
            return {"ended": True, "viewers": len(hub.viewers)}

        @app.get("/api/conversation/status")
        async def status(request: Request, participant: str = "") -> dict[str, Any]:
            hub = await talker_hub(request, request.headers.get(ADMIN_HEADER), participant)
            return {"participant": participant, "viewers": len(hub.viewers),
                    "turns": len(hub.turns), "busy": hub.busy,
                    "problems": list(hub.problems)}  # fmt: skip

        async def first_message(ws: WebSocket) -> dict[str, Any] | None:
            """The socket's first message as a JSON object, None (and closed) when it is
            not one, comes too late, or the page is of another origin."""
            origin, host = ws.headers.get("origin"), ws.headers.get("host")
            await ws.accept()
            if origin is not None and origin.split("://", 1)[-1] != host:
                await ws.close(code=1008)
                return None
            try:
                msg = await asyncio.wait_for(ws.receive_text(), FIRST_MESSAGE_S)
                hello = json.loads(msg)
            except Exception:  # too late, binary, closed or not JSON
                await ws.close(code=1008)
                return None
            return hello if isinstance(hello, dict) else None

        async def refuse(ws: WebSocket, why: str) -> None:
            try:
                await ws.send_text(json.dumps({"error": why}))
                await ws.close(code=1008)
            except Exception:  # gone already
                pass

        @app.websocket("/ws/conversation/view")
        async def view(ws: WebSocket) -> None:
            hello = await first_message(ws)
            if hello is None:
                return
            try:
                hub = await open_hub(hello.get("token"))
            except RefusedError as exc:
                await refuse(ws, exc.message)
                return
            await view_socket(hub, ws)

        @app.websocket("/ws/conversation/talk")
        async def talk(ws: WebSocket) -> None:
            hello = await first_message(ws)
            if hello is None:
                return
            try:
                hub = await talker_hub(ws, hello.get("admin"), hello.get("participant"))
            except RefusedError as exc:
                await refuse(ws, exc.message)
                return
            await ws.send_text(json.dumps({"joined": hello.get("participant"),
                                           "viewers": len(hub.viewers)}))  # fmt: skip
            await talk_socket(hub, ws)


def conversation_routes(
    protocol: Protocol,
    *,
    protocol_path: Path,
    folder: Path,
    talker: str | Path = "mic",
    playout_ms: float = 120.0,
) -> Callable[[FastAPI, StudyServer], None]:
    """The live conversation's routes for ``facelab serve`` (``prepare_server(routes=...)``),
    checked first: SessionError when the conversation's condition cannot run live or the
    talker's file cannot be read."""
    from facelab.experiment.online.serve import vendor_dir

    conversations = Conversations(protocol_path=protocol_path, folder=folder, talker=talker,
                                  playout_ms=playout_ms, vendor=vendor_dir())  # fmt: skip
    conversations.check(protocol)
    return conversations.add_routes
