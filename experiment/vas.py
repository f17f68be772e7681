"""The visual analogue scale as a pure state machine (no psychopy): geometry and rules.

Rules (from the failures of other tools, see shared/research/frameworks.md):

* no marker until the participant acts: a click on (or near) the line places it there;
  with the keyboard, the first arrow press shows it at the midpoint;
* the marker follows the mouse while the button is held, and arrow keys move it
  (1 point; 10 with shift);
* the confirm button is enabled only once a rating exists; confirming records the value,
  the time since the item appeared and every position taken (for the log);
* the start position is never a response: with the marker hidden, ``rating_start`` is None.

Coordinates are window pixels with the origin at the centre (PsychoPy ``units="pix"``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["VasGeometry", "VasState"]


@dataclass(frozen=True)
class VasGeometry:
    """Where the line and the confirm button are, for a window of ``width`` x ``height``."""

    width: int
    height: int
    low: float = 0.0
    high: float = 100.0
    y_line: float = -40.0

    @property
    def half_length(self) -> float:
        return 0.35 * self.width

    @property
    def x_left(self) -> float:
        return -self.half_length

    @property
    def x_right(self) -> float:
        return self.half_length

    @property
    def grab_tolerance(self) -> float:
        return max(18.0, 0.03 * self.height)

    @property
    def confirm_centre(self) -> tuple[float, float]:
        return (0.0, self.y_line - 0.22 * self.height)

    @property
    def confirm_size(self) -> tuple[float, float]:
        return (max(160.0, 0.14 * self.width), max(50.0, 0.06 * self.height))

    def value_at(self, x: float) -> float:
        """The scale value at horizontal position ``x`` (clamped to the line)."""
        t = (min(max(x, self.x_left), self.x_right) - self.x_left) / (self.x_right - self.x_left)
        return self.low + t * (self.high - self.low)

    def x_of(self, value: float) -> float:
        t = (value - self.low) / (self.high - self.low)
        return self.x_left + t * (self.x_right - self.x_left)

    def on_line(self, x: float, y: float) -> bool:
        tol = self.grab_tolerance
        return self.x_left - tol <= x <= self.x_right + tol and abs(y - self.y_line) <= tol

    def on_confirm(self, x: float, y: float) -> bool:
        (cx, cy), (w, h) = self.confirm_centre, self.confirm_size
        return abs(x - cx) <= w / 2 and abs(y - cy) <= h / 2


@dataclass
class VasState:
    """One item being answered."""

    geometry: VasGeometry
    onset: float  # time the item appeared (s, session clock)
    rating: float | None = None
    dragging: bool = False
    confirmed_at: float | None = None
    trace: list[tuple[float, float]] = field(default_factory=list)  # (time, value) per change

    @property
    def marker_visible(self) -> bool:
        return self.rating is not None

    @property
    def can_confirm(self) -> bool:
        return self.rating is not None and self.confirmed_at is None

    def _set(self, value: float, t: float) -> None:
        g = self.geometry
        value = min(max(value, g.low), g.high)
        if value != self.rating:
            self.rating = value
            self.trace.append((t, value))

    # -- mouse
    def press(self, x: float, y: float, t: float) -> None:
        if self.confirmed_at is not None:
            return
        if self.geometry.on_line(x, y):
            self.dragging = True
            self._set(self.geometry.value_at(x), t)
        elif self.geometry.on_confirm(x, y) and self.can_confirm:
            self.confirmed_at = t

    def move(self, x: float, y: float, t: float) -> None:
        if self.dragging and self.confirmed_at is None:
            self._set(self.geometry.value_at(x), t)

    def release(self) -> None:
        self.dragging = False

    # -- keyboard
    def key(self, name: str, t: float, *, shift: bool = False) -> None:
        if self.confirmed_at is not None:
            return
        g = self.geometry
        step = (10.0 if shift else 1.0) * (g.high - g.low) / 100.0
        if name in ("left", "right"):
            if self.rating is None:
                self._set((g.low + g.high) / 2, t)
            else:
                self._set(self.rating + (step if name == "right" else -step), t)
        elif name in ("return", "space", "num_enter") and self.can_confirm:
            self.confirmed_at = t

    @property
    def rt(self) -> float | None:
        return None if self.confirmed_at is None else self.confirmed_at - self.onset
