"""facelab.experiment: the session layer - participant sessions, simulation, the demo and the
command line. It sits on top: it may import the bottom layer (:mod:`facelab`), the stimuli and
the analysis; nothing imports it.

Importing this package is cheap: psychopy is imported only by the runner modules.
"""
