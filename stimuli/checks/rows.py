"""One measured check of one stimulus: the rows of ``stimulus_checks.csv``.

Columns (DESIGN.md): ``clip, condition, check, measure, value, threshold, passed, note``, then
``severity`` (``error``: a failure stops the render unless the check is accepted;
``warning``: said, recorded, never stops) and ``accepted`` (the failure was accepted by name).
``passed`` is empty for a row that only reports a measure (e.g. each vowel's aperture, which
the rules rows then compare). ``value`` is a number (NaN when it could not be measured: the
note says why); ``threshold`` says the comparison in words, e.g. ``>= 0.5``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace

from facelab.errors import StageError
from facelab.formats import STIMULUS_CHECK_COLUMNS
from facelab.protocol_checks import CHECK_NAMES, accept_name_problem

__all__ = ["CHECK_COLUMNS", "CheckRow", "accept_checks", "at_least", "at_most", "info"]

CHECK_COLUMNS = STIMULUS_CHECK_COLUMNS


@dataclass(frozen=True)
class CheckRow:
    clip: str
    condition: str
    check: str
    measure: str
    value: float
    threshold: str
    passed: bool | None
    note: str = ""
    severity: str = "error"
    accepted: bool = False

    @property
    def failed(self) -> bool:
        """A failure that stops: an error row that did not pass and was not accepted."""
        return self.passed is False and self.severity == "error" and not self.accepted

    def accept(self) -> CheckRow:
        return replace(self, accepted=True) if self.passed is False else self

    @classmethod
    def from_dict(cls, r: Mapping[str, str]) -> CheckRow:
        """The row :meth:`as_dict` wrote (read back from ``stimulus_checks.csv``); a value
        that is not a number raises ValueError."""
        value = float(r["value"]) if r.get("value") else math.nan
        passed = {"true": True, "false": False}.get(r.get("passed") or "")
        return cls(r["clip"], r.get("condition", ""), r["check"], r["measure"], value,
                   r.get("threshold", ""), passed, r.get("note", ""),
                   r.get("severity") or "error", r.get("accepted") == "true")  # fmt: skip

    def as_dict(self) -> dict:
        value = "" if self.value is None or math.isnan(self.value) else round(self.value, 6)
        passed = "" if self.passed is None else str(bool(self.passed)).lower()
        return {
            "clip": self.clip, "condition": self.condition, "check": self.check,
            "measure": self.measure, "value": value, "threshold": self.threshold,
            "passed": passed, "note": self.note, "severity": self.severity,
            "accepted": str(self.accepted).lower(),
        }  # fmt: skip

    def where(self) -> str:
        """The clip (or the avatar) and its condition, e.g. ``s__m01__baseline [baseline]``."""
        return " ".join(x for x in (self.clip or "(avatar)", self.condition and
                                    f"[{self.condition}]") if x)  # fmt: skip

    def what(self) -> str:
        """The measure's value against its threshold, and the note."""
        value = "not measured" if math.isnan(self.value) else f"{self.value:.4g}"
        return f"{self.measure} = {value}, expected {self.threshold}" + (
            f" ({self.note})" if self.note else ""
        )

    def describe(self) -> str:
        """One line for the terminal: what failed, where, the value against its threshold."""
        return f"{self.check}: {self.where()}: {self.what()}"


def _num(value: float | None) -> float:
    return float("nan") if value is None else float(value)


def _judged(
    limit: float, value: float | None, *, above: bool, clip: str, condition: str, check: str,
    measure: str, note: str, severity: str, unit: str,
) -> CheckRow:  # fmt: skip
    v = _num(value)
    ok = (v >= limit if above else v <= limit) if not math.isnan(v) else False
    sign = ">=" if above else "<="
    return CheckRow(clip, condition, check, measure, v, f"{sign} {limit:g}{unit}", bool(ok),
                    note, severity)  # fmt: skip


def at_least(
    limit: float, value: float | None, *, clip: str, condition: str, check: str, measure: str,
    note: str = "", severity: str = "error", unit: str = "",
) -> CheckRow:  # fmt: skip
    """A row that passes when ``value >= limit`` (fails when it could not be measured)."""
    return _judged(limit, value, above=True, clip=clip, condition=condition, check=check,
                   measure=measure, note=note, severity=severity, unit=unit)  # fmt: skip


def at_most(
    limit: float, value: float | None, *, clip: str, condition: str, check: str, measure: str,
    note: str = "", severity: str = "error", unit: str = "",
) -> CheckRow:  # fmt: skip
    """A row that passes when ``value <= limit`` (fails when it could not be measured)."""
    return _judged(limit, value, above=False, clip=clip, condition=condition, check=check,
                   measure=measure, note=note, severity=severity, unit=unit)  # fmt: skip


def info(
    value: float | None, *, clip: str, condition: str, check: str, measure: str, note: str = ""
) -> CheckRow:
    """A row that reports a measure without a threshold."""
    return CheckRow(clip, condition, check, measure, _num(value), "", None, note, "info")


def accept_checks(rows: Iterable[CheckRow], names: Iterable[str]) -> list[CheckRow]:
    """The rows with the failures of the checks ``names`` marked accepted: a check's name
    accepts all its failures, ``NAME:CLIP`` only those of one clip (as the failure lines
    name it, e.g. ``track_source:s__r01__standard``)."""
    names = set(names)
    unknown = sorted(n for n in names if accept_name_problem(n) is not None)
    if unknown:
        raise StageError(
            f"--accept-check {', '.join(unknown)}: unknown check; checks: "
            f"{', '.join(CHECK_NAMES)} (each alone, or NAME:CLIP for one clip)"
        )
    rows = list(rows)
    whole = {n for n in names if ":" not in n}
    one = {tuple(n.split(":", 1)) for n in names if ":" in n}
    for check, clip in sorted(one):  # a mistyped clip would accept nothing, silently
        if not any(r.check == check and r.clip == clip for r in rows):
            failing = sorted({r.clip for r in rows if r.check == check and r.failed and r.clip})
            raise StageError(
                f"--accept-check {check}:{clip}: no clip {clip!r} has {check} results; "
                + (f"clips it failed on: {', '.join(failing[:10])}" if failing
                   else f"{check} failed on no clip")
            )  # fmt: skip
    return [r.accept() if r.check in whole or (r.check, r.clip) in one else r for r in rows]
