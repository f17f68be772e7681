"""The EMBOS planner (seed 003, eq. 1) for a talking head, deterministic for a seed.

Each layer (network) is planned in turn, upper to lower (:data:`LAYERS`), on a time grid of
``library.step_s``. While a unit holds (its L_d) the layer chooses nothing; otherwise every
unit m of the layer is scored

    score(m, t) = ω_c(m_d, m) · ω_l(m, M_u) · φ_time(m, t) · φ_state(m, t)          (eq. 1)

* ω_c - continuity from the previous unit of the layer (``library.continuity``; missing 1);
* ω_l - 0 when m would share a channel with a unit of an upper layer during its L_d, else 1;
* φ_time - 1 (max) while m holds, 0 (min) during its wait L_w after it ends, otherwise the
  steady value ``library.steady_time``;
* φ_state - closeness of m's intensity vector to the character's,
  c = 1 − Σ_k ĉ_k·(1 − I_m,k) with ĉ = I(t)/ΣI(t) (:func:`_closeness`), times
  E(rank) = (D − rank + 1)/D of c among the layer's D units (rank 1 = closest), times a
  trigger gain: units whose triggers ``require`` one get × 1
  when its start (placed so that its stroke lands on a trigger word or prosodic event) lies
  within :data:`LOOKAHEAD_S` after t
  and × ``min_gain`` otherwise; ``boost`` triggers give × ``gain`` near a trigger.

The best unit starts at t when its score exceeds ``library.rest_score``; its duration, wait
and pose are blended over the emotions by eq. 5 with Γ = exp(−(1 − i_k)²/r²) (each example
was acted at full intensity of its emotion k; i_k is the character's intensity) and σ_k = 1
where the unit was observed in k. The character's neutral component is eq. 4:
i_neutral = 1 − Σ_k i_k when that sum is below 1, else 0.

Randomness (the log-normal spread of waits, the first wait's phase, the side of a mirrored
unit) comes from one generator per layer seeded by ``(seed, layer)``: a layer planned with the
same seed, emotion, speech cues and upper layers gives the same events in every condition
(yoked randomness).
"""

from __future__ import annotations

import bisect
import hashlib
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from xml.sax.saxutils import quoteattr

import numpy as np

from facelab.errors import BehaviourError
from facelab.stimuli.behaviour.library import EMOTIONS, LAYERS, Library, Unit

__all__ = [
    "EmotionTimeline",
    "Event",
    "Plan",
    "SpeechCues",
    "complete_emotion",
    "parse_emotion",
    "plan_behaviour",
]


#: A triggered gesture whose start lies within this many seconds competes now; the layer waits
#: for the best candidate's start, so a better-suited gesture starting a little later is not
#: pre-empted by an earlier one.
LOOKAHEAD_S = 0.25


def parse_emotion(text: str) -> dict[str, float]:
    """``"joy=0.8,anger=0.1"`` -> {emotion: value}; errors name the bad part."""
    out: dict[str, float] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        name, sep, value = part.partition("=")
        name = name.strip().lower()
        if not sep or name not in EMOTIONS:
            raise BehaviourError(
                f"emotion {part!r}: write name=value with a name from {', '.join(EMOTIONS)}"
            )
        try:
            out[name] = float(value)
        except ValueError:
            raise BehaviourError(f"emotion {part!r}: {value!r} is not a number") from None
    if not out:
        raise BehaviourError(f"emotion {text!r}: give at least one name=value")
    return out


def complete_emotion(values: Mapping[str, float]) -> np.ndarray:
    """(7,) intensities in :data:`EMOTIONS` order, neutral by eq. 4 (a given neutral is
    replaced). Values must lie in [0, 1]."""
    vec = np.zeros(len(EMOTIONS))
    for name, v in values.items():
        if name not in EMOTIONS:
            raise BehaviourError(f"unknown emotion {name!r}; use {', '.join(EMOTIONS)}")
        if not 0 <= float(v) <= 1:
            raise BehaviourError(f"emotion {name}={v}: intensities lie in [0, 1]")
        vec[EMOTIONS.index(name)] = float(v)
    total = vec[:-1].sum()
    vec[-1] = 1 - total if total < 1 else 0.0
    return vec


