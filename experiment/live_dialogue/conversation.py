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
                                 (a page that joins later is told at once)
``GET /api/conversation/status`` (experimenter secret) ``?participant=ID``: pages in it,
                                 turns, seconds left (409 before the participant reaches it)
===============================  ==========================================================

The conversation's clock runs on the server from the moment the participant's page first
joins: a page that reloads rejoins with the time left and the turns recorded so far. A room
is let go once the conversation's answer is stored and no page or turn is in it.

The sockets refuse a page of another origin (the browser's ``Origin`` header), an unknown
token or a wrong secret; the token travels in the socket's first message, never in its URL.
"""

from __future__ import annotations

import asyncio
import json
import time
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

__all__ = ["Conversations", "Room", "conversation_routes"]

FIRST_MESSAGE_S = 10.0  # a socket that does not say who it is within this long is closed
FIRST_MESSAGE_MAX = 4096  # characters of a socket's first message (a token, a secret, an id)
MAX_VIEWERS = 3  # pages of one participant in their conversation at once (a reload: two)


@dataclass
class Room:
    """One participant's conversation: its hub, when their page first joined (the
    conversation's clock runs from then, across reloads) and whether the talker ended it."""

    hub: LiveHub
    seconds: float
    started: float | None = None  # time.monotonic() at the first viewer's join
    ended_by_talker: bool = False

    def remaining_s(self) -> float:
        if self.started is None:
            return self.seconds
        return max(0.0, self.seconds - (time.monotonic() - self.started))

    def over(self) -> bool:
        return self.ended_by_talker or (self.started is not None and self.remaining_s() <= 0)


@dataclass
class Conversations:
    """The live conversations of one study's participants: a room each, opened when their
    conversation screen asks for it, kept while their page may come back to it (a reload
    rejoins it, its clock running on), and let go once its answer is stored and no page is
    in it."""

    protocol_path: Path
    folder: Path  # turns go to <folder>/<participant>/turn-NNN
    talker: str | Path = "mic"  # "mic": the talker's page; a WAV: the server talks
    playout_ms: float = 120.0
    vendor: Path | None = None
    rooms: dict[str, Room] = field(default_factory=dict)
    locks: dict[str, asyncio.Lock] = field(default_factory=dict)

    def config(
        self, protocol: Protocol, participant: str, *, owner: dict[str, Any] | None = None
    ) -> LiveConfig:
        conv = protocol.presentation.conversation
        if conv is None:
            raise SessionError(f"{self.protocol_path}: the protocol has no "
                               "presentation.conversation")  # fmt: skip
        display = "webxr" if protocol.presentation.display == "webxr" else "live3d"
        return LiveConfig(protocol=protocol, protocol_path=self.protocol_path,
                          condition=conv.condition, session=self.folder / participant,
                          talker=self.talker, display=display, playout_ms=self.playout_ms,
                          vendor=self.vendor, owner=owner)  # fmt: skip

    def check(self, protocol: Protocol) -> None:
        """Open the conversation once (SessionError naming what cannot run live): a
        condition whose method cannot run on streaming audio is refused before anyone
        joins."""
        LiveHub.open(self.config(protocol, "check"))

    async def room(self, server: StudyServer, participant: Any) -> Room:
        """The participant's room, opened now if it is not open (RefusedError when their
        conversation is answered already, or cannot start)."""
        pid = participant.participant
        lock = self.locks.setdefault(pid, asyncio.Lock())
        async with lock:
            if pid not in self.rooms:
                answered = await asyncio.to_thread(server.answered, participant)
                if (0, "conversation") in answered:
                    raise RefusedError(409, "this participant's conversation is over")
                protocol = server.study_of(participant).protocol
                owner = {"participant": pid, "session": participant.session,
                         "protocol_sha256": participant.protocol_sha256}  # fmt: skip
                config = self.config(protocol, pid, owner=owner)
                try:
                    hub = await asyncio.to_thread(LiveHub.open, config)
                except FacelabError as exc:
                    raise RefusedError(503, f"the conversation cannot start: {exc}") from None
                except Exception:  # an avatar or a talker's file gone bad since the start
                    raise RefusedError(503, "the conversation cannot start: its avatar or "
                                       "talker could not be loaded (see the server's "
                                       "protocol check: facelab validate)") from None  # fmt: skip
                seconds = protocol.presentation.conversation.minutes * 60.0  # type: ignore[union-attr]
                self.rooms[pid] = Room(hub=hub, seconds=seconds)
            return self.rooms[pid]

    async def release(self, server: StudyServer, participant: Any) -> None:
        """Let a room go once its conversation is answered (its end stored: a page that
        comes back before that must find it, ended or with its time left) and no page or
        turn is in it."""
        pid = participant.participant
        room = self.rooms.get(pid)
        if room is None or room.hub.viewers or room.hub.busy:
            return
        answered = await asyncio.to_thread(server.answered, participant)
        still_empty = self.rooms.get(pid) is room and not room.hub.viewers and not room.hub.busy
        if (0, "conversation") in answered and still_empty:
            del self.rooms[pid]

    def viewer_json(self, room: Room) -> dict[str, Any]:
        hub = room.hub
        out = hub.live_json()
        out["scene"]["avatar"] = "/conversation/avatar/" + hub.scene["name"]
        out["turns"] = len(hub.turns)  # recorded before this page joined (a reload)
        out["remaining_s"] = round(room.remaining_s(), 3)
        out["ended"] = room.ended_by_talker
        return out

    def add_routes(self, app: FastAPI, server: StudyServer) -> None:
        """The routes of the module docstring, on ``app`` over ``server``."""
        conversations = self

        async def participant_room(token: Any) -> tuple[Any, Room]:
            p = await asyncio.to_thread(server.participant, token if isinstance(token, str)
                                        else None)  # fmt: skip
            return p, await conversations.room(server, p)

        @app.get("/api/conversation")
        async def conversation(request: Request) -> dict[str, Any]:
            _, room = await participant_room(request.headers.get(TOKEN_HEADER))
            return conversations.viewer_json(room)

        @app.get("/conversation/avatar/{name}")
        def avatar(name: str) -> Response:
            for room in list(conversations.rooms.values()):
                if room.hub.scene["name"] == name:
                    return Response(room.hub.scene["glb"], media_type="model/gltf-binary")
            raise RefusedError(404, "not found")

        @app.get("/talk")
        def talk_page() -> HTMLResponse:
            lang = server.study.protocol.presentation.language
            return HTMLResponse(
                f"<!doctype html><html lang='{lang}'><head><meta charset='utf-8'>"
                "<title>facelab: talker</title><link rel='stylesheet' "
                "href='/static/facelab.css'>"
                f"<script type='importmap'>{IMPORT_MAP}</script></head>"
                "<body data-role='talk' data-online='1'><main id='facelab-live'></main>"
                "<script type='module' src='/static/dialogue.js'></script></body></html>",
                headers={"cache-control": "no-store"},
            )

        async def talker_room(request_or_ws: Any, secret: Any, participant: Any) -> Room:
            """The open room of ``participant``, for the experimenter (their secret)."""
            address = request_or_ws.client.host if request_or_ws.client else "?"
            await asyncio.to_thread(server.check_admin, secret if isinstance(secret, str)
                                    else None, address=address)  # fmt: skip
            if not isinstance(participant, str) or len(participant) > 32:
                raise RefusedError(422, "participant: expected a participant id, e.g. P0001")
            await asyncio.to_thread(server.participant_by_id, participant)  # 404 if none
            room = conversations.rooms.get(participant)
            if room is None:
                raise RefusedError(409, f"{participant} is not in their conversation (their "
                                   "page opens it when they reach it)")  # fmt: skip
            return room

        @app.post("/api/conversation/end")
        async def end(request: Request) -> dict[str, Any]:
            try:
                body = await request.json()
            except ValueError:
                body = None
            who = body.get("participant") if isinstance(body, dict) else None
            room = await talker_room(request, request.headers.get(ADMIN_HEADER), who)
            room.ended_by_talker = True  # a page joining later is told at once
            await room.hub.broadcast(json.dumps({"conversation_end": 1}))
            return {"ended": True, "viewers": len(room.hub.viewers)}

        @app.get("/api/conversation/status")
        async def status(request: Request, participant: str = "") -> dict[str, Any]:
            room = await talker_room(request, request.headers.get(ADMIN_HEADER), participant)
            hub = room.hub
            return {"participant": participant, "viewers": len(hub.viewers),
                    "turns": len(hub.turns), "busy": hub.busy,
                    "remaining_s": round(room.remaining_s(), 1),
                    "ended": room.ended_by_talker,
                    "problems": list(hub.problems)}  # fmt: skip

        async def first_message(ws: WebSocket) -> dict[str, Any] | None:
            """The socket's first message as a JSON object; None (the socket closed) when it
            is not one, comes too late, is too long, or the page is of another origin."""
            origin, host = ws.headers.get("origin"), ws.headers.get("host")
            await ws.accept()
            hello = None
            if origin is None or origin.split("://", 1)[-1] == host:
                try:
                    msg = await asyncio.wait_for(ws.receive_text(), FIRST_MESSAGE_S)
                    if len(msg) <= FIRST_MESSAGE_MAX:
                        hello = json.loads(msg)
                except Exception:  # too late, binary, closed or not JSON
                    hello = None
            if isinstance(hello, dict):
                return hello
            await refuse(ws, "expected a first message saying who this is, from this site")
            return None

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
                p, room = await participant_room(hello.get("token"))
            except RefusedError as exc:
                await refuse(ws, exc.message)
                return
            if len(room.hub.viewers) >= MAX_VIEWERS:
                await refuse(ws, f"this conversation has {MAX_VIEWERS} pages open already")
                return
            if room.started is None:
                room.started = time.monotonic()  # the conversation's clock starts
            if room.ended_by_talker:
                await ws.send_text(json.dumps({"conversation_end": 1}))
            try:
                await view_socket(room.hub, ws)
            finally:
                await conversations.release(server, p)

        @app.websocket("/ws/conversation/talk")
        async def talk(ws: WebSocket) -> None:
            hello = await first_message(ws)
            if hello is None:
                return
            try:
                room = await talker_room(ws, hello.get("admin"), hello.get("participant"))
            except RefusedError as exc:
                await refuse(ws, exc.message)
                return
            if room.over():
                await refuse(ws, "this participant's conversation is over")
                return
            await ws.send_text(json.dumps({"joined": hello.get("participant"),
                                           "viewers": len(room.hub.viewers)}))  # fmt: skip
            await talk_socket(room.hub, ws)


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
