"""The HTTP routes of ``facelab serve`` over a ``StudyServer`` (the table of routes and what
each does is in :mod:`facelab.experiment.online.server`)."""

from __future__ import annotations

import html
import re
import urllib.parse
from typing import Any

from fastapi import FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from facelab.experiment.online.api_models import AnswerIn, EventIn, PlaybackIn, ScreenPosesIn
from facelab.experiment.online.middleware import IMPORT_MAP, SecurityHeaders
from facelab.experiment.online.server import (
    ADMIN_HEADER,
    EARLIER_TOKEN_HEADER,
    RECRUITMENT_PARAMS,
    THREE_FILES,
    TOKEN_HEADER,
    VENDOR_FILES,
    WEB,
    InUseError,
    RefusedError,
    StudyServer,
    _own_plugin,
)

__all__ = ["JOIN_WORDS", "create_app"]

#: the recruitment link's page and its refusal, in the study's language (English otherwise)
JOIN_WORDS = {
    "ja": {
        "title": "実験への参加",
        "intro": "募集サイトのリンクから来られた方は、下のボタンで実験を始めてください。",
        "start": "実験を始める",
        "busy": "ただいま参加の受付が混み合っています。1分ほど待ってから、もう一度お試しください。",
        "in_use": "このリンクは今は開けません。別の画面やブラウザーで実験を始めている場合は、"
        "その画面で続けてください。そうでない場合は、{minutes}分後にもう一度このリンクを開いて"
        "ください。",
    },
    "en": {
        "title": "Study",
        "intro": "If you came through your recruitment platform's link, start the study below.",
        "start": "Start the session",
        "busy": "Many people are joining right now. Please wait a minute and try again.",
        "in_use": "This link cannot be opened right now. If you started the study in another "
        "window or browser, please continue there; otherwise open this link again in "
        "{minutes} minutes.",
    },
}


def client_address(request: Request) -> str:
    """The client's address (a trusted proxy's X-Forwarded-For already applied by uvicorn)."""
    return request.client.host if request.client else "?"


