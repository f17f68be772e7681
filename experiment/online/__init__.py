"""Online sessions: the same protocol and timeline in participants' browsers.

``facelab serve`` (:mod:`.server`) serves a study; every response is stored in a database
(:mod:`.db`: SQLite by default, PostgreSQL through the same models) the moment it arrives;
``facelab export`` (:mod:`.export`) writes the lab runner's session files from it;
:mod:`.browser` drives simulated participants through the real pages in headless Chromium.
"""
