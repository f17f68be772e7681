"""``facelab export``: the online database as the lab runner's session files.

For every participant with at least one stored response::

    <results>/<study>/sub-<ID>/ses-1/sub-<ID>_ses-1_task-<study>_beh.tsv       (same columns)
                                     …_session.json   (mode: online, browser, recruitment
                                                       source; no recruitment id, no token)
                                     …_playback.jsonl (the browser's frame records)
                                     …_actions.jsonl  (simulated participants only)
                                     …_staircase.jsonl (staircase blocks)
    <results>/<study>/protocol-<sha256[:12]>.yaml   the protocol file the sessions ran

so ``facelab analyze`` reads online and lab sessions side by side. The server keeps the bytes
of every protocol file it serves (``protocols`` table); the staircase record - every step of
every staircase, as the lab runner writes it - is replayed under the protocol the session
ran (same SHA-256) from the stored answers, exactly as the server chose each level, and
marked ``"rebuilt": true``. ``facelab export --protocol P`` supplies the file when the
database does not hold it (made before it kept protocols) or when the stored copy does not
load on its own (it names files beside the original).

Exporting again adds what arrived since (rows are appended through
:class:`~facelab.sessionlog.SessionLog`, never rewritten); a session folder whose rows
disagree with the database is an error.
"""

from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session

from facelab.errors import ProtocolError, SessionError, StageError
from facelab.experiment.adaptive import Staircases
from facelab.experiment.online.db import (
    Action,
    Event,
    Participant,
    PlaybackRecord,
    ProtocolFile,
    Response,
    ScreenPoses,
)
from facelab.formats import LIVE_PLAYBACK_KEYS
from facelab.protocol import Protocol, load_protocol
from facelab.sessionlog import SessionLog, append_jsonl, fsync_dir, session_paths

__all__ = ["export_sessions"]

#: the keys every record has (the lab's; None where the browser had none)
_LAB_KEYS = (
    "trial_index",
    "clip",
    "replay",
    "onset",
    "frames_expected",
    "dropped",
    "flip_times",
    "frames_shown",
)
#: the keys of an exported record's top level: the lab's, then the live 3D / VR views'
_PLAYBACK_KEYS = (
    *_LAB_KEYS, *LIVE_PLAYBACK_KEYS, "audio_times", "viewer_poses", "controller_poses"
)
#: the fields only the live 3D / VR views fill (left out of a video record's export)
_LIVE_ONLY = frozenset(LIVE_PLAYBACK_KEYS) | {"audio_times", "viewer_poses", "controller_poses"}


def _exported(record: dict[str, Any]) -> dict[str, Any]:
    """A stored playback record as ``_playback.jsonl`` holds it: the lab keys, the live keys
    it filled, and what else the browser sent under ``browser``."""
    rest = {
        k: v
        for k, v in record.items()
        if k not in _LAB_KEYS and not (k in _LIVE_ONLY and v is None)
    }
    return (
        {k: record.get(k) for k in _LAB_KEYS}
        | {k: v for k, v in rest.items() if k in _PLAYBACK_KEYS}
        | {"browser": {k: v for k, v in rest.items() if k not in _PLAYBACK_KEYS}}
    )


_UNWRITABLE = re.compile(r"[\ud800-\udfff\u2028\u2029]")  # (U+2028/9: line breaks to readers)
_UNWRITABLE_TSV = re.compile(r"[\ud800-\udfff\x00-\x1f\x7f\u2028\u2029]")


def escaped(value: Any, *, tsv: bool = False) -> tuple[Any, int]:
    """``value`` (JSON-like) with what no file can hold written as escapes, and how many
    strings changed: lone UTF-16 surrogates (valid JSON, but no UTF-8 text) as ``\\udXXX``
    and, with ``tsv``, control characters (a tab or newline would split a log row) as
    ``\\xNN``. Data stored before the server refused such text at the door is exported
    this way rather than stopping the export."""
    pattern = _UNWRITABLE_TSV if tsv else _UNWRITABLE
    if isinstance(value, str):
        if not pattern.search(value):
            return value, 0
        return pattern.sub(lambda m: f"\\u{ord(m.group()):04x}" if ord(m.group()) > 0xFF
                           else f"\\x{ord(m.group()):02x}", value), 1  # fmt: skip
    if isinstance(value, dict):
        out, n = {}, 0
        for k, v in value.items():
            key, a = escaped(k, tsv=tsv) if isinstance(k, str) else (k, 0)
            out[key], b = escaped(v, tsv=tsv)
            n += a + b
        return out, n
    if isinstance(value, list | tuple):
        pairs = [escaped(v, tsv=tsv) for v in value]
        return [v for v, _ in pairs], sum(n for _, n in pairs)
    return value, 0


