"""facelab.stimuli.methods: animation methods, viseme track -> blendshape track.

* :mod:`.types` - :class:`DriveInput` and :class:`BlendshapeTrack`;
* :mod:`.registry` - the :class:`Method` plugin type, :func:`register`, :func:`get`,
  :func:`drive` (see there how a method is added);
* :mod:`.visemes`, :mod:`.vowel_blend`, :mod:`.impression`, :mod:`.external_track` - the
  built-in methods.
"""

from facelab.stimuli.methods import (  # noqa: F401  (register)
    external_track,
    impression,
    visemes,
    vowel_blend,
)
from facelab.stimuli.methods.registry import (
    REGISTRY,
    Method,
    Playback,
    check_playable,
    drive,
    get,
    load_plugins,
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
    "load_plugins",
    "register",
]

load_plugins()  # installed packages' methods (entry points facelab.methods)
