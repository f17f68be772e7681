"""Protocol files: typed models for a study, loading from YAML, and validation.

A protocol is one YAML file describing a whole study: metadata, conditions (an animation
method from :data:`stimuli.methods.METHODS` plus its parameters), stimulus sets, blocks,
VAS items, presentation and rendering settings, and the seed.

:func:`load_protocol` reads a file and returns a frozen :class:`Protocol`, or raises
:class:`~experiment.errors.ProtocolError` listing every problem with the file, the line and
the key path, and what was expected. Unknown keys are errors everywhere. Nothing in a
protocol is evaluated as code.

The JSON Schema of the format is :func:`json_schema`; ``protocols/schema/protocol.schema.json``
is generated from it (``facelab schema``) and a test keeps the two identical.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Annotated, Any, Literal, get_args, get_origin

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StringConstraints,
    ValidationError,
    model_validator,
)

from experiment.errors import Issue, ProtocolError
from stimuli.methods import BUILTIN_Z, METHODS

__all__ = [
    "SCHEMA_VERSION",
    "Block",
    "Condition",
    "Protocol",
    "Rendering",
    "Stimulus",
    "StimulusSet",
    "VasItem",
    "json_schema",
    "load_protocol",
    "protocol_hash",
]

SCHEMA_VERSION = 1

Id = Annotated[
    str,
    StringConstraints(pattern=r"^[A-Za-z][A-Za-z0-9_-]{0,63}$"),
    Field(description="An identifier: a letter, then letters, digits, _ or - (at most 64)."),
]
LangCode = Annotated[str, StringConstraints(pattern=r"^[a-z]{2,3}(-[A-Za-z0-9]+)?$")]
Text = Annotated[str, StringConstraints(min_length=1)]
Localized = Annotated[
    dict[LangCode, Text],
    Field(
        min_length=1,
        description="Text by language code, e.g. {ja: 自然な表情, en: natural expression}.",
    ),
]
AUDIO_SUFFIXES = (".wav", ".flac")
AVATAR_SUFFIXES = (".gltf", ".glb")


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


# --------------------------------------------------------------------------- study & conditions


class Study(_Model):
    """Who and what: identifies the study in every log row and report."""

    id: Id = Field(description="Short study id; results go to results/<id>/.")
    title: Text
    description: str = ""
    reference: str = Field("", description="The publication this protocol reproduces, if any.")
    participants_planned: int = Field(ge=1, le=10_000)
    notes: str = ""


class Condition(_Model):
    """One animation condition: a registered method and its parameters."""

    id: Id
    label: Localized
    method: str = Field(description=f"One of: {', '.join(METHODS)}.")
    params: dict[str, Any] = Field(
        default_factory=dict, description="Parameters of the method; see stimuli.methods."
    )


# --------------------------------------------------------------------------- stimuli


class TtsOptions(_Model):
    """OpenJTalk synthesis options for a text stimulus."""

    voice: Literal["mei_normal"] = "mei_normal"
    speed: float = Field(1.0, ge=0.5, le=2.0, description="Speaking rate factor (open_jtalk -r).")
    pitch_halftones: float = Field(0.0, ge=-12, le=12, description="Pitch shift (open_jtalk -fm).")
    alpha: float | None = Field(
        None,
        ge=0.0,
        le=1.0,
        description="All-pass constant, a voice-quality change (open_jtalk -a).",
    )


class Stimulus(_Model):
    """One speech stimulus: a text for TTS or a recorded audio file."""

    id: Id
    text: Text | None = Field(None, description="Japanese text to synthesise.")
    audio: Text | None = Field(None, description="WAV or FLAC file, relative to the protocol.")
    tts: TtsOptions = Field(default_factory=TtsOptions)
    expected_vowels: Annotated[str, StringConstraints(pattern=r"^[aiueo]+$")] | None = Field(
        None, description="The vowels spoken, in order (e.g. aiueo); needed for vowel isolation."
    )
    vowel_isolation: list[Id] = Field(
        default_factory=list,
        description="Condition ids for which only the intended vowel's intensity is kept in "
        "each vowel segment (the rest set to 0).",
    )
    note: str = ""

    @model_validator(mode="after")
    def _one_source(self) -> Stimulus:
        if (self.text is None) == (self.audio is None):
            raise ValueError("give exactly one of 'text' (for TTS) or 'audio' (a recording)")
        if self.vowel_isolation and self.expected_vowels is None:
            raise ValueError("'vowel_isolation' needs 'expected_vowels' (e.g. aiueo)")
        return self


class StimulusSet(_Model):
    id: Id
    description: str = ""
    stimuli: list[Stimulus] = Field(min_length=1)


# --------------------------------------------------------------------------- blocks & items

Order = Literal["random_within_set", "fixed", "latin_square"]


class Block(_Model):
    """A run of sets; each set shows every (stimulus, condition) pair a fixed number of times."""

    id: Id
    stimulus_set: Id
    sets: int = Field(ge=1, le=100, description="How many sets the block has.")
    presentations_per_condition: int = Field(
        ge=1, le=100, description="How often each condition is shown per stimulus in one set."
    )
    order: Order = Field(
        "random_within_set",
        description="random_within_set: shuffled anew in every set; fixed: protocol order; "
        "latin_square: condition order from a balanced Latin square row chosen by the "
        "participant number (needs ids ending in a number).",
    )
    conditions: list[Id] | None = Field(None, description="Subset of conditions; default all.")
    break_after: bool = Field(True, description="Offer a break screen after this block.")


class VasItem(_Model):
    """One visual analogue scale item shown after each clip."""

    id: Id
    question: Localized
    left_anchor: Localized
    right_anchor: Localized
    range: list[float] = Field(
        default_factory=lambda: [0.0, 100.0],
        min_length=2,
        max_length=2,
        description="[left end, right end] of the scale; within 0..100.",
    )
    marker_start: Literal["hidden"] = Field(
        "hidden",
        description="No marker until the first click, so no start value can be logged "
        "as an answer.",
    )
    confirm: bool = Field(True, description="Require a confirm button press after rating.")


# ------------------------------------------------------------------------ presentation, rendering


class Practice(_Model):
    stimulus_set: Id
    stimulus: Id
    condition: Id


class Presentation(_Model):
    language: LangCode = Field("ja", description="Language of all participant-facing text.")
    items_layout: Literal["sequential", "together"] = "sequential"
    fullscreen: bool = True
    instructions: Localized | None = None
    practice: Practice | None = None
    break_text: Localized | None = None
    end_text: Localized | None = None


class Camera(_Model):
    distance_m: float = Field(0.65, gt=0.1, le=5.0, description="Eye-to-face distance.")
    fov_deg: float = Field(30.0, gt=5, lt=120, description="Vertical field of view.")
    height_m: float = Field(0.0, ge=-0.5, le=0.5, description="Camera height relative to the eyes.")


class Rendering(_Model):
    width: int = Field(1280, ge=64, le=7680)
    height: int = Field(720, ge=64, le=4320)
    fps: int = Field(30, ge=1, le=240)
    avatar: Text = Field("default", description="'default' or a .gltf/.glb file.")
    camera: Camera = Field(default_factory=Camera)
    pad_s: float = Field(0.3, ge=0.0, le=5.0, description="Neutral face before and after speech.")
    msaa: Literal[1, 2, 4, 8] = Field(
        1,
        description="Multisample anti-aliasing: 1 renders 720p faster than real time on a "
        "2-core CPU; 4 is smoother and about 1.7x slower.",
    )
    audio_sample_rate: int = Field(48000, ge=8000, le=192000)
    background: list[float] = Field(
        default_factory=lambda: [0.5, 0.5, 0.5], min_length=3, max_length=3
    )


# ------------------------------------------------------------------ simulation, reported results


class SimulationModel(_Model):
    """Simulated rating = clip(mean + effect + participant offset + interaction + noise, scale)."""

    mean: float = Field(50.0, ge=0, le=100, description="Mean rating with no condition effect.")
    participant_sd: float = Field(
        10.0, ge=0, le=100, description="SD of participant offsets (per item)."
    )
    interaction_sd: float = Field(
        4.0, ge=0, le=100, description="SD of participant x condition effects."
    )
    noise_sd: float = Field(12.0, ge=0, le=100, description="SD of rating-to-rating noise.")
    rt_median_s: float = Field(3.0, gt=0, le=60, description="Median response time (log-normal).")
    rt_log_sd: float = Field(0.35, ge=0, le=3, description="SD of log response time.")


class EffectOverride(_Model):
    """Condition effects for one item and/or stimulus set, replacing the defaults there."""

    item: Id | None = None
    stimulus_set: Id | None = None
    effects: dict[Id, float]


class Simulation(_Model):
    """How ``facelab simulate`` generates ratings; never presented as data."""

    model: SimulationModel = Field(default_factory=SimulationModel)
    effects: dict[Id, float] = Field(
        default_factory=dict, description="Condition id -> points added to the mean (default 0)."
    )
    overrides: list[EffectOverride] = Field(default_factory=list)


class ReportedPair(_Model):
    a: Id
    b: Id
    p: float = Field(ge=0, le=1)


class ReportedTest(_Model):
    item: Id
    stimulus_set: Id
    anova_p: float = Field(ge=0, le=1)
    pairs: list[ReportedPair] = Field(
        default_factory=list, description="Pairs reported as different; others were not."
    )


class ReportedResults(_Model):
    """Statistics a publication reported for this design, shown beside facelab's."""

    source: Text
    procedure: Text
    tests: list[ReportedTest] = Field(min_length=1)


