"""Head and controller poses while a VR screen waits for an answer (one row per screen shown:
the screen's trial, kind and item, the poses per frame).

Revision ID: 0004
Revises: 0003
"""

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"


def upgrade() -> None:
    op.create_table(
        "screen_poses",
        sa.Column("pk", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("participant_pk", sa.Integer, sa.ForeignKey("participants.pk"), index=True),
        sa.Column("client_key", sa.String(64), nullable=False),
        sa.Column("record", sa.JSON, nullable=False),
        sa.Column("bytes", sa.Integer, nullable=False),
        sa.Column("received", sa.DateTime(timezone=True), nullable=False),
        sa.UniqueConstraint("client_key", name="uq_screen_poses_key"),
    )


def downgrade() -> None:
    op.drop_table("screen_poses")
