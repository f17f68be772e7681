"""``facelab live --simulate FILE.wav``: the talker and the viewer in headless Chromium (or
the viewer in the lab window, ``--display window``), the file as the talker's microphone
(Chromium's fake media-stream capture), one turn recorded and its latency reported. The server
runs in a thread of this process."""

from __future__ import annotations

import base64
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from facelab.errors import SessionError
from facelab.experiment.live_dialogue.app import LiveConfig, LiveHub, create_live_app
from facelab.experiment.online.serve import BackgroundServer
from facelab.stimuli.speech.audio import Speech

__all__ = ["simulate_live"]


def _wait(driver, script: str, *, timeout_s: float, what: str) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = driver.execute_script(script)
        if value:
            return value
        time.sleep(0.1)
    raise SessionError(f"simulated live session: {what} (waited {timeout_s:.0f} s)")


def simulate_live(
    config: LiveConfig, *, wav: Path, screenshot: Path | None = None, timeout_s: float = 120.0,
    window_size: tuple[int, int] = (1280, 800),
) -> dict[str, Any]:
    """Run one simulated turn of ``wav`` (any rate; sent to Chromium as 16-bit 48 kHz PCM)
    and return its turn.json (with ``recording``, the turn's folder, and ``screenshot``).
    With ``config.display == "window"`` the viewer is the lab window (``window_size`` px; an
    X display and a sound output needed), the talker page still Chromium."""
    from facelab.stimuli.speech.audio import load_audio

    speech = load_audio(wav, sample_rate=48_000)
    duration = len(speech.samples) / speech.sample_rate
    hub = LiveHub.open(config)
    snapped = None
    with tempfile.TemporaryDirectory(prefix="facelab-live-") as tmp:
        fake = _fake_microphone(speech, Path(tmp))
        with BackgroundServer(None, app=create_live_app(hub)) as server:
            if config.display == "window":
                snapped = _window_turn(hub, server.url, fake=fake, duration_s=duration,
                                       screenshot=screenshot, window_size=window_size,
                                       timeout_s=timeout_s)  # fmt: skip
                return _record(hub, wav=wav, duration_s=duration, screenshot=screenshot,
                               snapped=snapped)  # fmt: skip
            driver = _talker_browser(fake)
            try:
                if config.display == "webxr":  # an emulated headset (IWER), turning its head
                    from facelab.experiment.online.browser import emulator_js

                    driver.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument",
                                           {"source": emulator_js()})  # fmt: skip
                driver.get(server.url + "/")
                _wait(driver, "return window.FacelabDialogue && "
                      "window.FacelabDialogue.state === 'waiting'",
                      timeout_s=60, what="the viewer page did not load its avatar")  # fmt: skip
                if config.display == "webxr":  # the participant enters VR with a click
                    _wait(driver, "return !!document.querySelector('[data-facelab=enter_vr]')",
                          timeout_s=30, what="the viewer offered no VR session")
                    driver.execute_script("document.querySelector('[data-facelab=enter_vr]')"
                                          ".click()")  # fmt: skip
                    _wait(driver, "return window.FacelabLive.inVR()", timeout_s=30,
                          what="the viewer did not enter VR")
                viewer = driver.current_window_handle
                driver.switch_to.new_window("window")
                _talk(driver, server.url, duration_s=duration)
                driver.switch_to.window(viewer)
                if screenshot is not None:  # mid-sentence: a third in, the mouth open (or
                    driver.execute_script(  # the most open face drawn, for a short turn)
                        "window.FacelabDialogue.snap = arguments[0]",
                        {"after_s": duration / 3, "peak": 0.25},
                    )
                deadline = time.monotonic() + duration + timeout_s
                while not hub.turns and not (screenshot is not None and driver.execute_script(
                        "return !!window.FacelabDialogue.snapshot")):  # fmt: skip
                    if time.monotonic() > deadline:
                        raise SessionError("simulated live session: no turn was recorded")
                    time.sleep(0.05)
                in_vr = config.display == "webxr"
                if screenshot is not None and in_vr:  # the XR layer is not the canvas' own
                    driver.save_screenshot(str(screenshot))  # buffer: the page as shown now
                while not hub.turns:
                    if time.monotonic() > deadline:
                        raise SessionError("simulated live session: no turn was recorded")
                    time.sleep(0.2)
                if screenshot is not None and in_vr:
                    snapped = driver.execute_script(
                        "const a = window.FacelabDialogue; return a.snapped || a.best || null")
                elif screenshot is not None:
                    shot, snapped = driver.execute_script(
                        "const a = window.FacelabDialogue; return a.snapshot ? "
                        "[a.snapshot, a.snapped] : [a.bestShot || null, a.best || null]")
                    if shot is None:
                        raise SessionError("simulated live session: the viewer drew no frame "
                                           "of the turn")  # fmt: skip
                    Path(screenshot).write_bytes(base64.b64decode(shot.split(",", 1)[1]))
            finally:
                driver.quit()
    return _record(hub, wav=wav, duration_s=duration, screenshot=screenshot, snapped=snapped)


