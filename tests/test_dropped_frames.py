"""The runner's dropped-frame report (issue 34.3): a clip over the threshold named at once,
a count at the end of each block and of the session; each trial counted once."""

from __future__ import annotations

from facelab.experiment.presentation import DroppedFrames


def test_drops_are_named_per_clip_block_and_session() -> None:
    said: list[str] = []
    drops = DroppedFrames(warn_over=5, say=said.append)
    rows = [  # block, trial, condition, dropped (two items per trial: counted once)
        ("vowels", 1, "baseline", 0), ("vowels", 1, "baseline", 0),
        ("vowels", 2, "standard", 23), ("vowels", 2, "standard", 23),
        ("vowels", 3, "emphasized", 2), ("sentences", 4, "baseline", 0),
        ("sentences", 5, "standard", 7),
    ]  # fmt: skip
    for block, trial, cond, dropped in rows:
        drops.row({"block": block, "trial_index": trial, "condition": cond,
                   "clip_frames_dropped": dropped})  # fmt: skip
    drops.end_block()
    assert said == [
        "warning: trial 2 (standard): its clip dropped 23 frames (more than 5); facelab analyze "
        "--max-dropped-frames can leave such trials out",
        "block vowels: 25 frames dropped in 2 of 3 trials, at most 23 in one clip",
        "warning: trial 5 (standard): its clip dropped 7 frames (more than 5); facelab analyze "
        "--max-dropped-frames can leave such trials out",
        "block sentences: 7 frames dropped in 1 of 2 trials, at most 7 in one clip",
    ]
    assert drops.summary() == {
        "trials": 5, "trials_with_drops": 3, "frames_dropped": 32, "max_dropped": 23
    }
