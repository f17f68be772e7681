"""The lab window takes every click from the window's events, where it was made: a press and
release that both arrive between two polls of the button (a quick click during a slow frame,
on a busy machine) is still an answer - on button screens (``show``: 2AFC, identification,
screen kinds from packages) and on the VAS. A PsychoPy window under Xvfb; the clicks are
pyglet mouse events dispatched to it, the press and the release in the same frame."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

pytestmark = [pytest.mark.display]

SCRIPT = textwrap.dedent(
    """
    import json, sys
    from facelab.design import Trial
    from facelab.experiment.timeline import VasScreen, trial_screens
    from facelab.experiment.vas import VasGeometry
    from facelab.experiment.window import Window
    from facelab.protocol import load_protocol
    from facelab.resources import protocol_path

    W, H = 800, 500
    protocol = load_protocol(protocol_path("kato2021"))
    out = {}
    with Window(protocol, clips={}, size=(W, H), fullscreen=False) as window:
        handle, real_flip = window.win.winHandle, window.win.flip
        scale = handle.width / W  # stimulus pixels -> window points
        plan, flips = {}, [0]

        def flip(*args, **kwargs):
            done = real_flip(*args, **kwargs)
            flips[0] += 1
            for event in plan.pop(flips[0], []):
                if event[0] == "key":  # a key pressed and let go
                    handle.dispatch_event("on_key_press", event[1], 0)
                    handle.dispatch_event("on_key_release", event[1], 0)
                    continue
                if len(event) == 2:  # a quick click: press and release at once
                    event = ("press", *event), ("release", *event)
                else:
                    event = (event,)
                for kind, x, y in event:
                    px, py = round((x + W / 2) * scale), round((y + H / 2) * scale)
                    if kind == "drag":
                        handle.dispatch_event("on_mouse_drag", px, py, 0, 0, 1, 0)
                    else:
                        handle.dispatch_event(f"on_mouse_{kind}", px, py, 1, 0)
            if flips[0] > 300:
                raise SystemExit("no answer after 300 frames: the clicks were missed")
            return done

        window.win.flip = flip
        from pyglet.window import key

        # a button screen (a plugin's stimulus, in height units): a click beside the button,
        # then one on it
        box = window.visual.Rect(window.win, width=0.4, height=0.2, pos=(0.3, -0.1),
                                 units="height")
        plan.update({2: [(-300, 0)], 4: [(150, -50)]})
        value, rt = window.show(stims=[box], keys={}, clickable=[(box, "right one")])
        out["show"] = [value, flips[0]]
        # Escape: while the quit question is up, a click where the button was is no answer;
        # after "n" the screen is back and a click answers it
        start = flips[0]
        plan.update({start + 2: [("key", key.ESCAPE)], start + 4: [(150, -50)],
                     start + 6: [("key", key.N)], start + 10: [(150, -50)]})
        value, rt = window.show(stims=[box], keys={}, clickable=[(box, "after the question")])
        out["escape"] = [value, flips[0] - start]
        # the VAS: a click on each item's line, then on Confirm
        trial = Trial(trial_index=1, block="vowels", set_index=1, stimulus_set="vowels",
                      stimulus="aiueo", condition="standard", repetition=1)
        screen = next(s for s in trial_screens(protocol, trial) if isinstance(s, VasScreen))
        n = len(screen.items)
        geometry = []
        for k, item in enumerate(screen.items):
            offset = (0.25 * H * (n - 1) / 2 - 0.32 * H * k) if n > 1 else 0.0
            geometry.append(VasGeometry(width=W, height=H, low=item.range[0],
                                        high=item.range[1], y_line=-0.02 * H + offset))
        wanted = [0.25, 0.75][:n]
        start = flips[0]
        for k, (g, share) in enumerate(zip(geometry, wanted)):
            plan[start + 2 + 2 * k] = [(g.x_left + share * (g.x_right - g.x_left), g.y_line)]
        plan[start + 2 + 2 * n] = [geometry[-1].confirm_centre]
        answers = window.vas(screen)
        out["vas"] = [[a.item, a.rating] for a in answers]
        out["vas_wanted"] = [g.low + s * (g.high - g.low) for g, s in zip(geometry, wanted)]
        # a drag: pressed at 25 %, dragged to 50 % (a frame), then to 80 % and let go there
        # within one frame: the rating is where the button was let go
        g = geometry[0]
        at = lambda share: g.x_left + share * (g.x_right - g.x_left)  # noqa: E731
        start = flips[0]
        plan.update({start + 2: [("press", at(0.25), g.y_line)],
                     start + 3: [("drag", at(0.5), g.y_line)],
                     start + 4: [("drag", at(0.8), g.y_line), ("release", at(0.8), g.y_line)],
                     start + 6: [g.confirm_centre]})
        (dragged, *_) = window.vas(screen)
        out["drag"] = [dragged.rating, g.low + 0.8 * (g.high - g.low)]
    print(json.dumps(out))
    """
)


def test_quick_clicks_between_two_polls_answer_buttons_and_the_vas(tmp_path) -> None:
    """Also: a plugin's stimulus in other units than pixels takes its click, a click made
    while the quit question is up is no answer, and a VAS drag ends where it was let go."""
    if not os.environ.get("DISPLAY"):
        pytest.fail("no DISPLAY: run the tests with the README's test command (xvfb-run)")
    env = {**os.environ, "SDL_AUDIODRIVER": "dummy"}
    proc = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True,
                          timeout=300, env=env, cwd=tmp_path)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    value, flips = out["show"]
    assert value == "right one" and flips == 4  # the click beside the button was no answer
    value, flips = out["escape"]
    assert value == "after the question" and flips == 10, out["escape"]
    assert [item for item, _ in out["vas"]] == ["naturalness"]  # items shown one at a time
    for (_, rating), wanted in zip(out["vas"], out["vas_wanted"], strict=True):
        assert rating == pytest.approx(wanted, abs=0.5)
    rating, let_go = out["drag"]
    assert rating == pytest.approx(let_go, abs=0.5)
