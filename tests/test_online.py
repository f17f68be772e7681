"""Online sessions: the server's API (tokens, validation, idempotency, completion, privacy),
export to the lab files, and real headless Chromium participants - a full session, a tab
closed mid-trial, the server SIGKILLed and restarted - and a 200-client load test on SQLite
and PostgreSQL. Needs Debian's chromium, chromium-driver and postgresql (scripts/setup.sh)."""

from __future__ import annotations

import csv
import hashlib
import json
import os
import re
import shutil
import signal
import threading
import time
from pathlib import Path

import pandas as pd
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from facelab.experiment.cli import main
from facelab.experiment.online.app import create_app
from facelab.experiment.online.browser import SimulatedBrowser, chromium
from facelab.experiment.online.db import (
    Action,
    Event,
    Participant,
    PlaybackRecord,
    ProtocolFile,
    Response,
)
from facelab.experiment.online.export import export_sessions
from facelab.experiment.online.load import (
    load_test,
    postgres_cluster,
    start_server,
    wait_for_server,
)
from facelab.experiment.online.middleware import MAX_BODY_BYTES
from facelab.experiment.online.serve import BackgroundServer, free_port, prepare_server
from facelab.experiment.online.server import RefusedError
from facelab.protocol import load_protocol, protocol_hash
from facelab.sessionlog import SessionLog
from tests.protocol_edits import kato_short
from tests.shared_renders import rendered_clips
from tests.task_protocols import SIDE_BY_SIDE, short_task_protocol

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parents[1]
PLANNED = 18  # 9 trials x 2 VAS items in the short study


