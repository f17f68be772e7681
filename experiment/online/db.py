"""The online session database: SQLAlchemy 2 models, engines, Alembic migrations.

One database holds any number of studies (a protocol is identified by its study id and its
SHA-256). Tables:

* ``settings``      one row per key: the server's secrets (the HMAC key for recruitment ids
                    and simulated tokens, the experimenter secret's hash), made on first use;
* ``participants``  one row per participant and study: the id the server assigned (``P0001``;
                    the design's Latin squares use its number), the SHA-256 of the access token
                    (never the token), the keyed hash of the recruitment id (never the id), the
                    design seed and trial order, the clips' hashes, the browser's description;
* ``responses``     one row per (participant, trial_index, item): the lab log row as JSON plus
                    the client's idempotency key (unique);
* ``playback``      one row per clip shown (client key unique): the ``_playback.jsonl`` record;
* ``screen_poses``  one row per VR screen shown (client key unique): the head's and the
                    controllers' poses while it waited for an answer
                    (``_screen_poses.jsonl``);
* ``actions``       one row per action of a simulated participant (``_actions.jsonl``);
* ``events``        what else happened (joined, resumed, play() refused, completed);
* ``protocols``     the bytes of every protocol file the server has served, by SHA-256 (the
                    hash each participant row names), so ``facelab export`` can put the exact
                    protocol beside the sessions and replay their staircases.

No IP address is stored anywhere. SQLite runs in WAL mode with ``synchronous=FULL``: a
response is on disk when the server answers 200, as in the lab runner.
"""

from __future__ import annotations

import datetime as dt
import hashlib
from pathlib import Path
from typing import Any, ClassVar

from sqlalchemy import (
    JSON,
    Boolean,
    DateTime,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    String,
    UniqueConstraint,
    create_engine,
    event,
)
from sqlalchemy.engine import Engine
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column

from facelab.errors import SessionError

__all__ = [
    "Action",
    "Base",
    "Event",
    "Participant",
    "PlaybackRecord",
    "ProtocolFile",
    "Response",
    "Setting",
    "default_url",
    "open_engine",
    "store_protocol",
    "utcnow",
]

MIGRATIONS = Path(__file__).resolve().parent / "migrations"


def utcnow() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


class Base(DeclarativeBase):
    type_annotation_map: ClassVar[dict[Any, Any]] = {dict[str, Any]: JSON, list[Any]: JSON}


class Setting(Base):
    __tablename__ = "settings"
    key: Mapped[str] = mapped_column(String(64), primary_key=True)
    value: Mapped[str] = mapped_column(String(256))


class Participant(Base):
    __tablename__ = "participants"
    __table_args__ = (
        UniqueConstraint("study", "participant", name="uq_participant"),
        UniqueConstraint("token_sha256", name="uq_token"),
    )
    pk: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    study: Mapped[str] = mapped_column(String(64), index=True)
    participant: Mapped[str] = mapped_column(String(32))
    number: Mapped[int] = mapped_column(Integer)
    session: Mapped[int] = mapped_column(Integer, default=1)
    token_sha256: Mapped[str] = mapped_column(String(64))
    recruitment_hash: Mapped[str | None] = mapped_column(String(64), index=True)
    recruitment_source: Mapped[str | None] = mapped_column(String(16))
    simulated: Mapped[bool] = mapped_column(Boolean, default=False)
    protocol_sha256: Mapped[str] = mapped_column(String(64))
    design_seed: Mapped[str] = mapped_column(String(24))
    trial_order: Mapped[list[Any]] = mapped_column(JSON)
    clips: Mapped[dict[str, Any]] = mapped_column(JSON)
    browser: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    created: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    completed: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)


