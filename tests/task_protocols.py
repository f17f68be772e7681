"""A shipped task protocol cut down for tests (two vowels, edited by regex) and rendered
small - shared by the lab-window and the online-session tests."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from facelab.resources import protocol_path
from tests.shared_renders import rendered_clips


def short_task_protocol(
    name: str, root: Path, edits: dict[str, str], *, files: dict[str, bytes] | None = None,
    extra: tuple[str, ...] = (),
) -> Path:
    """Write ``root/<name>.yaml`` (the shipped protocol with a two-vowel stimulus and
    ``edits`` applied, ``{regex: replacement}``) and render its clips into ``root/clips``
    at 320x180, 15 fps; ``files`` (name -> bytes, e.g. an avatar the edits name) are written
    beside it, ``extra`` are more render options."""
    text = protocol_path(name).read_text(encoding="utf-8")
    text = text.replace(
        "text: あ。い。う。え。お。, tts: {speed: 0.8}, expected_vowels: aiueo",
        "text: あ。い。, expected_vowels: ai",
    )
    # files the protocol names beside itself (impression models) stay where they ship
    text = re.sub(
        r"model: ([\w.-]+\.json)",
        lambda m: f"model: {protocol_path(name).parent / m.group(1)}",
        text,
    )
    for old, new in edits.items():
        text = re.sub(old, new, text)
    for file_name, data in (files or {}).items():
        (root / file_name).write_bytes(data)
    rendered_clips(None, text=text, into=root, name=f"{name}.yaml", size="320x180", fps="15",
                   files=files, extra=extra)  # fmt: skip
    return root / f"{name}.yaml"


#: horii_impression_side cut to two side-by-side trials (comparison left once, right once)
SIDE_BY_SIDE = (
    "horii_impression_side",
    {
        r"sets: 2": "sets: 1",
        r"presentations_per_condition: 4": "presentations_per_condition: 2",
        r"conditions: \[q025, q05, q075, q1, q15\]": "conditions: [q15]",
        r"silence_s: 2.7": "silence_s: 1.2",
        r"  practice: .*\n": "",
    },
)


def one_online_session(path: Path, root: Path) -> tuple[Any, list[dict[str, Any]]]:
    """Serve the protocol at ``path`` (clips rendered into ``root/clips``, an SQLite database
    in ``root``), run one simulated participant through it in headless Chromium (screenshots
    in ``root/shots``) and return (the server, the stored response rows)."""
    from sqlalchemy import select
    from sqlalchemy.orm import Session

    from facelab.experiment.online.browser import SimulatedBrowser
    from facelab.experiment.online.db import Response
    from facelab.experiment.online.serve import BackgroundServer, prepare_server
    from facelab.protocol import load_protocol

    server, _ = prepare_server(
        load_protocol(path), protocol_path=path, clips_dir=root / "clips",
        db_url=f"sqlite:///{root / 'db.sqlite'}", results=root, admin_secret="s" * 20,
    )  # fmt: skip
    with BackgroundServer(server) as bg:
        assert SimulatedBrowser(server, bg.url, 1, screenshots=root / "shots").run() == "complete"
    with Session(server.engine) as db:
        rows = [r.row for r in db.scalars(select(Response))]
    return server, rows
