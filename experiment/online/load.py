"""The online server under load: many participants posting answers at once.

:func:`load_test` starts ``facelab serve`` in a child process on 127.0.0.1 (the real server,
its own interpreter), makes N participants in the database, and lets N asyncio clients post
every planned answer of their sessions concurrently - each answer once, and a share of them
a second time with the same idempotency key (a retry after a lost reply). It reports the
latency of the first posts (p50/p99/max, ms), the requests per second, and what the database
holds afterwards: rows lost (planned but not stored) and rows duplicated (stored twice).

:func:`postgres_cluster` starts a throw-away PostgreSQL (Debian's ``postgresql`` binaries)
in a temporary folder, for the load test and the tests.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from facelab.errors import SessionError
from facelab.experiment.online.db import Participant, Response
from facelab.experiment.online.serve import free_port, prepare_server
from facelab.protocol import load_protocol

__all__ = ["load_test", "postgres_cluster", "start_server", "wait_for_server"]

PG_BIN = Path("/usr/lib/postgresql/15/bin")


def wait_for_server(url: str, *, timeout_s: float = 60.0) -> None:
    import httpx2 as httpx

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            if httpx.get(url + "/", timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    raise SessionError(f"the server at {url} did not answer within {timeout_s} s")


def start_server(
    protocol: Path, *, clips: Path, db_url: str, port: int, results: Path
) -> subprocess.Popen[bytes]:
    """``facelab serve`` in a child process (its own session, so it can be SIGKILLed)."""
    exe = Path(sys.executable).with_name("facelab")
    cmd = [str(exe), "serve", str(protocol), "--clips", str(clips), "--db", db_url,
           "--port", str(port), "--results", str(results)]  # fmt: skip
    env = {**os.environ, "FACELAB_ADMIN_SECRET": os.environ.get("FACELAB_ADMIN_SECRET", "x" * 24)}
    return subprocess.Popen(
        cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True
    )


@contextlib.contextmanager
def postgres_cluster() -> Iterator[str]:
    """A PostgreSQL 15 server in a temporary folder; yields its SQLAlchemy URL."""
    if not (PG_BIN / "initdb").exists():
        raise SessionError("PostgreSQL is not installed (apt-get install postgresql)")
    folder = Path(tempfile.mkdtemp(prefix="facelab-pg-"))
    data = folder / "data"
    prefix: list[str] = []
    if os.geteuid() == 0:  # initdb refuses to run as root: use Debian's postgres user
        if shutil.which("runuser") is None:
            raise SessionError("running as root without runuser: cannot start PostgreSQL")
        shutil.chown(folder, "postgres", "postgres")
        prefix = ["runuser", "-u", "postgres", "--"]
    port = free_port()
    subprocess.run(
        [*prefix, str(PG_BIN / "initdb"), "-D", str(data), "-A", "trust", "-U", "facelab"],
        check=True,
        capture_output=True,
    )
    options = f"-p {port} -k {folder} -c listen_addresses=127.0.0.1 -c max_connections=300"
    subprocess.run(
        [*prefix, str(PG_BIN / "pg_ctl"), "-D", str(data), "-o", options, "-w", "-l",
         str(folder / "log"), "start"],
        check=True,
        capture_output=True,
    )  # fmt: skip
    try:
        yield f"postgresql+psycopg://facelab@127.0.0.1:{port}/postgres"
    finally:
        subprocess.run(
            [*prefix, str(PG_BIN / "pg_ctl"), "-D", str(data), "-m", "immediate", "stop"],
            check=False,
            capture_output=True,
        )
        shutil.rmtree(folder, ignore_errors=True)


def _answers(study: Any, participant: str, rng: np.random.Generator) -> list[dict[str, Any]]:
    """Every planned answer of one participant, in timeline order, as the browser posts it
    (a simulated participant answers each response screen; the screen gives the posted form)."""
    from facelab.experiment.simulate import ChoiceModel, RatingModel, SimulatedParticipant

    protocol = study.protocol
    sim = SimulatedParticipant(
        RatingModel(protocol, rng=rng),
        ChoiceModel(protocol, rng=rng) if protocol.tasks else None,
    )
    out = []
    for s in study.screens(participant):
        if not s.response_keys():
            continue
        base = {"trial_index": s.trial_index, "rt_s": 1.0, "clip_onset": 1.0,
                "clip_frames_dropped": 0}  # fmt: skip
        for answer in s.present(sim):
            out.append({**base, "item": s.answer_item(answer), **s.posted(answer)})
    return out


async def _drive(url: str, people: list[tuple[str, str]], study: Any, seed: int) -> dict[str, Any]:
    import httpx2 as httpx

    latencies: list[float] = []
    failures: list[str] = []
    limits = httpx.Limits(max_connections=len(people), max_keepalive_connections=len(people))
    async with httpx.AsyncClient(base_url=url, timeout=60, limits=limits) as client:

        async def one(k: int, pid: str, token: str) -> None:
            rng = np.random.default_rng([seed, k])
            headers = {"X-Facelab-Token": token}
            for n, answer in enumerate(_answers(study, pid, rng)):
                body = {**answer, "client_key": f"load{k:05d}x{n:05d}",
                        "timestamp": "2026-01-01T00:00:00.000Z"}  # fmt: skip
                for attempt in range(5):
                    t0 = time.perf_counter()
                    try:
                        r = await client.post("/api/response", json=body, headers=headers)
                    except httpx.HTTPError as exc:
                        failures.append(f"{pid}: {exc!r}")
                        await asyncio.sleep(0.5 * (attempt + 1))
                        continue
                    if attempt == 0:
                        latencies.append(time.perf_counter() - t0)
                    if r.status_code == 200:
                        break
                    failures.append(f"{pid}: HTTP {r.status_code} {r.text[:200]}")
                    await asyncio.sleep(0.5 * (attempt + 1))
                if rng.random() < 0.05:  # a retry after a lost reply: must be harmless
                    r = await client.post("/api/response", json=body, headers=headers)
                    if r.status_code != 200 or not r.json().get("replay"):
                        failures.append(f"{pid}: replay answered {r.status_code} {r.text[:200]}")

        t0 = time.perf_counter()
        await asyncio.gather(*(one(k, pid, tok) for k, (pid, tok) in enumerate(people)))
        wall = time.perf_counter() - t0
    ms = np.array(latencies) * 1000
    return {
        "requests": len(latencies),
        "wall_s": round(wall, 2),
        "requests_per_s": round(len(latencies) / wall, 1),
        "latency_ms": {
            "p50": round(float(np.percentile(ms, 50)), 1),
            "p99": round(float(np.percentile(ms, 99)), 1),
            "max": round(float(ms.max()), 1),
        },
        "failures": failures[:10],
        "failure_count": len(failures),
    }


def load_test(
    *,
    protocol_path: Path,
    clips: Path,
    db_url: str,
    participants: int = 200,
    seed: int = 1,
    results: Path,
) -> dict[str, Any]:
    """Run the load test (see the module docstring); returns the figures as a dict."""
    protocol = load_protocol(protocol_path)
    server, _ = prepare_server(
        protocol, protocol_path=protocol_path, clips_dir=clips, db_url=db_url, results=results
    )
    people = []
    for _ in range(participants):
        p, token = server.join(recruitment=None, source="load-test")
        people.append((p.participant, token))
    port = free_port()
    proc = start_server(protocol_path, clips=clips, db_url=db_url, port=port, results=results)
    try:
        wait_for_server(f"http://127.0.0.1:{port}")
        figures = asyncio.run(_drive(f"http://127.0.0.1:{port}", people, server.study, seed))
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)
    planned = {pid: len(server.study.planned(pid)) for pid, _ in people}
    with Session(server.engine) as db:
        stored = dict(
            db.execute(
                select(Participant.participant, func.count(Response.pk))
                .join(Response, Response.participant_pk == Participant.pk)
                .where(Participant.recruitment_source == "load-test")
                .group_by(Participant.participant)
            ).all()
        )
        distinct = db.scalar(
            select(func.count()).select_from(
                select(Response.participant_pk, Response.trial_index, Response.item)
                .distinct()
                .subquery()
            )
        )
        total = db.scalar(select(func.count(Response.pk)))
    lost = sum(max(0, n - stored.get(pid, 0)) for pid, n in planned.items())
    database = "postgresql" if db_url.startswith("postgresql") else "sqlite"
    return {
        "database": database,
        "participants": participants,
        "responses_planned": sum(planned.values()),
        "responses_stored": int(sum(stored.values())),
        "lost": int(lost),
        "duplicated": int((total or 0) - (distinct or 0)),
        **figures,
    }
