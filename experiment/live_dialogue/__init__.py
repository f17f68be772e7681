"""facelab.experiment.live_dialogue: a talker's voice drives the avatar live (``facelab live``).

* :mod:`.turn` - a recorded turn (audio, the track as shown, the viewers' frame logs) and its
  latency summary (pure but for the folder it writes);
* :mod:`.app` - the server: pages, sockets, the condition's method run on the stream
  (:class:`facelab.stimuli.methods.live_drive.LiveDriver`);
* :mod:`.simulate` - talker and viewer in headless Chromium with a file as the microphone.
"""
