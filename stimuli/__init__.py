"""facelab.stimuli: speech, viseme analysis, animation methods, avatar and rendering.

pyrender is imported only in ``facelab.stimuli.render.renderer``; everything else is numpy/scipy.
"""
