"""``facelab serve``: one study in participants' browsers (FastAPI on uvicorn).

Pages and routes (all same-origin; no cookies; the participant's token travels in the
``X-Facelab-Token`` header, never in a cookie, so there is nothing for CSRF to ride on):

========================  ===================================================================
``GET /join``             the recruitment link's page, in the study's language: creates
                          nothing (link previews and crawlers fetch it); its button posts to
``POST /join``            a new participant (or the returning one, by recruitment id): the
                          server assigns the id (``P0001`` …, so Latin squares work) and a
                          random 256-bit token, and redirects to ``/run#t=TOKEN`` (the
                          fragment never reaches a server log or a Referer). Prolific's
                          ``PROLIFIC_PID`` / MTurk's ``workerId`` are stored only as HMAC-SHA256
                          under the server's key.
``GET /run``              the session page (jsPsych shell + facelab's plugins)
``GET /api/session``      the participant's remaining timeline (compiled here, never in the
                          browser), clip names, counts
``POST /api/response``    one answer; stored (one row per trial and item, the client's
                          idempotency key unique) before the 200; a replay answers 200 again,
                          a different value for a stored trial/item is 409
``POST /api/playback``    one clip's presentation record (``_playback.jsonl`` keys)
``POST /api/event``       play() refusals, fullscreen exits, the browser's description
``GET /api/complete``     the completion code/redirect, only once every planned response is
                          stored (409 with the count missing otherwise)
``GET /clips/SHA.mp4``    a clip by its SHA-256 (the name never reveals the condition)
``GET /admin``            progress per participant, behind the experimenter secret
                          (``X-Facelab-Admin`` header; the page asks for it)
========================  ===================================================================

Every response carries a strict Content-Security-Policy (scripts, media and connections
from this origin only - media, images and fetches also from the blob: URLs that jsPsych's
preload and the live view's avatar textures make; style
attributes are allowed because jsPsych's plugins write them in their HTML), ``nosniff``,
``no-referrer`` and ``frame-ancestors 'none'``. Requests are rate-limited per token (and
``/join`` per client address, kept in memory only; no IP address is stored).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import hashlib
import hmac
import json
import math
import secrets
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.engine import Engine
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from facelab.design import participant_seed, trial_order
from facelab.experiment.online.api_models import AnswerIn, EventIn, PlaybackIn, ScreenPosesIn
from facelab.experiment.online.db import (
    Event,
    Participant,
    PlaybackRecord,
    ProtocolFile,
    Response,
    ScreenPoses,
    Setting,
    utcnow,
)
from facelab.experiment.online.limits import Clock, RateLimiter, TokenCache
from facelab.experiment.online.live import LiveScene, checked_tracks
from facelab.experiment.online.served import ServedFiles, served_files
from facelab.experiment.online.study import AnswerError, OnlineStudy, checked_study
from facelab.experiment.timeline import SCREEN_KINDS, Playback, needed_clips

__all__ = [
    "EARLIER_TOKEN_HEADER",
    "THREE_FILES",
    "InUseError",
    "RefusedError",
    "ServeConfig",
    "StudyServer",
    "token_sha256",
]

WEB = Path(__file__).resolve().parent / "web"
VENDOR_FILES = {
    "jspsych.js": "jspsych/dist/index.browser.min.js",
    "jspsych.css": "jspsych/css/jspsych.css",
    "plugin-fullscreen.js": "@jspsych/plugin-fullscreen/dist/index.browser.min.js",
    "plugin-browser-check.js": "@jspsych/plugin-browser-check/dist/index.browser.min.js",
    "plugin-preload.js": "@jspsych/plugin-preload/dist/index.browser.min.js",
    "plugin-html-button-response.js": (
        "@jspsych/plugin-html-button-response/dist/index.browser.min.js"
    ),
}
#: three.js files the live 3D and VR views load (ES modules, by the paths they import each
#: other by; the page's import map names "three"), served from node_modules/three
THREE_FILES = (
    "build/three.module.js",
    "build/three.core.js",
    "examples/jsm/loaders/GLTFLoader.js",
    "examples/jsm/utils/BufferGeometryUtils.js",
    "examples/jsm/utils/SkeletonUtils.js",
)
TOKEN_HEADER = "X-Facelab-Token"
ADMIN_HEADER = "X-Facelab-Admin"
#: an answer saved under the session's earlier token (see StudyServer.check_earlier_token)
EARLIER_TOKEN_HEADER = "X-Facelab-Earlier-Token"
TOKEN_CACHE_S = 5.0  # a rotated token stops working within this time in other processes
RECRUITMENT_PARAMS = {"PROLIFIC_PID": "prolific", "workerId": "mturk", "PARTICIPANT": "link"}

# What one participant may store besides answers. Sized from real sessions with headroom: a
# clip's playback record is ~30 bytes a frame in a browser (flip time, frame shown) and ~90
# in VR (audio time, viewer pose too), ~230 with two controllers' poses; a 240 Hz display
# draws 240 frames a second. So a record may hold 64 kB per second of its clip (a 240 Hz VR
# record with two controllers, with headroom) plus 32 kB; a trial
# at most 16 records (a pair trial records both clips of each showing: its showing, replays,
# reloaded pages); a session 32 MB of playback and 1,000 events it posted, of at most 4,000
# characters each (a session sends a handful; the server's own events are not counted).
PLAYBACK_BYTES_PER_CLIP_S = 64_000
PLAYBACK_BYTES_BASE = 32_000
PLAYBACK_RECORDS_PER_TRIAL = 16
PLAYBACK_BYTES_PER_SESSION = 32_000_000
EVENTS_PER_SESSION = 1_000
# VR screens' poses (head and two controllers, ~230 bytes a frame): a session may store 4,000
# screens' records (a screen shown again after a reload sends another) and 32 MB of them
SCREEN_POSES_PER_SESSION = 4_000
SCREEN_POSES_BYTES_PER_SESSION = 32_000_000
ADMIN_FAILURES_PER_MIN = 10
#: refused rejoins logged per session (someone trying the participant's id cannot fill the
#: database through them)
REJOIN_REFUSALS_LOGGED = 20

#: a session whose protocol version cannot be served now (the experimenter changed the
#: study under it), as the participant reads it
PAUSED = {
    "ja": "実験の準備が変更されたため、今は続けられません。回答はこのブラウザーに保存されており、"
    "研究者が対応すると送られます。このページを開いたままにするか、後で同じリンクを開いてください。",
    "en": "The study was changed and cannot continue right now. Your answers are kept in this "
    "browser and are sent once the researcher has fixed it; keep this page open or open the "
    "same link later.",
}


def _own_plugin(kind: str) -> Path | None:
    """The jsPsych plugin file a screen kind added to facelab brings (None for the built-in
    kinds, whose plugins are in web/static/plugins.js)."""
    cls = SCREEN_KINDS.get(kind)
    return None if cls is None else cls.plugin_js


def token_sha256(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


@dataclass
class ServeConfig:
    """What ``facelab serve`` was given."""

    study: OnlineStudy
    clip_paths: dict[str, Path]  # "<sha256>.mp4" -> file
    vendor: Path  # node_modules with jsPsych (npm ci in experiment/online/web)
    completion_url: str | None = None  # e.g. Prolific's https://app.prolific.com/…?cc=CODE
    completion_code: str | None = None
    consent: str | None = None
    rate_per_s: float = 20.0  # requests per second per token (burst: 4 s worth)
    joins_per_min: int = 30  # new participants per minute per client address
    # a recruitment id alone reopens a session only after it has been idle this long; the
    # browser that holds the session's token reopens it at any time (see StudyServer.join)
    rejoin_idle_s: float = 1800.0
    live: LiveScene | None = None  # display live3d / webxr: the avatar, camera and tracks
    # where the protocol file and the clips are: sessions that started under an earlier
    # version of the file (kept in the database by its SHA-256) are served that version
    protocol_dir: Path | None = None
    clips_dir: Path | None = None
    # where the copies browsers fetch are written (see facelab.experiment.online.served);
    # None serves the rendered files under their SHA-256
    served_dir: Path | None = None
    # what adds routes of its own to the app (``add(app, server)``): the live conversation of
    # a protocol with one (facelab.experiment.live_dialogue.conversation)
    routes: tuple[Any, ...] = ()


class InUseError(Exception):
    """A recruitment id whose session is live in another browser (see StudyServer.join)."""


class RefusedError(Exception):
    """An HTTP error with a message for the participant's browser (and the tests)."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status
        self.message = message


