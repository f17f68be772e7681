"""Helpers shared by the command modules: option parsing and the registration signature."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from facelab.errors import FacelabError

__all__ = ["AddCommand", "Handler", "parse_size"]

Handler = Callable[[argparse.Namespace], int]
#: ``add(name, help, handler) -> parser``: what each family's ``register`` receives.
AddCommand = Callable[[str, str, Handler], argparse.ArgumentParser]


def parse_size(text: str | None) -> tuple[int, int] | None:
    """``WIDTHxHEIGHT`` -> (width, height); even numbers >= 64 (H.264 needs even sizes)."""
    if not text:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise FacelabError(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 640x360") from None
    if w % 2 or h % 2 or w < 64 or h < 64:
        raise FacelabError(f"--size {text!r}: width and height must be even and >= 64")
    return w, h
