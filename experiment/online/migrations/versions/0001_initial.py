"""The first schema: settings, participants, responses, playback, actions, events.

Revision ID: 0001
Revises:
"""

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None


def _when(name: str, nullable: bool = False) -> sa.Column:
    return sa.Column(name, sa.DateTime(timezone=True), nullable=nullable)


def upgrade() -> None:
    op.create_table(
        "settings",
        sa.Column("key", sa.String(64), primary_key=True),
        sa.Column("value", sa.String(256), nullable=False),
    )
    op.create_table(
        "participants",
        sa.Column("pk", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("study", sa.String(64), nullable=False, index=True),
        sa.Column("participant", sa.String(32), nullable=False),
        sa.Column("number", sa.Integer, nullable=False),
        sa.Column("session", sa.Integer, nullable=False),
        sa.Column("token_sha256", sa.String(64), nullable=False),
        sa.Column("recruitment_hash", sa.String(64), nullable=True, index=True),
        sa.Column("recruitment_source", sa.String(16), nullable=True),
        sa.Column("simulated", sa.Boolean, nullable=False),
        sa.Column("protocol_sha256", sa.String(64), nullable=False),
        sa.Column("design_seed", sa.String(24), nullable=False),
        sa.Column("trial_order", sa.JSON, nullable=False),
        sa.Column("clips", sa.JSON, nullable=False),
        sa.Column("browser", sa.JSON, nullable=True),
        _when("created"),
        _when("completed", nullable=True),
        sa.UniqueConstraint("study", "participant", name="uq_participant"),
        sa.UniqueConstraint("token_sha256", name="uq_token"),
    )
    op.create_table(
        "responses",
        sa.Column("pk", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("participant_pk", sa.Integer, sa.ForeignKey("participants.pk"), index=True),
        sa.Column("trial_index", sa.Integer, nullable=False),
        sa.Column("item", sa.String(64), nullable=False),
        sa.Column("client_key", sa.String(64), nullable=False),
        sa.Column("row", sa.JSON, nullable=False),
        _when("received"),
        sa.UniqueConstraint("participant_pk", "trial_index", "item", name="uq_response"),
        sa.UniqueConstraint("client_key", name="uq_response_key"),
    )
    op.create_table(
        "playback",
        sa.Column("pk", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("participant_pk", sa.Integer, sa.ForeignKey("participants.pk"), index=True),
        sa.Column("client_key", sa.String(64), nullable=False),
        sa.Column("record", sa.JSON, nullable=False),
        _when("received"),
        sa.UniqueConstraint("client_key", name="uq_playback_key"),
    )
    op.create_table(
        "actions",
        sa.Column("pk", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("participant_pk", sa.Integer, sa.ForeignKey("participants.pk"), index=True),
        sa.Column("record", sa.JSON, nullable=False),
    )
    op.create_table(
        "events",
        sa.Column("pk", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column(
            "participant_pk",
            sa.Integer,
            sa.ForeignKey("participants.pk"),
            index=True,
            nullable=True,
        ),
        sa.Column("kind", sa.String(32), nullable=False),
        sa.Column("detail", sa.JSON, nullable=False),
        _when("at"),
    )


def downgrade() -> None:
    for table in ("events", "actions", "playback", "responses", "participants", "settings"):
        op.drop_table(table)
