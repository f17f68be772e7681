"""The registry of animation methods: one :class:`Method` object per method, registered once.

A method has two halves because the layers do: the protocol half is its
:class:`facelab.methods.MethodSpec` (name, typed parameter model, summary, protocol checks),
which the protocol loader uses without this layer; the stimulus half is the :class:`Method`
here (how it drives a track, the targets it needs, how it plays on an avatar). A method is
added by defining one :class:`Method` subclass with its ``spec`` and calling :func:`register`
once: that puts the spec into the protocol registry too. Nothing else dispatches on a method's
name: rendering, ``avatar inspect``, target checks and protocol checks ask the registry.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

from pydantic import BaseModel

from facelab.errors import AvatarError, StageError
from facelab.methods import METHODS, MethodSpec, register_spec
from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.methods.types import BlendshapeTrack, DriveInput

__all__ = ["REGISTRY", "Method", "Playback", "drive", "get", "load_plugins", "register"]


@dataclass(frozen=True)
class Playback:
    """How a method plays on one avatar.

    playable : whether clips can be made; ``problem`` says why not (an avatar error message).
    how : one line for ``facelab avatar inspect``.
    stand_in : what plays in place of the method's own targets (recorded in clip metadata),
        e.g. a VRM's vowel presets for the ARKit Z matrix; None when the method plays as is.
    """

    playable: bool
    how: str
    stand_in: str | None = None
    problem: str | None = None


P = TypeVar("P")


class Method(Generic[P]):
    """One animation method, generic in its parameter model ``P`` (a subclass of
    :class:`facelab.methods.Params`): ``class JawOnly(Method[JawOnlyParams])``. Subclasses
    set ``spec`` and define :meth:`drive`; the defaults of the other hooks fit a method that
    drives a fixed set of targets."""

    spec: MethodSpec
    #: drives ``viseme_*`` targets, which an avatar without them gets from ARKit mixes
    uses_visemes: bool = False
    #: why the method cannot drive an avatar from streaming audio (``facelab live``), None
    #: when it can: each frame then depends only on the viseme track up to that frame. A
    #: method that says None is still checked (chunked and whole drives must agree).
    live_problem: str | None = "it does not say it can run on streaming audio"

    @property
    def name(self) -> str:
        return self.spec.name

    def drive(self, inp: DriveInput, params: P) -> BlendshapeTrack:
        """The blendshape track (T, K) of one clip from its viseme track."""
        raise NotImplementedError

    def targets(self, params: P, *, base_dir: Path = Path(".")) -> set[str]:
        """The avatar targets the method drives (an empty set: known only from a file read
        when the clip is built)."""
        return set()

    def driven_targets(self, avatar: Avatar, params: P, *, base_dir: Path = Path(".")) -> set[str]:
        """The targets of ``avatar`` the method moves with weight a viewer would see (what the
        stimulus checks' avatar audit measures): by default its :meth:`targets` the avatar
        has."""
        return self.targets(params, base_dir=base_dir) & set(avatar.targets)

    def playback(self, avatar: Avatar, params: P, *, base_dir: Path = Path(".")) -> Playback:
        """Whether and how the method plays on ``avatar``."""
        missing = sorted(self.targets(params, base_dir=base_dir) - set(avatar.targets))
        if missing:
            return Playback(
                False,
                f"no: lacks {_first(missing)}",
                problem=f"avatar {avatar.name!r} lacks {len(missing)} target(s) that method "
                f"{self.name!r} needs: {', '.join(missing)}",
            )
        return Playback(True, "yes")

    def input_files(self, params: P) -> dict[str, str]:
        """The files the parameters name (relative to the protocol's folder), by role: their
        bytes are part of each clip's input hash, so a changed file re-renders its clips."""
        return {}

    def stimulus_files(
        self, params: P, *, base_dir: Path, stimulus_set: str, stimulus_id: str
    ) -> dict[str, str]:
        """The files one stimulus' clip reads besides :meth:`input_files` (a method with one
        file per stimulus), by role, relative to the protocol's folder; hashed like them."""
        return {}

    def stimulus_problems(
        self, params: P, *, base_dir: Path, stimulus_set: str, stimulus_id: str
    ) -> Iterator[str]:
        """Why one stimulus' clip cannot be made (its file missing or unreadable): ``facelab
        validate`` reports them at the condition."""
        return iter(())

    def input_problems(self, params: P, *, base_dir: Path) -> Iterator[tuple[tuple[str, ...], str]]:
        """Read the files the parameters name as rendering will: ``(key path under the
        condition, message)`` for each that cannot be used (``facelab validate`` reports them
        with the protocol's line, so "valid" means "will render")."""
        return iter(())

    def protocol_notes(
        self, settings: Sequence[P], *, base_dir: Path, has_tasks: bool
    ) -> list[str]:
        """Warnings on the protocol's conditions that use this method, seen together (one
        parameter set per condition, in protocol order): what ``validate`` and ``render``
        print before any clip is made, e.g. levels of one manipulation too close to tell
        apart. ``has_tasks``: the protocol has forced-choice or identification tasks."""
        return []

    def examples(self) -> tuple[P | None, ...]:
        """Parameter sets ``facelab avatar inspect`` reports on: the defaults, or None for a
        method with required parameters (its :meth:`playback` then describes what it needs)."""
        try:
            return (self.spec.parse({}),)
        except ValueError:
            return (None,)

    def drive_on(self, avatar: Avatar, inp: DriveInput, params: P) -> BlendshapeTrack:
        """The track for this avatar (a method with a stand-in overrides this)."""
        return self.drive(inp, params)

    def prepared(
        self, avatar: Avatar, params: P, *, base_dir: Path
    ) -> Callable[[DriveInput], BlendshapeTrack]:
        """:meth:`drive_on` for one avatar and parameter set, called many times on short
        tracks (a live stream): a method whose per-avatar decisions are costly makes them
        once here."""
        return lambda inp: self.drive_on(avatar, inp, params)


def _first(names: list[str], n: int = 6) -> str:
    return ", ".join(names[:n]) + (f" and {len(names) - n} more" if len(names) > n else "")


REGISTRY: dict[str, Method[Any]] = {}


def register(method: Method[Any]) -> Method[Any]:
    """Add ``method`` (and its protocol spec) to the registries; a name is registered once."""
    name = method.spec.name
    if name in REGISTRY:
        raise ValueError(f"method {name!r} is registered already")
    if METHODS.get(name, method.spec) is not method.spec:
        raise ValueError(f"method {name!r}: another protocol spec has this name")
    register_spec(method.spec)
    REGISTRY[name] = method
    return method


def load_plugins() -> None:
    """Register every installed method plugin (entry-point group ``facelab.methods``: a
    :class:`Method` subclass, or an instance, whose spec has the entry point's name). One that
    does not load, names something else, or takes a name already registered is recorded in
    its entry (``facelab plugins`` says why) and skipped: the rest of facelab works."""
    from facelab.plugins import GROUPS, loaded

    for entry in loaded(GROUPS["methods"]):
        obj = entry.obj
        where = f"plugin {entry.name!r} from package {entry.package!r} ({entry.value})"
        try:
            method = obj() if isinstance(obj, type) and issubclass(obj, Method) else obj
        except Exception:
            entry.problem = f"{where}: making the method object raised an error"
            continue
        if not isinstance(method, Method) or not isinstance(getattr(method, "spec", None),
                                                              MethodSpec):  # fmt: skip
            entry.problem = (f"{where} is not a facelab Method subclass with a spec "
                             "(facelab.methods.MethodSpec)")  # fmt: skip
            continue
        if method.spec.name != entry.name:
            entry.problem = (f"{where}: the entry point is named {entry.name!r} but its "
                             f"method is {method.spec.name!r}")  # fmt: skip
            continue
        current = REGISTRY.get(entry.name)
        if current is not None:
            if type(current) is not type(method):
                entry.problem = f"{where}: a method named {entry.name!r} is registered already"
            continue
        if METHODS.get(entry.name, method.spec) is not method.spec:
            entry.problem = f"{where}: a method named {entry.name!r} is registered already"
            continue
        register(method)


def get(name: str) -> Method[Any]:
    """The registered method called ``name``."""
    if name not in REGISTRY:
        load_plugins()
    try:
        return REGISTRY[name]
    except KeyError:
        raise StageError(f"unknown method {name!r}; registered: {', '.join(REGISTRY)}") from None


def drive(
    name: str, inp: DriveInput, params: Mapping[str, Any] | BaseModel | None
) -> BlendshapeTrack:
    """Run a registered method; ``params`` is its typed model or a dict as written in a
    protocol (validated here)."""
    method = get(name)
    return method.drive(inp, method.spec.parse(params))


def check_playable(
    avatar: Avatar, name: str, params: Mapping[str, Any] | BaseModel | None, *, base_dir: Path
) -> Playback:
    """:meth:`Method.playback`, raising the avatar error when the method cannot play."""
    method = get(name)
    playback = method.playback(avatar, method.spec.parse(params), base_dir=base_dir)
    if not playback.playable:
        raise AvatarError(playback.problem or f"method {name!r} cannot play on this avatar")
    return playback
