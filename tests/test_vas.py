"""The VAS rules, without a window."""

from __future__ import annotations

import pytest

from facelab.experiment.vas import VasGeometry, VasState

G = VasGeometry(width=1000, height=800)


def test_marker_hidden_and_confirm_disabled_until_a_rating_exists() -> None:
    s = VasState(geometry=G, onset=10.0)
    assert not s.marker_visible and not s.can_confirm and s.rating is None
    cx, cy = G.confirm_centre
    s.press(cx, cy, 11.0)  # clicking confirm before rating does nothing
    assert s.confirmed_at is None
    s.key("return", 11.1)
    assert s.confirmed_at is None
    s.press(0.0, G.y_line + 200, 11.2)  # a click away from the line places nothing
    assert s.rating is None


def test_click_places_the_marker_where_clicked_and_drag_moves_it() -> None:
    s = VasState(geometry=G, onset=0.0)
    s.press(G.x_of(25.0), G.y_line + 5, 1.0)
    assert s.marker_visible and s.rating == pytest.approx(25.0)
    s.move(G.x_of(60.0), G.y_line + 50, 1.1)  # dragging follows x even off the line
    s.release()
    s.move(G.x_of(90.0), G.y_line, 1.2)  # not dragging: no change
    assert s.rating == pytest.approx(60.0)
    s.press(G.x_right + 500, G.y_line, 1.3)  # far right of the line: not on it
    assert s.rating == pytest.approx(60.0)
    s.press(G.x_right + 5, G.y_line, 1.4)  # just past the end: clamped to 100
    assert s.rating == 100.0
    cx, cy = G.confirm_centre
    s.release()
    s.press(cx, cy, 2.5)
    assert s.confirmed_at == 2.5 and s.rt == pytest.approx(2.5)
    s.press(G.x_of(10.0), G.y_line, 3.0)  # nothing changes after confirming
    assert s.rating == 100.0
    assert [v for _, v in s.trace] == pytest.approx([25.0, 60.0, 100.0])


def test_keyboard_operation() -> None:
    s = VasState(geometry=G, onset=0.0)
    s.key("right", 0.5)  # first arrow shows the marker at the midpoint
    assert s.rating == 50.0
    s.key("right", 0.6, shift=True)
    s.key("left", 0.7)
    assert s.rating == 59.0
    for _ in range(80):
        s.key("right", 0.8)
    assert s.rating == 100.0
    s.key("space", 1.0)
    assert s.confirmed_at == 1.0


def test_value_mapping_round_trips_for_other_ranges() -> None:
    g = VasGeometry(width=800, height=600, low=0.0, high=10.0)
    for v in (0.0, 2.5, 10.0):
        assert g.value_at(g.x_of(v)) == pytest.approx(v)
    assert g.value_at(-10_000) == 0.0 and g.value_at(10_000) == 10.0