@dataclass(frozen=True)
class EmotionTimeline:
    """The character's emotion over time: keys (time s, {emotion: value}), linearly
    interpolated, held before the first and after the last key; two keys at one time make a
    step (in the order given)."""

    keys: tuple[tuple[float, tuple[tuple[str, float], ...]], ...]

    @classmethod
    def constant(cls, values: Mapping[str, float]) -> EmotionTimeline:
        complete_emotion(values)  # validates
        return cls(((0.0, tuple(sorted(values.items()))),))

    @classmethod
    def from_keys(cls, keys: Iterable[tuple[float, Mapping[str, float]]]) -> EmotionTimeline:
        # sorted by time only (stable): keys given at one time keep their order, a step
        rows = sorted(((float(t), tuple(sorted(v.items()))) for t, v in keys), key=lambda r: r[0])
        if not rows:
            raise BehaviourError("an emotion timeline needs at least one key")
        bad = [t for t, _ in rows if not np.isfinite(t)]
        if bad:
            raise BehaviourError(f"emotion timeline: time {bad[0]} s is not a finite number")
        for _, v in rows:
            complete_emotion(dict(v))
        return cls(tuple(rows))

    def at(self, t: float) -> np.ndarray:
        vecs = [complete_emotion(dict(v)) for _, v in self.keys]
        times = [k[0] for k in self.keys]
        if t <= times[0]:
            return vecs[0]
        for i in range(len(times) - 1):
            (t0, v0), (t1, v1) = (times[i], vecs[i]), (times[i + 1], vecs[i + 1])
            if t0 <= t <= t1:
                a = (t - t0) / (t1 - t0) if t1 > t0 else 1.0
                return (1 - a) * v0 + a * v1
        return vecs[-1]

    def describe(self) -> list[dict]:
        return [{"time_s": t, **dict(v)} for t, v in self.keys]


