"""Wiring for ``facelab serve``: the protocol and its checked clips, the database, jsPsych
from npm, the server on uvicorn (in the foreground, or in a thread while simulated
participants run)."""

from __future__ import annotations

import secrets
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from facelab.errors import SessionError
from facelab.experiment.online.app import create_app
from facelab.experiment.online.db import default_url, open_engine, store_protocol
from facelab.experiment.online.live import live_scene
from facelab.experiment.online.server import (
    THREE_FILES,
    VENDOR_FILES,
    WEB,
    ServeConfig,
    StudyServer,
)
from facelab.experiment.online.study import checked_study
from facelab.protocol import Protocol, protocol_hash

__all__ = ["BackgroundServer", "free_port", "prepare_server", "vendor_dir"]


def vendor_dir() -> Path:
    """jsPsych and its plugins, installed by ``npm ci`` from the pinned lockfile."""
    base = WEB / "node_modules"
    wanted = [*VENDOR_FILES.values(), *(f"three/{rel}" for rel in THREE_FILES)]
    missing = [rel for rel in wanted if not (base / rel).is_file()]
    if missing:
        raise SessionError(
            f"jsPsych is not installed in {base} (missing {missing[0]}); run "
            f"`npm ci --prefix {WEB}` (scripts/setup.sh does it)"
        )
    return base


def prepare_server(
    protocol: Protocol,
    *,
    protocol_path: Path,
    clips_dir: Path,
    db_url: str | None,
    results: Path,
    completion_url: str | None = None,
    completion_code: str | None = None,
    consent: str | None = None,
    admin_secret: str | None = None,
    routes: tuple[Any, ...] = (),
) -> tuple[StudyServer, str | None]:
    """The server for ``protocol``; returns it and a newly made experimenter secret (None
    when ``admin_secret`` was given). Every clip is checked first (present, unchanged, from
    the protocol as it is now), as before a lab session. ``routes`` add routes of their own
    to the app (``add(app, server)``); a protocol with a live conversation needs its routes
    (:func:`facelab.experiment.live_dialogue.conversation.conversation_routes`)."""
    if protocol.presentation.conversation is not None and not routes:
        raise SessionError(
            f"{protocol_path}: presentation.conversation: this server has no live "
            "conversation (serve the study with facelab serve, which adds it)"
        )
    base = protocol_path.parent
    study = checked_study(
        protocol, protocol_sha256=protocol_hash(protocol_path), clips_dir=clips_dir, base_dir=base
    )
    clips = study.clips
    live = None
    if protocol.presentation.display != "video":
        live = live_scene(protocol, base_dir=base, clips=clips)
    config = ServeConfig(
        study=study,
        clip_paths={ref.sha256 + ".mp4": ref.path for ref in clips.values()},
        vendor=vendor_dir(),
        live=live,
        protocol_dir=base,
        clips_dir=clips_dir,
        served_dir=Path(results) / protocol.study.id / "served",
        completion_url=completion_url,
        completion_code=completion_code,
        consent=consent,
        routes=tuple(routes),
    )
    engine = open_engine(db_url or default_url(results, protocol.study.id))
    store_protocol(engine, protocol_path=protocol_path, study=protocol.study.id)
    server = StudyServer(engine, config)
    made = None
    if admin_secret is None:
        made = admin_secret = secrets.token_urlsafe(24)
    server.set_admin_secret(admin_secret)
    return server, made


def free_port(host: str = "127.0.0.1") -> int:
    """A port nobody listens on now (for servers started by tests and benchmarks)."""
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def proxy_options(forwarded_allow_ips: str | None) -> dict[str, Any]:
    """uvicorn's options for ``--forwarded-allow-ips``: a client's address is taken from
    ``X-Forwarded-For`` only on connections from those proxies (comma-separated addresses);
    without it the header is ignored, whoever sends it - a client cannot choose the address
    the join limit counts."""
    if not forwarded_allow_ips:
        return {"proxy_headers": False}
    return {"proxy_headers": True, "forwarded_allow_ips": forwarded_allow_ips}


@dataclass
class BackgroundServer:
    """uvicorn serving ``server`` in a thread (for simulated participants and tests); or
    another ASGI ``app`` (the live-dialogue server) when ``server`` is None."""

    server: StudyServer | None
    host: str = "127.0.0.1"
    port: int = 0
    forwarded_allow_ips: str | None = None
    app: Any = None

    def __enter__(self) -> BackgroundServer:
        import uvicorn

        if self.port == 0:
            self.port = free_port(self.host)
        config = uvicorn.Config(
            self.app if self.server is None else create_app(self.server), host=self.host,
            port=self.port, log_level="warning", **proxy_options(self.forwarded_allow_ips),
        )  # fmt: skip
        self._uv = uvicorn.Server(config)
        self._thread = threading.Thread(target=self._uv.run, daemon=True)
        self._thread.start()
        deadline = time.monotonic() + 20
        while not self._uv.started:
            if time.monotonic() > deadline or not self._thread.is_alive():
                raise SessionError(f"the server did not start on {self.host}:{self.port}")
            time.sleep(0.05)
        return self

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def __exit__(self, *exc: Any) -> None:
        self._uv.should_exit = True
        self._thread.join(timeout=10)