def _count_lines(path: Path) -> int:
    if not path.exists():
        return 0
    # records are separated by "\n" only (a U+2028 inside a stored string is not a break)
    return sum(1 for line in path.read_text(encoding="utf-8").split("\n") if line.strip())


def _append_new(path: Path, records: Sequence[dict[str, Any]]) -> int:
    """Append the records beyond those already in the file (both in database order)."""
    have = _count_lines(path)
    for record in records[have:]:
        append_jsonl(path, record)
    return max(0, len(records) - have)


def export_sessions(
    engine: Engine,
    *,
    results: Path,
    study: str | None = None,
    protocol: Protocol | None = None,
    protocol_sha256: str | None = None,
    notes: list[str] | None = None,
    quarantine: list[str] | None = None,
) -> list[Path]:
    """Write or extend the session folders of every participant (of ``study``, or all).

    One participant's data never stops the export of the others: text no file can hold
    (stored before the server refused it) is written escaped, and a session that cannot be
    written at all is skipped; each is a line in ``quarantine`` naming the participant.

    The protocol file each session ran (kept by the server under its SHA-256) is written to
    ``<results>/<study>/protocol-<sha256[:12]>.yaml``, and sessions with staircase blocks get
    their ``_staircase.jsonl`` replayed under it. ``protocol`` (with its file's
    ``protocol_sha256``) is used for the sessions that ran that version - for databases from
    before the server kept protocols, or a protocol whose side files (models, libraries)
    are needed to load it. What could not be done is said in ``notes``."""
    if (protocol is None) != (protocol_sha256 is None):
        raise ValueError("give protocol and protocol_sha256 together")
    if protocol is not None and study is not None and study != protocol.study.id:
        raise SessionError(f"--study {study!r} is not the protocol's study {protocol.study.id!r}")
    notes = notes if notes is not None else []
    quarantine = quarantine if quarantine is not None else []
    known: dict[str, Protocol | None] = {}
    copied: set[str] = set()
    if protocol is not None and protocol_sha256 is not None:
        known[protocol_sha256] = protocol
    out: list[Path] = []
    with Session(engine) as db:
        query = select(Participant).order_by(Participant.study, Participant.number)
        if study is not None:
            query = query.where(Participant.study == study)
        people = db.scalars(query).all()
        if study is not None and not people:
            raise SessionError(f"the database has no participants of study {study!r}")
        for p in people:
            rows = db.scalars(
                select(Response)
                .where(Response.participant_pk == p.pk)
                .order_by(Response.received, Response.pk)
            ).all()
            if not rows:
                continue
            playback = db.scalars(
                select(PlaybackRecord)
                .where(PlaybackRecord.participant_pk == p.pk)
                .order_by(PlaybackRecord.pk)
            ).all()
            actions = db.scalars(
                select(Action).where(Action.participant_pk == p.pk).order_by(Action.pk)
            ).all()
            events = db.scalars(
                select(Event).where(Event.participant_pk == p.pk).order_by(Event.pk)
            ).all()
            poses = db.scalars(
                select(ScreenPoses).where(ScreenPoses.participant_pk == p.pk)
                .order_by(ScreenPoses.pk)
            ).all()  # fmt: skip
            try:
                log, changed = _export_one(p, rows, playback, actions, events, results=results,
                                           screen_poses=poses)  # fmt: skip
            except (UnicodeError, StageError, ValueError, TypeError, RecursionError) as exc:
                quarantine.append(f"study {p.study} participant {p.participant}: not exported "
                                  f"({exc}); the database still holds it")  # fmt: skip
                continue
            if changed:
                quarantine.append(
                    f"study {p.study} participant {p.participant}: {changed} stored text "
                    "field(s) held characters no file can hold (lone surrogates or control "
                    "characters); written escaped (\\uXXXX, \\xNN) - check them"
                )
            out.append(log.paths.tsv)
            if p.protocol_sha256 not in copied:  # once per protocol version
                copied.add(p.protocol_sha256)
                stored = db.get(ProtocolFile, p.protocol_sha256)
                if stored is not None:
                    copy = _write_protocol_copy(stored, results=results)
                    if p.protocol_sha256 not in known:  # --protocol comes first
                        known[p.protocol_sha256] = _load_copy(copy, notes=notes)
                elif p.protocol_sha256 not in known:
                    known[p.protocol_sha256] = None
                    notes.append(
                        f"study {p.study}: the database does not hold protocol "
                        f"{p.protocol_sha256[:12]}… (a database from before the server kept "
                        "protocols): pass --protocol with that file for the staircase records"
                    )
            run = known[p.protocol_sha256]
            if run is not None and any(b.design == "staircase" for b in run.blocks):
                # the steps not yet in the file are added; one that disagrees is an error
                Staircases(run, logged=log.rows, record=log.paths.staircase)
    ran = {p.protocol_sha256 for p in people}
    if protocol_sha256 is not None and protocol_sha256 not in ran:
        notes.append(
            f"--protocol: no exported session ran this version of the file (SHA-256 "
            f"{protocol_sha256[:12]}…); the sessions' own protocols were used"
        )
    return out


