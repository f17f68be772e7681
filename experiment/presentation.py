"""Presentation quality during a session: the frames clips dropped, reported as they happen
(the lab runner; online sessions report theirs in the playback records)."""

from __future__ import annotations

from typing import Any

__all__ = ["DroppedFrames"]


class DroppedFrames:
    """The frames clips dropped, as the session goes: a clip over the threshold is named at
    once, each block and the session end with a summary line (rows of one trial share their
    clip, so each trial counts once)."""

    def __init__(self, *, warn_over: int, say: Any = print):
        self.warn_over = warn_over
        self.say = say
        self.block: str | None = None
        self.seen: set[int] = set()
        self.by_block: dict[str, list[int]] = {}

    def row(self, row: dict[str, Any]) -> None:
        block, trial = str(row["block"]), int(row["trial_index"])
        if self.block is not None and block != self.block:
            self.end_block()
        self.block = block
        if trial in self.seen:
            return
        self.seen.add(trial)
        dropped = int(row.get("clip_frames_dropped") or 0)
        self.by_block.setdefault(block, []).append(dropped)
        if dropped > self.warn_over:
            self.say(
                f"warning: trial {trial} ({row['condition']}): its clip dropped {dropped} frames "
                f"(more than {self.warn_over}); facelab analyze --max-dropped-frames can leave "
                "such trials out"
            )

    @staticmethod
    def _line(what: str, drops: list[int]) -> str:
        hit = [d for d in drops if d > 0]
        worst = f", at most {max(hit)} in one clip" if hit else ""
        return (
            f"{what}: {sum(hit)} frames dropped in {len(hit)} of {len(drops)} trials{worst}"
        )

    def end_block(self) -> None:
        if self.block is not None and self.block in self.by_block:
            self.say(self._line(f"block {self.block}", self.by_block[self.block]))

    def summary(self) -> dict[str, int]:
        every = [d for drops in self.by_block.values() for d in drops]
        return {
            "trials": len(every),
            "trials_with_drops": sum(d > 0 for d in every),
            "frames_dropped": sum(every),
            "max_dropped": max(every, default=0),
        }
