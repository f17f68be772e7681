"""facelab.stimuli.capture: face-capture data in ARKit coefficients.

* :mod:`.zmatrix` - Z matrices (52 ARKit rows x 5 vowels): the shipped ones and CSV files;
* :mod:`.measure_z` - a Z matrix the paper's way from Live Link Face / ARKit captures.
"""
