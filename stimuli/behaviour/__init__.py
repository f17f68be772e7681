"""facelab.stimuli.behaviour: seed 003's planned non-verbal behaviour (EMBOS) for the head.

* :mod:`.library` - motion units with emotion intensities, durations, waits, body parts;
* :mod:`.fit` - a unit library from annotated recordings (eqs. 2-4);
* :mod:`.plan` - the planner (eq. 1, RBF blends of eq. 5) over an emotion timeline and speech;
* :mod:`.realise` - a plan as per-frame blendshape offsets and head/eye pose;
* :mod:`.clip` - the behaviour layer of one protocol clip;
* :mod:`.synth` - a SYNTHETIC annotation table planned from a library.

Demonstration clips are made by :mod:`facelab.stimuli.render.behaviour_clips`.
"""

from facelab.stimuli.behaviour.clip import *  # noqa: F403
from facelab.stimuli.behaviour.clip import __all__  # noqa: F401