@pytest.fixture(scope="module")
def study(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The paper's design, one set per block, 1-2 s clips at 320x180, rendered once."""
    root = tmp_path_factory.mktemp("online")
    text = kato_short((ROOT / "protocols" / "kato2021.yaml").read_text(encoding="utf-8"))
    rendered_clips(tmp_path_factory, text=text, into=root, name="short.yaml", size="320x180",
                   fps="15")  # fmt: skip
    return root


def _server(study: Path, db: Path, **kw):
    protocol = load_protocol(study / "short.yaml")
    server, _ = prepare_server(
        protocol,
        protocol_path=study / "short.yaml",
        clips_dir=study / "clips",
        db_url=f"sqlite:///{db}",
        results=db.parent,
        admin_secret="experimenter-secret-123",
        **kw,
    )
    return server


def _answer(trial: int, item: str, rating: float, key: str) -> dict:
    return {
        "client_key": key,
        "trial_index": trial,
        "item": item,
        "rt_s": 1.5,
        "rating": rating,
        "timestamp": "2026-11-23T08:00:00.000Z",
        "clip_onset": 2.0,
        "clip_frames_dropped": 0,
    }


def _task_server(name: str, edits: dict[str, str], root: Path):
    """A shipped task protocol cut short, rendered small, and its server on a fresh SQLite."""
    path = short_task_protocol(name, root, edits)
    protocol = load_protocol(path)
    server, _ = prepare_server(
        protocol, protocol_path=path, clips_dir=root / "clips",
        db_url=f"sqlite:///{root / 'db.sqlite'}", results=root, admin_secret="s" * 20,
    )  # fmt: skip
    return protocol, server


def _rows(server, participant: str) -> list[dict]:
    with Session(server.engine) as db:
        p = db.scalars(select(Participant).where(Participant.participant == participant)).first()
        if p is None:
            return []
        return [r.row for r in db.scalars(select(Response).where(Response.participant_pk == p.pk))]


# --------------------------------------------------------------------------- the API


def test_tokens_origin_and_every_field_are_checked(study: Path, tmp_path: Path) -> None:
    server = _server(study, tmp_path / "db.sqlite")
    client = TestClient(create_app(server))
    _, token = server.join(recruitment=None, source=None)
    ok = {"X-Facelab-Token": token}
    assert client.get("/api/session").status_code == 401
    assert client.get("/api/session", headers={"X-Facelab-Token": "x" * 43}).status_code == 401
    r = client.get("/api/session", headers=ok)
    assert r.status_code == 200
    state = r.json()
    assert state["participant"] == "P0001" and state["planned"] == PLANNED
    clips = [s["clip"] for s in state["timeline"] if s["kind"] == "clip"]
    assert clips and all(re.fullmatch(r"[0-9a-f]{64}\.mp4", c) for c in clips)
    csp = r.headers["Content-Security-Policy"]
    assert "script-src 'self'" in csp and "frame-ancestors 'none'" in csp
    assert r.headers["X-Content-Type-Options"] == "nosniff"

    good = _answer(1, "naturalness", 40.0, "aaaaaaaaaaaa0001")
    bad = {**good, "rating": 140.0}
    r = client.post("/api/response", json=bad, headers=ok)
    assert r.status_code == 422 and "rating" in r.json()["error"]
    r = client.post("/api/response", json={**good, "extra": 1}, headers=ok)
    assert r.status_code == 422 and "extra" in r.json()["error"]
    r = client.post("/api/response", json={**good, "trial_index": 99}, headers=ok)
    assert r.status_code == 422 and "trial_index 99" in r.json()["error"]
    r = client.post("/api/response", json={**good, "rating": "40"}, headers=ok)
    assert r.status_code == 422  # strict: a string is not a number
    r = client.post("/api/response", json=good, headers={**ok, "Origin": "https://evil.example"})
    assert r.status_code == 403
    r = client.post("/api/response", json=good, headers={"X-Facelab-Token": "y" * 43})
    assert r.status_code == 401
    assert _rows(server, "P0001") == []  # nothing refused was stored
    r = client.get("/api/admin/progress", headers={"X-Facelab-Admin": "wrong"})
    assert r.status_code == 401
    r = client.get("/api/admin/progress", headers={"X-Facelab-Admin": "experimenter-secret-123"})
    assert r.status_code == 200 and r.json()["participants"][0]["participant"] == "P0001"


def test_rejoin_through_the_link_in_chromium_keeps_the_session_and_refuses_a_stranger(
    study: Path, tmp_path: Path
) -> None:
    """The real join page in headless Chromium: the participant's browser returns through
    the Prolific link and gets its own session (same token); another browser with the same
    PID is turned away while the session is live."""
    from selenium.webdriver.common.by import By

    server = _server(study, tmp_path / "db.sqlite")
    link = "/join?PROLIFIC_PID=60a1b2c3d4e5f60718293a4b"
    with BackgroundServer(server) as bg:
        owner, stranger = chromium(), chromium()
        try:
            tokens = []
            for _ in range(2):
                owner.get(bg.url + link)
                owner.find_element(By.CSS_SELECTOR, "[data-facelab=join]").click()
                deadline = time.monotonic() + 20
                while time.monotonic() < deadline and not (
                    "/run" in owner.current_url
                    and owner.execute_script("return localStorage.getItem('facelab.token')")
                ):
                    time.sleep(0.1)
                tokens.append(owner.execute_script("return localStorage.getItem('facelab.token')"))
            assert tokens[0] and tokens[0] == tokens[1]  # the same session, the same token
            stranger.get(bg.url + link)
            stranger.find_element(By.CSS_SELECTOR, "[data-facelab=join]").click()
            time.sleep(1.0)
            assert "#t=" not in stranger.current_url
            assert "別の画面やブラウザー" in stranger.find_element(By.TAG_NAME, "body").text
        finally:
            owner.quit()
            stranger.quit()
    assert [p["participant"] for p in server.progress()] == ["P0001"]


def test_answers_saved_under_a_rotated_token_are_sent_first_after_a_rejoin(
    study: Path, tmp_path: Path
) -> None:
    """A participant answered offline in browser A (the answer waits in A's outbox under
    token T1), then continued on another device after the idle time (T1 retired), then came
    back to A through the recruitment link: A's waiting answer is sent first, with T1, and
    stored under the participant; a leftover of another participant's session on the same
    computer is refused and held, never stored under this one."""
    from selenium.webdriver.common.by import By

    server = _server(study, tmp_path / "db.sqlite")
    server.config.rejoin_idle_s = 0.0  # "after the idle time", at once
    link = "/join?PROLIFIC_PID=70a1b2c3d4e5f60718293a4b"
    with BackgroundServer(server) as bg:
        a = chromium()
        try:
            a.get(bg.url + link)
            a.find_element(By.CSS_SELECTOR, "[data-facelab=join]").click()
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and not a.execute_script(
                "return localStorage.getItem('facelab.token')"
            ):
                time.sleep(0.1)
            t1 = a.execute_script("return localStorage.getItem('facelab.token')")
            (p,) = [q for q in server.progress() if q["participant"] == "P0001"]
            keys = sorted(server.study.planned("P0001"))
            other, other_token = server.join(recruitment=None, source=None)  # P0002
            offline = _answer(*keys[0], 12.34, "aaaaaaaaaaaa0001")
            leftover = _answer(*keys[1], 98.76, "aaaaaaaaaaaa0002")
            a.get("about:blank")  # the tab is closed with the answer unsent
            # another device continues the session after the idle time: T1 is retired
            server.join(recruitment="70a1b2c3d4e5f60718293a4b", source="prolific")
            a.get(bg.url + link)  # back in browser A through the link (its page creates nothing)
            a.execute_script(
                "localStorage.setItem('facelab.outbox.' + arguments[0], JSON.stringify("
                "[{url: '/api/response', body: arguments[1]}]));"
                "localStorage.setItem('facelab.outbox.' + arguments[2], JSON.stringify("
                "[{url: '/api/response', body: arguments[3]}]));",
                t1, offline, other_token, leftover,
            )  # fmt: skip
            a.refresh()  # the join page reads this browser's token again
            a.find_element(By.CSS_SELECTOR, "[data-facelab=join]").click()
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and not _rows(server, "P0001"):
                time.sleep(0.2)
            time.sleep(1.0)
            held = a.execute_script(
                "return Object.keys(localStorage).filter((k) => k.startsWith('facelab.held.'))"
                ".map((k) => JSON.parse(localStorage.getItem(k))).flat()"
            )
        finally:
            a.quit()
    rows = _rows(server, "P0001")
    assert [(r["trial_index"], r["item"], r["rating"]) for r in rows] == [(*keys[0], 12.34)]
    assert _rows(server, other.participant) == []  # the leftover is not stored anywhere
    assert [h["body"]["rating"] for h in held] == [98.76]  # held in the browser, with why
    assert "another session's token" in held[0]["why"]
    assert p["responses"] == 0


def test_served_files_tell_no_condition(study: Path, tmp_path: Path) -> None:
    """Clips are served as padded copies under their own hash: every condition of a
    stimulus has the same size, the practice clip is a copy of its own (same size, other
    bytes), the rendered files are not reachable by their hash, and a track's header does
    not name its clip (which names the condition)."""
    live = study / "live.yaml"
    text = (study / "short.yaml").read_text(encoding="utf-8")
    live.write_text(text.replace("presentation:\n", "presentation:\n  display: live3d\n", 1),
                    encoding="utf-8")  # fmt: skip
    protocol = load_protocol(live)
    server, _ = prepare_server(
        protocol, protocol_path=live, clips_dir=study / "clips",
        db_url=f"sqlite:///{tmp_path / 'db.sqlite'}", results=tmp_path, admin_secret="s" * 20,
    )  # fmt: skip
    client = TestClient(create_app(server))
    _, token = server.join(recruitment=None, source=None)
    state = client.get("/api/session", headers={"X-Facelab-Token": token}).json()
    rendered = {ref.sha256 for ref in server.study.clips.values()}
    sizes: dict[tuple[str, str], set[int]] = {}
    for key, copy in server.served.main.items():
        body = client.get(f"/clips/{copy.clip}").content
        assert hashlib.sha256(body).hexdigest() == copy.clip[:-4] not in rendered
        original = server.study.clips[key].path.read_bytes()
        assert body.startswith(original) and body[len(original) + 4 :][:4] == b"free"
        sizes.setdefault(key[:2], set()).add(len(body))
        track = client.get(f"/tracks/{copy.track}").content
        header = json.loads(track[12 : 12 + int.from_bytes(track[8:12], "little")])
        assert header["clip_id"] == "" and key[2] not in json.dumps(header)
    assert all(len(v) == 1 for v in sizes.values())  # one size per stimulus
    for ref in server.study.clips.values():  # the rendered files are not served
        assert client.get(f"/clips/{ref.sha256}.mp4").status_code == 404
    (key,) = server.served.practice
    practice, main = server.served.practice[key], server.served.main[key]
    assert practice.clip != main.clip and practice.track != main.track
    a, b = client.get(f"/clips/{practice.clip}").content, client.get(f"/clips/{main.clip}").content
    assert len(a) == len(b) and a != b
    shown = [s for s in state["timeline"] if s["kind"] == "clip"]
    assert next(s for s in shown if s["practice"])["clip"] == practice.clip
    assert practice.clip in state["clips"] and all(
        s["clip"] != practice.clip for s in shown if not s["practice"]
    )
    # a playback record names the copy shown; the rendered clip is what is stored
    record = {"client_key": "pppppppppppp0001", "trial_index": 1, "clip": shown[1]["clip"],
              "replay": False, "onset": 1.0, "frames_expected": 10, "dropped": 0,
              "flip_times": [], "frames_shown": [], "presented_frames": 10}  # fmt: skip
    r = client.post("/api/playback", json=record, headers={"X-Facelab-Token": token})
    assert r.status_code == 200, r.json()
    with Session(server.engine) as db:
        stored = db.scalars(select(PlaybackRecord)).one().record
    assert stored["clip"][:-4] in rendered and stored["served_as"] == shown[1]["clip"]


def test_limited_joins_get_a_page_in_the_study_language_and_clips_carry_no_dates(
    study: Path, tmp_path: Path
) -> None:
    server = _server(study, tmp_path / "db.sqlite")
    server.join_limiter.limit = 2
    client = TestClient(create_app(server))
    codes = [client.post("/join", follow_redirects=False).status_code for _ in range(3)]
    assert codes == [303, 303, 429]
    r = client.post("/join", follow_redirects=False)
    assert r.headers["content-type"].startswith("text/html") and "1分ほど待って" in r.text
    assert r.headers["Retry-After"] == "60" and "{" not in r.text  # a page, not raw JSON
    assert len(server.progress()) == 2  # the refused ones created nobody
    name = next(iter(server.config.clip_paths))
    clip = client.get(f"/clips/{name}")
    assert clip.status_code == 200 and clip.content[4:8] == b"ftyp"
    # a file date (or an ETag made from it) would order clips by rendering, i.e. by condition
    assert "last-modified" not in clip.headers and "etag" not in clip.headers


def test_join_limit_counts_forwarded_addresses_only_from_the_configured_proxy(
    study: Path, tmp_path: Path
) -> None:
    """uvicorn used to trust X-Forwarded-For from 127.0.0.1 always (a client behind the
    README's proxy chose its address; without a proxy everyone shared one limit)."""
    import httpx

    def joins(url: str, addresses: list[str]) -> list[int]:
        with httpx.Client(base_url=url, follow_redirects=False) as http:
            return [
                http.post("/join", headers={"X-Forwarded-For": a}).status_code for a in addresses
            ]

    behind = _server(study, tmp_path / "proxied.sqlite")
    with BackgroundServer(behind, forwarded_allow_ips="127.0.0.1") as bg:
        launch = joins(bg.url, [f"10.{i // 250}.{i % 250}.7" for i in range(300)])
        assert launch == [303] * 300  # a launch: 300 people, 300 addresses, nobody limited
        flood = joins(bg.url, ["198.51.100.9"] * 35)
        assert flood == [303] * 30 + [429] * 5  # one address still cannot flood
    assert len(behind.progress()) == 330

    direct = _server(study, tmp_path / "direct.sqlite")
    with BackgroundServer(direct) as bg:  # no proxy configured: the header is ignored
        spoofed = joins(bg.url, [f"203.0.113.{i}" for i in range(35)])
    assert spoofed == [303] * 30 + [429] * 5
    assert len(direct.progress()) == 30


def test_impossible_times_and_non_finite_numbers_are_422_not_500(
    study: Path, tmp_path: Path
) -> None:
    """Year 1 or 9999 timestamps were a 500 (OverflowError); NaN in an answer, a playback
    record or event data was stored on SQLite and a 500 on PostgreSQL."""
    server = _server(study, tmp_path / "db.sqlite")
    client = TestClient(create_app(server))
    p, token = server.join(recruitment=None, source=None)
    ok = {"X-Facelab-Token": token, "Content-Type": "application/json"}
    key = sorted(server.study.planned(p.participant))[0]
    for n, stamp in enumerate(["0001-01-01T00:00:00Z", "9999-12-31T23:59:59+14:00", "junk"]):
        r = client.post(
            "/api/response",
            headers=ok,
            json={**_answer(*key, 50.0, f"eeeeeeeeeeee000{n}"), "timestamp": stamp},
        )
        assert r.status_code == 422 and "between the years 2000 and 2200" in r.json()["error"]
    body = json.dumps(_answer(*key, 50.0, "eeeeeeeeeeee0009")).replace("50.0", "NaN")
    r = client.post("/api/response", content=body, headers=ok)
    assert r.status_code == 422 and "rating" in r.json()["error"]
    clip = next(c for c in p.clips.values()) + ".mp4"
    playback = {
        "client_key": "ffffffffffff0001", "trial_index": 1, "clip": clip, "replay": False,
        "onset": 1.0, "frames_expected": 3, "dropped": 0, "flip_times": [0.0, 0.033, 0.066],
        "frames_shown": [0, 1, 2], "presented_frames": 3, "media_time_end": 0.1,
    }  # fmt: skip
    r = client.post("/api/playback", headers=ok,
                    content=json.dumps(playback).replace("0.033", "Infinity"))  # fmt: skip
    assert r.status_code == 422
    r = client.post("/api/event", headers=ok, content='{"kind": "error", "detail": {"x": NaN}}')
    assert r.status_code == 422 and "finite" in r.json()["error"]
    assert _rows(server, p.participant) == []
    r = client.post("/api/playback", headers=ok, json=playback)
    assert r.status_code == 200  # the same record with finite numbers is stored


def test_oversized_bodies_are_refused_before_parsing(study: Path, tmp_path: Path) -> None:
    """A public server parsed any body whole (a 100 MB JSON event was read into memory
    before the 4000-character detail check); bodies over MAX_BODY_BYTES get 413, declared
    or chunked, and nothing is stored."""
    server = _server(study, tmp_path / "db.sqlite")
    client = TestClient(create_app(server))
    _, token = server.join(recruitment=None, source=None)
    ok = {"X-Facelab-Token": token, "Content-Type": "application/json"}
    huge = json.dumps({"kind": "error", "detail": {"x": "y" * (MAX_BODY_BYTES + 10)}}).encode()
    r = client.post("/api/event", content=huge, headers=ok)
    assert r.status_code == 413 and "larger than" in r.json()["error"]
    assert r.headers["X-Content-Type-Options"] == "nosniff"

    def chunks():
        for _ in range(5):
            yield b"x" * (MAX_BODY_BYTES // 4)

    r = client.post("/api/response", content=chunks(), headers=ok)
    assert r.status_code == 413
    for name in ("a" * 300, "..%2f..%2fpyproject.toml", ".hidden", "run.js%00"):
        assert client.get(f"/static/{name}").status_code == 404  # 300 chars: was an OSError
    assert client.get("/static/run.js").status_code == 200
    good = _answer(1, "naturalness", 40.0, "cccccccccccc0001")
    r = client.post("/api/response", content=json.dumps(good).encode(), headers=ok)
    assert r.status_code == 200, r.text  # a body within the limit still reaches the app
    assert [row["rating"] for row in _rows(server, "P0001")] == [40.0]


def test_replays_are_harmless_conflicts_refused_completion_waits(
    study: Path, tmp_path: Path
) -> None:
    server = _server(study, tmp_path / "db.sqlite", completion_code="C0DE42")
    client = TestClient(create_app(server))
    p, token = server.join(recruitment=None, source=None)
    ok = {"X-Facelab-Token": token}
    keys = sorted(server.study.planned(p.participant))
    first = _answer(*keys[0], 55.5, "bbbbbbbbbbbb0000")
    r = client.post("/api/response", json=first, headers=ok)
    assert r.json() == {"stored": True, "replay": False, "complete": False}
    r = client.post("/api/response", json=first, headers=ok)  # the same request again
    assert r.status_code == 200 and r.json()["replay"] is True
    # a new key for the answered trial: one refusal whatever the value (no oracle: guessing
    # values until one is "a replay" would read the stored answer)
    same = client.post("/api/response", json={**first, "client_key": "bbbbbbbbbbbb9999"},
                       headers=ok)  # fmt: skip
    r = client.post(
        "/api/response",
        json={**first, "client_key": "cccccccccccc0000", "rating": 10.0},
        headers=ok,
    )
    assert same.status_code == r.status_code == 409 and same.json() == r.json()
    assert "is answered already" in r.json()["error"]
    assert "55.5" not in r.json()["error"] and "10.0" not in r.json()["error"]
    # the stored key with another value is a conflict, not "stored"
    r = client.post("/api/response", json={**first, "rating": 12.0}, headers=ok)
    assert r.status_code == 409 and "stored with another answer" in r.json()["error"]
    assert [row["rating"] for row in _rows(server, p.participant)] == [55.5]
    assert client.get("/api/complete", headers=ok).status_code == 409
    for n, key in enumerate(keys[1:], start=1):
        r = client.post(
            "/api/response", json=_answer(*key, 50.0, f"dddddddddddd{n:04d}"), headers=ok
        )
        assert r.status_code == 200
    assert r.json()["complete"] is True
    done = client.get("/api/complete", headers=ok)
    assert done.status_code == 200 and done.json()["code"] == "C0DE42"
    rows = _rows(server, p.participant)
    assert len(rows) == PLANNED == len({(r["trial_index"], r["item"]) for r in rows})


def test_a_session_keeps_the_protocol_version_it_started_with(study: Path, tmp_path: Path) -> None:
    """A fix for new participants never strands current ones: the server keeps every version
    of the file it served; a session that started under an earlier one is served that one
    (its texts, its design) when its clips are still there, and refused with the reason when
    they are not."""
    folder = tmp_path / "study"
    shutil.copytree(study / "clips", folder / "clips")
    path = folder / "short.yaml"
    v1 = (study / "short.yaml").read_text(encoding="utf-8")
    path.write_text(v1, encoding="utf-8")
    first = _server(folder, tmp_path / "db.sqlite")
    p, token = first.join(recruitment=None, source=None)
    ok = {"X-Facelab-Token": token}
    keys = sorted(first.study.planned(p.participant))
    client = TestClient(create_app(first))
    for n, key in enumerate(keys[:2]):
        r = client.post("/api/response", json=_answer(*key, 40.0, f"vvvvvvvvvvvv{n:04d}"),
                        headers=ok)  # fmt: skip
        assert r.status_code == 200
    # the experimenter fixes a typo in the end text and restarts the server with the new file
    v2 = v1.replace("ご協力ありがとうございました", "ご協力、誠にありがとうございました", 1)
    assert v2 != v1
    path.write_text(v2, encoding="utf-8")
    second = _server(folder, tmp_path / "db.sqlite")
    assert second.study.protocol_sha256 != first.study.protocol_sha256
    client = TestClient(create_app(second))
    state = client.get("/api/session", headers=ok)
    assert state.status_code == 200 and state.json()["answered"] == 2
    for n, key in enumerate(keys[2:], start=2):
        r = client.post("/api/response", json=_answer(*key, 60.0, f"vvvvvvvvvvvv{n:04d}"),
                        headers=ok)  # fmt: skip
        assert r.status_code == 200, r.json()
    assert r.json()["complete"] is True
    assert client.get("/api/complete", headers=ok).status_code == 200
    newcomer, _ = second.join(recruitment=None, source=None)
    assert newcomer.protocol_sha256 == second.study.protocol_sha256
    progress = {row["participant"]: row for row in second.progress()}
    assert progress[p.participant]["protocol"] == f"earlier {first.study.protocol_sha256[:12]}"
    assert progress[newcomer.participant]["protocol"] == "current"
    # a version whose clips are gone (rendered over for another design) cannot be served
    other, other_token = second.join(recruitment=None, source=None)
    import sqlalchemy

    with Session(second.engine) as db:
        db.execute(
            sqlalchemy.update(Participant)
            .where(Participant.pk == other.pk)
            .values(protocol_sha256="f" * 64)
        )
        db.commit()
    second._by_token.drop(lambda q: False)
    r = client.get("/api/session", headers={"X-Facelab-Token": other_token})
    # the participant reads why in the study's language, without the server's internals;
    # the experimenter's progress page says what is wrong
    assert r.status_code == 409 and "実験の準備が変更された" in r.json()["error"]
    assert "protocol" not in r.json()["error"] and "/" not in r.json()["error"]
    progress = {row["participant"]: row for row in second.progress()}
    assert progress[other.participant]["protocol"].startswith("cannot be served: protocol ffff")


def test_join_assigns_ids_hashes_recruitment_ids_and_rejoin_resumes(
    study: Path, tmp_path: Path
) -> None:
    db = tmp_path / "db.sqlite"
    server = _server(study, db)
    client = TestClient(create_app(server))
    pid = "5f1e2d3c4b5a69788796a5b4"
    # looking at the link (a preview, a crawler) creates nobody and takes no slot
    for _ in range(3):
        page = client.get(f"/join?PROLIFIC_PID={pid}", follow_redirects=False)
        assert page.status_code == 200 and "実験を始める" in page.text
        assert f'action="/join?PROLIFIC_PID={pid}"' in page.text and 'method="post"' in page.text
    assert server.progress() == []
    r = client.post(f"/join?PROLIFIC_PID={pid}", follow_redirects=False)
    assert r.status_code == 303
    token = re.fullmatch(r"/run#t=([A-Za-z0-9_-]+)", r.headers["location"]).group(1)
    assert len(token) >= 43  # >= 256 bits, URL-safe base64
    r2 = client.post("/join", follow_redirects=False)
    token2 = r2.headers["location"].split("=", 1)[1]
    names = [client.get("/api/session", headers={"X-Facelab-Token": t}).json()["participant"]
             for t in (token, token2)]  # fmt: skip
    assert names == ["P0001", "P0002"]  # numbered by the server: Latin squares work
    # knowing the PID is not enough: the live session stays with its browser
    grab = client.post(f"/join?PROLIFIC_PID={pid}", follow_redirects=False)
    # worded and answered so that trying an id tells nothing about that person
    assert grab.status_code == 200 and "別の画面やブラウザー" in grab.text
    assert "location" not in grab.headers and "進行中" not in grab.text
    assert client.get("/api/session", headers={"X-Facelab-Token": token}).status_code == 200
    # the same browser (the join page sends the token it holds) gets the session back as it was
    back = client.post(f"/join?PROLIFIC_PID={pid}", data={"previous_token": token},
                       follow_redirects=False)  # fmt: skip
    assert back.status_code == 303 and back.headers["location"] == f"/run#t={token}"
    # a new browser after the session has been idle long enough gets it with a fresh token
    server.config.rejoin_idle_s = 0.0
    r3 = client.post(f"/join?PROLIFIC_PID={pid}", follow_redirects=False)
    assert r3.status_code == 303
    token3 = r3.headers["location"].split("=", 1)[1]
    time.sleep(5.1)  # the token cache's lifetime
    assert (
        client.get("/api/session", headers={"X-Facelab-Token": token3}).json()["participant"]
        == "P0001"
    )
    assert client.get("/api/session", headers={"X-Facelab-Token": token}).status_code == 401
    server.engine.dispose()
    raw = b"".join(p.read_bytes() for p in tmp_path.glob("db.sqlite*"))
    assert pid.encode() not in raw and token.encode() not in raw  # neither stored in clear


def test_export_writes_the_lab_files_and_only_adds(study: Path, tmp_path: Path) -> None:
    server = _server(study, tmp_path / "db.sqlite")
    client = TestClient(create_app(server))
    p, token = server.join(recruitment=None, source="prolific")
    keys = sorted(server.study.planned(p.participant))
    for n, key in enumerate(keys[:5]):
        body = _answer(*key, 20.0 + n, f"eeeeeeeeeeee{n:04d}")
        client.post("/api/response", json=body, headers={"X-Facelab-Token": token})
    out = tmp_path / "results"
    (tsv,) = export_sessions(server.engine, results=out)
    log = SessionLog.resume(out, study="kato2021", participant=p.participant, session=1)
    assert len(log.rows) == 5 and log.provenance()["mode"] == "online"
    for n, key in enumerate(keys[5:], start=5):
        body = _answer(*key, 20.0 + n, f"eeeeeeeeeeee{n:04d}")
        client.post("/api/response", json=body, headers={"X-Facelab-Token": token})
    export_sessions(server.engine, results=out)
    export_sessions(server.engine, results=out)  # again: nothing new, nothing doubled
    rows = list(csv.DictReader(tsv.read_text(encoding="utf-8").splitlines(), delimiter="\t"))
    assert len(rows) == PLANNED
    assert [float(r["rating"]) for r in rows] == [20.0 + n for n in range(PLANNED)]
    assert (
        json.loads(tsv.with_name(tsv.name.replace("_beh.tsv", "_session.json")).read_text())[
            "recruitment_source"
        ]
        == "prolific"
    )


# --------------------------------------------------------------------------- real browsers


def _check_session(server, participant: str) -> None:
    """Every planned response once, and each equal to what the participant clicked."""
    rows = _rows(server, participant)
    assert len(rows) == PLANNED == len({(r["trial_index"], r["item"]) for r in rows})
    with Session(server.engine) as db:
        p = db.scalars(select(Participant).where(Participant.participant == participant)).one()
        actions = [
            a.record for a in db.scalars(select(Action).where(Action.participant_pk == p.pk))
        ]
        assert p.completed is not None
    clicked = {(a["trial_index"], a["item"]): a["value"] for a in actions}
    for r in rows:  # the click lands on a pixel: within a fraction of a scale point
        assert abs(r["rating"] - clicked[(r["trial_index"], r["item"])]) < 0.5, r


def test_simulated_participants_in_chromium_then_export_and_analyze(
    study: Path, tmp_path: Path
) -> None:
    db = tmp_path / "online.sqlite"
    shots = tmp_path / "shots"
    args = ["serve", str(study / "short.yaml"), "--clips", str(study / "clips"),
            "--db", f"sqlite:///{db}", "--results", str(tmp_path), "--port", "0",
            "--simulate-participants", "2", "--screenshots", str(shots)]  # fmt: skip
    assert main(args) == 0
    assert {p.name for p in shots.glob("*.png")} >= {
        "text-instructions.png",
        "clip.png",
        "vas.png",
        "complete.png",
    }
    server = _server(study, db)
    for pid in ("P0001", "P0002"):
        _check_session(server, pid)
    with Session(server.engine) as s:
        records = [r.record for r in s.scalars(select(PlaybackRecord))]
    assert len(records) == 18  # 9 clips x 2 participants
    for rec in records:  # requestVideoFrameCallback saw the frames
        assert (
            rec["frames_expected"] > 0 and rec["presented_frames"] >= 0.8 * rec["frames_expected"]
        )
        assert rec["play_refused"] is None and rec["onset"] > 0
    assert main(args) == 0  # a second start: the same two, already complete
    assert len(_rows(server, "P0001")) == PLANNED
    out = tmp_path / "results"
    assert main(["export", "--db", f"sqlite:///{db}", "--results", str(out)]) == 0
    session = json.loads(next((out / "kato2021" / "sub-P0001").rglob("*_session.json")).read_text())
    assert session["mode"] == "online" and session["simulated"] is True
    assert next((out / "kato2021" / "sub-P0002").rglob("*_actions.jsonl")).stat().st_size > 0
    report = tmp_path / "report"
    code = main(
        ["analyze", str(study / "short.yaml"), str(out), "--force", "--out", str(report),
         "--bootstrap", "0"]
    )  # fmt: skip
    assert code == 0
    assert any(report.rglob("*.csv"))


def test_a_tab_closed_mid_trial_resumes_at_the_first_unanswered_screen(
    study: Path, tmp_path: Path
) -> None:
    server = _server(study, tmp_path / "db.sqlite")
    with BackgroundServer(server) as bg:
        driver = chromium()
        try:
            first = SimulatedBrowser(server, bg.url, 1, stop_after=3, driver=driver)
            assert first.run() == "stopped"  # on trial 2's second VAS screen
            time.sleep(1.0)  # the outbox sends the third answer
            driver.get("about:blank")  # the tab is gone
            assert len(_rows(server, "P0001")) == 3
            again = SimulatedBrowser(server, bg.url, 1, driver=driver)
            assert again.run() == "complete"
            assert "再開" in again.texts["resume"]  # the resume screen says so, in Japanese
        finally:
            driver.quit()
    _check_session(server, "P0001")
    with Session(server.engine) as s:
        records = [r.record for r in s.scalars(select(PlaybackRecord))]
    replays = [r for r in records if r["replay"]]
    assert [r["trial_index"] for r in replays] == [2]  # the clip is shown again before rating
    with Session(server.engine) as s:
        resumed = [e.detail for e in s.scalars(select(Event).where(Event.kind == "resumed"))]
    assert resumed == [{"answered": 3, "first_trial": 2}]  # the return is logged, once
    export_sessions(server.engine, results=tmp_path / "out")
    saved = json.loads(next((tmp_path / "out").rglob("*_session.json")).read_text("utf-8"))
    assert [(r["answered"], r["first_trial"]) for r in saved["resumes"]] == [(3, 2)]


def test_a_participant_who_stops_answers_the_questionnaire_after_and_keeps_their_answers(
    study: Path, tmp_path: Path
) -> None:
    """The page's Stop button (confirmed) mid-study: a withdrawn event, the page reloads as a
    stopped session - the sickness questionnaire after, then a note that the answers are kept
    - and opened again it stays stopped; the answers given are stored, exported (the session
    file says when it was stopped) and the questionnaire scored."""
    text = (study / "short.yaml").read_text(encoding="utf-8")
    text = text.replace("\n  language: ja\n", "\n  language: ja\n  ssq: [before, after]\n", 1)
    path = tmp_path / "ssq.yaml"
    path.write_text(text, encoding="utf-8")
    server, _ = prepare_server(
        load_protocol(path), protocol_path=path, clips_dir=study / "clips",
        db_url=f"sqlite:///{tmp_path / 'db.sqlite'}", results=tmp_path, admin_secret="s" * 20,
    )  # fmt: skip
    shots = tmp_path / "shots"
    with BackgroundServer(server) as bg:
        driver = chromium()
        try:
            # the 16 answers of the questionnaire before, then three ratings
            first = SimulatedBrowser(server, bg.url, 1, withdraw_after=16 + 3, driver=driver,
                                     screenshots=shots)  # fmt: skip
            assert first.run() == "withdrawn"
            again = SimulatedBrowser(server, bg.url, 1, driver=driver)  # the link, later
            assert again.run() == "withdrawn"
            note = driver.find_element("css selector", "[data-facelab=withdrawn]").text
            assert "回答は保存されています" in note
            assert not driver.find_elements("css selector", "[data-facelab=withdraw]")
        finally:
            driver.quit()
    assert {"withdraw-ask.png", "withdrawn.png"} <= {p.name for p in shots.glob("*.png")}
    rows = _rows(server, "P0001")
    sickness = sorted(r["item"] for r in rows if r["screen"] == "ssq")
    assert sum(i.startswith("ssq_before_") for i in sickness) == 16
    assert sum(i.startswith("ssq_after_") for i in sickness) == 16 and len(sickness) == 32
    assert len([r for r in rows if r["screen"] != "ssq"]) == 3  # the three ratings given
    with Session(server.engine) as db:
        stopped = [e.detail for e in db.scalars(select(Event).where(Event.kind == "withdrawn"))]
        person = db.scalars(select(Participant)).one()
    assert len(stopped) == 1 and stopped[0]["screen"] == "vas" and person.completed is None
    with pytest.raises(RefusedError, match="stopped by the participant"):  # no code, ever
        server.completion(person)
    state = server.session_state(person)
    assert state["withdrawn"] and state["timeline"] == [] and state["display"] == "video"
    (progress,) = server.progress()
    assert progress["withdrawn"] is True and progress["completed"] is None
    out = tmp_path / "out"
    export_sessions(server.engine, results=out)
    saved = json.loads(next(out.rglob("*_session.json")).read_text("utf-8"))
    assert saved["withdrawn"] and saved["finished"] is None
    report = tmp_path / "report"
    assert main(["analyze", str(path), str(out), "--force", "--out", str(report),
                 "--bootstrap", "0"]) == 0  # fmt: skip
    table = pd.read_csv(next(report.rglob("ssq.csv")))
    assert sorted(table["moment"]) == ["after", "before"]
    assert table["total"].notna().all()


def test_answers_refused_while_the_protocol_was_changed_are_held_and_stored_after(
    study: Path, tmp_path: Path
) -> None:
    """outbox.js used to drop every answer the server refused: after a protocol edit under
    running sessions, every answer got 409 and was thrown away, and the end page waited for
    ever. Now refused answers are held and retried; once the reason goes (here: the session's
    protocol version could not be served, then could) they are stored and the session
    completes; meanwhile the progress page lists what the browser holds and why."""
    server = _server(study, tmp_path / "db.sqlite")
    original = server.study.protocol_sha256
    outcome: list[str] = []
    with BackgroundServer(server) as bg:
        browser = SimulatedBrowser(server, bg.url, 1)
        thread = threading.Thread(target=lambda: outcome.append(browser.run(timeout_s=300)))
        thread.start()
        deadline = time.monotonic() + 120
        while len(_rows(server, "P0001")) < 4 and time.monotonic() < deadline:
            time.sleep(0.1)
        # the version the session started with cannot be served (e.g. its clips were
        # rendered over): every request of the session is refused
        server._versions[original] = "its clips were rendered for another version"
        server._by_token.drop(lambda p: False)
        at_edit = len(_rows(server, "P0001"))
        time.sleep(12.0)
        during = len(_rows(server, "P0001"))
        listed = {p["participant"]: p for p in server.progress()}["P0001"]
        server._versions[original] = server.study  # restored
        thread.join(timeout=300)
    assert outcome == ["complete"]
    assert 4 <= at_edit == during < PLANNED  # nothing was stored while refused
    _check_session(server, "P0001")  # every answer given is stored once, as clicked
    with Session(server.engine) as s:
        held = [e.detail for e in s.scalars(select(Event).where(Event.kind == "error"))]
    # the reason the browser held them: the study's language, no file path or hash
    assert held and all("実験の準備が変更された" in h["why"] and "/" not in h["why"]
                        for h in held)  # fmt: skip
    # meanwhile the progress page said why the session was refused; the held answers were
    # reported once it was served again, and are stored now
    assert listed["protocol"] == "cannot be served: its clips were rendered for another version"
    assert {p["participant"]: p for p in server.progress()}["P0001"]["held"] == 0


def test_the_server_killed_mid_session_and_restarted_loses_nothing(
    study: Path, tmp_path: Path
) -> None:
    db = tmp_path / "db.sqlite"
    server = _server(study, db)
    port = free_port()
    url = f"http://127.0.0.1:{port}"

    def start():
        return start_server(
            study / "short.yaml", clips=study / "clips", db_url=f"sqlite:///{db}", port=port,
            results=tmp_path,
        )  # fmt: skip

    proc = start()
    wait_for_server(url)
    outcome: list[str] = []
    browser = SimulatedBrowser(server, url, 1)
    thread = threading.Thread(target=lambda: outcome.append(browser.run(timeout_s=300)))
    thread.start()
    deadline = time.monotonic() + 120
    while len(_rows(server, "P0001")) < 4 and time.monotonic() < deadline:
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    stored_at_kill = len(_rows(server, "P0001"))
    time.sleep(4.0)  # the participant goes on answering; answers wait in localStorage
    proc = start()
    try:
        thread.join(timeout=300)
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)
    assert outcome == ["complete"]
    assert 4 <= stored_at_kill < PLANNED
    _check_session(server, "P0001")


# --------------------------------------------------------------------------- load


@pytest.mark.parametrize("database", ["sqlite", "postgresql"])
def test_200_concurrent_participants_lose_and_duplicate_nothing(
    study: Path, tmp_path: Path, database: str
) -> None:
    kw = dict(protocol_path=study / "short.yaml", clips=study / "clips", participants=200,
              results=tmp_path)  # fmt: skip
    if database == "postgresql":
        with postgres_cluster() as url:
            figures = load_test(db_url=url, **kw)
    else:
        figures = load_test(db_url=f"sqlite:///{tmp_path / 'load.sqlite'}", **kw)
    print(json.dumps(figures))
    assert figures["responses_planned"] == 200 * PLANNED
    assert figures["lost"] == 0 and figures["duplicated"] == 0
    assert figures["responses_stored"] == 200 * PLANNED
    assert figures["wall_s"] < 400  # bounded; the figures themselves go to bench online


# --------------------------------------------------------------------------- task screens


@pytest.mark.parametrize(
    ("name", "edits", "screen"),
    [
        (
            "gain_2afc",
            {
                r"    sets: 2": "    sets: 1",
                r"presentations_per_condition: 5": ("presentations_per_condition: 1"),
            },
            "choice_2afc",
        ),
        (
            "method_identify",
            {
                r"    sets: 4": "    sets: 1",
                r"presentations_per_condition: 2": ("presentations_per_condition: 1"),
                r"      - \{id: sentence.*\n": "",
            },
            "identify",
        ),
    ],
)
def test_forced_choice_and_identification_in_chromium(
    tmp_path: Path, name: str, edits: dict[str, str], screen: str
) -> None:
    _, server = _task_server(name, edits, tmp_path)
    shots = tmp_path / "shots"
    with BackgroundServer(server) as bg:
        assert SimulatedBrowser(server, bg.url, 1, screenshots=shots).run() == "complete"
    assert (shots / f"{screen}.png").exists()
    rows = _rows(server, "P0001")
    assert rows and {r["screen"] for r in rows} == {screen}
    assert len(rows) == len(server.study.planned("P0001"))
    with Session(server.engine) as db:
        actions = {(a.record["trial_index"]): a.record["value"] for a in db.scalars(select(Action))}
    for r in rows:
        if screen == "identify":
            assert r["response"] == actions[r["trial_index"]]
            assert r["correct"] in (0, 1)
        else:  # the interval clicked -> the condition shown in it, scored against position
            chose_comparison = actions[r["trial_index"]] == r["position"]
            assert r["response"] == (r["condition"] if chose_comparison else "g100")
            assert r["correct"] == int(chose_comparison)


def test_bad_serve_and_export_input_is_a_clear_error(
    study: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = ["serve", str(study / "short.yaml"), "--clips", str(study / "clips"),
            "--results", str(tmp_path)]  # fmt: skip
    assert main([*base, "--consent", str(tmp_path / "missing.txt")]) == 2
    assert "--consent" in capsys.readouterr().err
    assert main([*base, "--db", "mysql://x/y"]) == 2
    assert "expected a sqlite:///PATH or postgresql" in capsys.readouterr().err
    assert main(["serve", str(study / "short.yaml"), "--clips", str(tmp_path)]) == 2
    assert "no clip manifest" in capsys.readouterr().err
    missing = f"sqlite:///{tmp_path / 'none.sqlite'}"
    assert main(["export", "--db", missing, "--results", str(tmp_path / "out")]) == 2
    assert "no such database file" in capsys.readouterr().err
    assert not (tmp_path / "none.sqlite").exists()


def test_a_staircase_runs_online_as_in_the_lab(tmp_path: Path) -> None:
    """The server runs the rule: each staircase trial's level is chosen from the stored
    answers before it (never by the browser), in order; Chromium walks it to the end and
    the levels shown follow the 1-up-2-down rule, as the lab runner's replay checks."""
    from facelab.experiment.adaptive import Staircases

    protocol, server = _task_server(
        "gain_staircase", {r"trials: 50": "trials: 6", r"practice: .*\n": ""}, tmp_path
    )
    client = TestClient(create_app(server))
    _, token = server.join(recruitment=None, source=None)
    ok = {"X-Facelab-Token": token}
    state = client.get("/api/session", headers=ok).json()
    adaptive = [s for s in state["timeline"] if s["kind"] == "adaptive"]
    assert len(adaptive) == 6 and state["planned"] == 6
    assert len(state["clips"]) == len(protocol.conditions)  # every level preloads
    first, second = adaptive[0]["trial_index"], adaptive[1]["trial_index"]
    r = client.get(f"/api/adaptive/{second}", headers=ok)
    assert r.status_code == 409 and f"answer to trial {first}" in r.json()["error"]
    assert client.get("/api/adaptive/999", headers=ok).status_code == 409
    screens = client.get(f"/api/adaptive/{first}", headers=ok).json()["screens"]
    assert [s["kind"] for s in screens] == ["clip", "clip", "choice_2afc"]
    answer = {"client_key": "b" * 16, "trial_index": first, "item": "stronger", "rt_s": 0.8,
              "choice": 1, "timestamp": "2026-11-23T08:00:00.000Z"}  # fmt: skip
    assert client.post("/api/response", json=answer, headers=ok).status_code == 200
    assert client.get(f"/api/adaptive/{second}", headers=ok).status_code == 200
    (row,) = _rows(server, "P0001")
    assert row["condition"] == "g160" and row["block"] == "main"  # the staircase's start

    with BackgroundServer(server) as bg:  # a second participant, in the browser
        assert SimulatedBrowser(server, bg.url, 1, seed=3).run() == "complete"
    rows = sorted(_rows(server, "P0002"), key=lambda r: r["trial_index"])
    assert len(rows) == 6 and all(r["screen"] == "choice_2afc" for r in rows)
    with Session(server.engine) as db:  # the clips of every level are the participant's own
        pk = db.scalars(select(Participant.pk).where(Participant.participant == "P0002")).one()
        shown = [
            r.record["trial_index"]
            for r in db.scalars(select(PlaybackRecord).where(PlaybackRecord.participant_pk == pk))
        ]
    assert sorted(shown) == sorted(r["trial_index"] for r in rows for _ in range(2))
    Staircases(protocol, logged=rows)  # replaying the rule gives exactly the levels shown
    from facelab.staircase import new_staircase

    rule = new_staircase(protocol, "main")
    for r in rows:
        assert r["condition"] == rule.condition
        rule.update(bool(r["correct"]))

    # export: the server kept the protocol it ran, so the export puts it beside the sessions
    # and writes the lab runner's staircase record from it
    out = tmp_path / "export"
    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    proto = tmp_path / "gain_staircase.yaml"
    assert main(["export", "--db", url, "--results", str(out)]) == 0
    sha = protocol_hash(proto)
    copy = out / protocol.study.id / f"protocol-{sha[:12]}.yaml"
    assert copy.read_bytes() == proto.read_bytes()
    stair_file = next(out.rglob("sub-P0002*_staircase.jsonl"))
    steps = [json.loads(line) for line in stair_file.read_text().splitlines()]
    rule = new_staircase(protocol, "main")
    assert [s["trial_index"] for s in steps] == [r["trial_index"] for r in rows]
    for step, r in zip(steps, rows, strict=True):
        assert step["block"] == "main" and step["rebuilt"] is True
        assert step["condition"] == r["condition"]
        rule.update(bool(r["correct"]))
        assert step["next_condition"] == rule.condition
    assert main(["export", "--db", url, "--results", str(out), "--protocol", str(proto)]) == 0
    assert stair_file.read_text().count("\n") == len(rows)  # again: nothing doubled
    # a --protocol nobody ran is said, and the sessions' own protocol is used
    notes: list[str] = []
    export_sessions(
        server.engine, results=tmp_path / "export2", protocol=protocol,
        protocol_sha256="0" * 64, notes=notes,
    )  # fmt: skip
    assert any("no exported session ran this version" in n for n in notes)
    assert len(list((tmp_path / "export2").rglob("*_staircase.jsonl"))) == 2
    # a database from before the server kept protocols: said, and --protocol fills in
    with Session(server.engine) as db:
        db.execute(delete(ProtocolFile))
        db.commit()
    notes = []
    export_sessions(server.engine, results=tmp_path / "export3", notes=notes)
    assert any("does not hold protocol" in n for n in notes)
    assert not list((tmp_path / "export3").rglob("*_staircase.jsonl"))
    export_sessions(
        server.engine, results=tmp_path / "export3", protocol=protocol, protocol_sha256=sha
    )
    assert len(list((tmp_path / "export3").rglob("*_staircase.jsonl"))) == 2


def test_a_quest_plus_staircase_is_served_at_the_levels_the_rule_chooses(tmp_path: Path) -> None:
    """QUEST+ online: each trial's level comes from the stored answers before it, as the
    rule replayed in the lab gives it (answered through the API; the browser walk is the
    up-down test's)."""
    from facelab.staircase import new_staircase

    protocol, server = _task_server(
        "gain_questplus", {r"trials: 30": "trials: 5", r"practice: .*\n": ""}, tmp_path
    )
    client = TestClient(create_app(server))
    _, token = server.join(recruitment=None, source=None)
    ok = {"X-Facelab-Token": token}
    adaptive = [
        s for s in client.get("/api/session", headers=ok).json()["timeline"]
        if s["kind"] == "adaptive"
    ]  # fmt: skip
    rule = new_staircase(protocol, "main")
    for n, screen in enumerate(adaptive):
        trial = screen["trial_index"]
        client.get(f"/api/adaptive/{trial}", headers=ok).raise_for_status()
        choice = 1 if n % 3 else 2  # some right, some wrong, whichever side the comparison is
        answer = {"client_key": f"{n:016d}", "trial_index": trial, "item": "stronger",
                  "rt_s": 0.8, "choice": choice, "timestamp": "2026-11-23T08:00:00Z"}  # fmt: skip
        assert client.post("/api/response", json=answer, headers=ok).status_code == 200
        (row,) = [r for r in _rows(server, "P0001") if r["trial_index"] == trial]
        assert row["condition"] == rule.condition  # the level QUEST+ chose
        rule.update(bool(row["correct"]))
    assert len({r["condition"] for r in _rows(server, "P0001")}) >= 2


def test_side_by_side_choice_in_chromium(tmp_path: Path) -> None:
    """Two videos at once: both play (requestVideoFrameCallback saw each one's frames), a
    playback record per video, the side clicked scored against the logged position."""
    _, server = _task_server(*SIDE_BY_SIDE, tmp_path)
    shots = tmp_path / "shots"
    with BackgroundServer(server) as bg:
        assert SimulatedBrowser(server, bg.url, 1, screenshots=shots).run() == "complete"
    assert (shots / "clip_pair.png").exists() and (shots / "choice_2afc.png").exists()
    rows = _rows(server, "P0001")
    assert len(rows) == 2 and {r["position"] for r in rows} == {1, 2}
    with Session(server.engine) as db:
        actions = {a.record["trial_index"]: a.record["value"] for a in db.scalars(select(Action))}
        records = [r.record for r in db.scalars(select(PlaybackRecord))]
    for r in rows:
        chose_comparison = actions[r["trial_index"]] == r["position"]
        assert r["response"] == ("q15" if chose_comparison else "q0")
        assert r["clip_onset"] is not None
    assert sorted(rec["trial_index"] for rec in records) == [1, 1, 2, 2]
    for trial in (1, 2):
        pair = [rec for rec in records if rec["trial_index"] == trial]
        assert len({rec["clip"] for rec in pair}) == 2  # the two different clips
        for rec in pair:
            assert rec["presented_frames"] >= 0.8 * rec["frames_expected"] > 0
            assert rec["play_refused"] is None


def test_export_says_when_the_stored_protocol_needs_its_side_files(tmp_path: Path) -> None:
    """A protocol that names a file beside it (an impression model) cannot be loaded from
    the database's copy alone: the export still writes the sessions and the copy, and says
    that --protocol is needed (only staircase records depend on it)."""
    import numpy as np

    from facelab.experiment.online.db import open_engine, store_protocol
    from facelab.experiment.simulate import simulated_rows
    from facelab.resources import protocol_path

    path = protocol_path("horii_impression")
    protocol = load_protocol(path)
    engine = open_engine(f"sqlite:///{tmp_path / 'db.sqlite'}")
    sha = store_protocol(engine, protocol_path=path, study=protocol.study.id)
    assert store_protocol(engine, protocol_path=path, study=protocol.study.id) == sha  # once
    rows = simulated_rows(protocol, participant="P0001", rng=np.random.default_rng(1))[:3]
    with Session(engine) as db:
        p = Participant(
            study=protocol.study.id, participant="P0001", number=1, session=1,
            token_sha256="t" * 64, simulated=True, protocol_sha256=sha, design_seed="1",
            trial_order=[], clips={},
        )  # fmt: skip
        db.add(p)
        db.flush()
        for i, row in enumerate(rows):
            db.add(
                Response(
                    participant_pk=p.pk, trial_index=row["trial_index"], item=row["item"],
                    client_key=f"{i:016d}", row={**row, "protocol_sha256": sha},
                )
            )  # fmt: skip
        db.commit()
    notes: list[str] = []
    (tsv,) = export_sessions(engine, results=tmp_path / "out", notes=notes)
    assert len(tsv.read_text().splitlines()) == 1 + len(rows)
    copy = tmp_path / "out" / protocol.study.id / f"protocol-{sha[:12]}.yaml"
    assert copy.read_bytes() == path.read_bytes()
    assert any("does not load on its own" in n and "--protocol" in n for n in notes), notes
