"""The study protocols shipped with facelab (data, not code).

Installed as ``facelab.protocols`` so that an installed wheel carries them; find them with
:func:`facelab.resources.shipped_protocols` or ``facelab protocols``.
"""
