"""MkDocs hooks for facelab's documentation (mkdocs.yml ``hooks``).

Two directives in a page's Markdown, expanded at build time so the site never drifts from the
repository:

- ``{{ readme "HEADING" }}`` - the README section under that ``##`` heading (to the next
  heading of its level), its own heading dropped; a heading that is not there fails the build.
- ``{{ protocol_schema }}`` - the protocol reference, generated from the committed JSON
  Schema (``protocols/schema/protocol.schema.json``): one table per object, every key with
  its type, whether it is required, its default and its description.
- ``{{ cli_usage }}`` - ``facelab --help`` and every verb's usage, from the parser itself.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
_README = re.compile(r"\{\{\s*readme\s+\"([^\"]+)\"\s*\}\}")
#: where the API pages' sources are laid out as the installed package (mkdocs.yml's
#: mkdocstrings ``paths``): facelab maps ``core/`` to ``facelab`` and the stage folders to its
#: sub-packages (pyproject.toml), which a static reader of the tree cannot follow
API_SOURCES = ROOT / ".docs-src"
_SUBPACKAGES = ("analysis", "experiment", "protocols", "stimuli")


def on_startup(command: str, dirty: bool) -> None:
    """Lay out ``.docs-src/facelab`` as links: core's files, then the stage folders. Made in
    place, never removed first: two builds at once (the test suite's parallel workers) each
    find the links the other made, and links that point elsewhere are replaced."""
    package = API_SOURCES / "facelab"
    package.mkdir(parents=True, exist_ok=True)
    wanted = {
        entry.name: entry
        for entry in (ROOT / "core").iterdir()
        if entry.suffix == ".py" or (entry.is_dir() and (entry / "__init__.py").is_file())
    }
    wanted.update({name: ROOT / name for name in _SUBPACKAGES})
    for link in package.iterdir():
        if link.name in wanted and link.is_symlink() and link.resolve() == wanted[link.name]:
            continue
        with contextlib.suppress(FileNotFoundError):  # a build beside this one removed it
            if link.is_symlink() or link.is_file():
                link.unlink()
            else:
                shutil.rmtree(link)
    for name, target in wanted.items():
        # made by this layout before, or by a build running beside this one
        with contextlib.suppress(FileExistsError):
            os.symlink(target, package / name)


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    markdown = _README.sub(lambda m: readme_section(m.group(1), page=page.file.src_path), markdown)
    if "{{ protocol_schema }}" in markdown:
        markdown = markdown.replace("{{ protocol_schema }}", protocol_reference())
    if "{{ cli_usage }}" in markdown:
        markdown = markdown.replace("{{ cli_usage }}", cli_usage())
    return markdown


def readme_section(heading: str, *, page: str) -> str:
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    level = len(heading) - len(heading.lstrip("#"))
    try:
        start = lines.index(heading)
    except ValueError:
        raise ValueError(f"{page}: README.md has no heading {heading!r}") from None
    body: list[str] = []
    fenced = False
    for line in lines[start + 1 :]:
        if line.startswith("```"):
            fenced = not fenced
        if not fenced and line.startswith("#") and len(line) - len(line.lstrip("#")) <= level:
            break
        # the README's sub-headings become this page's sections
        if not fenced and line.startswith("#"):
            line = line[level - 1 :]
        body.append(line)
    return "\n".join(body).strip() + "\n"


def _type(spec: dict[str, Any]) -> str:
    if "$ref" in spec:
        name = spec["$ref"].rsplit("/", 1)[-1]
        return f"[{name}](#{name.lower()})"
    if "anyOf" in spec:
        return " or ".join(_type(s) for s in spec["anyOf"])
    if "enum" in spec:
        return "one of " + ", ".join(f"`{v}`" for v in spec["enum"])
    if "const" in spec:
        return f"`{spec['const']}`"
    kind = spec.get("type", "any")
    if kind == "array":
        return f"list of {_type(spec.get('items', {}))}"
    if kind == "object" and isinstance(spec.get("additionalProperties"), dict):
        return f"mapping to {_type(spec['additionalProperties'])}"
    return str(kind)


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _object_table(name: str, spec: dict[str, Any]) -> list[str]:
    out = [f"### {name}", ""]
    if spec.get("description"):
        out += [_cell(spec["description"]), ""]
    props = spec.get("properties", {})
    if not props:
        return [*out, f"Type: {_type(spec)}.", ""]
    required = set(spec.get("required", ()))
    out += ["| key | type | required | default | description |", "|---|---|---|---|---|"]
    for key, sub in props.items():
        default = f"`{json.dumps(sub['default'], ensure_ascii=False)}`" if "default" in sub else ""
        out.append(
            f"| `{key}` | {_type(sub)} | {'yes' if key in required else ''} | {default} | "
            f"{_cell(sub.get('description', ''))} |"
        )
    return [*out, ""]


def protocol_reference() -> str:
    schema = json.loads(
        (ROOT / "protocols" / "schema" / "protocol.schema.json").read_text(encoding="utf-8")
    )
    out = _object_table("Protocol", schema)
    for name, spec in sorted(schema.get("$defs", {}).items()):
        out += _object_table(name, spec)
    return "\n".join(out)


def cli_usage() -> str:
    from facelab.experiment.cli import build_parser

    parser = build_parser()
    out = ["```text", parser.format_help().rstrip(), "```", ""]
    for action in parser._subparsers._group_actions:  # the verbs, in their order
        for verb, sub in action.choices.items():
            out += [f"### facelab {verb}", "", "```text", sub.format_help().rstrip(), "```", ""]
    return "\n".join(out)