class Response(Base):
    __tablename__ = "responses"
    __table_args__ = (
        UniqueConstraint("participant_pk", "trial_index", "item", name="uq_response"),
        UniqueConstraint("client_key", name="uq_response_key"),
    )
    pk: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    participant_pk: Mapped[int] = mapped_column(ForeignKey("participants.pk"), index=True)
    trial_index: Mapped[int] = mapped_column(Integer)
    item: Mapped[str] = mapped_column(String(64))
    client_key: Mapped[str] = mapped_column(String(64))
    row: Mapped[dict[str, Any]] = mapped_column(JSON)
    received: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class PlaybackRecord(Base):
    __tablename__ = "playback"
    __table_args__ = (
        UniqueConstraint("client_key", name="uq_playback_key"),
        Index("ix_playback_participant_trial", "participant_pk", "trial_index"),
    )
    pk: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    participant_pk: Mapped[int] = mapped_column(ForeignKey("participants.pk"), index=True)
    client_key: Mapped[str] = mapped_column(String(64))
    record: Mapped[dict[str, Any]] = mapped_column(JSON)
    received: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    # the record's trial and its size in bytes (JSON), for the caps on what one stores
    trial_index: Mapped[int | None] = mapped_column(Integer, nullable=True)
    bytes: Mapped[int | None] = mapped_column(Integer, nullable=True)


class ScreenPoses(Base):
    __tablename__ = "screen_poses"
    __table_args__ = (UniqueConstraint("client_key", name="uq_screen_poses_key"),)
    pk: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    participant_pk: Mapped[int] = mapped_column(ForeignKey("participants.pk"), index=True)
    client_key: Mapped[str] = mapped_column(String(64))
    record: Mapped[dict[str, Any]] = mapped_column(JSON)
    bytes: Mapped[int] = mapped_column(Integer)
    received: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class Action(Base):
    __tablename__ = "actions"
    pk: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    participant_pk: Mapped[int] = mapped_column(ForeignKey("participants.pk"), index=True)
    record: Mapped[dict[str, Any]] = mapped_column(JSON)


class Event(Base):
    __tablename__ = "events"
    pk: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    participant_pk: Mapped[int | None] = mapped_column(
        ForeignKey("participants.pk"), index=True, nullable=True
    )
    kind: Mapped[str] = mapped_column(String(32))
    detail: Mapped[dict[str, Any]] = mapped_column(JSON)
    at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    bytes: Mapped[int | None] = mapped_column(Integer, nullable=True)


class ProtocolFile(Base):
    __tablename__ = "protocols"
    sha256: Mapped[str] = mapped_column(String(64), primary_key=True)
    study: Mapped[str] = mapped_column(String(64), index=True)
    name: Mapped[str] = mapped_column(String(255))
    content: Mapped[bytes] = mapped_column(LargeBinary)
    stored: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


def store_protocol(engine: Engine, *, protocol_path: Path, study: str) -> str:
    """Keep the protocol file's bytes under their SHA-256 (once; a second server start with
    the same file adds nothing). Returns the SHA-256."""
    content = Path(protocol_path).read_bytes()
    digest = hashlib.sha256(content).hexdigest()
    with Session(engine) as db:
        if db.get(ProtocolFile, digest) is None:
            db.add(
                ProtocolFile(
                    sha256=digest, study=study, name=Path(protocol_path).name[:255],
                    content=content,
                )
            )  # fmt: skip
            try:
                db.commit()
            except IntegrityError:  # another server process stored it first
                db.rollback()
    return digest


def default_url(results: Path, study: str) -> str:
    """The embedded default: ``<results>/<study>/online.sqlite``."""
    return f"sqlite:///{(Path(results) / study / 'online.sqlite').resolve()}"


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    cur = dbapi_connection.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA synchronous=FULL")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA busy_timeout=10000")
    cur.close()


def open_engine(url: str, *, migrate: bool = True) -> Engine:
    """An engine for ``url`` with the schema at the newest migration.

    SQLite files get WAL and ``synchronous=FULL`` on every connection; their folder is made.
    Raises :class:`SessionError` naming the URL when the database cannot be opened."""
    kwargs: dict[str, Any] = {"pool_pre_ping": True}
    if url.startswith("sqlite"):
        path = url.split("///", 1)[-1]
        if path and path != ":memory:":
            Path(path).parent.mkdir(parents=True, exist_ok=True)
        kwargs = {"connect_args": {"check_same_thread": False, "timeout": 30}}
    elif url.startswith("postgresql"):
        kwargs.update(pool_size=20, max_overflow=20)
    else:
        raise SessionError(f"--db {url!r}: expected a sqlite:///PATH or postgresql+psycopg://… URL")
    try:
        engine = create_engine(url, **kwargs)
    except Exception as exc:
        raise SessionError(f"--db {url!r}: cannot open it ({exc})") from None
    if url.startswith("sqlite"):
        event.listen(engine, "connect", _sqlite_pragmas)
    if migrate:
        upgrade(engine)
    return engine


