"""Files shipped inside the package, found through :mod:`importlib.resources`.

The study protocols live in the ``protocols/`` folder of the repository, installed as the
``facelab.protocols`` package: from a clone (editable install) and from an installed wheel
they are found the same way, whatever the working directory.
"""

from __future__ import annotations

import shutil
from importlib import resources
from pathlib import Path

from facelab.errors import FacelabError
from facelab.protocol_yaml import read_data

__all__ = ["cjk_font", "copy_protocol", "package_file", "protocol_path", "shipped_protocols"]

_PROTOCOLS = "facelab.protocols"


def package_file(package: str, *parts: str) -> Path:
    """A data file shipped inside ``package`` (e.g. ``"facelab.stimuli", "data", "x.csv"``).

    facelab is installed as files on disk (wheel or editable), so this is a real path.
    """
    return Path(str(resources.files(package).joinpath(*parts)))


def _folder() -> Path:
    return package_file(_PROTOCOLS)


def shipped_protocols() -> dict[str, Path]:
    """Shipped protocol names (file stems) -> their files, sorted by name."""
    return {p.stem: p for p in sorted(_folder().glob("*.yaml"))}


def protocol_path(name: str) -> Path:
    """The file of a shipped protocol, by name (``kato2021``) or file name."""
    stem = Path(name).stem if name.endswith((".yaml", ".yml")) else name
    found = shipped_protocols()
    if stem not in found:
        raise FacelabError(f"no shipped protocol {name!r}; shipped: {', '.join(found) or '(none)'}")
    return found[stem]


def copy_protocol(name: str, dest: Path, *, force: bool = False) -> list[Path]:
    """Copy a shipped protocol - and the files beside it that it names - into ``dest``.

    ``dest`` is a folder (created if missing); returns the files written. Refuses to replace
    an existing file unless ``force``.
    """
    source = protocol_path(name)
    folder = source.parent
    files = [source, *_companions(source)]
    dest.mkdir(parents=True, exist_ok=True)
    targets = [dest / f.relative_to(folder) for f in files]
    clash = [t for t in targets if t.exists()]
    if clash and not force:
        raise FacelabError(
            f"{clash[0]} exists; nothing was copied (choose another folder or pass --force)"
        )
    for f, t in zip(files, targets, strict=True):
        t.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(f, t)
    return targets


def _companions(protocol: Path) -> list[Path]:
    """Files a shipped protocol names relative to itself (audio, Z matrices, models…)."""
    try:  # facelab's own reader: it parses what load_protocol parses (PyYAML alone does not)
        data = read_data(protocol.read_text(encoding="utf-8"))
    except ValueError:
        return []
    out: list[Path] = []

    def walk(node: object) -> None:
        if isinstance(node, dict):
            for value in node.values():
                walk(value)
        elif isinstance(node, list):
            for value in node:
                walk(value)
        elif isinstance(node, str) and "/" not in node[:1] and "\n" not in node:
            candidate = protocol.parent / node
            if (
                len(node) < 260
                and candidate.suffix
                and candidate.is_file()
                and candidate.resolve().is_relative_to(protocol.parent.resolve())
            ):
                out.append(candidate)

    walk(data)
    return sorted(set(out))


def cjk_font() -> str | None:
    """Name of an installed font family with Japanese glyphs (for matplotlib), or None."""
    from matplotlib import font_manager

    names = {f.name for f in font_manager.fontManager.ttflist}
    for name in ("Noto Sans CJK JP", "Noto Sans JP", "IPAexGothic", "IPAGothic", "TakaoGothic"):
        if name in names:
            return name
    return None
