"""A protocol's conversation phase (``presentation.conversation``) in the lab: ``facelab run``
shows the partner's live avatar in the session's own window, for the conversation's minutes.

The talker is the ``/talk`` page of a live server this starts for the conversation (a
microphone page on this or another machine of the lab network) or a file the server streams
(``--conversation-input``, for demonstrations and tests). The session's window is the viewer
(:class:`~facelab.experiment.live_dialogue.window_view.WindowViewer`): the partner's voice on
the lab machine's speakers, the face drawn by the offline renderer. Each turn is recorded as
online, in ``results/<study>/conversations/<participant>/turn-NNN`` with the participant,
session and protocol SHA-256 in its turn.json. The runner gets this as a callable
(:attr:`RunOptions.conversation`), so the session layer does not import the live one.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from facelab.errors import SessionError
from facelab.experiment.live_dialogue.app import LiveConfig, LiveHub, create_live_app
from facelab.experiment.live_dialogue.window_view import WindowViewer
from facelab.experiment.online.serve import BackgroundServer
from facelab.experiment.timeline import ConversationAnswer, ConversationScreen
from facelab.protocol import Protocol
from facelab.sessionlog import utc_now

__all__ = ["LabConversation"]

TURN_END_WAIT_S = 10.0


@dataclass
class LabConversation:
    """Hosts the conversation of a lab session (see the module docstring). Called by the
    window with the screen; returns how it ended."""

    protocol: Protocol
    protocol_path: Path
    results: Path
    talker: str | Path = "mic"
    playout_ms: float = 120.0
    host: str = "127.0.0.1"
    port: int = 8010

    def check(self, *, conditions: list[str]) -> None:
        """Before the session starts: each conversation condition runs live on the avatar,
        the talker's file reads, and the port is free (SessionError naming what is not)."""
        import socket

        for condition in conditions:
            LiveHub.open(LiveConfig(protocol=self.protocol, protocol_path=self.protocol_path,
                                    condition=condition, talker=self.talker,
                                    session=self.results))  # fmt: skip
        with socket.socket() as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
            try:
                probe.bind((self.host, self.port))
            except OSError:
                raise SessionError(f"--conversation-port {self.port}: {self.host}:{self.port} "
                                   "is taken or not this machine's; give another") from None

    def __call__(
        self, window: Any, screen: ConversationScreen, *, participant: str, session: int,
        protocol_sha256: str,
    ) -> ConversationAnswer:  # fmt: skip
        config = LiveConfig(
            protocol=self.protocol, protocol_path=self.protocol_path,
            condition=screen.condition, talker=self.talker, display="window",
            session=self.results / self.protocol.study.id / "conversations" / participant,
            playout_ms=self.playout_ms,
            owner={"participant": participant, "session": session,
                   "protocol_sha256": protocol_sha256},
        )  # fmt: skip
        hub = LiveHub.open(config)
        with BackgroundServer(None, host=self.host, port=self.port, app=create_live_app(hub)):
            loop = hub.running_loop()
            url = f"http://{self.host}:{self.port}/talk"
            who = url if self.talker == "mic" else f"{self.talker} (streamed once)"
            print(f"conversation under {screen.condition!r} for {screen.seconds:g} s; "
                  f"the talker: {who}", flush=True)  # fmt: skip
            window.text_stim(screen.text).draw()
            window.win.flip()  # while the avatar's renderer starts (its clock not yet running)
            with WindowViewer(hub, loop=loop, window=window) as view:
                shown = view.run(seconds=screen.seconds, quit_raises=True, caption=screen.text)
            lasted = shown["seconds_shown"]
            window.win.flip()  # the partner gone while a turn still being spoken is saved
            end = time.monotonic() + TURN_END_WAIT_S  # a turn spoken when time ran out:
            while hub.busy and time.monotonic() < end:  # saved once the talker stops (or
                time.sleep(0.05)  # as far as it got, when the server closes its socket)
        return ConversationAnswer("time", len(hub.turns), round(lasted, 3), utc_now())