def _write_protocol_copy(stored: ProtocolFile, *, results: Path) -> Path:
    """``<results>/<study>/protocol-<sha12>.yaml`` with the bytes the sessions ran (written
    once; a file of that name with other bytes is an error, never overwritten)."""
    path = Path(results) / stored.study / f"protocol-{stored.sha256[:12]}.yaml"
    if path.exists():
        if hashlib.sha256(path.read_bytes()).hexdigest() != stored.sha256:
            raise SessionError(f"{path}: not the protocol the sessions ran; move it away")
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "xb") as fh:  # never overwrite
        fh.write(stored.content)
        fh.flush()
        os.fsync(fh.fileno())
    fsync_dir(path.parent)
    return path


def _load_copy(path: Path, *, notes: list[str]) -> Protocol | None:
    try:
        return load_protocol(path)
    except ProtocolError as exc:
        first = str(exc).splitlines()[1:2] or [str(exc)]
        notes.append(
            f"{path.name} does not load on its own ({first[0].strip()}); if the study has "
            "staircase blocks, pass --protocol with the original file for their records"
        )
        return None


def _export_one(
    p: Participant,
    rows: Sequence[Response],
    playback: Sequence[PlaybackRecord],
    actions: Sequence[Action],
    events: Sequence[Event],
    *,
    results: Path,
    screen_poses: Sequence[ScreenPoses] = (),
) -> tuple[SessionLog, int]:
    """One participant's session folder written or extended; also how many stored text
    fields had to be written escaped (see :func:`escaped`)."""
    paths = session_paths(results, study=p.study, participant=p.participant, session=p.session)
    provenance = {
        "study": p.study,
        "participant": p.participant,
        "session": p.session,
        "simulated": p.simulated,
        "mode": "online",
        "protocol_sha256": p.protocol_sha256,
        "design_seed": int(p.design_seed),
        "trial_order": p.trial_order,
        "clips": p.clips,
        "recruitment_source": p.recruitment_source,
        "browser": p.browser,
        # what presented the clips: the protocol's display and what ran (webxr falls back to
        # live3d without a headset where the protocol allows it); None for a video study
        "display": next((e.detail for e in reversed(events) if e.kind == "display"), None),
        "started": p.created.isoformat() if p.created else None,
        "finished": p.completed.isoformat() if p.completed else None,
        # the participant stopped the study from its page (when), its answers until then kept
        "withdrawn": None if p.completed else next(
            (e.at.isoformat() for e in events if e.kind == "withdrawn"), None),
        "events": [
            {"kind": e.kind, "at": e.at.isoformat(), **({"detail": e.detail} if e.detail else {})}
            for e in events
            if e.kind != "browser"
        ],
        # each page load of a session that had answers and was not complete
        "resumes": [
            {"at": e.at.isoformat(), "how": "online page load", **(e.detail or {})}
            for e in events
            if e.kind == "resumed"
        ],
    }
    provenance, changed = escaped(provenance)
    if paths.tsv.exists():
        log = SessionLog.resume(
            results, study=p.study, participant=p.participant, session=p.session
        )
        saved = log.provenance()
        if saved.get("mode") != "online" or saved.get("protocol_sha256") != p.protocol_sha256:
            raise SessionError(
                f"{paths.folder} holds another session (mode {saved.get('mode')!r}); export "
                "into another --results folder"
            )
        have = {(r["trial_index"], r["item"]) for r in log.rows}
        log.update_provenance(
            **{k: v for k, v in provenance.items() if k not in ("resumes", "events")},
            events=provenance["events"][len(saved.get("events", [])) :],
            resumes=provenance["resumes"][len(saved.get("resumes", [])) :],
        )
    else:
        log = SessionLog.create(
            results,
            study=p.study,
            participant=p.participant,
            session=p.session,
            provenance=provenance,
        )
        have = set()
    for r in rows:
        if (r.trial_index, r.item) in have:
            continue
        row, n = escaped(r.row, tsv=True)
        changed += n
        log.append(row)
    records, n = escaped([_exported(rec.record) for rec in playback])
    changed += n
    _append_new(paths.playback, records)
    if actions:
        records, n = escaped([a.record for a in actions])
        changed += n
        _append_new(paths.actions, records)
    if screen_poses:  # VR: the poses while each screen waited for an answer
        records, n = escaped([r.record for r in screen_poses])
        changed += n
        _append_new(paths.screen_poses, records)
    return log, changed