# --------------------------------------------------------------------------- the protocol


class Protocol(_Model):
    """A whole study. Build one with :func:`load_protocol`, which also checks references."""

    schema_version: Literal[1] = SCHEMA_VERSION
    study: Study
    seed: int = Field(ge=0, lt=2**63, description="Study seed; participant seeds derive from it.")
    conditions: list[Condition] = Field(min_length=1)
    stimulus_sets: list[StimulusSet] = Field(min_length=1)
    blocks: list[Block] = Field(min_length=1)
    items: list[VasItem] = Field(min_length=1)
    presentation: Presentation = Field(default_factory=Presentation)
    rendering: Rendering = Field(default_factory=Rendering)
    simulation: Simulation = Field(default_factory=Simulation)
    reported_results: ReportedResults | None = None

    # -- convenience lookups (the loader guarantees the ids are unique)
    def condition(self, condition_id: str) -> Condition:
        return next(c for c in self.conditions if c.id == condition_id)

    def stimulus_set(self, set_id: str) -> StimulusSet:
        return next(s for s in self.stimulus_sets if s.id == set_id)

    def block_conditions(self, block: Block) -> list[str]:
        return list(block.conditions) if block.conditions else [c.id for c in self.conditions]


def json_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of the protocol format."""
    schema = Protocol.model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "facelab protocol"
    return schema


def protocol_hash(path: Path | str) -> str:
    """SHA-256 of the protocol file's bytes, as logged with every session."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


