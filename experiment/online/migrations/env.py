"""Alembic environment for facelab's online database: runs on the connection the caller
passes in ``config.attributes["connection"]`` (see :func:`facelab.experiment.online.db.upgrade`)."""

from alembic import context

from facelab.experiment.online.db import Base

connection = context.config.attributes["connection"]
context.configure(connection=connection, target_metadata=Base.metadata, render_as_batch=True)
with context.begin_transaction():
    context.run_migrations()
