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
Times run on a simulated clock, so the same seed writes byte-identical logs. Every session's
JSON says ``"simulated": true`` with the model used.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from facelab.design import build_trials, participant_seed
from facelab.errors import StageError
from facelab.protocol import Protocol, protocol_hash
from facelab.sessionlog import SessionLog, SessionPaths, rating_row, session_paths

__all__ = ["RatingModel", "condition_effect", "simulate_participant", "simulate_study"]

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
    provenance: dict[str, Any] = {
        "simulated": True,
        "study": protocol.study.id,
        "participant": participant,
        "session": session,
        "protocol_file": str(protocol_path),
        "protocol_sha256": protocol_hash(protocol_path),
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
    log = SessionLog.create(
        results,
        study=protocol.study.id,
        participant=participant,
        session=session,
        provenance=provenance,
    )
    rater = RatingModel(protocol, rng=rng, effects=effects)
    clock = 0.0
    for trial in trials:
        clip_onset = clock
        clock += _CLIP_S
        for item in protocol.items:
            rating, rt = rater.rate(
                item=item.id, stimulus_set=trial.stimulus_set, condition=trial.condition
            )
            clock += rt
            log.append(
                rating_row(
                    study=protocol.study.id,
                    participant=participant,
                    session=session,
                    trial=trial,
                    item=item.id,
                    rating=rating,
                    rt_s=round(rt, 3),
                    clip_onset=round(clip_onset, 3),
                    clip_frames_dropped=0,
                    timestamp=(_CLOCK_START + dt.timedelta(seconds=clock)).isoformat(),
                )
            )
    return log.paths


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
    unknown = sorted(set(effects or {}) - {c.id for c in protocol.conditions})
    if unknown:
        raise StageError(
            f"unknown condition(s) in effects: {', '.join(unknown)}; conditions: "
            f"{', '.join(c.id for c in protocol.conditions)}"
        )
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
