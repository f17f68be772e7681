"""The size of each stored playback record and event, and a playback record's trial, so the
server can cap what one participant stores (per trial and per session) with one query.

Revision ID: 0003
Revises: 0002
"""

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"


def upgrade() -> None:
    with op.batch_alter_table("playback") as batch:
        batch.add_column(sa.Column("trial_index", sa.Integer, nullable=True))
        batch.add_column(sa.Column("bytes", sa.Integer, nullable=True))
        batch.create_index("ix_playback_participant_trial", ["participant_pk", "trial_index"])
    with op.batch_alter_table("events") as batch:
        batch.add_column(sa.Column("bytes", sa.Integer, nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("events") as batch:
        batch.drop_column("bytes")
    with op.batch_alter_table("playback") as batch:
        batch.drop_index("ix_playback_participant_trial")
        batch.drop_column("bytes")
        batch.drop_column("trial_index")
