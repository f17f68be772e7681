"""A study as the browser sees it: a participant's timeline as JSON, and a submitted answer
checked against it and turned into the lab log row. Pure (no web, no database).

The server is the only place the design runs: :meth:`OnlineStudy.screens` compiles the same
timeline as the lab runner (:func:`facelab.experiment.timeline.compile_timeline`) for the
participant id the server assigned, and :func:`facelab.experiment.timeline.remaining` gives
what is left after a closed tab or a restart. The browser never randomises, and never runs
a staircase: a staircase trial's level comes from :meth:`OnlineStudy.adaptive_json`, which
replays the participant's stored answers with the lab's
:class:`~facelab.experiment.adaptive.Staircases`.

Answers are validated field by field against the screen that asked for them (the trial and
item must be the participant's, a rating within the item's range, a choice 1 or 2, a label
one of the task's); anything else is an :class:`AnswerError` naming the field.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from facelab.design import build_trials
from facelab.errors import SessionError
from facelab.experiment.adaptive import Staircases
from facelab.experiment.preflight import check_clips
from facelab.experiment.timeline import (
    AdaptiveTrial,
    AnswerError,
    BrowserContext,
    ClipKey,
    Playback,
    ResponseScreen,
    Screen,
    TextScreen,
    compile_timeline,
    needed_clips,
    number,
    remaining,
    vr_texts,
)
from facelab.protocol import Protocol
from facelab.sessionlog import SessionContext

__all__ = ["AnswerError", "OnlineStudy", "checked_study"]


@dataclass
class OnlineStudy:
    """One protocol served online, with its checked clips (``{clip key: ClipRef}``: the
    file's ``sha256``, ``fps`` and ``duration_s``, from :func:`~facelab.experiment.preflight.
    check_clips`)."""

    protocol: Protocol
    protocol_sha256: str
    clips: Mapping[ClipKey, Any]
    # the copies browsers fetch (facelab.experiment.online.served; None: the rendered files
    # by their SHA-256)
    served: Any = None
    _screens: dict[str, list[Screen]] = field(default_factory=dict, repr=False)

    @property
    def clip_sha256(self) -> dict[ClipKey, str]:
        return {k: ref.sha256 for k, ref in self.clips.items()}

    @property
    def study(self) -> str:
        return self.protocol.study.id

    # -- the design

    def trials(self, participant: str) -> list[Any]:
        return build_trials(self.protocol, participant=participant)

    def screens(self, participant: str, session: int = 1) -> list[Screen]:
        """Every screen of the participant's session (cached: the design is pure)."""
        key = f"{participant}/{session}"
        if key not in self._screens:
            trials = self.trials(participant)
            self._screens[key] = compile_timeline(
                self.protocol, trials, participant=participant, session=session
            )
        return self._screens[key]

    def needed(self) -> set[ClipKey]:
        """Every clip any participant may see (checked before serving)."""
        return needed_clips(self.screens("P1"))

    def planned(self, participant: str) -> set[tuple[int, str]]:
        """Every (trial_index, item) the participant's session asks for."""
        return set(self.planned_in_order(participant))

    def planned_in_order(self, participant: str) -> list[tuple[int, str]]:
        """Every (trial_index, item) the participant's session asks for, in the order of its
        screens."""
        return [k for s in self.screens(participant) for k in s.response_keys()]

    # -- to the browser

    def timeline_json(
        self, participant: str, answered: set[tuple[int, str]], *, session: int = 1
    ) -> tuple[list[dict[str, Any]], list[str]]:
        """The screens still to show, as JSON for the browser's plugins, and the clip files
        they may show (for preloading: both clips of a pair, every level of a staircase). A
        staircase trial is a placeholder (``kind: adaptive``): the browser asks
        :meth:`adaptive_json` for its screens once the answers before it are stored."""
        lang = self.protocol.presentation.language
        todo = remaining(self.screens(participant, session), answered, language=lang)
        shown_before = {t for t, _ in answered}
        out: list[dict[str, Any]] = []
        for s in todo:
            if isinstance(s, TextScreen) and s.role == "welcome":
                continue  # online: the consent/instructions page greets the participant
            out.append(self._screen_json(s, shown_before))
        main = needed_clips([s for s in todo if not getattr(s, "practice", False)])
        names = {self._clip_json(k)["clip"] for k in main}
        names |= {s.get("clip") for s in out if s.get("practice") and s.get("clip")}
        return out, sorted(names)

    def adaptive_json(
        self,
        participant: str,
        trial_index: int,
        *,
        logged: Sequence[Mapping[str, Any]],
        session: int = 1,
    ) -> list[dict[str, Any]]:
        """The screens of staircase trial ``trial_index`` at the level the block's staircase
        chooses after the participant's stored answers ``logged`` (log rows). Refused
        (:class:`AnswerError`) for a trial that is not a staircase trial of this session or
        while an earlier trial of its block has no stored answer."""
        screen = self._adaptive(participant, trial_index, session)
        expanded = self.expand_adaptive(participant, session, screen, logged)
        shown_before = {int(r["trial_index"]) for r in logged}
        return [self._screen_json(s, shown_before) for s in expanded]

    def _adaptive(self, participant: str, trial_index: int, session: int = 1) -> AdaptiveTrial:
        for s in self.screens(participant, session):
            if isinstance(s, AdaptiveTrial) and s.trial_index == trial_index:
                return s
        raise AnswerError(f"trial_index {trial_index}: not a staircase trial of this session")

    def expand_adaptive(
        self,
        participant: str,
        session: int,
        screen: AdaptiveTrial,
        logged: Sequence[Mapping[str, Any]],
    ) -> list[Screen]:
        """``screen``'s screens at the condition its staircase gives after the stored answers
        of the earlier trials of its block (all of which must be stored)."""
        trial = screen.trial
        assert trial is not None
        before = [r for r in logged if int(r["trial_index"]) < trial.trial_index]
        have = {int(r["trial_index"]) for r in before if r.get("block") == trial.block}
        earlier = [
            s.trial_index
            for s in self.screens(participant, session)
            if isinstance(s, AdaptiveTrial)
            and s.trial is not None
            and s.trial.block == trial.block
            and s.trial_index < trial.trial_index
        ]
        missing = [t for t in earlier if t not in have]
        if missing:
            raise AnswerError(
                f"trial_index {trial.trial_index}: the staircase needs the answer to trial "
                f"{missing[0]} first"
            )
        try:
            staircases = Staircases(self.protocol, logged=before)
        except SessionError as exc:
            raise AnswerError(str(exc)) from None
        return screen.expand(staircases.resolve(trial))

    def _clip_json(self, key: ClipKey, *, practice: bool = False) -> dict[str, Any]:
        """A clip as the browser fetches it: by a hash (the name never says the condition) -
        of the served copy (:mod:`~facelab.experiment.online.served`) when there is one."""
        ref = self.clips[key]
        track_sha = getattr(ref, "track_sha256", None)
        live = self.protocol.presentation.display != "video" and track_sha
        clip, track = ref.sha256 + ".mp4", f"{track_sha}.bin"
        if self.served is not None:
            copy = (self.served.practice if practice else self.served.main).get(key)
            copy = copy or self.served.main[key]
            clip, track = copy.clip, copy.track
        return {
            "clip": clip,
            "fps": ref.fps,
            "frames": round(ref.duration_s * ref.fps),
            # display live3d / webxr: the animation track drawn live ("" for video)
            "track": track if live else "",
        }

    def _screen_json(self, s: Screen, shown_before: set[int]) -> dict[str, Any]:
        ctx = BrowserContext(
            lang=self.protocol.presentation.language,
            clip_json=self._clip_json,
            shown_before=frozenset(shown_before),
            practice_json=lambda key: self._clip_json(key, practice=True),
            vr_texts=vr_texts(self.protocol),
        )
        return s.browser(ctx)

    # -- from the browser

    def _screen_for(self, participant: str, trial_index: int, item: str) -> ResponseScreen:
        for s in self.screens(participant):
            if isinstance(s, ResponseScreen) and (trial_index, item) in s.response_keys():
                return s
        raise AnswerError(
            f"trial_index {trial_index}, item {item!r}: not a response of this participant's "
            "session"
        )

    def row(
        self,
        *,
        participant: str,
        session: int,
        simulated: bool,
        answer: Mapping[str, Any],
        playback: Playback | None,
        timestamp: str,
        logged: Callable[[], Sequence[Mapping[str, Any]]] | None = None,
    ) -> dict[str, Any]:
        """The log row for one submitted answer, exactly as the lab runner writes it.

        ``answer`` holds ``trial_index``, ``item``, ``rt_s`` and one of ``rating`` (VAS),
        ``choice`` (2AFC: 1 or 2) or ``label`` (identify). ``logged`` gives the participant's
        stored rows (asked only for a staircase trial, whose level they decide)."""
        trial_index, item = answer["trial_index"], answer["item"]
        screen = self._screen_for(participant, trial_index, item)
        if isinstance(screen, AdaptiveTrial):  # at the level its staircase chose
            expanded = self.expand_adaptive(
                participant, session, screen, logged() if logged else []
            )
            screen = next(
                x
                for x in expanded
                if isinstance(x, ResponseScreen) and (trial_index, item) in x.response_keys()
            )
        rt = number(answer, "rt_s", lo=0.0, hi=24 * 3600.0)
        context = SessionContext(
            study=self.study,
            participant=participant,
            session=session,
            simulated=simulated,
            protocol_sha256=self.protocol_sha256,
        )
        given = screen.answer(item, answer, rt_s=rt, timestamp=timestamp)
        return screen.row(item, given, context=context, playback=playback)


def checked_study(
    protocol: Protocol, *, protocol_sha256: str, clips_dir: Path, base_dir: Path
) -> OnlineStudy:
    """``protocol`` served with every clip any participant may see checked first (present,
    unchanged since rendering, rendered from this protocol), as before a lab session;
    SessionError naming the clip otherwise."""
    probe = OnlineStudy(protocol=protocol, protocol_sha256=protocol_sha256, clips={})
    clips = check_clips(protocol, probe.needed(), clips_dir, base_dir=base_dir,
                        verify_hashes=True)  # fmt: skip
    return OnlineStudy(protocol=protocol, protocol_sha256=protocol_sha256, clips=clips)
