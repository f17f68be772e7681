"""Checks that span sections of a protocol: unique ids, references between sections,
files that must exist, method parameters (against the method registry) and languages.

:func:`cross_check` yields :class:`~facelab.errors.Issue` objects with key paths; the loader
adds their line numbers.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from facelab import sickness_questionnaire as ssq
from facelab.emotions import BEHAVIOUR_MODES
from facelab.errors import Issue
from facelab.methods import METHODS, method_spec
from facelab.protocol_model import (
    AUDIO_SUFFIXES,
    AVATAR_SUFFIXES,
    CHECK_NAMES,
    Protocol,
    StaircaseRule,
    accept_name_problem,
)
from facelab.protocol_yaml import read_data

__all__ = [
    "CHECK_NAMES",
    "accept_name_problem",
    "clean_loc",
    "cross_check",
    "describe",
    "pydantic_message",
]


def clean_loc(loc: tuple[Any, ...]) -> tuple[str | int, ...]:
    # pydantic adds union/validator tags such as 'str' or 'function-after[...]'; drop them.
    out: list[str | int] = []
    for i, part in enumerate(loc):
        if isinstance(part, str) and (part.startswith("function-") or part in _TYPE_TAGS):
            continue
        if i == 2 and loc[0] == "tasks" and part in _TASK_TAGS:
            continue  # the task union's tag
        out.append(part)
    return tuple(out)


_TASK_TAGS = {"choice_2afc", "identify", "typed", "matrix"}


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


def describe(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def pydantic_message(err: Any) -> str:
    """A pydantic error as the message users read: "expected a value that is …" with the value
    given, and a hint for numbers YAML read as text (``1e9``, ``"3"``)."""
    value = err.get("input")
    if isinstance(value, float) and value != value:  # .nan compares false with every bound
        return "expected a number (got .nan)"
    got = f" (got {describe(value)})" if "input" in err else ""
    message = err["msg"]
    plain = _PLAIN.get(str(err.get("type", "")))
    ctx = err.get("ctx") or {}
    if plain is not None:  # the common type errors in words, not the library's
        message = plain
    elif err.get("type") == "too_short":  # a list or mapping
        n = ctx.get("min_length", 1)
        message = f"expected at least {n} {'entry' if n == 1 else 'entries'}"
    elif err.get("type") == "too_long":
        message = f"expected at most {ctx.get('max_length')} entries"
    elif err.get("type") == "string_too_short":
        message = "expected a text (not empty)"
    elif err.get("type") == "string_too_long":
        message = f"expected at most {ctx.get('max_length')} characters"
    elif message.startswith("Value error, "):
        message = message[len("Value error, ") :]
        got = ""
    elif message.startswith("Input should be"):
        message = "expected a value that " + message[len("Input ") :].replace("should be", "is", 1)
    if isinstance(value, str) and _looks_numeric(value):
        if "e" in value.lower() and _yaml_float(value) != value.strip().lower():
            got += (
                f"; YAML reads {value} as text: write it with a decimal point and a signed "
                f"exponent ({_yaml_float(value)}) or in full"
            )
        else:
            got += "; a number in quotes is text: remove the quotes"
    return message + got


#: pydantic's type errors as users read them
_PLAIN = {
    "dict_type": "expected a mapping (key: value lines)",
    "model_type": "expected a mapping (key: value lines)",
    "list_type": "expected a list",
    "float_type": "expected a number",
    "float_parsing": "expected a number",
    "int_type": "expected a whole number",
    "int_parsing": "expected a whole number",
    "int_from_float": "expected a whole number",
    "bool_type": "expected true or false",
    "bool_parsing": "expected true or false",
    "string_type": "expected text",
}


def _looks_numeric(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return text.strip().lower() not in {"nan", "inf", "-inf", "+inf", "infinity"}


def _yaml_float(text: str) -> str:
    """``1e9`` -> ``1.0e+9``: the spelling YAML 1.1 reads as a number."""
    mantissa, _, exponent = text.strip().lower().partition("e")
    if "." not in mantissa:
        mantissa += ".0"
    if exponent and exponent[0] not in "+-":
        exponent = "+" + exponent
    return f"{mantissa}e{exponent}" if exponent else mantissa


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
    for i, task in enumerate(protocol.tasks):
        yield ("tasks", i, "question"), task.question
        for j, label in enumerate(getattr(task, "labels", [])):
            yield ("tasks", i, "labels", j, "text"), label.text
    pres = protocol.presentation
    for key in ("instructions", "break_text", "end_text"):
        if getattr(pres, key) is not None:
            yield ("presentation", key), getattr(pres, key)
        if getattr(pres.vr, key) is not None:
            yield ("presentation", "vr", key), getattr(pres.vr, key)


#: (top-level sections a check reads, the check). A check runs only when every section it
#: reads validated, so one broken section does not hide the problems of the others.
CHECKS: list[tuple[frozenset[str], Callable[[Protocol, Path], Iterator[Issue]]]] = []


def _check(*sections: str) -> Callable:
    def register(fn: Callable[[Protocol, Path], Iterator[Issue]]) -> Callable:
        CHECKS.append((frozenset(sections), fn))
        return fn

    return register


def cross_check(
    protocol: Protocol, *, base_dir: Path, available: Iterable[str] | None = None
) -> Iterator[Issue]:
    """Checks that span sections: ids, references, files, method parameters, languages.

    ``available``: the top-level sections that validated (all when None); checks reading
    any other section are skipped.
    """
    have = set(Protocol.model_fields) if available is None else set(available)
    for needs, check in CHECKS:
        if needs <= have:
            yield from check(protocol, base_dir)


@_check("conditions")
def _conditions(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """Unique condition ids; registered methods; their parameters; Z files."""
    yield from _duplicates((c.id for c in protocol.conditions), ("conditions",), "condition")
    for i, cond in enumerate(protocol.conditions):
        where = ("conditions", i)
        spec = method_spec(cond.method)
        if spec is None:
            yield Issue(
                (*where, "method"),
                f"unknown method {cond.method!r}; registered methods: {', '.join(METHODS)}",
            )
            continue
        try:
            params = spec.parse(cond.params)
        except ValidationError as exc:
            for err in exc.errors():
                loc = clean_loc(err["loc"])
                if err["type"] == "extra_forbidden":
                    msg = (
                        f"unknown parameter for method {cond.method!r}; "
                        f"allowed: {', '.join(spec.params.model_fields) or '(none)'}"
                    )
                else:
                    msg = pydantic_message(err)
                yield Issue((*where, "params", *loc), msg)
            continue
        for key_path, message in spec.problems(params, base_dir):
            yield Issue((*where, *key_path), message)
        if cond.behaviour not in BEHAVIOUR_MODES:
            yield from _behaviour_library(base_dir / cond.behaviour, (*where, "behaviour"))


def _behaviour_library(path: Path, where: tuple) -> Iterator[Issue]:
    """A condition's custom behaviour library: a readable JSON/YAML mapping with units (the
    units themselves are checked when clips are rendered, in facelab.stimuli)."""
    try:
        text = path.read_text(encoding="utf-8")
        data = read_data(text, json_too=path.suffix.lower() == ".json")
    except FileNotFoundError:
        yield Issue(where, f"behaviour library {path} was not found")
        return
    except (OSError, ValueError) as exc:
        yield Issue(where, f"{path}: not readable JSON/YAML ({exc})")
        return
    if not isinstance(data, dict) or not isinstance(data.get("units"), list):
        yield Issue(where, f"{path}: a behaviour library is a mapping with a list 'units'")


@_check("stimulus_sets", "conditions")
def _stimulus_sets(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """Unique ids; audio files; vowel isolation names conditions."""
    yield from _duplicates(
        (s.id for s in protocol.stimulus_sets), ("stimulus_sets",), "stimulus set"
    )
    condition_ids = {c.id for c in protocol.conditions}
    known_conditions = ", ".join(c.id for c in protocol.conditions)
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


@_check("blocks", "stimulus_sets", "conditions", "tasks")
def _blocks(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """Unique ids; sets and conditions exist; methods that need texts get texts."""
    yield from _duplicates((b.id for b in protocol.blocks), ("blocks",), "block")
    condition_ids = {c.id for c in protocol.conditions}
    known_conditions = ", ".join(c.id for c in protocol.conditions)
    sets = {s.id: s for s in protocol.stimulus_sets}
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


#: each rule's own keys of a staircase rule (the others: every rule's)
_RULE_KEYS = {
    "up_down": ("up", "down", "step"),
    "quest_plus": ("sigmoid", "threshold_points", "slopes", "lapse_rates"),
    "brand_kollmeier": ("target_score", "assumed_slope", "step_start", "step_decay", "step_min"),
}
_SHARED_RULE_KEYS = {"rule", "start", "trials", "easier"}


def _staircase_rule(
    rule: StaircaseRule, levels: list[float | None], where: tuple[Any, ...]
) -> Iterator[Issue]:
    """The keys of a staircase rule fit its kind (each rule's own keys only)."""
    where = (*where, "staircase")
    own = _RULE_KEYS[rule.rule]
    for key in sorted(rule.model_fields_set - set(own) - _SHARED_RULE_KEYS):
        owner = next(name for name, keys in _RULE_KEYS.items() if key in keys)
        yield Issue(
            (*where, key),
            f"{key!r} belongs to rule {owner}, not {rule.rule!r} (this rule's keys: "
            f"{', '.join(own)})",
        )
    if rule.rule in ("up_down", "brand_kollmeier") and rule.start is None:
        yield Issue((*where, "start"), f"rule {rule.rule!r} needs a 'start' condition (an "
                    "easy one)")  # fmt: skip
    if rule.rule == "quest_plus" and not any(lp > 0 for lp in rule.lapse_rates):
        yield Issue(
            (*where, "lapse_rates"),
            "QUEST+ needs a lapse rate above 0 on its grid: without one, a single wrong answer "
            "at an easy level can rule out every psychometric function",
        )
    if rule.rule == "quest_plus" and rule.sigmoid == "weibull":
        if rule.easier != "higher":
            yield Issue(
                (*where, "easier"),
                "the Weibull function rises with the level: use "
                "easier: higher, or sigmoid: logistic",
            )
        if any(lv is not None and lv <= 0 for lv in levels):
            yield Issue(
                (*where, "sigmoid"),
                "the Weibull function needs every level > 0; use sigmoid: logistic",
            )


@_check("tasks", "blocks", "conditions", "items", "stimulus_sets", "presentation")
def _tasks(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """Tasks are used consistently: references exist, graded designs have levels, a
    staircase has a correct answer to adapt on and a start in its grid."""
    yield from _duplicates((t.id for t in protocol.tasks), ("tasks",), "task")
    tasks = {t.id: t for t in protocol.tasks}
    conditions = {c.id: c for c in protocol.conditions}
    for ti, task in enumerate(protocol.tasks):
        where = ("tasks", ti)
        if task.type == "choice_2afc" and task.standard not in conditions:
            yield Issue((*where, "standard"), f"unknown condition {task.standard!r}")
        if (
            task.type == "choice_2afc"
            and task.layout == "side_by_side"
            and "gap_s" in task.model_fields_set
        ):
            yield Issue(
                (*where, "gap_s"), "gap_s is the blank between sequential clips: not side_by_side"
            )
        if task.type == "identify":
            yield from _duplicates((lb.id for lb in task.labels), (*where, "labels"), "label")
            labels = {lb.id for lb in task.labels}
            stimuli = {st.id for s in protocol.stimulus_sets for st in s.stimuli}
            for cond_id, label in task.answers.items():
                if cond_id not in conditions and cond_id not in stimuli:
                    yield Issue(
                        (*where, "answers", cond_id),
                        f"unknown condition or stimulus {cond_id!r}",
                    )
                if label not in labels:
                    yield Issue(
                        (*where, "answers", cond_id),
                        f"unknown label {label!r}; labels: {', '.join(sorted(labels))}",
                    )
        if task.type == "typed":
            yield from _typed_task(protocol, task, where)
        if task.type == "matrix":
            yield from _matrix_task(protocol, task, where)
    for bi, block in enumerate(protocol.blocks):
        where = ("blocks", bi)
        task = tasks.get(block.task) if block.task else None
        if block.task and task is None:
            yield Issue(
                (*where, "task"),
                f"unknown task {block.task!r}; tasks: {', '.join(tasks) or '(none declared)'}",
            )
            continue
        if task is None and not protocol.items:
            yield Issue(
                (*where,), "a block without a task shows the VAS items, but 'items' is empty"
            )
        block_conds = [c for c in protocol.block_conditions(block) if c in conditions]
        if block.design in ("constant_stimuli", "staircase"):
            unlevelled = [c for c in block_conds if conditions[c].level is None]
            if unlevelled:
                yield Issue(
                    (*where, "design"),
                    f"design {block.design!r} needs a 'level' on every condition of the block; "
                    f"missing on {', '.join(unlevelled)}",
                )
            levels = [conditions[c].level for c in block_conds]
            if len(set(levels)) != len(levels):
                yield Issue((*where, "design"), "two conditions of the block share one level")
        if block.design == "staircase":
            rule = block.staircase
            if rule is None:
                yield Issue((*where, "staircase"), "design 'staircase' needs a 'staircase' rule")
            else:
                yield from _staircase_rule(rule, [conditions[c].level for c in block_conds], where)
                if rule.start is not None and rule.start not in block_conds:
                    yield Issue(
                        (*where, "staircase", "start"),
                        f"start {rule.start!r} is not among the block's conditions "
                        f"({', '.join(block_conds)})",
                    )
            if len(block_conds) < 2:
                yield Issue((*where, "conditions"), "a staircase needs two or more levels")
            if (rule is not None and rule.rule == "brand_kollmeier" and task is not None
                    and task.type == "choice_2afc"):
                yield Issue((*where, "staircase", "rule"), "brand_kollmeier adapts on the "
                            "share of words understood: use a typed, matrix or identify "
                            "task")  # fmt: skip
            scorable = (
                task is not None and task.type == "choice_2afc" and task.correct == "comparison"
            ) or (task is not None and task.type in ("typed", "matrix")) or (
                task is not None
                and task.type == "identify"
                and (
                    all(c in task.answers for c in block_conds)
                    or all(st.id in task.answers for s in protocol.stimulus_sets
                           if s.id == block.stimulus_set for st in s.stimuli)
                )
            )  # fmt: skip
            if not scorable:
                yield Issue(
                    (*where, "task"),
                    "a staircase adapts on correct answers: use a choice_2afc task with "
                    "correct: comparison, an identify task with an answer for every condition "
                    "or every stimulus of the block (e.g. the word said in noise), or a typed "
                    "or matrix task",
                )
        elif block.staircase is not None:
            yield Issue((*where, "staircase"), f"a staircase rule on a {block.design!r} block")
        if task is not None and task.type == "choice_2afc" and task.standard in block_conds:
            yield Issue(
                (*where, "conditions"),
                f"the task's standard {task.standard!r} is also a comparison of the block",
            )


def _typed_task(protocol: Protocol, task: Any, where: tuple[Any, ...]) -> Iterator[Issue]:
    """A typed task knows what was said in every stimulus it is shown with, its answers and
    keywords name stimuli, and it is not shown in VR (a keyboard is needed)."""
    stimuli = {st.id: st for s in protocol.stimulus_sets for st in s.stimuli}
    for key in ("answers", "keywords"):
        for sid in getattr(task, key):
            if sid not in stimuli:
                yield Issue((*where, key, sid), f"unknown stimulus {sid!r}")
    sets = {b.stimulus_set for b in protocol.blocks if b.task == task.id}
    for stimulus_set in protocol.stimulus_sets:
        if stimulus_set.id not in sets:
            continue
        for st in stimulus_set.stimuli:
            if st.silence_s is None and task.said(st) is None:
                yield Issue((*where, "answers"), f"stimulus {st.id!r} of set "
                            f"{stimulus_set.id!r} has no text or transcript: give what it "
                            "says under answers")  # fmt: skip
    yield from _keywords_said(protocol, task, where, sets)
    if sets and protocol.presentation.display == "webxr":
        yield Issue((*where, "type"), "typed answers need a keyboard, which a participant "
                    "in a headset cannot use: use an identify task (a closed set of words) "
                    "with display: webxr")  # fmt: skip


def _matrix_task(protocol: Protocol, task: Any, where: tuple[Any, ...]) -> Iterator[Issue]:
    """A matrix task's answers name stimuli, and every stimulus it is shown with says one
    word of each column, in the columns' order (else no pick could be right). Shown in VR
    too: a panel of the columns, a word picked with the controller's ray or the gaze."""
    stimuli = {st.id for s in protocol.stimulus_sets for st in s.stimuli}
    for sid in task.answers:
        if sid not in stimuli:
            yield Issue((*where, "answers", sid), f"unknown stimulus {sid!r}")
    for bi, block in enumerate(protocol.blocks):  # staircases that adapt on whole sentences
        rule = block.staircase
        if block.task == task.id and rule is not None and rule.rule != "brand_kollmeier":
            yield Issue(("blocks", bi, "staircase", "rule"), f"{rule.rule} adapts on whole "
                        "sentences right, which a matrix scores word by word: use "
                        "brand_kollmeier (it moves by the share of words right)")  # fmt: skip
    sets = {b.stimulus_set for b in protocol.blocks if b.task == task.id}
    practice = protocol.presentation.practice
    if practice is not None:  # the practice trial shows the matrix of its block's task
        sets.add(practice.stimulus_set)
    n = len(task.columns)
    for si, stimulus_set in enumerate(protocol.stimulus_sets):
        if stimulus_set.id not in sets:
            continue
        for sti, st in enumerate(stimulus_set.stimuli):
            words = task.words_said(st)
            name = f"stimulus {st.id!r} of set {stimulus_set.id!r}"
            # the key the words come from: the task's answer, else the stimulus' own text
            source = ((*where, "answers", st.id) if task.answers.get(st.id) else
                      ("stimulus_sets", si, "stimuli", sti,
                       "text" if st.text else "transcript"))  # fmt: skip
            if st.silence_s is not None:
                yield Issue(("stimulus_sets", si, "stimuli", sti, "silence_s"), f"{name} is "
                            "silence: a matrix trial needs a sentence, one word of each "
                            "column")  # fmt: skip
                continue
            if words is None:
                yield Issue((*where, "answers"), f"{name} has no text or transcript: give "
                            "its words under answers")  # fmt: skip
                continue
            if len(words) != n:
                yield Issue(source, f"{name} says {len(words)} word(s) "
                            f"({' '.join(words)}), expected {n}, one from each column: "
                            "write its text with spaces between the words, or give them "
                            "under answers")  # fmt: skip
                continue
            for i, (word, column) in enumerate(zip(words, task.columns, strict=True)):
                if word not in column:
                    yield Issue(source, f"{name}: word {i + 1} {word!r} "
                                f"is not in column {i + 1} ({', '.join(column)})")  # fmt: skip


def _keywords_said(
    protocol: Protocol, task: Any, where: tuple[Any, ...], sets: set[str]
) -> Iterator[Issue]:
    """Each stimulus' keywords are said in it, in the order given (as pronounced): else even
    the answer that repeats it word for word would score below 1. Needs OpenJTalk's reading;
    without pyopenjtalk this is not checked."""
    if task.scoring != "keywords":
        return
    try:
        from facelab.japanese_reading import first_unsaid_keyword, morae, pronunciation

        pronunciation("あ")
    except Exception:  # no reader here (pyopenjtalk missing): not checked
        return
    for stimulus_set in protocol.stimulus_sets:
        if stimulus_set.id not in sets:
            continue
        for st in stimulus_set.stimuli:
            said = task.said(st)
            words = task.keywords_of(st)
            if said is None or words is None:
                continue
            word = first_unsaid_keyword(said, words)
            if word is not None:
                heard = "".join(morae(pronunciation(said)))
                yield Issue((*where, "keywords", st.id), f"keyword {word!r} is not said "
                            f"in {said!r} after the keywords before it (read {heard}): list "
                            "the keywords as said, in order")  # fmt: skip


@_check("conditions", "rendering")
def _audio_offsets(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """An offset moves the voice within the clip's padding (no speech is cut) and needs a
    voice and a face to shift against each other; noise needs a voice and its file."""
    pad_ms = protocol.rendering.pad_s * 1000.0
    for i, cond in enumerate(protocol.conditions):
        where = ("conditions", i, "audio_offset_ms")
        if cond.audio_offset_ms == 0:
            continue
        if abs(cond.audio_offset_ms) > pad_ms + 1e-9:
            yield Issue(where, f"an offset of {cond.audio_offset_ms:g} ms would cut the speech: "
                        f"at most rendering.pad_s ({pad_ms:g} ms); raise pad_s")  # fmt: skip
        if cond.modality != "audiovisual":
            yield Issue(where, f"an audio offset needs voice and face: this condition is "
                        f"{cond.modality}")  # fmt: skip
    for i, cond in enumerate(protocol.conditions):
        if cond.noise is None:
            continue
        where = ("conditions", i, "noise")
        if cond.modality == "visual_only":
            yield Issue(where, "noise is mixed with the voice: this condition is visual_only "
                        "(muted)")  # fmt: skip
        source = cond.noise.source
        if source != "speech_shaped":
            if not source.lower().endswith(AUDIO_SUFFIXES):
                yield Issue((*where, "source"), f"{source!r}: use speech_shaped or a noise file "
                            f"ending in {' or '.join(AUDIO_SUFFIXES)}")  # fmt: skip
            elif not (base_dir / source).is_file():
                yield Issue((*where, "source"), f"noise file not found: {base_dir / source}")


@_check("tasks", "conditions", "blocks", "rendering")
def _noise_tasks(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """Words in noise: a threshold at 50 % right needs a guess rate below 1/2 (three or more
    labels); speech-shaped noise must not clip; the clip's padding must hold noise without
    the voice beyond the fades (the noise check measures it there)."""
    conditions = {c.id: c for c in protocol.conditions}
    for ti, task in enumerate(protocol.tasks):
        if task.type != "identify" or not task.answers or task.timing is not None:
            continue
        noisy = [c for b in protocol.blocks if b.task == task.id
                 for c in protocol.block_conditions(b)
                 if c in conditions and conditions[c].noise is not None]  # fmt: skip
        if noisy and len(task.labels) < 3:
            yield Issue(("tasks", ti, "labels"), "words in noise need three or more labels: "
                        "with two, guessing alone gives 50 % right and no threshold can be "
                        "fitted")  # fmt: skip
    pad = protocol.rendering.pad_s
    for i, cond in enumerate(protocol.conditions):
        noise = cond.noise
        if noise is None:
            continue
        where = ("conditions", i, "noise")
        rms = noise.speech_level_dbfs - noise.snr_db
        if noise.source == "speech_shaped" and rms > -13.0:
            yield Issue(where, f"the noise would be at {rms:g} dBFS RMS and clip (Gaussian noise "
                        "peaks about 13 dB above its RMS): lower speech_level_dbfs or raise "
                        "snr_db")  # fmt: skip
        if pad < noise.ramp_s + 0.1:
            yield Issue(where, f"rendering.pad_s ({pad:g} s) leaves no noise without the voice "
                        f"beyond the {noise.ramp_s:g} s fades to measure: make pad_s at least "
                        f"{noise.ramp_s + 0.1:g} s")  # fmt: skip


@_check("tasks", "conditions", "blocks")
def _timing_tasks(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """A timing task names one of its labels and is shown at three or more offsets of a
    series, four for a simultaneity window with a floor (else no window can be fitted)."""
    conditions = {c.id: c for c in protocol.conditions}
    for ti, task in enumerate(protocol.tasks):
        if task.type != "identify" or task.timing is None:
            continue
        where = ("tasks", ti, "timing")
        labels = [lb.id for lb in task.labels]
        if task.timing.label not in labels:
            yield Issue((*where, "label"), f"unknown label {task.timing.label!r}; labels: "
                        f"{', '.join(labels)}")  # fmt: skip
        offsets: dict[str, set[float]] = {}
        for block in protocol.blocks:
            if block.task == task.id:
                for c in protocol.block_conditions(block):
                    if c in conditions:
                        cond = conditions[c]
                        offsets.setdefault(cond.series_id, set()).add(cond.audio_offset_ms)
        floor = task.timing.judgment == "simultaneity" and task.timing.floor == "fit"
        need = 4 if floor else 3
        few = [s for s, values in offsets.items() if len(values) < need]
        if few or not offsets:
            which = ", ".join(few) or "no block shows it"
            kind = " (a window with a floor; timing.floor: none needs three)" if floor else ""
            yield Issue(where, f"a timing task needs {'four' if floor else 'three'} or more "
                        f"audio_offset_ms values per condition series{kind}; {which} has "
                        "fewer")  # fmt: skip


@_check("items")
def _items(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """Unique item ids; VAS ranges inside 0..100."""
    yield from _duplicates((i.id for i in protocol.items), ("items",), "item")
    for ii, item in enumerate(protocol.items):
        lo, hi = item.range
        if not (0.0 <= lo < hi <= 100.0):
            yield Issue(
                ("items", ii, "range"),
                f"expected [left, right] with 0 <= left < right <= 100, got [{lo:g}, {hi:g}]",
            )


@_check("conditions", "items", "presentation", "tasks")
def _languages(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """Every participant-facing text exists in the presentation language."""
    lang = protocol.presentation.language
    for path, text in _localized(protocol):
        if lang not in text:
            yield Issue(
                path,
                f"no {lang!r} text (presentation.language is {lang!r}); has: {', '.join(text)}",
            )


@_check("presentation", "stimulus_sets", "conditions")
def _practice(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """The practice trial names a real stimulus and condition."""
    condition_ids = {c.id for c in protocol.conditions}
    sets = {s.id: s for s in protocol.stimulus_sets}
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


@_check("presentation", "items", "tasks")
def _questionnaire_items(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """No item or task has the id of a sickness questionnaire item the protocol asks for."""
    taken = {ssq.item_id(moment=m, symptom=s.id) for m in protocol.presentation.ssq
             for s in ssq.SYMPTOMS}  # fmt: skip
    for section, entries in (("items", protocol.items), ("tasks", protocol.tasks)):
        for k, entry in enumerate(entries):
            if entry.id in taken:
                yield Issue((section, k, "id"), f"{entry.id!r} is an item of the sickness "
                            "questionnaire (presentation.ssq) in the logs; choose another id")


@_check("presentation", "conditions", "items", "blocks")
def _conversation(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """The conversation names a real condition and real VAS items."""
    conversation = protocol.presentation.conversation
    if conversation is None:
        return
    where = ("presentation", "conversation")
    for b, block in enumerate(protocol.blocks):
        if block.id == "conversation":
            yield Issue(("blocks", b, "id"), "'conversation' is the conversation's own block in "
                        "the logs; give this block another id")  # fmt: skip
    if conversation.condition not in {c.id for c in protocol.conditions}:
        yield Issue((*where, "condition"), f"unknown condition {conversation.condition!r}")
    for k, item in enumerate(protocol.items):
        if item.id == "conversation":
            yield Issue(("items", k, "id"), "'conversation' is the conversation's own item in "
                        "the logs; give this item another id")  # fmt: skip
    known = {i.id for i in protocol.items}
    for k, item in enumerate(conversation.items or ()):
        if item not in known:
            yield Issue((*where, "items", k),
                        f"unknown item {item!r}; the protocol's VAS items: "
                        f"{', '.join(sorted(known)) or 'none'}")  # fmt: skip


@_check("presentation")
def _added_screens(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """Each added screen names an installed screen kind and gives it options it accepts."""
    from pydantic import ValidationError

    from facelab.plugins import GROUPS, plugin_entries, screen_kinds

    added = protocol.presentation.added_screens
    if not added:
        return
    entries = {e.name: e for e in plugin_entries(GROUPS["screens"])}
    kinds = screen_kinds()
    for i, spec in enumerate(added):
        where = ("presentation", "added_screens", i)
        cls = kinds.get(spec.kind)
        if spec.kind in entries and cls is None:  # installed, but facelab plugins calls it broken
            yield Issue((*where, "kind"), f"screen kind {spec.kind!r} is installed but cannot "
                        f"be used: {entries[spec.kind].problem}")  # fmt: skip
            continue
        if cls is None:
            hint = ("none; a screen kind comes from an installed package (pip install it "
                    "beside facelab)") if not kinds else ", ".join(kinds)  # fmt: skip
            yield Issue((*where, "kind"), f"unknown screen kind {spec.kind!r}; installed: "
                        f"{hint} (facelab plugins lists them)")  # fmt: skip
            continue
        model = getattr(cls, "Options", None)
        if model is None:
            continue
        try:
            model.model_validate(dict(spec.options))
        except ValidationError as exc:
            for err in exc.errors():
                loc = clean_loc(err["loc"])
                allowed = ", ".join(model.model_fields) or "none"
                msg = (f"unknown option; allowed: {allowed}" if err["type"] == "extra_forbidden"
                       else pydantic_message(err))  # fmt: skip
                yield Issue((*where, "options", *loc), msg)
    kinds_used = [s.kind for s in added]
    for kind in dict.fromkeys(k for k in kinds_used if kinds_used.count(k) > 1):
        yield Issue(("presentation", "added_screens"), f"screen kind {kind!r} is added twice")


@_check("analysis", "conditions")
def _analysis(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """The reference condition is a condition."""
    ref = protocol.analysis.reference
    if ref is not None and ref not in {c.id for c in protocol.conditions}:
        known = ", ".join(c.id for c in protocol.conditions)
        yield Issue(("analysis", "reference"), f"unknown condition {ref!r}; conditions: {known}")


@_check("simulation", "conditions", "items", "stimulus_sets", "tasks")
def _simulation(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """Simulated effects name real conditions, items and sets."""
    condition_ids = {c.id for c in protocol.conditions}
    known_conditions = ", ".join(c.id for c in protocol.conditions)
    sets = {s.id: s for s in protocol.stimulus_sets}
    item_ids = {i.id for i in protocol.items}
    sim = protocol.simulation
    for cond_id in sim.effects:
        if cond_id not in condition_ids:
            yield Issue(
                ("simulation", "effects", cond_id),
                f"unknown condition {cond_id!r}; conditions: {known_conditions}",
            )
    for cond_id in sim.identifier.condition_accuracy:
        if cond_id not in condition_ids:
            yield Issue(
                ("simulation", "identifier", "condition_accuracy", cond_id),
                f"unknown condition {cond_id!r}; conditions: {known_conditions}",
            )
    labels = {lb.id for t in protocol.tasks if t.type == "identify" for lb in t.labels}
    tables = [(("simulation", "identifier", "confusion"), sim.identifier.confusion)]
    for cond_id, table in sim.identifier.condition_confusion.items():
        where = ("simulation", "identifier", "condition_confusion", cond_id)
        if cond_id not in condition_ids:
            yield Issue(where, f"unknown condition {cond_id!r}; conditions: {known_conditions}")
        tables.append((where, table))
    for where, table in tables:  # a confusion table names the identify tasks' labels
        for shown, row in table.items():
            for label in (shown, *row):
                if labels and label not in labels:
                    yield Issue((*where, shown), f"unknown label {label!r}; the identify "
                                f"tasks' labels: {', '.join(sorted(labels))}")  # fmt: skip
                    break
            if row and sum(row.values()) <= 0:
                yield Issue((*where, shown), "the probabilities sum to 0")
    series = {c.series_id for c in protocol.conditions}
    for name in sim.srt:
        if name not in series:
            yield Issue(("simulation", "srt", name), f"unknown condition series {name!r}; "
                        f"series: {', '.join(sorted(series))}")  # fmt: skip
    for name in sim.timing:
        if name not in series:
            yield Issue(("simulation", "timing", name), f"unknown condition series {name!r}; "
                        f"series: {', '.join(sorted(series))}")  # fmt: skip
    for oi, override in enumerate(sim.overrides):
        where = ("simulation", "overrides", oi)
        if override.item is not None and override.item not in item_ids:
            yield Issue((*where, "item"), f"unknown item {override.item!r}")
        if override.stimulus_set is not None and override.stimulus_set not in sets:
            yield Issue((*where, "stimulus_set"), f"unknown stimulus set {override.stimulus_set!r}")
        for cond_id in override.effects:
            if cond_id not in condition_ids:
                yield Issue((*where, "effects", cond_id), f"unknown condition {cond_id!r}")


@_check("reported_results", "items", "stimulus_sets", "conditions")
def _reported(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """Reported results name real items, sets and conditions."""
    condition_ids = {c.id for c in protocol.conditions}
    sets = {s.id: s for s in protocol.stimulus_sets}
    item_ids = {i.id for i in protocol.items}
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


@_check("rendering")
def _rendering(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """The avatar file exists; colours in 0..1; even frame sizes."""
    avatar = protocol.rendering.avatar
    if avatar != "default":
        avatar_path = base_dir / avatar
        if avatar_path.suffix.lower() not in AVATAR_SUFFIXES:
            yield Issue(
                ("rendering", "avatar"),
                f"expected 'default' or a .gltf/.glb/.vrm file, got {avatar!r}",
            )
        elif not avatar_path.is_file():
            yield Issue(("rendering", "avatar"), f"avatar file not found: {avatar_path}")
    for ci, value in enumerate(protocol.rendering.background):
        if not 0.0 <= value <= 1.0:
            yield Issue(
                ("rendering", "background", ci), f"expected a colour channel in 0..1, got {value:g}"
            )
    for side in ("width", "height"):
        value = getattr(protocol.rendering, side)
        if value % 2:
            yield Issue(("rendering", side), f"expected an even number (H.264 needs even "
                        f"sizes), got {value}")  # fmt: skip


@_check("presentation", "tasks")
def _live_display(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """The live 3D and VR views draw one avatar at a time: a side-by-side comparison (two
    clips at once) plays only as video."""
    display = protocol.presentation.display
    if display == "video":
        return
    for i, task in enumerate(protocol.tasks):
        if getattr(task, "layout", "sequential") == "side_by_side":
            yield Issue(
                ("tasks", i, "layout"),
                f"presentation.display {display!r} shows one avatar at a time; a side_by_side "
                "comparison needs display: video (or layout: sequential)",
            )


@_check("checks", "conditions")
def _stimulus_checks(protocol: Protocol, base_dir: Path) -> Iterator[Issue]:
    """The stimulus checks' rules name real conditions and checks."""
    condition_ids = {c.id for c in protocol.conditions}
    known = ", ".join(c.id for c in protocol.conditions)
    checks = protocol.checks
    for gi, group in enumerate(checks.equal_conditions):
        if len(group) < 2:
            yield Issue(("checks", "equal_conditions", gi), "a group needs two conditions or more")
        for ci, cond_id in enumerate(group):
            if cond_id not in condition_ids:
                yield Issue(("checks", "equal_conditions", gi, ci),
                            f"unknown condition {cond_id!r}; conditions: {known}")  # fmt: skip
    for ri, rule in enumerate(checks.articulation):
        for key in ("condition", "relative_to"):
            if getattr(rule, key) not in condition_ids:
                name = getattr(rule, key)
                yield Issue(("checks", "articulation", ri, key),
                            f"unknown condition {name!r}; conditions: {known}")  # fmt: skip
    for ai, name in enumerate(checks.accept):
        if (problem := accept_name_problem(name)) is not None:
            yield Issue(("checks", "accept", ai), problem)
