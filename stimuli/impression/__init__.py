"""facelab.stimuli.impression: seed 001's impression manipulation.

* :mod:`.model` - expression samples, PCA per expression, the impression direction (SVM,
  mean difference or ridge), δ, the graded face f̂ = f + q·δ·w and its easing (eqs. 1-4);
* :mod:`.synth` - a SYNTHETIC sample database with a known direction (demos and tests).

Clips of a model are made by :mod:`facelab.stimuli.render.impression_clips`; the protocol
method ``impression`` is :mod:`facelab.stimuli.methods`.
"""

from facelab.stimuli.impression.model import *  # noqa: F403
from facelab.stimuli.impression.model import __all__  # noqa: F401
