"""Every distribution facelab imports is declared in pyproject.toml, and the lock file that
scripts/setup.sh installs from pins every declared requirement at a version it allows."""

from __future__ import annotations

import ast
import importlib.metadata as md
import re
import sys
import tomllib
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]
PACKAGE_DIRS = ("core", "analysis", "experiment", "stimuli")
#: modules that run in another environment (the face tracker's own venv), not in facelab's
OTHER_ENVIRONMENTS = {"stimuli/checks/tracker_worker.py"}


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))


def _declared() -> dict[str, Requirement]:
    project = _pyproject()["project"]
    reqs = [Requirement(r) for r in project["dependencies"]]
    for extra in project["optional-dependencies"].values():
        reqs += [Requirement(r) for r in extra]
    return {canonicalize_name(r.name): r for r in reqs if canonicalize_name(r.name) != "facelab"}


def _imported_top_levels() -> dict[str, str]:
    """Top-level names imported anywhere in facelab -> one file that imports it."""
    found: dict[str, str] = {}
    for folder in PACKAGE_DIRS:
        for path in (ROOT / folder).rglob("*.py"):
            rel = path.relative_to(ROOT).as_posix()
            if rel in OTHER_ENVIRONMENTS:
                continue
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                for name in names:
                    found.setdefault(name.split(".")[0], rel)
    return found


def test_every_imported_distribution_is_declared() -> None:
    declared = set(_declared())
    owners = md.packages_distributions()
    undeclared = []
    for top, where in sorted(_imported_top_levels().items()):
        if top == "facelab" or top in sys.stdlib_module_names:
            continue
        dists = {canonicalize_name(d) for d in owners.get(top, [])}
        if not dists:  # an extra setup.sh does not install (training): named as it imports
            dists = {canonicalize_name(top)}
        if not dists & declared:
            undeclared.append(f"{top} ({', '.join(sorted(dists))}; imported in {where})")
    assert not undeclared, "imported but not declared in pyproject.toml: " + "; ".join(undeclared)


def _locked() -> dict[str, tuple[str, list[str]]]:
    text = (ROOT / "requirements" / "lock.txt").read_text(encoding="utf-8")
    pins: dict[str, tuple[str, list[str]]] = {}
    for block in re.split(r"\n(?=[A-Za-z0-9])", text):
        head = re.match(r"([A-Za-z0-9._-]+)(\[[^\]]*\])?==([^\s;\\]+)", block)
        if head:
            hashes = re.findall(r"--hash=sha256:([0-9a-f]{64})", block)
            pins[canonicalize_name(head.group(1))] = (head.group(3), hashes)
    return pins


def test_the_lock_pins_every_declared_requirement_with_hashes() -> None:
    pins = _locked()
    assert len(pins) > 100
    for name, (version, hashes) in pins.items():
        assert hashes, f"requirements/lock.txt: {name}=={version} has no hash"
    training = {canonicalize_name(Requirement(r).name)
                for r in _pyproject()["project"]["optional-dependencies"]["training"]}  # fmt: skip
    for name, req in _declared().items():
        if name in training:  # not in `all`: never installed by setup.sh
            assert name not in pins
            continue
        assert name in pins, f"requirements/lock.txt has no pin for {req} (run scripts/lock.sh)"
        version = pins[name][0]
        assert req.specifier.contains(version, prereleases=True), (
            f"requirements/lock.txt pins {name}=={version}, outside pyproject's {req}"
        )


def test_the_installed_environment_is_the_lock() -> None:
    """What setup.sh installed is what the lock says (a stale .venv is reinstalled)."""
    wrong = []
    for name, (version, _) in _locked().items():
        try:
            have = md.version(name)
        except md.PackageNotFoundError:
            wrong.append(f"{name} missing")
            continue
        if canonicalize_name(have) != canonicalize_name(version) and have != version:
            wrong.append(f"{name} {have} != {version}")
    assert not wrong, wrong


def test_the_environment_has_the_pinned_pip() -> None:
    """setup.sh puts the pinned pip into the venv before the lock (Python 3.11's own pip took
    an unpinned httpx for blosc2's ``httpx[http2]`` and refused the hashed install)."""
    text = (ROOT / "requirements" / "pip.txt").read_text(encoding="utf-8")
    pin = re.search(r"^pip==(\S+) \\\n\s+--hash=sha256:[0-9a-f]{64}", text, re.M)
    assert pin, "requirements/pip.txt: expected a line 'pip==VERSION \\' and a --hash line"
    assert md.version("pip") == pin.group(1)
