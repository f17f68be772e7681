"""Shared fixtures: the repository paths, the paper's protocol, and a fixed-seed generator."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
KATO = ROOT / "protocols" / "kato2021.yaml"


@pytest.fixture
def kato_path() -> Path:
    return KATO


@pytest.fixture
def kato_text() -> str:
    return KATO.read_text(encoding="utf-8")


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20260101)
