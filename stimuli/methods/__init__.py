"""facelab.stimuli.methods: animation methods, viseme track -> blendshape track.

* :mod:`.types` - :class:`DriveInput` and :class:`BlendshapeTrack`;
* :mod:`.registry` - the :class:`Method` plugin type, :func:`register`, :func:`get`,
  :func:`drive` (see there how a method is added);
* :mod:`.visemes`, :mod:`.vowel_blend`, :mod:`.impression` - the built-in methods.
"""

from facelab.stimuli.methods import impression, visemes, vowel_blend  # noqa: F401  (register)
from facelab.stimuli.methods.registry import (
    REGISTRY,
    Method,
    Playback,
    check_playable,
    drive,
    get,
    register,
)
from facelab.stimuli.methods.types import BlendshapeTrack, DriveInput

__all__ = [
    "REGISTRY",
    "BlendshapeTrack",
    "DriveInput",
    "Method",
    "Playback",
    "check_playable",
    "drive",
    "get",
    "register",
]