@dataclass(frozen=True)
class SpeechCues:
    """What the planner knows about the utterance, in clip seconds: words (surface, start,
    end), accent peaks, breath-group ends, speaking intervals, pause starts."""

    words: tuple[tuple[str, float, float], ...] = ()
    accents: tuple[float, ...] = ()
    phrase_ends: tuple[float, ...] = ()
    speaking: tuple[tuple[float, float], ...] = ()
    pauses: tuple[float, ...] = ()
    text: str = ""

    @classmethod
    def from_speech(cls, speech, *, offset_s: float = 0.0) -> SpeechCues:
        """Cues of a :class:`~facelab.stimuli.speech.audio.Speech` (TTS: words and accent phrases
        from OpenJTalk; recorded audio: energy peaks as accent proxies), shifted by
        ``offset_s`` (the clip's leading pad)."""
        o = offset_s
        if speech.phones:
            spans, start = [], None
            pauses = []
            for p in speech.phones:
                if p.phoneme in ("sil", "pau"):
                    if start is not None:
                        spans.append((start + o, p.start + o))
                        start = None
                    if p.phoneme == "pau":
                        pauses.append(p.start + o)
                elif start is None:
                    start = p.start
            if start is not None:
                spans.append((start + o, speech.phones[-1].end + o))
            return cls(
                words=tuple(
                    (w.surface, w.start + o, w.end + o) for w in speech.words if w.morae > 0
                ),
                accents=tuple(a.peak + o for a in speech.accents),
                phrase_ends=tuple(a.end + o for a in speech.accents if a.final),
                speaking=tuple(spans),
                pauses=tuple(pauses),
                text=speech.source.removeprefix("tts:"),
            )
        return cls.from_audio(speech.samples, sample_rate=speech.sample_rate, offset_s=o)

    @classmethod
    def from_audio(
        cls, samples: np.ndarray, *, sample_rate: int, offset_s: float = 0.0
    ) -> SpeechCues:
        """Recorded speech without text: speaking where the 20 ms RMS is within 30 dB of the
        loudest frame; accent proxies at energy peaks at least 0.35 s apart."""
        hop = max(1, sample_rate // 100)
        n = len(samples) // hop
        if n < 3 or not np.any(samples):
            return cls()
        frames = samples[: n * hop].reshape(n, hop).astype(np.float64)
        rms = np.sqrt(np.convolve((frames**2).mean(axis=1), np.ones(2) / 2, mode="same"))
        db = 20 * np.log10(rms + 1e-9)
        voiced = db > db.max() - 30
        spans, i = [], 0
        while i < n:
            if voiced[i]:
                j = i
                while j < n and voiced[j]:
                    j += 1
                if j - i >= 5:
                    spans.append((i / 100 + offset_s, j / 100 + offset_s))
                i = j
            else:
                i += 1
        smooth = np.convolve(rms, np.hanning(15) / np.hanning(15).sum(), mode="same")
        peaks, last = [], -1.0
        for k in range(1, n - 1):
            t = k / 100
            if (
                voiced[k]
                and smooth[k] >= smooth[k - 1]
                and smooth[k] > smooth[k + 1]
                and t - last >= 0.35
            ):
                peaks.append(t + offset_s)
                last = t
        return cls(
            accents=tuple(peaks),
            phrase_ends=tuple(b for _, b in spans),
            speaking=tuple(spans),
            pauses=tuple(b for _, b in spans[:-1]),
        )

    def is_speaking(self, t: float) -> bool:
        return any(a <= t < b for a, b in self.speaking)

    def trigger_times(self, unit: Unit) -> list[tuple[float, str]]:
        """(time s, what) of every trigger of ``unit`` in this utterance."""
        trig = unit.triggers
        if trig is None:
            return []
        out: list[tuple[float, str]] = []
        for word in trig.words:
            for surface, a, b in self.words:
                if word in surface:
                    peak = next((p for p in self.accents if a <= p < b), a)
                    out.append((peak, f"word:{surface}"))
        for kind in trig.prosody:
            if kind == "accent":
                out += [(t, "accent") for t in self.accents]
            elif kind == "phrase_end":
                out += [(t, "phrase_end") for t in self.phrase_ends]
            elif kind == "pause":
                out += [(t, "pause") for t in self.pauses]
            elif kind == "utterance_start" and self.speaking:
                out.append((self.speaking[0][0], "utterance_start"))
        return sorted(set(out))


@dataclass
class Event:
    """One planned unit: times in clip seconds, channel amplitudes, BML sync times, scores."""

    unit: str
    layer: str
    start_s: float
    end_s: float
    channels: dict[str, float]
    sync: dict[str, float]
    scores: dict[str, float]
    trigger: str | None = None
    wait_s: float = 0.0
    emotion: dict[str, float] = field(default_factory=dict)


@dataclass
class Plan:
    """A behaviour plan: events of every layer, and how it was made."""

    events: list[Event]
    duration_s: float
    seed: int
    emotion: list[dict]
    layers: dict[str, str]  # layer -> "emotion" | "neutral"
    library_sha256: str
    notes: list[str] = field(default_factory=list)

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for e in self.events:
            out[e.unit] = out.get(e.unit, 0) + 1
        return dict(sorted(out.items()))

    def layer_counts(self) -> dict[str, int]:
        return {layer: sum(e.layer == layer for e in self.events) for layer in LAYERS}

    def to_json(self) -> dict:
        return {
            "format": "facelab-behaviour-plan-1",
            "duration_s": self.duration_s,
            "seed": self.seed,
            "emotion": self.emotion,
            "layers": self.layers,
            "library_sha256": self.library_sha256,
            "counts": self.counts(),
            "notes": self.notes,
            "events": [_round(asdict(e)) for e in self.events],
        }

    @classmethod
    def from_json(cls, data: Mapping) -> Plan:
        try:
            return cls(
                events=[Event(**e) for e in data["events"]],
                duration_s=float(data["duration_s"]),
                seed=int(data["seed"]),
                emotion=list(data.get("emotion", [])),
                layers=dict(data.get("layers", {})),
                library_sha256=str(data.get("library_sha256", "")),
                notes=list(data.get("notes", [])),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise BehaviourError(f"not a behaviour plan ({exc})") from None

    def to_bml(self, library: Library, *, character: str = "facelab") -> str:
        """The plan as BML 1.0 XML: one element per event (the unit's ``bml`` tag and
        attributes, else ``facelab:unit``), sync points as absolute times in seconds."""
        lines = [
            '<?xml version="1.0" encoding="UTF-8"?>',
            f'<bml xmlns="http://www.bml-initiative.org/bml/bml-1.0" '
            f'xmlns:facelab="https://facelab.invalid/bml" id="plan_seed{self.seed}" '
            f"characterId={quoteattr(character)}>",
        ]
        known = {u.behaviour: u for u in library.units}
        for i, e in enumerate(self.events, start=1):
            spec = dict(known[e.unit].bml) if e.unit in known else {}
            tag = spec.pop("tag", "facelab:unit")
            attrs = {"id": f"e{i}_{e.unit}", **spec}
            if tag == "facelab:unit":
                attrs["name"] = e.unit
            for name, t in e.sync.items():
                attrs[name.replace("_", "")] = f"{t:.3f}"
            if "amount" not in attrs and e.channels:
                attrs["amount"] = f"{max(abs(v) for v in e.channels.values()):.3f}"
            body = " ".join(f"{k}={quoteattr(str(v))}" for k, v in attrs.items())
            lines.append(f"  <{tag} {body}/>")
        lines.append("</bml>")
        return "\n".join(lines) + "\n"


def _round(obj):
    if isinstance(obj, float):
        return round(obj, 4)
    if isinstance(obj, dict):
        return {k: _round(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_round(v) for v in obj]
    return obj


def library_sha256(library: Library) -> str:
    text = json.dumps(library.model_dump(mode="json"), sort_keys=True, ensure_ascii=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


# ---------------------------------------------------------------------------- eq. 5


def _rbf_weights(character: np.ndarray, radius: float) -> np.ndarray:
    """Γ(1, i_k) = exp(−(1 − i_k)² / r²) per emotion k."""
    return np.exp(-((1.0 - character) ** 2) / radius**2)


def blend(values: Mapping[str, float], character: np.ndarray, *, radius: float) -> float:
    """Eq. 5 over the emotions a value exists for (σ_k = 1)."""
    if not values:
        raise BehaviourError("nothing to blend: the unit has no per-emotion values")
    w = _rbf_weights(character, radius)
    num = den = 0.0
    for name, v in values.items():
        k = EMOTIONS.index(name)
        num += w[k] * v
        den += w[k]
    if den < 1e-12:
        return float(np.mean(list(values.values())))
    return num / den


def blend_pose(unit: Unit, character: np.ndarray, *, radius: float) -> dict[str, float]:
    """Channel amplitudes: eq. 5 over the unit's examples (its per-emotion pose where given,
    else its ``channels``) for the emotions it was observed in."""
    if not unit.pose_by_emotion:
        return dict(unit.channels)
    observed = [e for e in EMOTIONS if e in unit.duration_s] or list(unit.pose_by_emotion)
    names = sorted(unit.channel_names())
    out = {}
    for ch in names:
        vals = {e: unit.pose_by_emotion.get(e, unit.channels).get(ch, 0.0) for e in observed}
        out[ch] = blend(vals, character, radius=radius)
    return out


# ---------------------------------------------------------------------------- eq. 1


def _closeness(units: Sequence[Unit], character: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """c_m = 1 − Σ_k ĉ_k·(1 − I_m,k) with ĉ = I/ΣI the character's normalised emotion: the
    distance of the unit's intensities from full intensity on the emotions the character
    feels, weighted by how much it feels them (1 = the unit fully expresses that mixture,
    0 = it belongs to other emotions); and each unit's rank by c (1 = closest, ties share the
    smallest rank)."""
    vecs = np.array([[u.intensity.get(e, 0.0) for e in EMOTIONS] for u in units])
    weights = character / character.sum() if character.sum() > 0 else character
    c = 1.0 - (weights * (1.0 - vecs)).sum(axis=1)
    order = (-c).argsort(kind="stable")
    ranks = np.empty(len(c), int)
    for pos, j in enumerate(order):  # ties share the smallest rank
        ranks[j] = pos + 1 if pos == 0 or c[j] != c[order[pos - 1]] else ranks[order[pos - 1]]
    return c, ranks


def _lognormal_factor(rng: np.random.Generator, cv: float) -> float:
    if cv <= 0:
        return 1.0
    sigma = math.sqrt(math.log1p(cv * cv))
    return float(rng.lognormal(-sigma * sigma / 2, sigma))


def plan_behaviour(
    library: Library,
    *,
    emotion: EmotionTimeline,
    duration_s: float,
    seed: int,
    cues: SpeechCues | None = None,
    layers: Sequence[str] = LAYERS,
    neutral_layers: Sequence[str] = (),
) -> Plan:
    """Plan ``duration_s`` seconds of behaviour (eq. 1 per layer, upper layers first).

    ``layers`` - the networks to plan; ``neutral_layers`` - networks planned with the
    neutral emotion whatever ``emotion`` says (the seed's gesture-only comparison keeps
    postures and mannerisms unchanged). Deterministic for (library, emotion, duration, seed,
    cues, layers)."""
    if duration_s <= 0:
        raise BehaviourError(f"duration {duration_s} s: must be positive")
    unknown = [layer for layer in [*layers, *neutral_layers] if layer not in LAYERS]
    if unknown:
        raise BehaviourError(f"unknown layer(s) {', '.join(unknown)}; use {', '.join(LAYERS)}")
    cues = cues or SpeechCues()
    neutral = EmotionTimeline.constant({"neutral": 1.0})
    notes: list[str] = []
    events: list[Event] = []
    for li, layer in enumerate(LAYERS):
        if layer not in layers:
            continue
        units = [u for u in library.layer(layer) if u.has_motion]
        skipped = [u.behaviour for u in library.layer(layer) if not u.has_motion]
        if skipped:
            notes.append(f"{layer}: no motion for {', '.join(skipped)} (not planned)")
        if not units:
            continue
        state = neutral if layer in neutral_layers else emotion
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), li]))
        events += _plan_layer(
            library, units, layer, state, duration_s, rng, cues, upper=list(events)
        )
    events.sort(key=lambda e: (e.start_s, LAYERS.index(e.layer)))
    return Plan(
        events=events,
        duration_s=float(duration_s),
        seed=int(seed),
        emotion=emotion.describe(),
        layers={
            layer: ("neutral" if layer in neutral_layers else "emotion")
            for layer in LAYERS
            if layer in layers
        },
        library_sha256=library_sha256(library),
        notes=notes,
    )


def _plan_layer(
    library: Library,
    units: list[Unit],
    layer: str,
    state: EmotionTimeline,
    duration_s: float,
    rng: np.random.Generator,
    cues: SpeechCues,
    *,
    upper: list[Event],
) -> list[Event]:
    step = library.step_s
    radius = library.rbf_radius
    d = len(units)
    start_char = state.at(0.0)
    wait_until = {}
    for u in units:
        # a stochastic untriggered unit (wait_cv > 0: blinks, mannerisms) starts at a random
        # phase of its wait, as a stationary process would; the others are ready at the start
        triggered = u.triggers is not None and u.triggers.mode == "require"
        first = (
            blend(u.wait_s, start_char, radius=radius) if u.wait_cv > 0 and not triggered else 0.0
        )
        wait_until[u.behaviour] = float(rng.uniform(0, first)) if first > 0 else 0.0
    triggers = {u.behaviour: cues.trigger_times(u) for u in units}  # sorted by time
    trigger_times = {b: [tau for tau, _ in times] for b, times in triggers.items()}
    channels = {u.behaviour: u.channel_names() for u in units}
    # the upper layers' events by start, to look only at those that can overlap a candidate
    # (looking at every one for every step and unit made a plan quadratic in its length)
    above = sorted(upper, key=lambda e: e.start_s)
    above_starts = [e.start_s for e in above]
    above_channels = [set(e.channels) for e in above]
    longest = max((e.end_s - e.start_s for e in above), default=0.0)
    out: list[Event] = []
    busy_until = -1.0
    last = "rest"
    n_steps = math.floor(duration_s / step)
    for k in range(n_steps):
        t = k * step
        if t < busy_until:
            continue
        char = state.at(t)
        close, ranks = _closeness(units, char)
        best: tuple[float, Unit, dict, float, str | None, float] | None = None
        for j, u in enumerate(units):
            l_d = blend(u.duration_s, char, radius=radius)
            trig_gain, trig_what, start = 1.0, None, t
            if u.triggers is not None:
                stroke = u.curve.phase("stroke") * l_d if u.curve else 0.0
                hit = None
                mine, times = triggers[u.behaviour], trigger_times[u.behaviour]
                if u.triggers.mode == "require":  # the first trigger whose stroke fits
                    ahead = t + max(step, LOOKAHEAD_S)
                    for tau, what in mine[bisect.bisect_left(times, t + stroke - 1e-9) :]:
                        s = tau - stroke
                        if s >= ahead:
                            break  # later triggers place it later still
                        if t <= s:
                            hit = (tau, what)
                            start = s  # placed so that its stroke lands on the trigger
                            break
                elif u.triggers.mode == "boost":
                    i = bisect.bisect_left(times, t - 0.3)
                    if i < len(mine) and mine[i][0] < t + step:
                        hit = mine[i]
                if u.triggers.mode == "require":
                    trig_gain = 1.0 if hit else u.triggers.min_gain
                else:
                    trig_gain = u.triggers.gain if hit else 1.0
                trig_what = hit[1] if hit else None
            if start + l_d > duration_s and layer != "posture":
                continue  # a posture may outlast the clip (it is seen being held)
            phi_time = 0.0 if start < wait_until[u.behaviour] else library.steady_time
            near = range(bisect.bisect_left(above_starts, start - longest - 1e-9),
                         bisect.bisect_left(above_starts, start + l_d))  # fmt: skip
            omega_l = (
                0.0
                if any(
                    above[i].start_s < start + l_d
                    and start < above[i].end_s
                    and channels[u.behaviour] & above_channels[i]
                    for i in near
                )
                else 1.0
            )
            omega_c = library.continuity.get(last, {}).get(u.behaviour, 1.0)
            e_rank = (d - ranks[j] + 1) / d
            phi_state = close[j] * e_rank * trig_gain
            total = omega_c * omega_l * phi_time * phi_state
            scores = {
                "omega_c": omega_c,
                "omega_l": omega_l,
                "phi_time": phi_time,
                "phi_state": phi_state,
                "closeness": float(close[j]),
                "rank": int(ranks[j]),
                "trigger_gain": trig_gain,
                "total": total,
            }
            if best is None or total > best[0]:
                best = (total, u, scores, l_d, trig_what, start)
        if best is None or best[0] <= library.rest_score:
            continue
        total, u, scores, l_d, trig_what, start = best
        if start >= t + step:
            continue  # the best starts later: wait for it (a better one may still appear)
        wait = blend(u.wait_s, char, radius=radius)
        if cues.is_speaking(start):
            wait *= u.speaking_wait_factor
        wait *= _lognormal_factor(rng, u.wait_cv)
        amps = blend_pose(u, char, radius=radius)
        if u.mirror and rng.random() < 0.5:
            amps = {c: (-v if Unit.mirrored(c) else v) for c, v in amps.items()}
        sync = {
            name: start + phase * l_d
            for name, phase in {
                "start": 0.0,
                **(u.curve.sync if u.curve else {}),
                "stroke": u.curve.phase("stroke") if u.curve else 0.5,
                "end": 1.0,
            }.items()
        }
        out.append(
            Event(
                unit=u.behaviour,
                layer=layer,
                start_s=start,
                end_s=start + l_d,
                channels=amps,
                sync=dict(sorted(sync.items(), key=lambda kv: kv[1])),
                scores=scores,
                trigger=trig_what,
                wait_s=wait,
                emotion={e: float(v) for e, v in zip(EMOTIONS, char, strict=True) if v > 0},
            )
        )
        busy_until = start + l_d
        wait_until[u.behaviour] = start + l_d + wait
        last = u.behaviour
    return out