def create_app(server: StudyServer) -> Any:
    """The FastAPI application of ``server`` (wrapped in the security-header middleware)."""
    app = FastAPI(title="facelab serve", docs_url=None, redoc_url=None, openapi_url=None)
    config = server.config

    @app.exception_handler(RefusedError)
    async def refused(_request: Request, exc: RefusedError) -> JSONResponse:
        return JSONResponse({"error": exc.message}, status_code=exc.status)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(_request: Request, exc: StarletteHTTPException) -> JSONResponse:
        # the framework's own refusals (a body that does not parse, a wrong method) in
        # facelab's shape, {"error": ...}
        text = exc.detail if isinstance(exc.detail, str) else "request refused"
        return JSONResponse({"error": text}, status_code=exc.status_code,
                            headers=getattr(exc, "headers", None))  # fmt: skip

    @app.exception_handler(RequestValidationError)
    async def invalid(_request: Request, exc: RequestValidationError) -> JSONResponse:
        problems = [
            str(e.get("msg", "")).removeprefix("Value error, ")
            if e.get("type") == "value_error" and len(e.get("loc", ())) <= 1
            else f"{'.'.join(str(x) for x in e.get('loc', ())[1:]) or 'body'}: {e.get('msg')}"
            for e in exc.errors()
        ]
        return JSONResponse({"error": "; ".join(problems)}, status_code=422)

    def page(name: str) -> HTMLResponse:
        return HTMLResponse((WEB / name).read_text(encoding="utf-8"))

    lang = server.study.protocol.presentation.language
    words = JOIN_WORDS.get(lang, JOIN_WORDS["en"])

    def recruitment_of(request: Request) -> tuple[str | None, str | None]:
        for param, name in RECRUITMENT_PARAMS.items():
            value = request.query_params.get(param)
            if value:
                if len(value) > 128:
                    raise RefusedError(422, f"{param}: at most 128 characters")
                return value, name
        return None, None

    @app.get("/join")
    def join_page(request: Request) -> HTMLResponse:
        """The recruitment link's page: nothing is created by looking at it (link previews,
        crawlers); the participant's button posts to the same address."""
        recruitment_of(request)  # an over-long id is refused now, not after the click
        action = "/join" + (f"?{request.url.query}" if request.url.query else "")
        return study_page(
            # the form's POST must carry this page's Origin (no-referrer would send "null")
            head='<meta name="referrer" content="same-origin">'
            '<meta name="robots" content="noindex">',
            body=f"<h1>{words['title']}</h1><p>{words['intro']}</p>"
            f'<form method="post" action="{html.escape(action, quote=True)}">'
            '<input type="hidden" name="previous_token" value="">'
            f'<button type="submit" data-facelab="join">{words["start"]}</button></form>'
            '<script src="/static/join.js"></script>',
        )

    def study_page(*, body: str, head: str = "", status: int = 200, **headers: str) -> HTMLResponse:
        """A page of the join flow in the study's language (never cached)."""
        return HTMLResponse(
            f'<!doctype html><html lang="{html.escape(lang)}"><head><meta charset="utf-8">{head}'
            f'<title>{words["title"]}</title><link rel="stylesheet" href="/static/facelab.css">'
            f'</head><body><main class="facelab-page">{body}</main></body></html>',
            status_code=status,
            headers={"Cache-Control": "no-store", **headers},
        )

    @app.post("/join", response_model=None)
    async def join(request: Request) -> RedirectResponse | HTMLResponse:
        """A new participant (or the returning one): only this deliberate POST creates one
        and takes a Latin-square slot. The form carries the token this browser holds, if
        any (a returning participant's session comes back under it)."""
        if not server.join_limiter.allow(client_address(request)):
            return study_page(body=f"<p>{words['busy']}</p>", status=429, **{"Retry-After": "60"})
        recruitment, source = recruitment_of(request)
        form = urllib.parse.parse_qs((await request.body()).decode("utf-8", "replace"))
        previous = (form.get("previous_token") or [""])[0]
        previous = previous if re.fullmatch(r"[A-Za-z0-9_-]{20,128}", previous) else None
        try:
            _p, token = await run_in_threadpool(
                server.join, recruitment=recruitment, source=source, previous_token=previous
            )
        except InUseError:
            # worded (and answered with 200) so that trying someone's id tells nothing about
            # whether that person is taking part
            minutes = round(server.config.rejoin_idle_s / 60)
            return study_page(body=f"<p>{words['in_use'].format(minutes=minutes)}</p>")
        # the token rides in the fragment of this redirect: never cached
        return RedirectResponse(f"/run#t={token}", status_code=303,
                                headers={"Cache-Control": "no-store"})  # fmt: skip

    @app.get("/")
    def index() -> HTMLResponse:
        return page("join.html")

    @app.get("/favicon.ico")
    def favicon() -> Any:
        from fastapi.responses import Response as Empty

        return Empty(status_code=204)

    @app.get("/run")
    def run() -> HTMLResponse:
        text = (WEB / "run.html").read_text(encoding="utf-8")
        return HTMLResponse(
            text.replace(
                "<!--facelab-importmap-->", f'<script type="importmap">{IMPORT_MAP}</script>'
            )
        )

    @app.get("/admin")
    def admin() -> HTMLResponse:
        return page("admin.html")

    # the page assets, listed once: a request names one of them or gets 404 (the name never
    # reaches the file system, so no path trick or over-long name can)
    assets = {p.name: p for p in (WEB / "static").iterdir() if p.is_file()}

    @app.get("/plugins/{name}")
    def plugin(name: str) -> FileResponse:
        """The jsPsych plugin of a screen kind added to facelab (``Screen.plugin_js``)."""
        path = _own_plugin(name.removesuffix(".js")) if name.endswith(".js") else None
        if path is None or not path.is_file():
            raise RefusedError(404, "no such plugin")
        return FileResponse(path, media_type="text/javascript")

    @app.get("/static/{name}")
    def static(name: str) -> FileResponse:
        if name not in assets:
            raise RefusedError(404, "not found")
        return FileResponse(assets[name])

    @app.get("/vendor/{name}")
    def vendor(name: str) -> FileResponse:
        rel = VENDOR_FILES.get(name)
        if rel is None or not (config.vendor / rel).is_file():
            raise RefusedError(404, "not found")
        return FileResponse(config.vendor / rel)

    three = {rel: config.vendor / "three" / rel for rel in THREE_FILES}

    @app.get("/vendor/three/{rel:path}")
    def vendor_three(rel: str) -> FileResponse:
        """three.js for the live 3D and VR views (only the files they import)."""
        if rel not in three or not three[rel].is_file():
            raise RefusedError(404, "not found")
        return FileResponse(three[rel], media_type="text/javascript")

    live = config.live

    @app.get("/avatar/{name}")
    def avatar(name: str) -> Any:
        """The avatar the live views draw (by its hash; only with display live3d/webxr)."""
        from fastapi.responses import Response as Raw

        if live is None or name != live.avatar_name:
            raise RefusedError(404, "not found")
        return Raw(live.avatar_glb, media_type="model/gltf-binary")

    @app.get("/tracks/{name}")
    def track(name: str) -> FileResponse:
        """A clip's animation track by its hash (never by its condition)."""
        path = live.tracks.get(name) if live is not None else None
        if path is None:
            raise RefusedError(404, "not found")
        response = FileResponse(path, media_type="application/octet-stream")
        for header in ("last-modified", "etag"):  # see /clips: no render order revealed
            if header in response.headers:
                del response.headers[header]
        return response

    @app.get("/clips/{name}")
    def clip(name: str) -> FileResponse:
        path = config.clip_paths.get(name)
        if path is None:
            raise RefusedError(404, "not found")
        response = FileResponse(path, media_type="video/mp4", stat_result=path.stat())
        # a file's time (and an ETag made from it) would order the clips as they were rendered
        # and so reveal their conditions: neither is sent
        for header in ("last-modified", "etag"):
            if header in response.headers:
                del response.headers[header]
        return response

    @app.get("/api/session")
    def session(request: Request) -> dict[str, Any]:
        p = server.participant(request.headers.get(TOKEN_HEADER))
        return server.session_state(p)

    @app.get("/api/adaptive/{trial_index}")
    def adaptive(request: Request, trial_index: int) -> dict[str, Any]:
        p = server.participant(request.headers.get(TOKEN_HEADER))
        return server.adaptive(p, trial_index)

    @app.post("/api/response")
    def response(request: Request, answer: AnswerIn) -> dict[str, Any]:
        p = server.participant(request.headers.get(TOKEN_HEADER))
        server.check_earlier_token(p, request.headers.get(EARLIER_TOKEN_HEADER))
        return server.store_answer(p, answer)

    @app.post("/api/playback")
    def playback(request: Request, record: PlaybackIn) -> dict[str, Any]:
        p = server.participant(request.headers.get(TOKEN_HEADER))
        server.check_earlier_token(p, request.headers.get(EARLIER_TOKEN_HEADER))
        return server.store_playback(p, record)

    @app.post("/api/screen_poses")
    def screen_poses(request: Request, record: ScreenPosesIn) -> dict[str, Any]:
        p = server.participant(request.headers.get(TOKEN_HEADER))
        server.check_earlier_token(p, request.headers.get(EARLIER_TOKEN_HEADER))
        return server.store_screen_poses(p, record)

    @app.post("/api/event")
    def event(request: Request, ev: EventIn) -> dict[str, Any]:
        p = server.participant(request.headers.get(TOKEN_HEADER))
        server.store_event(p, ev)
        return {"stored": True}

    @app.get("/api/complete")
    def complete(request: Request) -> dict[str, Any]:
        p = server.participant(request.headers.get(TOKEN_HEADER))
        return server.completion(p)

    @app.get("/api/admin/progress")
    def progress(request: Request) -> dict[str, Any]:
        server.check_admin(request.headers.get(ADMIN_HEADER), address=client_address(request))
        return {"study": server.study.study, "participants": server.progress()}

    for add in config.routes:  # routes of their own (a live conversation's)
        add(app, server)
    return SecurityHeaders(app)
