"""Simulated participants: complete sessions written through the same log path as real ones.

The rating model (all terms in VAS points, per item)::

    rating = clip(mean + effect[item, stimulus_set, condition]
                  + u[participant, item] + v[participant, item, stimulus_set, condition]
                  + e[trial, item],  low, high)

    u ~ N(0, participant_sd), v ~ N(0, interaction_sd), e ~ N(0, noise_sd)
    rt_s ~ LogNormal(log(rt_median_s), rt_log_sd)

``effect`` comes from the protocol's ``simulation`` section (defaults, then per item / set
overrides), with command-line effects replacing the defaults. The trial order is the
participant's real design (the protocol seed); the simulation seed only drives the ratings.
Times run on a simulated clock, so the same seed writes byte-identical logs. Every row says
``simulated = true`` and every session's JSON says ``"simulated": true`` with the model used.

A simulated session walks the same timeline of screens as a real one
(:func:`facelab.experiment.timeline.compile_timeline`) through the same walker and log.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from facelab.design import build_trials, needs_numbered_ids, participant_seed
from facelab.errors import StageError
from facelab.experiment.adaptive import Staircases
from facelab.experiment.timeline import (
    ChoiceAnswer,
    ChoiceScreen,
    ClipPairScreen,
    ClipScreen,
    ConversationAnswer,
    ConversationScreen,
    IdentifyAnswer,
    IdentifyScreen,
    MatrixScreen,
    PairPlayback,
    Playback,
    TextScreen,
    TypedAnswer,
    TypedScreen,
    VasAnswer,
    VasScreen,
    compile_timeline,
)
from facelab.experiment.walk import walk
from facelab.intelligibility_function import p_correct
from facelab.protocol import Protocol, protocol_hash
from facelab.protocol_model import TimingObserver
from facelab.sessionlog import (
    SessionContext,
    SessionLock,
    SessionLog,
    SessionPaths,
    session_paths,
)
from facelab.timing_function import p_timing

if TYPE_CHECKING:
    import pandas as pd

    from facelab.analysis.tasks import DesignSampler

__all__ = [
    "ChoiceModel",
    "RatingModel",
    "SimulatedParticipant",
    "check_effects",
    "condition_effect",
    "design_sampler",
    "simulate_participant",
    "simulate_study",
    "simulated_rows",
]

_CLOCK_START = dt.datetime(2026, 1, 1, 9, 0, 0, tzinfo=dt.UTC)
_CLIP_S = 8.0  # simulated clip length on the session clock (s)


def condition_effect(
    protocol: Protocol,
    *,
    item: str,
    stimulus_set: str,
    condition: str,
    effects: Mapping[str, float] | None = None,
) -> float:
    """The simulated effect (VAS points) for one item, stimulus set and condition."""
    sim = protocol.simulation
    value = (effects if effects is not None else sim.effects).get(condition, 0.0)
    for override in sim.overrides:
        if override.item not in (None, item) or override.stimulus_set not in (None, stimulus_set):
            continue
        value = override.effects.get(condition, value)
    return float(value)


class RatingModel:
    """Ratings of one simulated participant (see the module docstring); draws from ``rng``."""

    def __init__(
        self,
        protocol: Protocol,
        *,
        rng: np.random.Generator,
        effects: Mapping[str, float] | None = None,
    ):
        self.protocol = protocol
        self.model = protocol.simulation.model
        self.rng = rng
        self.effects = effects
        self.offsets = {
            item.id: rng.normal(0.0, self.model.participant_sd) for item in protocol.items
        }
        self.interaction: dict[tuple[str, str, str], float] = {}

    def rate(self, *, item: str, stimulus_set: str, condition: str) -> tuple[float, float]:
        """(rating on the item's scale, response time in s)."""
        key = (item, stimulus_set, condition)
        if key not in self.interaction:
            self.interaction[key] = self.rng.normal(0.0, self.model.interaction_sd)
        vas = next(i for i in self.protocol.items if i.id == item)
        value = (
            self.model.mean
            + condition_effect(
                self.protocol,
                item=item,
                stimulus_set=stimulus_set,
                condition=condition,
                effects=self.effects,
            )
            + self.offsets[item]
            + self.interaction[key]
            + self.rng.normal(0.0, self.model.noise_sd)
        )
        low, high = vas.range
        rt = float(self.rng.lognormal(np.log(self.model.rt_median_s), self.model.rt_log_sd))
        return round(float(np.clip(value, low, high)), 2), rt


class ChoiceModel:
    """Forced choices and identifications of one simulated participant (the protocol's
    ``simulation.observer`` and ``simulation.identifier``); draws from ``rng``.

    * forced choice: the comparison is chosen with ``P = gamma + (1 - gamma - lapse) *
      logistic(slope * (level - midpoint_p))``, gamma 1/2 when the task has a correct answer
      (else 0), ``midpoint_p ~ N(midpoint, midpoint_sd)`` per participant;
    * identification: the portrayed label with probability ``accuracy`` (or the trial's
      condition's ``condition_accuracy``, or a row of ``confusion``), otherwise one of the
      other labels uniformly.
    """

    def __init__(self, protocol: Protocol, *, rng: np.random.Generator):
        sim = protocol.simulation
        self.protocol, self.rng = protocol, rng
        self.observer, self.identifier = sim.observer, sim.identifier
        self.midpoint = float(
            rng.normal(sim.observer.midpoint, sim.observer.midpoint_sd)
            if sim.observer.midpoint_sd > 0
            else sim.observer.midpoint
        )
        self.rt = sim.model
        self._timing: dict[str, tuple[float, float]] = {}
        self._listener: float | None = None  # N(0, 1): how well this participant hears

    def p_comparison(self, *, level: float, scored: bool) -> float:
        gamma = 0.5 if scored else 0.0
        f = 1.0 / (1.0 + np.exp(-self.observer.slope * (level - self.midpoint)))
        return gamma + (1.0 - gamma - self.observer.lapse) * f

    def response_time(self) -> float:
        return float(self.rng.lognormal(np.log(self.rt.rt_median_s), self.rt.rt_log_sd))

    def choose(self, screen: ChoiceScreen) -> int:
        """The interval chosen, 1 or 2."""
        assert screen.trial is not None and screen.task is not None
        p = self.p_comparison(
            level=float(screen.level or 0.0), scored=screen.task.correct == "comparison"
        )
        comparison = bool(self.rng.random() < p)
        position = screen.trial.position or 1
        return position if comparison else 3 - position

    def timing_truth(self, series: str) -> tuple[float, float]:
        """This participant's (PSS, width) in ms for a condition series: the stated truth
        (``simulation.timing``), drawn once per series when it varies between people."""
        if series not in self._timing:
            truth = self.protocol.simulation.timing.get(series, TimingObserver())
            pss = truth.pss_ms + (self.rng.normal(0, truth.pss_sd_ms) if truth.pss_sd_ms else 0)
            width = truth.width_ms
            if truth.width_sd_ms:
                width = max(1.0, width + self.rng.normal(0, truth.width_sd_ms))
            self._timing[series] = (float(pss), float(width))
        return self._timing[series]

    def srt_of(self, series: str) -> float:
        """This participant's SRT (dB) in a condition series: the stated truth
        (``simulation.srt``) moved by ``srt_sd_db`` times one draw per participant - a
        listener better or worse than most is so in every series."""
        if self._listener is None:
            self._listener = float(self.rng.normal())
        truth = self.protocol.simulation.srt[series]
        return truth.srt_db + truth.srt_sd_db * self._listener

    def p_timing(self, *, judgment: str, series: str, offset_ms: float) -> float:
        """P(the task's timing label) at an offset: P(in sync) for simultaneity, P(voice
        first) for temporal order (:class:`~facelab.protocol_model.TimingObserver`)."""
        truth = self.protocol.simulation.timing.get(series, TimingObserver())
        pss, width = self.timing_truth(series)
        third = truth.peak if judgment == "simultaneity" else truth.lapse
        return float(p_timing(judgment, offset_ms, pss=pss, width=width, third=third,
                              floor=truth.floor))  # fmt: skip

    def _p_understood(self, screen: TypedScreen, *, guess: float = 0.0) -> float:
        """P(a word of the trial right): the series' listener at the SNR with the guess
        rate ``guess`` (``simulation.srt``), else the identifier's accuracy."""
        assert screen.trial is not None
        cond = self.protocol.condition(screen.trial.condition)
        listener = self.protocol.simulation.srt.get(cond.series_id)
        if cond.noise is not None and listener is not None:
            srt = self.srt_of(cond.series_id)
            return float(p_correct(cond.noise.snr_db, srt=srt, slope=listener.slope,
                                   guess=guess, lapse=listener.lapse))  # fmt: skip
        return float(self.identifier.condition_accuracy.get(screen.trial.condition,
                                                            self.identifier.accuracy))  # fmt: skip

    def typed(self, screen: TypedScreen) -> str:
        """A typed answer: each scoring unit of what was said (keyword, or mora of its
        reading) heard with P(SNR) of the series' listener (``simulation.srt``, no guessing
        in an open set), else with the identifier's accuracy; the units heard, in order."""
        assert screen.trial is not None and screen.task is not None
        p = self._p_understood(screen)
        if screen.task.scoring == "morae":
            from facelab.japanese_reading import morae, pronunciation

            units, sep = morae(pronunciation(screen.said)), ""
        else:
            units, sep = list(screen.keywords or screen.said.split() or [screen.said]), " "
        return sep.join(u for u in units if self.rng.random() < p)

    def matrix(self, screen: MatrixScreen) -> str:
        """A matrix answer: each word said picked right with P(SNR) of the series' listener
        (``simulation.srt``, its guess rate one in the column's length: the stated SRT is
        where half the words are right, as the analysis fits it), else a wrong word of its
        column at random; with no listener, right with the identifier's accuracy."""
        assert screen.task is not None
        picks = []
        for word, column in zip(screen.said.split(" "), screen.task.columns, strict=True):
            others = [w for w in column if w != word]
            right = self.rng.random() < self._p_understood(screen, guess=1.0 / len(column))
            picks.append(word if right else others[int(self.rng.integers(len(others)))])
        return " ".join(picks)

    def identify(self, screen: IdentifyScreen) -> str:
        assert screen.trial is not None and screen.task is not None
        labels = [lb.id for lb in screen.task.labels]
        timing = screen.task.timing
        if timing is not None:  # a synchrony judgment: the label, else another one
            cond = self.protocol.condition(screen.trial.condition)
            p = self.p_timing(judgment=timing.judgment, series=cond.series_id,
                              offset_ms=cond.audio_offset_ms)  # fmt: skip
            if self.rng.random() < p:
                return timing.label
            others = [lb for lb in labels if lb != timing.label]
            return others[int(self.rng.integers(len(others)))]
        target = screen.task.target(
            condition=screen.trial.condition, stimulus=screen.trial.stimulus
        )
        if target is None:
            return labels[int(self.rng.integers(len(labels)))]
        cond = self.protocol.condition(screen.trial.condition)
        listener = self.protocol.simulation.srt.get(cond.series_id)
        if cond.noise is not None and listener is not None:  # a word heard in noise
            p = p_correct(cond.noise.snr_db, srt=self.srt_of(cond.series_id),
                          slope=listener.slope, guess=1 / len(labels),
                          lapse=listener.lapse)  # fmt: skip
            if self.rng.random() < (p - 1 / len(labels)) / (1 - 1 / len(labels)):
                return target  # heard it; otherwise a guess among all the labels
            return labels[int(self.rng.integers(len(labels)))]
        row = self.identifier.condition_confusion.get(screen.trial.condition, {}).get(
            target
        ) or self.identifier.confusion.get(target)
        if row:
            probs = np.array([row.get(lb, 0.0) for lb in labels], dtype=float)
            return labels[int(self.rng.choice(len(labels), p=probs / probs.sum()))]
        accuracy = self.identifier.condition_accuracy.get(
            screen.trial.condition, self.identifier.accuracy
        )
        if self.rng.random() < accuracy:
            return target
        others = [lb for lb in labels if lb != target]
        return others[int(self.rng.integers(len(others)))]


class SimulatedParticipant:
    """A presenter (:mod:`facelab.experiment.walk`) that answers every screen from a
    :class:`RatingModel` on a simulated clock: clips take ``_CLIP_S`` seconds, each response
    its simulated response time. The practice trial is answered mid-scale without drawing
    from the generator, as the scripted participant of ``facelab run --simulate`` does."""

    def __init__(self, rater: RatingModel, chooser: ChoiceModel | None = None):
        self.rater = rater
        self.chooser = chooser
        self.clock = 0.0

    def text(self, screen: TextScreen) -> None:
        return None

    def clip(self, screen: ClipScreen) -> Playback:
        onset = self.clock
        self.clock += _CLIP_S
        return Playback(onset=round(onset, 3), dropped=0)

    def clip_pair(self, screen: ClipPairScreen) -> PairPlayback:
        both = self.clip(screen)  # watched together
        return PairPlayback(left=both, right=both)

    def vas(self, screen: VasScreen) -> list[VasAnswer]:
        answers = []
        for item in screen.items:
            if screen.trial is None or screen.practice:
                answers.append(
                    VasAnswer(item.id, (item.range[0] + item.range[1]) / 2, 1.0, self._stamp())
                )
                continue
            rating, rt = self.rater.rate(
                item=item.id,
                stimulus_set=screen.trial.stimulus_set,
                condition=screen.trial.condition,
            )
            self.clock += rt
            answers.append(VasAnswer(item.id, rating, round(rt, 3), self._stamp()))
        return answers

    def choice_2afc(self, screen: ChoiceScreen) -> list[ChoiceAnswer]:
        if screen.trial is None or screen.practice or self.chooser is None:
            return [ChoiceAnswer(1, 1.0, self._stamp())]
        choice = self.chooser.choose(screen)
        rt = self.chooser.response_time()
        self.clock += rt
        return [ChoiceAnswer(choice, round(rt, 3), self._stamp())]

    def identify(self, screen: IdentifyScreen) -> list[IdentifyAnswer]:
        assert screen.task is not None
        if screen.trial is None or screen.practice or self.chooser is None:
            return [IdentifyAnswer(screen.task.labels[0].id, 1.0, self._stamp())]
        label = self.chooser.identify(screen)
        rt = self.chooser.response_time()
        self.clock += rt
        return [IdentifyAnswer(label, round(rt, 3), self._stamp())]

    def typed(self, screen: TypedScreen) -> list[TypedAnswer]:
        return self._text_answer(screen, lambda chooser: chooser.typed(screen))

    def matrix(self, screen: MatrixScreen) -> list[TypedAnswer]:
        return self._text_answer(screen, lambda chooser: chooser.matrix(screen))

    def _text_answer(
        self, screen: TypedScreen, choose: Callable[[ChoiceModel], str]
    ) -> list[TypedAnswer]:
        """A typed or matrix answer: what was said on the practice trial, else the chooser's
        text after its response time."""
        if screen.trial is None or screen.practice or self.chooser is None:
            return [TypedAnswer(screen.said, 1.0, self._stamp())]
        text = choose(self.chooser)
        rt = self.chooser.response_time()
        self.clock += rt
        return [TypedAnswer(text, round(rt, 3), self._stamp())]

    def conversation(self, screen: ConversationScreen) -> list[ConversationAnswer]:
        """A live conversation: simulated as lasting its minutes, one turn heard."""
        self.clock += screen.seconds
        return [ConversationAnswer("time", 1, round(screen.seconds, 3), self._stamp())]

    def added_screen(self, screen: Any) -> list[Any]:
        """A package's added screen: the kind's own simulated answer
        (``AddedScreen.simulate``) with the rating model's response time."""
        from facelab.experiment.screen_kinds import AddedAnswer

        rng = self.chooser.rng if self.chooser is not None else self.rater.rng
        value = screen.simulate(rng)
        rt = float(rng.lognormal(np.log(self.rater.model.rt_median_s), self.rater.model.rt_log_sd))
        self.clock += rt
        return [AddedAnswer(value, round(rt, 3), self._stamp())]

    def _stamp(self) -> str:
        return (_CLOCK_START + dt.timedelta(seconds=self.clock)).isoformat()


def simulate_participant(
    protocol: Protocol,
    *,
    protocol_path: Path,
    results: Path,
    participant: str,
    session: int,
    rng: np.random.Generator,
    seed: int,
    effects: Mapping[str, float] | None = None,
) -> SessionPaths:
    """Write one complete simulated session; refuses to overwrite an existing one."""
    model = protocol.simulation.model
    trials = build_trials(protocol, participant=participant)
    digest = protocol_hash(protocol_path)
    provenance: dict[str, Any] = {
        "simulated": True,
        "mode": "simulated",
        "study": protocol.study.id,
        "participant": participant,
        "session": session,
        "protocol_file": str(protocol_path),
        "protocol_sha256": digest,
        "design_seed": participant_seed(protocol.seed, participant),
        "simulation_seed": seed,
        "simulation_model": model.model_dump(),
        "simulation_effects": {
            c.id: (effects if effects is not None else protocol.simulation.effects).get(c.id, 0.0)
            for c in protocol.conditions
        },
        "trial_order": [t.trial_index for t in trials],
        "trials": [[t.block, t.set_index, t.stimulus, t.condition, t.repetition] for t in trials],
    }
    paths = session_paths(
        results, study=protocol.study.id, participant=participant, session=session
    )
    with SessionLock(paths):
        log = SessionLog.create(
            results,
            study=protocol.study.id,
            participant=participant,
            session=session,
            provenance=provenance,
        )
        presenter = _answer_session(
            protocol,
            trials,
            participant=participant,
            session=session,
            rng=rng,
            effects=effects,
            protocol_sha256=digest,
            log=log,
            staircases=Staircases(protocol, record=log.paths.staircase),
        )
        log.update_provenance(finished=presenter._stamp())
    return log.paths


def _answer_session(
    protocol: Protocol,
    trials: list[Any],
    *,
    participant: str,
    session: int,
    rng: np.random.Generator,
    effects: Mapping[str, float] | None,
    protocol_sha256: str,
    log: Any,
    staircases: Staircases,
) -> SimulatedParticipant:
    """Walk one participant's timeline with a simulated participant, rows into ``log``."""
    context = SessionContext(
        study=protocol.study.id,
        participant=participant,
        session=session,
        simulated=True,
        protocol_sha256=protocol_sha256,
    )
    screens = compile_timeline(protocol, trials, participant=participant, session=session)
    rater = RatingModel(protocol, rng=rng, effects=effects)
    chooser = ChoiceModel(protocol, rng=rng) if protocol.tasks else None
    presenter = SimulatedParticipant(rater, chooser)
    walk(
        screens,
        presenter=presenter,
        log=log,
        context=context,
        record_playback=False,
        staircases=staircases,
    )
    return presenter


class _RowsInMemory:
    """The part of a session log :func:`walk` writes to, kept in memory."""

    def __init__(self) -> None:
        self.rows: list[dict[str, Any]] = []

    def append(self, row: dict[str, Any]) -> None:
        self.rows.append(dict(row))


def simulated_rows(
    protocol: Protocol,
    *,
    participant: str,
    rng: np.random.Generator,
    effects: Mapping[str, float] | None = None,
    session: int = 1,
) -> list[dict[str, Any]]:
    """One simulated participant's log rows, in memory (nothing is written): the same
    design, timeline and answer models as :func:`simulate_participant` - for power
    simulations that need thousands of sessions."""
    memory = _RowsInMemory()
    _answer_session(
        protocol,
        build_trials(protocol, participant=participant),
        participant=participant,
        session=session,
        rng=rng,
        effects=effects,
        protocol_sha256="",
        log=memory,
        staircases=Staircases(protocol),
    )
    return memory.rows


def design_sampler(protocol: Protocol) -> DesignSampler:
    """A :data:`facelab.analysis.tasks.DesignSampler` for ``protocol``: one participant
    simulated through the protocol's own design (its trial order, staircases or constant
    stimuli) by an observer with the given midpoint, logistic slope and lapse; returns the
    rows of the named task (the columns of :data:`facelab.analysis.tasks.SAMPLED_COLUMNS`).
    ``facelab analyze`` calibrates per-participant intervals with it."""

    import pandas as pd

    from facelab.analysis.tasks import SAMPLED_COLUMNS

    def sample(
        task: str, midpoint: float, slope: float, lapse: float, rng: np.random.Generator
    ) -> pd.DataFrame:
        observer = protocol.simulation.observer.model_copy(
            update={"midpoint": midpoint, "slope": min(slope, 1e4), "lapse": lapse,
                    "midpoint_sd": 0.0}
        )  # fmt: skip
        simulation = protocol.simulation.model_copy(update={"observer": observer})
        # a Latin-square order needs a participant number: a drawn one, so the calibration
        # spans the orders participants get
        participant = (f"C{int(rng.integers(1, 10**6))}" if needs_numbered_ids(protocol)
                       else "calibration")  # fmt: skip
        rows = simulated_rows(
            protocol.model_copy(update={"simulation": simulation}),
            participant=participant, rng=rng,
        )  # fmt: skip
        # the task's rows, only the columns the calibration reads (a frame of every column
        # took as long as the simulated session)
        mine = [r for r in rows if r["item"] == task]
        return pd.DataFrame({c: [r.get(c) for r in mine] for c in SAMPLED_COLUMNS})

    return sample


def check_effects(protocol: Protocol, effects: Mapping[str, float] | None) -> None:
    """Refuse effects (``--effect COND=POINTS``) of conditions the protocol does not have."""
    unknown = sorted(set(effects or {}) - {c.id for c in protocol.conditions})
    if unknown:
        raise StageError(
            f"--effect {', '.join(unknown)}: no such condition; conditions: "
            f"{', '.join(c.id for c in protocol.conditions)}"
        )


def simulate_study(
    protocol: Protocol,
    *,
    protocol_path: Path,
    results: Path,
    participants: int,
    seed: int,
    effects: Mapping[str, float] | None = None,
    session: int = 1,
) -> list[SessionPaths]:
    """Simulate ``participants`` sessions (P01, P02, …). Checks first that none exists."""
    if participants < 1:
        raise StageError(f"--participants must be at least 1, got {participants}")
    check_effects(protocol, effects)
    width = max(2, len(str(participants)))
    ids = [f"P{i:0{width}d}" for i in range(1, participants + 1)]
    existing = [
        pid
        for pid in ids
        if session_paths(
            results, study=protocol.study.id, participant=pid, session=session
        ).tsv.exists()
    ]
    if existing:
        raise StageError(
            f"sessions already exist in {results / protocol.study.id} for {', '.join(existing)}; "
            "nothing was overwritten - choose another results folder"
        )
    master = np.random.default_rng(seed)
    return [
        simulate_participant(
            protocol,
            protocol_path=protocol_path,
            results=results,
            participant=pid,
            session=session,
            rng=child,
            seed=seed,
            effects=effects,
        )
        for pid, child in zip(ids, master.spawn(len(ids)), strict=True)
    ]