#: the schema revisions this facelab knows (``migrations/versions``), oldest first
REVISIONS = tuple(sorted(p.name.split("_", 1)[0] for p in (MIGRATIONS / "versions").glob("0*.py")))


def facelab_revision(url: str) -> str | None:
    """The facelab schema revision of the database at ``url``, read without changing it (a
    SQLite file opened read-only, no pragmas); None when it holds no facelab tables (an
    empty file, another program's database). Raises :class:`SessionError` naming the URL
    when it cannot be read."""
    if url.startswith("sqlite"):
        import sqlite3
        from urllib.parse import quote

        path = url.split("///", 1)[-1].split("?", 1)[0]
        # a WAL database read even read-only gets -shm and -wal files: those this check
        # makes are removed again (ones that were there stay: a server may be using them)
        journals = [Path(path + end) for end in ("-wal", "-shm")]
        made = [j for j in journals if not j.exists()]
        try:
            if Path(path).stat().st_size == 0:
                return None
            con = sqlite3.connect(f"file:{quote(path)}?mode=ro", uri=True)
            try:
                tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master")}
                row = (con.execute("SELECT version_num FROM alembic_version").fetchone()
                       if "alembic_version" in tables else None)  # fmt: skip
            finally:
                con.close()
        except sqlite3.DatabaseError as exc:
            if "not a database" in str(exc):
                raise SessionError(f"--db {url!r}: not a SQLite database file") from None
            raise SessionError(f"--db {url!r}: cannot be opened for reading (check that its "
                               "folder and file can be read)") from None  # fmt: skip
        except OSError:
            raise SessionError(f"--db {url!r}: cannot be read") from None
        finally:
            for journal in made:
                journal.unlink(missing_ok=True)
        return None if row is None else str(row[0])
    from sqlalchemy import inspect as inspect_db
    from sqlalchemy import text
    from sqlalchemy.exc import DBAPIError

    engine = open_engine(url, migrate=False)
    try:
        with engine.connect() as connection:
            if not inspect_db(connection).has_table("alembic_version"):
                return None
            found = connection.execute(text("SELECT version_num FROM alembic_version")).first()
    except DBAPIError as exc:
        raise SessionError(f"database {engine.url!r}: cannot connect ({_reason(exc)})") from None
    finally:
        engine.dispose()
    return None if found is None else str(found[0])


def _reason(exc: Exception) -> str:
    """Why a database server could not be reached, in plain words (not the driver's)."""
    text = str(getattr(exc, "orig", exc)).lower()
    for clue, reason in (
        ("refused", "no database server answers at that host and port"),
        ("resolve host", "the host name is not known"),
        ("name or service not known", "the host name is not known"),
        ("password authentication failed", "the user name or password was refused"),
        ("does not exist", "the server has no such database or user"),
        ("timeout", "the server did not answer in time"),
        ("timed out", "the server did not answer in time"),
    ):
        if clue in text:
            return reason
    return "the server refused the connection"


def upgrade(engine: Engine) -> None:
    """Bring the schema to the newest Alembic revision (creates it in an empty database)."""
    from alembic import command
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    from sqlalchemy.exc import DBAPIError

    try:
        connection = engine.connect()
    except DBAPIError as exc:  # no server, wrong password, no such database…
        raise SessionError(f"database {engine.url!r}: cannot connect ({_reason(exc)})") from None
    try:
        with connection.begin():
            cfg.attributes["connection"] = connection
            command.upgrade(cfg, "head")
    except Exception as exc:
        raise SessionError(f"database {engine.url!r}: cannot migrate it ({exc})") from None
    finally:
        connection.close()