def _withdrew_in(db: Session, participant_pk: int) -> bool:
    """Whether participant ``participant_pk`` stopped the study from its page (a
    ``withdrawn`` event), asked in the open session ``db``."""
    return bool(db.scalar(select(func.count()).where(
        Event.participant_pk == participant_pk, Event.kind == "withdrawn")))  # fmt: skip


class StudyServer:
    """The study's state on top of the database; every method is one short transaction."""

    def __init__(self, engine: Engine, config: ServeConfig, *, clock: Clock = time.monotonic):
        self.engine = engine
        self.config = config
        self.study = config.study
        self.token_limiter = RateLimiter(
            limit=int(config.rate_per_s * 4), window_s=4.0, clock=clock
        )  # per token: a burst of 4 s worth
        self.join_limiter = RateLimiter(limit=config.joins_per_min, window_s=60.0, clock=clock)
        # wrong experimenter secrets per client address: past the limit every try is refused
        # (429) for a minute, the right secret too - guessing gains nothing
        self.admin_limiter = RateLimiter(limit=ADMIN_FAILURES_PER_MIN, window_s=60.0, clock=clock)
        self._join_lock = threading.Lock()
        # SQLite has one writer: queue writers here instead of in its busy handler (which
        # sleeps up to 100 ms per retry); PostgreSQL takes concurrent writers itself.
        self._writes: Any = (
            threading.Lock()
            if engine.url.get_backend_name() == "sqlite"
            else contextlib.nullcontext()
        )
        self._by_token: TokenCache[Participant] = TokenCache(ttl_s=TOKEN_CACHE_S, clock=clock)
        # protocol SHA-256 -> the study under that version of the file, or why it cannot be
        # served (sessions keep the protocol they started with)
        self._versions: dict[str, OnlineStudy | str] = {config.study.protocol_sha256: self.study}
        self._versions_lock = threading.Lock()
        self.hmac_key = bytes.fromhex(self._setting("hmac_key", lambda: secrets.token_hex(32)))
        self.served = ServedFiles()
        if config.served_dir is not None:
            self._serve_copies(self.study)

    # -- settings and secrets

    def _setting(self, key: str, make: Any) -> str:
        with Session(self.engine) as db:
            row = db.get(Setting, key)
            if row is None:
                db.add(Setting(key=key, value=make()))
                try:
                    db.commit()
                except IntegrityError:  # another process made it first
                    db.rollback()
                row = db.get(Setting, key)
            assert row is not None
            return row.value

    def keyed_hash(self, text: str) -> str:
        return hmac.new(self.hmac_key, text.encode(), hashlib.sha256).hexdigest()

    def set_admin_secret(self, secret: str) -> None:
        with Session(self.engine) as db:
            db.merge(Setting(key="admin_sha256", value=token_sha256(secret)))
            db.commit()

    def check_admin(self, secret: str | None, *, address: str = "?") -> None:
        if self.admin_limiter.blocked(address):
            raise RefusedError(429, "too many wrong experimenter secrets; wait a minute")
        with Session(self.engine) as db:
            row = db.get(Setting, "admin_sha256")
        if row is None or not secret or not hmac.compare_digest(row.value, token_sha256(secret)):
            self.admin_limiter.allow(address)
            raise RefusedError(401, "experimenter secret missing or wrong")

    # -- participants

    def join(
        self,
        *,
        recruitment: str | None,
        source: str | None,
        simulated: bool = False,
        token: str | None = None,
        previous_token: str | None = None,
    ) -> tuple[Participant, str]:
        """A new participant, or the returning one (by recruitment id).

        Knowing a recruitment id is not enough to take a session over: the returning
        participant gets their session back with the same token when their browser presents
        it (``previous_token``, read from the browser's storage by the join page - their
        unsent answers are stored under it and are sent next), or with a fresh token once
        the session has been idle for ``rejoin_idle_s`` (a new browser or device; the old
        token stops working). Otherwise :class:`InUseError`: the live session is untouched.
        ``token`` is given only for simulated participants (stable tokens)."""
        rid = self.keyed_hash(f"{source}:{recruitment}") if recruitment else None
        token = token or secrets.token_urlsafe(32)
        with self._join_lock, Session(self.engine) as db:
            existing = None
            if rid is not None:
                existing = db.scalars(
                    select(Participant).where(
                        Participant.study == self.study.study, Participant.recruitment_hash == rid
                    )
                ).first()
            if existing is not None:
                same_browser = previous_token is not None and hmac.compare_digest(
                    token_sha256(previous_token), existing.token_sha256
                )
                if same_browser:
                    db.add(Event(participant_pk=existing.pk, kind="rejoined",
                                 detail={"how": "same browser"}))  # fmt: skip
                    db.commit()
                    db.refresh(existing)
                    return existing, previous_token  # type: ignore[return-value]
                idle = (utcnow() - self._last_seen(db, existing)).total_seconds()
                if not simulated and idle < self.config.rejoin_idle_s:
                    refused = db.scalar(select(func.count()).where(
                        Event.participant_pk == existing.pk,
                        Event.kind == "rejoin_refused",
                    ))  # fmt: skip
                    if (refused or 0) < REJOIN_REFUSALS_LOGGED:  # others' tries fill nothing
                        db.add(Event(participant_pk=existing.pk, kind="rejoin_refused",
                                     detail={"idle_s": round(idle, 1)}))  # fmt: skip
                        db.commit()
                    raise InUseError(existing.participant)
                self._by_token.drop(lambda p: p.pk != existing.pk)
                # the retired token's hash is kept: answers a browser saved under it are
                # still this participant's (see earlier_token)
                how = {"how": "new browser after idle", "idle_s": round(idle),
                       "retired_token_sha256": existing.token_sha256}  # fmt: skip
                existing.token_sha256 = token_sha256(token)
                db.add(Event(participant_pk=existing.pk, kind="rejoined", detail=how))
                db.commit()
                db.refresh(existing)
                return existing, token
            for _ in range(5):
                number = (
                    db.scalar(
                        select(func.max(Participant.number)).where(
                            Participant.study == self.study.study
                        )
                    )
                    or 0
                ) + 1
                pid = f"P{number:04d}"
                trials = self.study.trials(pid)
                # every clip the session may show: both of a pair, every level of a staircase
                needed = needed_clips(self.study.screens(pid))
                p = Participant(
                    study=self.study.study,
                    participant=pid,
                    number=number,
                    session=1,
                    token_sha256=token_sha256(token),
                    recruitment_hash=rid,
                    recruitment_source=source,
                    simulated=simulated,
                    protocol_sha256=self.study.protocol_sha256,
                    design_seed=str(participant_seed(self.study.protocol.seed, pid)),
                    trial_order=trial_order(trials),
                    clips={"/".join(k): self.study.clip_sha256[k] for k in sorted(needed)},
                    created=utcnow(),
                )
                db.add(p)
                try:
                    db.flush()
                except IntegrityError:  # another server process took the number
                    db.rollback()
                    continue
                db.add(Event(participant_pk=p.pk, kind="joined", detail={"source": source}))
                db.commit()
                db.refresh(p)
                return p, token
        raise RefusedError(503, "could not assign a participant id; try again")

    def participant(self, token: str | None) -> Participant:
        if not token or len(token) > 128:
            raise RefusedError(401, f"missing or malformed {TOKEN_HEADER} header")
        digest = token_sha256(token)
        if not self.token_limiter.allow(digest):
            raise RefusedError(429, "too many requests; slow down")
        cached = self._by_token.get(digest)
        if cached is not None:
            return cached
        p = self._find_participant(Participant.token_sha256 == digest)
        if p is None:
            raise RefusedError(401, "unknown token (a rejoin gives a new one)")
        version = self._version(p.protocol_sha256)
        if isinstance(version, str):
            # the participant's browser shows this (and keeps it as a held answer's reason):
            # in the study's language, without the server's internals; the experimenter's
            # progress page gives the reason (protocol: "cannot be served: ...")
            lang = self.study.protocol.presentation.language
            raise RefusedError(409, PAUSED.get(lang, PAUSED["en"]))
        self._by_token.put(digest, p)
        return p

    def participant_by_id(self, participant: str) -> Participant:
        """The participant ``participant`` (e.g. P0001) of this study, for the experimenter's
        pages (behind the experimenter secret); 404 when there is none."""
        p = self._find_participant(Participant.participant == participant)
        if p is None:
            raise RefusedError(404, f"no participant {participant!r} in this study")
        return p

    def _find_participant(self, where: Any) -> Participant | None:
        """This study's participant matching the SQL condition ``where``, or None."""
        with Session(self.engine, expire_on_commit=False) as db:
            return db.scalars(
                select(Participant).where(where, Participant.study == self.study.study)
            ).first()

    def check_earlier_token(self, p: Participant, earlier: str | None) -> None:
        """Answers a browser saved under an earlier token of this session (before the token
        was rotated by a rejoin) are sent with it in ``X-Facelab-Earlier-Token``: accepted
        for ``p`` only when that token was one of ``p``'s, else refused (409) - a shared
        computer's leftovers never land in another participant's session."""
        if earlier is None:
            return
        if len(earlier) > 128:
            raise RefusedError(422, f"{EARLIER_TOKEN_HEADER}: malformed")
        digest = token_sha256(earlier)
        if hmac.compare_digest(digest, p.token_sha256):
            return
        with Session(self.engine) as db:
            retired = {
                (e.detail or {}).get("retired_token_sha256")
                for e in db.scalars(
                    select(Event).where(Event.participant_pk == p.pk, Event.kind == "rejoined")
                )
            }
        if digest not in retired:
            raise RefusedError(
                409, "these answers were saved under another session's token; not stored here"
            )

    def _serve_copies(self, study: OnlineStudy) -> None:
        """Serve ``study``'s clips and tracks as padded, renamed copies (conditions hidden;
        the practice clip a copy of its own) instead of the rendered files."""
        cfg = self.config
        assert cfg.served_dir is not None
        practice = study.protocol.presentation.practice
        copies = served_files(
            study.clips,
            folder=cfg.served_dir,
            key=self.hmac_key,
            practice=None
            if practice is None
            else (practice.stimulus_set, practice.stimulus, practice.condition),
            tracks=cfg.live is not None,
        )
        self.served.merge(copies)
        study.served = self.served
        # only the copies are served (every version's), not the rendered files by their hash
        cfg.clip_paths.clear()
        cfg.clip_paths.update({n: f for n, f in self.served.paths.items() if n.endswith(".mp4")})
        if cfg.live is not None:
            cfg.live.tracks.clear()
            cfg.live.tracks.update(
                {n: f for n, f in self.served.paths.items() if n.endswith(".bin")}
            )

    def study_of(self, p: Participant) -> OnlineStudy:
        """The study as the participant's session started it (its protocol version)."""
        version = self._version(p.protocol_sha256)
        if isinstance(version, str):  # checked by participant() before any use
            raise RefusedError(409, version)
        return version

    def _version(self, sha256: str) -> OnlineStudy | str:
        """The study under protocol version ``sha256`` (kept in the database when a server
        served it), its clips checked as at start; or the reason it cannot be served: the
        file is not stored, does not load beside the current one, its clips are not in the
        clip folder (rendered for another version), or it draws clips live and this server
        does not (or the other way round)."""
        with self._versions_lock:
            if sha256 not in self._versions:
                self._versions[sha256] = self._load_version(sha256)
            return self._versions[sha256]

    def _load_version(self, sha256: str) -> OnlineStudy | str:
        from facelab.errors import FacelabError
        from facelab.protocol import load_protocol_text

        cfg = self.config
        if cfg.protocol_dir is None or cfg.clips_dir is None:
            return "this server was not told where the protocol's files and clips are"
        with Session(self.engine) as db:
            stored = db.get(ProtocolFile, sha256)
            content = None if stored is None else bytes(stored.content)
        if content is None:
            return f"protocol {sha256[:12]}… is not stored in the database"
        try:
            protocol = load_protocol_text(
                content.decode("utf-8"),
                path=cfg.protocol_dir / f"protocol-{sha256[:12]}.yaml",
                base_dir=cfg.protocol_dir,
            )
            if protocol.study.id != self.study.study:
                return f"it is the protocol of study {protocol.study.id!r}"
            live = protocol.presentation.display != "video"
            if live != (cfg.live is not None):
                return (
                    "it shows clips "
                    + ("live" if live else "as video")
                    + ", and this server does not: serve a protocol with the same display"
                )
            version = checked_study(protocol, protocol_sha256=sha256, clips_dir=cfg.clips_dir,
                                    base_dir=cfg.protocol_dir)  # fmt: skip
            # its tracks must fit the avatar this server draws (checked as at start)
            tracks = {}
            if cfg.live is not None:
                tracks = checked_tracks(
                    protocol, clips=version.clips, avatar_sha256=cfg.live.avatar_sha256
                )
        except (FacelabError, UnicodeDecodeError) as exc:
            first = str(exc).strip().splitlines()
            return (first[-1] if first else "it does not load").strip()[:300]
        if cfg.served_dir is not None:
            self._serve_copies(version)
        else:  # the rendered files, by their own hash
            cfg.clip_paths.update({r.sha256 + ".mp4": r.path for r in version.clips.values()})
            if cfg.live is not None:
                cfg.live.tracks.update(tracks)
        return version

    def answered(self, p: Participant) -> set[tuple[int, str]]:
        with Session(self.engine) as db:
            rows = db.execute(
                select(Response.trial_index, Response.item).where(Response.participant_pk == p.pk)
            ).all()
        return {(int(t), str(i)) for t, i in rows}

    def logged(self, p: Participant) -> list[dict[str, Any]]:
        """The participant's stored log rows (what a staircase's next level depends on)."""
        with Session(self.engine) as db:
            rows = db.scalars(select(Response.row).where(Response.participant_pk == p.pk)).all()
        return [dict(r) for r in rows]

    def adaptive(self, p: Participant, trial_index: int) -> dict[str, Any]:
        """The screens of a staircase trial at the level the stored answers give."""
        try:
            screens = self.study_of(p).adaptive_json(
                p.participant, trial_index, logged=self.logged(p), session=p.session
            )
        except AnswerError as exc:
            raise RefusedError(409, str(exc)) from None
        return {"trial_index": trial_index, "screens": screens}

    def withdrew(self, p: Participant) -> bool:
        """The participant stopped the study from its page (a ``withdrawn`` event; it counts
        only while the session is not complete, and a stopped session is never completed)."""
        with Session(self.engine) as db:
            return _withdrew_in(db, p.pk)

    def session_state(self, p: Participant) -> dict[str, Any]:
        answered = self.answered(p)
        study = self.study_of(p)
        timeline, clips = study.timeline_json(p.participant, answered, session=p.session)
        planned = study.planned(p.participant)
        withdrawn = p.completed is None and self.withdrew(p)
        if withdrawn:  # only the sickness questionnaire after (if asked), on the plain page
            timeline = [s for s in timeline if s["kind"] == "ssq"
                        and str(s.get("item", "")).startswith("ssq_after_")]  # fmt: skip
            clips = []
        elif answered and p.completed is None:  # a page reload or a return: logged as a resume
            # the first trial still to answer, in the order shown (the questionnaire's trial 0
            # comes last when it follows the trials)
            left = [key[0] for key in study.planned_in_order(p.participant)
                    if key not in answered]  # fmt: skip
            with self._writes, Session(self.engine) as db:
                detail = {"answered": len(answered & planned),
                          "first_trial": left[0] if left else None}  # fmt: skip
                db.add(Event(participant_pk=p.pk, kind="resumed", detail=detail))
                db.commit()
        pres = study.protocol.presentation
        return {
            "study": self.study.study,
            "participant": p.participant,
            "language": pres.language,
            "fullscreen": pres.fullscreen and not withdrawn,
            "display": "video" if withdrawn else pres.display,
            **(
                {
                    "scene": self.config.live.scene_json(),
                    "vr": pres.vr.model_dump(),
                }
                if self.config.live is not None and not withdrawn
                else {}
            ),
            "withdrawn": withdrawn,
            "complete": p.completed is not None,
            "consent": self.config.consent or "",
            "resumed": bool(answered),
            "planned": len(planned),
            "answered": len(answered & planned),
            "clips": clips,
            "timeline": timeline,
            "plugins": sorted(
                {f"/plugins/{s['kind']}.js" for s in timeline if _own_plugin(s["kind"])}
            ),
        }

    def store_answer(self, p: Participant, answer: AnswerIn) -> dict[str, Any]:
        values = answer.model_dump()
        try:
            when = dt.datetime.fromisoformat(answer.timestamp.replace("Z", "+00:00"))
            if not 2000 <= when.year <= 2200:
                raise ValueError("out of range")
            stamp = when.astimezone(dt.UTC).isoformat(timespec="milliseconds")
        except (ValueError, OverflowError):
            raise RefusedError(
                422,
                f"timestamp: expected an ISO 8601 time between the years 2000 and 2200, got "
                f"{answer.timestamp!r}",
            ) from None
        playback = (
            None
            if answer.clip_onset is None
            else Playback(onset=answer.clip_onset, dropped=answer.clip_frames_dropped or 0)
        )
        try:
            row = self.study_of(p).row(
                participant=p.participant,
                session=p.session,
                simulated=p.simulated,
                answer=values,
                playback=playback,
                timestamp=stamp,
                logged=lambda: self.logged(p),
            )
        except AnswerError as exc:
            raise RefusedError(422, str(exc)) from None
        with Session(self.engine) as db:  # insert first: the common case is one query
            db.add(
                Response(
                    participant_pk=p.pk,
                    trial_index=answer.trial_index,
                    item=answer.item,
                    client_key=answer.client_key,
                    row=row,
                    received=utcnow(),
                )
            )
            try:
                with self._writes:
                    db.commit()
            except IntegrityError:  # stored before (a replay or a conflict), or a reused key
                db.rollback()
                same = self._stored(db, p, answer, row)
                if same is not None:
                    return same
                raise RefusedError(409, "this response conflicts with a stored one") from None
        done = self._maybe_complete(p)
        return {"stored": True, "replay": False, "complete": done}

    @staticmethod
    def _last_seen(db: Session, p: Participant) -> dt.datetime:
        """The participant's latest stored answer, playback record or event (or joining)."""
        times = [p.created]
        for column, key in (
            (Response.received, Response.participant_pk),
            (PlaybackRecord.received, PlaybackRecord.participant_pk),
            (Event.at, Event.participant_pk),
        ):
            latest = db.scalar(select(func.max(column)).where(key == p.pk))
            if latest is not None:
                times.append(latest)
        return max(t if t.tzinfo else t.replace(tzinfo=dt.UTC) for t in times)

    @staticmethod
    def _value(row: dict[str, Any]) -> Any:
        return row["rating"] if row.get("rating") is not None else row.get("response")

    def _stored(
        self, db: Session, p: Participant, answer: AnswerIn, row: dict[str, Any]
    ) -> dict[str, Any] | None:
        """A replay's answer (200: the same key and value again), or RefusedError(409); None
        if new. No answer tells anything about the stored value: a new key for an answered
        trial and item is refused alike whatever its value (else guessing values until one is
        "a replay" would read a stored answer), and a stored key with another value is a
        conflict."""
        old = db.scalars(
            select(Response).where(
                Response.participant_pk == p.pk,
                Response.trial_index == answer.trial_index,
                Response.item == answer.item,
            )
        ).first()
        if old is None:
            other = db.scalars(select(Response).where(Response.client_key == answer.client_key))
            if other.first() is not None:
                raise RefusedError(409, "client_key was already used for another response")
            return None
        if old.client_key == answer.client_key:
            if _same(self._value(old.row), self._value(row)):
                return {"stored": True, "replay": True, "complete": self._maybe_complete(p)}
            raise RefusedError(
                409, "client_key: this key was stored with another answer; it is kept and "
                "this one is refused",
            )  # fmt: skip
        # the stored value is never compared, nor shown: one refusal for every value
        raise RefusedError(
            409,
            f"trial {answer.trial_index} item {answer.item!r} is answered already; the stored "
            "answer is kept and this one is refused",
        )

    def _maybe_complete(self, p: Participant) -> bool:
        planned = len(self.study_of(p).planned(p.participant))
        with self._writes, Session(self.engine) as db:  # stored rows are planned ones
            count = db.scalar(select(func.count()).where(Response.participant_pk == p.pk))
            if (count or 0) < planned:
                return False
            fresh = db.get(Participant, p.pk)
            assert fresh is not None
            # stopped: never completed afterwards (asked in this transaction, under the lock)
            if fresh.completed is None and _withdrew_in(db, p.pk):
                return False
            if fresh.completed is None:
                fresh.completed = utcnow()
                db.add(Event(participant_pk=p.pk, kind="completed", detail={}))
                db.commit()
        return True

    def _clip_seconds(self, p: Participant, rendered: str) -> float:
        """The duration of one of the participant's clips (by the rendered file's hash)."""
        study = self.study_of(p)
        return max((float(ref.duration_s) for ref in study.clips.values()
                    if ref.sha256 == rendered), default=0.0)  # fmt: skip

    def _trial_indices(self, p: Participant) -> set[int]:
        """The trial indices of the participant's design (their answers' and clips')."""
        return {t for t, _ in self.study_of(p).planned(p.participant)}

    def store_playback(self, p: Participant, record: PlaybackIn) -> dict[str, Any]:
        known = set(p.clips.values())
        rendered = self.served.original.get(record.clip, record.clip[:-4])
        if rendered not in known:
            raise RefusedError(422, f"clip: {record.clip} is not one of this participant's clips")
        served_as = {"served_as": record.clip} if rendered != record.clip[:-4] else {}
        stored = record.model_dump(exclude={"client_key"}) | {"clip": rendered + ".mp4"}
        stored |= served_as
        size = len(json.dumps(stored, separators=(",", ":")))
        limit = PLAYBACK_BYTES_BASE + PLAYBACK_BYTES_PER_CLIP_S * self._clip_seconds(p, rendered)
        if size > limit:
            raise RefusedError(413, f"playback record of {size} bytes; a clip of this length "
                               f"records at most {int(limit)}")  # fmt: skip
        with Session(self.engine) as db:
            if db.scalars(
                select(PlaybackRecord).where(PlaybackRecord.client_key == record.client_key)
            ).first():
                return {"stored": True, "replay": True}
            total = db.scalar(
                select(func.coalesce(func.sum(PlaybackRecord.bytes), 0)).where(
                    PlaybackRecord.participant_pk == p.pk
                )
            ) or 0
            if total + size > PLAYBACK_BYTES_PER_SESSION:
                raise RefusedError(413, f"this session's playback records reached "
                                   f"{PLAYBACK_BYTES_PER_SESSION} bytes")  # fmt: skip
            if record.trial_index is not None and record.trial_index not in self._trial_indices(p):
                raise RefusedError(422, f"trial_index: {record.trial_index} is not one of this "
                                   "participant's trials")  # fmt: skip
            # the practice trial (trial_index null) is capped like any other
            same = (PlaybackRecord.trial_index.is_(None) if record.trial_index is None
                    else PlaybackRecord.trial_index == record.trial_index)  # fmt: skip
            per_trial = db.scalar(select(func.count()).where(
                PlaybackRecord.participant_pk == p.pk, same))  # fmt: skip
            if (per_trial or 0) >= PLAYBACK_RECORDS_PER_TRIAL:
                raise RefusedError(
                    413, f"trial {record.trial_index} has {PLAYBACK_RECORDS_PER_TRIAL} "
                    "playback records already",
                )  # fmt: skip
            db.add(
                PlaybackRecord(
                    participant_pk=p.pk,
                    client_key=record.client_key,
                    # the rendered clip's hash, as the lab logs it (and the copy shown)
                    record=stored,
                    received=utcnow(),
                    trial_index=record.trial_index,
                    bytes=size,
                )
            )
            return self._commit_keyed(db)

    def _commit_keyed(self, db: Session) -> dict[str, Any]:
        """Commit a record stored under its client key: a second store of the same key that
        raced this one is a replay, not an error."""
        try:
            with self._writes:
                db.commit()
        except IntegrityError:
            db.rollback()
            return {"stored": True, "replay": True}
        return {"stored": True, "replay": False}

    def store_screen_poses(self, p: Participant, record: ScreenPosesIn) -> dict[str, Any]:
        """Keep one VR screen's poses (idempotent by client key), capped per session."""
        if record.trial_index not in (None, 0) and record.trial_index not in self._trial_indices(p):
            raise RefusedError(422, f"trial_index: {record.trial_index} is not one of this "
                               "participant's trials")  # fmt: skip
        stored = record.model_dump(exclude={"client_key"})
        if not _finite(stored):
            raise RefusedError(422, "poses: numbers must be finite (no NaN or Infinity)")
        size = len(json.dumps(stored, separators=(",", ":")))
        with Session(self.engine) as db:
            if db.scalars(select(ScreenPoses).where(
                    ScreenPoses.client_key == record.client_key)).first():  # fmt: skip
                return {"stored": True, "replay": True}
            count, total = db.execute(
                select(func.count(), func.coalesce(func.sum(ScreenPoses.bytes), 0)).where(
                    ScreenPoses.participant_pk == p.pk)).one()  # fmt: skip
            if count >= SCREEN_POSES_PER_SESSION or total + size > SCREEN_POSES_BYTES_PER_SESSION:
                raise RefusedError(413, f"this session stored {count} screens' poses "
                                   f"({total} bytes) already")  # fmt: skip
            db.add(ScreenPoses(participant_pk=p.pk, client_key=record.client_key,
                               record=stored, bytes=size, received=utcnow()))  # fmt: skip
            return self._commit_keyed(db)

    def store_event(self, p: Participant, ev: EventIn) -> None:
        if len(repr(ev.detail)) > 4000:
            raise RefusedError(422, "detail: too large (at most 4000 characters)")
        if not _finite(ev.detail):
            raise RefusedError(422, "detail: numbers must be finite (no NaN or Infinity)")
        size = len(json.dumps(ev.detail, separators=(",", ":")))
        with self._writes, Session(self.engine) as db:
            count = db.scalar(select(func.count()).where(  # what this session posted
                Event.participant_pk == p.pk, Event.bytes.is_not(None))) or 0  # fmt: skip
            if count >= EVENTS_PER_SESSION and ev.kind != "withdrawn":  # a stop always counts
                raise RefusedError(413, f"this session has {EVENTS_PER_SESSION} events already")
            if ev.kind == "browser":
                fresh = db.get(Participant, p.pk)
                assert fresh is not None
                fresh.browser = ev.detail
            db.add(Event(participant_pk=p.pk, kind=ev.kind, detail=ev.detail, bytes=size))
            db.commit()

    def completion(self, p: Participant) -> dict[str, Any]:
        if p.completed is None and self.withdrew(p):
            raise RefusedError(409, "this session was stopped by the participant: it has no "
                               "completion code")  # fmt: skip
        planned = self.study_of(p).planned(p.participant)
        missing = planned - self.answered(p)
        if missing:
            raise RefusedError(
                409, f"{len(missing)} of {len(planned)} responses are not stored yet"
            )
        self._maybe_complete(p)
        return {
            "complete": True,
            "code": self.config.completion_code,
            "redirect": self.config.completion_url,
        }

    def progress(self) -> list[dict[str, Any]]:
        planned_n = {}
        with Session(self.engine) as db:
            counts = dict(
                db.execute(
                    select(Response.participant_pk, func.count()).group_by(Response.participant_pk)
                ).all()
            )
            people = db.scalars(
                select(Participant)
                .where(Participant.study == self.study.study)
                .order_by(Participant.number)
            ).all()
            pks = [p.pk for p in people]
            stored_bytes = dict(db.execute(
                select(PlaybackRecord.participant_pk,
                       func.coalesce(func.sum(PlaybackRecord.bytes), 0))
                .group_by(PlaybackRecord.participant_pk)
            ).all())  # fmt: skip
            event_counts = dict(db.execute(
                select(Event.participant_pk, func.count()).group_by(Event.participant_pk)
            ).all())  # fmt: skip
            full_trials = {pk for pk, in db.execute(
                select(PlaybackRecord.participant_pk)
                .where(PlaybackRecord.trial_index.is_not(None))
                .group_by(PlaybackRecord.participant_pk, PlaybackRecord.trial_index)
                .having(func.count() >= PLAYBACK_RECORDS_PER_TRIAL)
            ).all()}  # fmt: skip
            withdrawn = set(db.scalars(select(Event.participant_pk).where(
                Event.kind == "withdrawn", Event.participant_pk.in_(pks))))  # fmt: skip
            errors: dict[int, list[dict[str, Any]]] = {}
            for e in db.scalars(
                select(Event).where(Event.kind == "error", Event.participant_pk.in_(pks))
            ):
                errors.setdefault(e.participant_pk, []).append(dict(e.detail or {}))
        out = []
        for p in people:
            version = self._version(p.protocol_sha256)
            if p.participant not in planned_n:
                planned_n[p.participant] = (
                    len(version.planned(p.participant)) if not isinstance(version, str) else 0
                )
            stored = self.answered(p) if p.pk in errors else set()
            held = [
                d for d in errors.get(p.pk, [])
                if d.get("held") == "/api/response"
                and (d.get("trial_index"), d.get("item")) not in stored
            ]  # fmt: skip
            out.append(
                {
                    "participant": p.participant,
                    "simulated": p.simulated,
                    "source": p.recruitment_source,
                    "responses": counts.get(p.pk, 0),
                    "planned": planned_n[p.participant],
                    "started": p.created.isoformat() if p.created else None,
                    "completed": p.completed.isoformat() if p.completed else None,
                    # stopped from the page before it was complete (one rule: a stopped
                    # session is never completed, a Stop after completion does not count)
                    "withdrawn": p.pk in withdrawn and p.completed is None,
                    # the protocol version the session runs: "current", "earlier <sha12>",
                    # or why it cannot be served
                    "protocol": f"cannot be served: {version}"
                    if isinstance(version, str)
                    else (
                        "current"
                        if p.protocol_sha256 == self.study.protocol_sha256
                        else f"earlier {p.protocol_sha256[:12]}"
                    ),
                    # answers the server refused that the browser holds (and retries), why
                    "held": len(held),
                    "held_why": held[-1].get("why") if held else None,
                    # the end page waited over its limit with answers unsaved
                    "stuck": p.completed is None
                    and any(d.get("what") == "end page" for d in errors.get(p.pk, [])),
                    # what the session stored besides answers, and a cap it reached (413s)
                    "stored_kb": round(stored_bytes.get(p.pk, 0) / 1000, 1),
                    "at_cap": _at_cap(
                        stored_bytes.get(p.pk, 0), event_counts.get(p.pk, 0),
                        p.pk in full_trials,
                    ),
                }
            )
        return out


def _at_cap(playback_bytes: int, events: int, full_trial: bool) -> str | None:
    """Which storage cap a session reached (its further records are refused with 413)."""
    if playback_bytes >= 0.95 * PLAYBACK_BYTES_PER_SESSION:
        return "playback bytes"
    if events >= EVENTS_PER_SESSION:
        return "events"
    return "playback records of a trial" if full_trial else None


def _finite(value: Any) -> bool:
    """No NaN or infinity anywhere in a JSON value."""
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, dict):
        return all(_finite(v) for v in value.values())
    if isinstance(value, list):
        return all(_finite(v) for v in value)
    return True


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, int | float) and isinstance(b, int | float):
        return abs(float(a) - float(b)) < 1e-9
    return a == b