def _record(hub: LiveHub, *, wav: Path, duration_s: float, screenshot: Path | None,
            snapped: Any) -> dict[str, Any]:  # fmt: skip
    record = dict(hub.turns[0])
    record["recording"] = record.pop("folder")
    record["talker_file"] = str(wav)
    record["talker_file_s"] = round(duration_s, 3)
    if screenshot is not None:
        record["screenshot"] = str(screenshot)
        record["screenshot_frame"] = snapped
    return record


def _fake_microphone(speech: Speech, folder: Path) -> Path:
    """``speech`` (at 48 kHz) as 16-bit PCM in ``folder``, what Chromium's fake capture
    reads."""
    import soundfile as sf

    fake = folder / "talker.wav"
    sf.write(str(fake), speech.samples, speech.sample_rate, subtype="PCM_16")
    return fake


def _talker_browser(fake: Path):
    from facelab.experiment.online.browser import chromium

    return chromium(size=(1100, 760), extra_args=(
        "--use-fake-ui-for-media-stream",
        "--use-fake-device-for-media-stream",
        f"--use-file-for-fake-audio-capture={fake}%noloop",
    ))  # fmt: skip


def _talk(driver, url: str, *, duration_s: float) -> None:
    """Open the talker page in ``driver``'s current tab, speaking at once (the fake
    microphone) for ``duration_s`` and a little more; SessionError if it does not start."""
    driver.get(url + f"/talk?auto=1&seconds={duration_s + 0.3:.2f}")
    state = _wait(driver, "return window.FacelabDialogue && ['talking', 'refused']"
                  ".includes(window.FacelabDialogue.state) && "
                  "window.FacelabDialogue.state",
                  timeout_s=30, what="the talker page did not start")  # fmt: skip
    if state == "refused":
        raise SessionError("simulated live session: the server refused the talker: "
                           + str(driver.execute_script(
                               "return document.querySelector("
                               "'[data-facelab=live-status]').textContent")))


def _window_turn(hub: LiveHub, url: str, *, fake: Path, duration_s: float,
                 screenshot: Path | None, window_size: tuple[int, int],
                 timeout_s: float) -> Any:  # fmt: skip
    """The lab window (this process' main thread) as the viewer, the talker page in headless
    Chromium (a thread): one turn; the window's still saved to ``screenshot``."""
    from facelab.experiment.live_dialogue.window_view import WindowViewer

    loop = hub.running_loop()  # the server's loop, which the window joins the hub through
    stop, failures = threading.Event(), []

    def talker() -> None:
        try:
            driver = _talker_browser(fake)
            try:
                _talk(driver, url, duration_s=duration_s)
                end = time.monotonic() + duration_s + timeout_s
                while not hub.turns:
                    if time.monotonic() > end:
                        raise SessionError("simulated live session: no turn was recorded")
                    time.sleep(0.1)
            finally:
                driver.quit()
        except Exception as exc:  # said by the main thread, after the window closed
            failures.append(exc)
        finally:
            stop.set()

    with WindowViewer(hub, loop=loop, size=window_size, fullscreen=False) as view:
        if screenshot is not None:  # mid-sentence, the mouth open (as the browser viewer)
            view.snap = {"after_s": duration_s / 3, "peak": 0.25}
        thread = threading.Thread(target=talker, daemon=True)
        thread.start()
        view.run(stop=stop)
        thread.join(timeout=30)
    if failures:
        exc = failures[0]
        if isinstance(exc, SessionError):
            raise exc
        raise SessionError(f"simulated live session: the talker page failed ({exc})") from None
    if not hub.turns:
        raise SessionError("simulated live session: no turn was recorded")
    if screenshot is None:
        return None
    image = view.snapshot if view.snapshot is not None else view.best_shot
    if image is None:
        raise SessionError("simulated live session: the window showed no frame of the turn")
    image.save(str(screenshot))
    return view.snapped if view.snapshot is not None else view.best