# --------------------------------------------------------------------------- loading


def load_protocol(path: Path | str) -> Protocol:
    """Read, validate and cross-check a protocol file.

    Raises
    ------
    ProtocolError
        With every problem found: file, line, key path and what was expected.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ProtocolError(path, [Issue((), "file not found")]) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ProtocolError(
            path, [Issue((), f"cannot read the file as UTF-8 text: {exc}")]
        ) from None

    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.load(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        problem = getattr(exc, "problem", None) or str(exc)
        raise ProtocolError(path, [Issue((), f"not valid YAML: {problem}", line)]) from None
    if root is None or not isinstance(data, dict):
        raise ProtocolError(path, [Issue((), "expected a YAML mapping with the study's sections")])

    locator = _Locator(root)
    issues = list(locator.duplicate_keys())
    if issues:
        raise ProtocolError(path, issues)

    try:
        protocol = Protocol.model_validate(data)
    except ValidationError as exc:
        found: dict[tuple[str | int, ...], Issue] = {}
        for err in exc.errors():
            issue = _issue_from_pydantic(err, locator)
            found.setdefault(issue.path, issue)  # one message per key path
        raise ProtocolError(path, list(found.values())) from None

    issues = [
        Issue(i.path, i.message, locator.line(i.path))
        for i in _cross_check(protocol, base_dir=path.parent)
    ]
    if issues:
        raise ProtocolError(path, issues)
    return protocol


class _Locator:
    """Maps key paths to 1-based line numbers using the composed YAML node tree."""

    def __init__(self, root: yaml.Node):
        self.root = root

    def node(self, path: Iterable[str | int]) -> tuple[yaml.Node, bool]:
        """The deepest node along ``path`` and whether the whole path was found."""
        node = self.root
        for part in path:
            child = None
            if isinstance(node, yaml.MappingNode):
                for key, value in node.value:
                    if key.value == str(part):
                        child = value
                        break
            elif (
                isinstance(node, yaml.SequenceNode)
                and isinstance(part, int)
                and 0 <= part < len(node.value)
            ):
                child = node.value[part]
            if child is None:
                return node, False
            node = child
        return node, True

    def key_line(self, path: tuple[str | int, ...]) -> int | None:
        """Line of the *key* that ends ``path`` (for unknown keys), else of the value."""
        if path and isinstance(path[-1], str):
            parent, found = self.node(path[:-1])
            if found and isinstance(parent, yaml.MappingNode):
                for key, _ in parent.value:
                    if key.value == path[-1]:
                        return key.start_mark.line + 1
        return self.line(path)

    def line(self, path: tuple[str | int, ...]) -> int | None:
        node, _ = self.node(path)
        return node.start_mark.line + 1

    def duplicate_keys(self) -> Iterator[Issue]:
        def walk(node: yaml.Node, path: tuple[str | int, ...]) -> Iterator[Issue]:
            if isinstance(node, yaml.MappingNode):
                seen: dict[str, int] = {}
                for key, value in node.value:
                    name = str(key.value)
                    if name in seen:
                        yield Issue(
                            (*path, name),
                            f"duplicate key (first given on line {seen[name]}); give it once",
                            key.start_mark.line + 1,
                        )
                    seen.setdefault(name, key.start_mark.line + 1)
                    yield from walk(value, (*path, name))
            elif isinstance(node, yaml.SequenceNode):
                for i, item in enumerate(node.value):
                    yield from walk(item, (*path, i))

        yield from walk(self.root, ())


def _clean_loc(loc: tuple[Any, ...]) -> tuple[str | int, ...]:
    # pydantic adds union/validator tags such as 'str' or 'function-after[...]'; drop them.
    out: list[str | int] = []
    for part in loc:
        if isinstance(part, str) and (part.startswith("function-") or part in _TYPE_TAGS):
            continue
        out.append(part)
    return tuple(out)


_TYPE_TAGS = {
    "str",
    "int",
    "float",
    "bool",
    "list[str]",
    "none",
    "dict[str,str]",
    "list[float]",
    "constrained-str",
    "dict[str,any]",
}


def _describe(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _issue_from_pydantic(err: Any, locator: _Locator) -> Issue:
    path = _clean_loc(err["loc"])
    kind = err["type"]
    if "[key]" in path:
        path = path[: path.index("[key]")]
        return Issue(
            path,
            f"{path[-1]!r} is not a language code (expected e.g. ja, en); "
            "quote texts that contain commas or colons",
            locator.key_line(path),
        )
    if kind == "extra_forbidden":
        allowed = _allowed_keys(path[:-1])
        hint = f"; allowed keys here: {', '.join(allowed)}" if allowed else ""
        return Issue(path, f"unknown key{hint}", locator.key_line(path))
    if kind == "missing":
        return Issue(path, "required key is missing", locator.key_line(path[:-1]))
    got = f" (got {_describe(err['input'])})" if "input" in err else ""
    message = err["msg"]
    if message.startswith("Value error, "):
        message = message[len("Value error, ") :]
        got = ""
    elif message.startswith("Input should be"):
        message = "expected a value that " + message[len("Input ") :].replace("should be", "is", 1)
    return Issue(path, message + got, locator.line(path))


def _allowed_keys(path: tuple[str | int, ...]) -> list[str]:
    """Field names of the model found at ``path`` inside :class:`Protocol`, if any."""
    model: Any = Protocol
    for part in path:
        if isinstance(part, int):
            continue
        field = getattr(model, "model_fields", {}).get(part)
        if field is None:
            return []
        model = _unwrap(field.annotation)
    return list(getattr(model, "model_fields", {}))


def _unwrap(annotation: Any) -> Any:
    while get_origin(annotation) is not None:
        args = [a for a in get_args(annotation) if a is not type(None)]
        if not args:
            return annotation
        annotation = args[0]
    return annotation


# --------------------------------------------------------------------------- cross-references


def _duplicates(ids: Iterable[str], path: tuple[str | int, ...], what: str) -> Iterator[Issue]:
    seen: dict[str, int] = {}
    for i, item_id in enumerate(ids):
        if item_id in seen:
            yield Issue(
                (*path, i, "id"), f"duplicate {what} id {item_id!r} (also at index {seen[item_id]})"
            )
        seen.setdefault(item_id, i)


def _localized(protocol: Protocol) -> Iterator[tuple[tuple[str | int, ...], dict[str, str]]]:
    for i, cond in enumerate(protocol.conditions):
        yield ("conditions", i, "label"), cond.label
    for i, item in enumerate(protocol.items):
        for key in ("question", "left_anchor", "right_anchor"):
            yield ("items", i, key), getattr(item, key)
    pres = protocol.presentation
    for key in ("instructions", "break_text", "end_text"):
        if getattr(pres, key) is not None:
            yield ("presentation", key), getattr(pres, key)


def _cross_check(protocol: Protocol, *, base_dir: Path) -> Iterator[Issue]:
    """Checks that span sections: ids, references, files, method parameters, languages."""
    yield from _duplicates((c.id for c in protocol.conditions), ("conditions",), "condition")
    yield from _duplicates(
        (s.id for s in protocol.stimulus_sets), ("stimulus_sets",), "stimulus set"
    )
    yield from _duplicates((b.id for b in protocol.blocks), ("blocks",), "block")
    yield from _duplicates((i.id for i in protocol.items), ("items",), "item")
    condition_ids = {c.id for c in protocol.conditions}
    known_conditions = ", ".join(c.id for c in protocol.conditions)
    sets = {s.id: s for s in protocol.stimulus_sets}

    for i, cond in enumerate(protocol.conditions):
        where = ("conditions", i)
        spec = METHODS.get(cond.method)
        if spec is None:
            yield Issue(
                (*where, "method"),
                f"unknown method {cond.method!r}; registered methods: {', '.join(METHODS)}",
            )
            continue
        try:
            params = spec.params.model_validate(cond.params)
        except ValidationError as exc:
            for err in exc.errors():
                loc = _clean_loc(err["loc"])
                if err["type"] == "extra_forbidden":
                    msg = (
                        f"unknown parameter for method {cond.method!r}; "
                        f"allowed: {', '.join(spec.params.model_fields) or '(none)'}"
                    )
                else:
                    msg = f"{err['msg']} (got {_describe(err.get('input'))})"
                yield Issue((*where, "params", *loc), msg)
            continue
        z = getattr(params, "z", None)
        if z is not None and z not in BUILTIN_Z:
            z_path = base_dir / z
            if z_path.suffix.lower() != ".csv" or not z_path.is_file():
                yield Issue(
                    (*where, "params", "z"),
                    f"expected one of {', '.join(BUILTIN_Z)} or an existing .csv file "
                    f"(52 rows x 5 vowels); {z_path} was not found",
                )

    for si, sset in enumerate(protocol.stimulus_sets):
        yield from _duplicates(
            (s.id for s in sset.stimuli), ("stimulus_sets", si, "stimuli"), "stimulus"
        )
        for ti, stim in enumerate(sset.stimuli):
            where = ("stimulus_sets", si, "stimuli", ti)
            if stim.audio is not None:
                audio = base_dir / stim.audio
                if audio.suffix.lower() not in AUDIO_SUFFIXES:
                    yield Issue(
                        (*where, "audio"), f"expected a .wav or .flac file, got {stim.audio!r}"
                    )
                elif not audio.is_file():
                    yield Issue((*where, "audio"), f"audio file not found: {audio}")
            for ci, cond_id in enumerate(stim.vowel_isolation):
                if cond_id not in condition_ids:
                    yield Issue(
                        (*where, "vowel_isolation", ci),
                        f"unknown condition {cond_id!r}; conditions: {known_conditions}",
                    )

    for bi, block in enumerate(protocol.blocks):
        where = ("blocks", bi)
        sset = sets.get(block.stimulus_set)
        if sset is None:
            yield Issue(
                (*where, "stimulus_set"),
                f"unknown stimulus set {block.stimulus_set!r}; sets: {', '.join(sets)}",
            )
        if block.conditions is not None:
            if not block.conditions:
                yield Issue(
                    (*where, "conditions"),
                    "empty list: the block would have no trials; "
                    "omit the key to use every condition",
                )
            for ci, cond_id in enumerate(block.conditions):
                if cond_id not in condition_ids:
                    yield Issue(
                        (*where, "conditions", ci),
                        f"unknown condition {cond_id!r}; conditions: {known_conditions}",
                    )
            if len(set(block.conditions)) != len(block.conditions):
                yield Issue((*where, "conditions"), "a condition is listed twice")
        if sset is not None:
            for cond_id in protocol.block_conditions(block):
                cond = next((c for c in protocol.conditions if c.id == cond_id), None)
                spec = METHODS.get(cond.method) if cond else None
                if spec and spec.needs_text and any(s.text is None for s in sset.stimuli):
                    yield Issue(
                        (*where, "stimulus_set"),
                        f"condition {cond_id!r} uses method {cond.method!r}, which needs a "
                        f"text for every stimulus, but set {sset.id!r} has recorded audio",
                    )

    for ii, item in enumerate(protocol.items):
        lo, hi = item.range
        if not (0.0 <= lo < hi <= 100.0):
            yield Issue(
                ("items", ii, "range"),
                f"expected [left, right] with 0 <= left < right <= 100, got [{lo:g}, {hi:g}]",
            )

    lang = protocol.presentation.language
    for path, text in _localized(protocol):
        if lang not in text:
            yield Issue(
                path,
                f"no {lang!r} text (presentation.language is {lang!r}); has: {', '.join(text)}",
            )

    practice = protocol.presentation.practice
    if practice is not None:
        where = ("presentation", "practice")
        pset = sets.get(practice.stimulus_set)
        if pset is None:
            yield Issue((*where, "stimulus_set"), f"unknown stimulus set {practice.stimulus_set!r}")
        elif practice.stimulus not in {s.id for s in pset.stimuli}:
            yield Issue(
                (*where, "stimulus"),
                f"stimulus {practice.stimulus!r} is not in set {practice.stimulus_set!r}",
            )
        if practice.condition not in condition_ids:
            yield Issue((*where, "condition"), f"unknown condition {practice.condition!r}")

    item_ids = {i.id for i in protocol.items}
    sim = protocol.simulation
    for cond_id in sim.effects:
        if cond_id not in condition_ids:
            yield Issue(
                ("simulation", "effects", cond_id),
                f"unknown condition {cond_id!r}; conditions: {known_conditions}",
            )
    for oi, override in enumerate(sim.overrides):
        where = ("simulation", "overrides", oi)
        if override.item is not None and override.item not in item_ids:
            yield Issue((*where, "item"), f"unknown item {override.item!r}")
        if override.stimulus_set is not None and override.stimulus_set not in sets:
            yield Issue((*where, "stimulus_set"), f"unknown stimulus set {override.stimulus_set!r}")
        for cond_id in override.effects:
            if cond_id not in condition_ids:
                yield Issue((*where, "effects", cond_id), f"unknown condition {cond_id!r}")
    if protocol.reported_results is not None:
        for ti, test in enumerate(protocol.reported_results.tests):
            where = ("reported_results", "tests", ti)
            if test.item not in item_ids:
                yield Issue((*where, "item"), f"unknown item {test.item!r}")
            if test.stimulus_set not in sets:
                yield Issue((*where, "stimulus_set"), f"unknown stimulus set {test.stimulus_set!r}")
            for pi, pair in enumerate(test.pairs):
                for key in ("a", "b"):
                    if getattr(pair, key) not in condition_ids:
                        yield Issue(
                            (*where, "pairs", pi, key), f"unknown condition {getattr(pair, key)!r}"
                        )

    avatar = protocol.rendering.avatar
    if avatar != "default":
        avatar_path = base_dir / avatar
        if avatar_path.suffix.lower() not in AVATAR_SUFFIXES:
            yield Issue(
                ("rendering", "avatar"), f"expected 'default' or a .gltf/.glb file, got {avatar!r}"
            )
        elif not avatar_path.is_file():
            yield Issue(("rendering", "avatar"), f"avatar file not found: {avatar_path}")
    for ci, value in enumerate(protocol.rendering.background):
        if not 0.0 <= value <= 1.0:
            yield Issue(
                ("rendering", "background", ci), f"expected a colour channel in 0..1, got {value:g}"
            )
    if protocol.rendering.width % 2 or protocol.rendering.height % 2:
        yield Issue(
            ("rendering", "width"), "width and height must be even (H.264 needs even sizes)"
        )


def schema_json_text() -> str:
    """The schema as committed in protocols/schema/protocol.schema.json."""
    return json.dumps(json_schema(), indent=2, ensure_ascii=False, sort_keys=True) + "\n"
