"""The documentation site builds with warnings as errors, its generated references are
complete, and the examples in the documented API's docstrings run (doctests)."""

from __future__ import annotations

import doctest
import importlib
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from facelab.experiment.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("site")
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
        cwd=ROOT, capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


def test_every_page_of_the_navigation_is_built(site: Path) -> None:
    nav = re.findall(r":\s*([\w/-]+)\.md\s*$", (ROOT / "mkdocs.yml").read_text(), re.M)
    assert len(nav) >= 10
    for page in nav:
        built = site / ("index.html" if page == "index" else f"{page}/index.html")
        text = built.read_text(encoding="utf-8")
        directives = re.findall(r"\{\{\s*(readme|protocol_schema|cli_usage)", text)
        assert not directives, f"{page}: a directive was not expanded"
    getting_started = (site / "index.html").read_text(encoding="utf-8")
    assert "scripts/demo.sh" in getting_started and "requirements/lock.txt" in getting_started
    # a how-to page carries its README section
    assert "--scheduler" in (site / "howto/cluster/index.html").read_text(encoding="utf-8")


def test_the_protocol_reference_has_every_key_of_the_schema(site: Path) -> None:
    schema = json.loads((ROOT / "protocols/schema/protocol.schema.json").read_text("utf-8"))
    page = (site / "reference/protocol/index.html").read_text(encoding="utf-8")
    for key in schema["properties"]:
        assert f"<code>{key}</code>" in page, key
    for name, spec in schema["$defs"].items():
        assert f'id="{name.lower()}"' in page, name
        for key in spec.get("properties", {}):
            assert f"<code>{key}</code>" in page, (name, key)


def test_the_command_reference_has_every_verb(site: Path) -> None:
    page = (site / "reference/cli/index.html").read_text(encoding="utf-8")
    verbs = build_parser()._subparsers._group_actions[0].choices  # type: ignore[union-attr]
    for verb in verbs:
        assert f"facelab {verb}" in page, verb


def _documented_modules() -> list[str]:
    names = re.findall(r"^::: ([\w.]+)$", (ROOT / "docs/reference/api.md").read_text(), re.M)
    modules = set()
    for name in names:
        parts = name.split(".")
        for cut in range(len(parts), 0, -1):
            try:
                importlib.import_module(".".join(parts[:cut]))
            except ModuleNotFoundError:
                continue
            modules.add(".".join(parts[:cut]))
            break
    return sorted(modules)


def test_the_api_page_documents_its_objects(site: Path) -> None:
    page = (site / "reference/api/index.html").read_text(encoding="utf-8")
    for name in re.findall(r"^::: ([\w.]+)$", (ROOT / "docs/reference/api.md").read_text(), re.M):
        assert name.rsplit(".", 1)[-1] in page, name


@pytest.mark.parametrize("module", _documented_modules())
def test_the_documented_examples_run(module: str) -> None:
    result = doctest.testmod(importlib.import_module(module), optionflags=doctest.ELLIPSIS)
    assert result.failed == 0, module
