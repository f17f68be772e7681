"""facelab: perception experiments on talking 3D avatar heads.

This package's own modules (the ``core/`` folder of the repository) are the bottom layer that
everything else builds on, and they import nothing else of facelab:

* :mod:`facelab.errors` - the error hierarchy (``FacelabError`` and its subclasses);
* :mod:`facelab.protocol` - the protocol model, YAML loading and validation
  (:mod:`facelab.protocol_model`, :mod:`facelab.protocol_yaml`, :mod:`facelab.protocol_checks`);
* :mod:`facelab.methods` - the registry of animation methods and their parameters;
* :mod:`facelab.design` - the pure trial design (protocol, participant -> trial list);
* :mod:`facelab.sessionlog` - the session-log format (one row per response, fsynced);
* :mod:`facelab.resources` - the protocols shipped inside the package.

On top of it: :mod:`facelab.stimuli` (speech, visemes, methods, avatar, rendering) and
:mod:`facelab.analysis` (loading, statistics, figures, reports) import only this layer and
themselves; :mod:`facelab.experiment` (sessions, simulation, the command line) sits on top.
``tests/test_architecture.py`` keeps it so.
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("facelab")
except PackageNotFoundError:  # pragma: no cover - a source tree that was never installed
    __version__ = "0+unknown"
