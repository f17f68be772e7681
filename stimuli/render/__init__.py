"""facelab.stimuli.render: everything that makes clips and pictures.

* :mod:`.renderer` - offscreen rendering with pyrender (EGL); the only module importing it;
* :mod:`.clip` - encoding frames and audio to mp4 (ffmpeg), probing, A/V offset;
* :mod:`.clipspec` - the clips a protocol needs and the hash of each clip's inputs;
* :mod:`.prepare` - a stimulus's speech and viseme tracks;
* :mod:`.build` - ``facelab render``: every clip of a protocol, the manifest, contact sheets;
* :mod:`.impression_clips`, :mod:`.behaviour_clips` - clips of impression models and
  behaviour plans outside a protocol;
* :mod:`.inspect` - what an avatar file offers and a sheet of it;
* :mod:`.plots` - figures of viseme tracks and behaviour plans.
"""
