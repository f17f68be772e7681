"""A template facelab plugin (see README.md): the animation method ``jaw_only``."""
