"""``jaw_only``: jawOpen follows the vowel track's opening, nothing else moves.

A template for a new animation method: a parameter model (subclass of
``facelab.methods.Params``), a spec (``facelab.methods.MethodSpec``) and a ``Method``
subclass generic in the parameters. The package's ``pyproject.toml`` names the class under the
entry-point group ``facelab.methods``; facelab registers it when it is installed.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
from pydantic import Field

from facelab.methods import MethodSpec, Params
from facelab.stimuli.methods import BlendshapeTrack, DriveInput, Method

#: how far each vowel a, i, u, e, o opens the jaw (a: fully)
OPENNESS = np.array([1.0, 0.25, 0.3, 0.55, 0.7])


class JawOnlyParams(Params):
    """jawOpen = gain x the vowel track's opening, clipped to [0, 1]."""

    gain: float = Field(0.8, gt=0, le=2, description="jawOpen at a fully open /a/")


def _checks(params: JawOnlyParams, base_dir: Path) -> Iterator[tuple[tuple[str, ...], str]]:
    """A protocol check with the file's line: a gain that opens the jaw past its limit."""
    if params.gain > 1.5:
        yield ("params", "gain"), "a gain above 1.5 holds the jaw fully open on every /a/"


class JawOnly(Method[JawOnlyParams]):
    spec = MethodSpec(
        "jaw_only", JawOnlyParams, "jawOpen follows the vowel track's opening, nothing else",
        checks=_checks,
    )

    def drive(self, inp: DriveInput, params: JawOnlyParams) -> BlendshapeTrack:
        opening = inp.track.vowels() @ OPENNESS  # (T,)
        jaw = np.clip(params.gain * opening, 0.0, 1.0)[:, None]
        return BlendshapeTrack(inp.track.times, jaw, ("jawOpen",))

    def targets(self, params: JawOnlyParams, *, base_dir: Path = Path(".")) -> set[str]:
        return {"jawOpen"}
