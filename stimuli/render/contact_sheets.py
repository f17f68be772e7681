"""Contact sheets of a protocol's clips (``facelab render --contact-sheet``, the demo): the
face of each condition at each vowel's peak, or every condition at its strongest frame, framed
from the avatar's face box (:func:`~facelab.stimuli.render.scene.face_closeup`), with the
stimulus checks marked on them when the clips were checked (``stimulus_checks.csv``): a
banner per condition (how many checks passed, which failed or warned) and, per vowel tile, the
tracker's aperture and width and a coloured frame around a vowel whose rule failed.

:func:`sheet_marks` (which rows mark which tile) is pure; the drawing uses Pillow.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from facelab.errors import FormatError, StageError
from facelab.formats import read_manifest, read_stimulus_checks
from facelab.protocol import Protocol
from facelab.stimuli.render.build import _blendshapes, vowel_peaks
from facelab.stimuli.render.clip import weights_at
from facelab.stimuli.render.clipspec import ClipJob, plan
from facelab.stimuli.render.prepare import speech_for, tracks_for
from facelab.stimuli.render.renderer import Renderer
from facelab.stimuli.render.scene import face_closeup, load_avatar

__all__ = [
    "FAILED",
    "PASSED",
    "WARNED",
    "SheetMarks",
    "contact_sheets",
    "sheet_font",
    "sheet_marks",
]

#: mark colours (RGB): a failure that stops the render, a warning or accepted failure, all passed
FAILED, WARNED, PASSED = (230, 60, 50), (245, 170, 40), (90, 200, 110)
#: the default vowel rules' names and the vowel each is about (see clip_checks.VOWEL_RULES)
_RULE_VOWEL = {"a_largest_aperture": "a", "u_smallest_aperture": "u", "i_widest_mouth": "i"}
TILE_PX = 480


@dataclass
class SheetMarks:
    """What one condition's sheet shows of the checks: banner lines (text, colour), and per
    vowel the measures (text) and the rule marks (text, colour)."""

    banner: list[tuple[str, tuple[int, int, int]]] = field(default_factory=list)
    measures: dict[str, str] = field(default_factory=dict)
    rules: dict[str, list[tuple[str, tuple[int, int, int]]]] = field(default_factory=dict)


def _status(row: Mapping[str, str]) -> tuple[int, int, int] | None:
    if row.get("passed") != "false":
        return PASSED if row.get("passed") == "true" else None
    stops = row.get("severity", "error") == "error" and row.get("accepted") != "true"
    return FAILED if stops else WARNED


def _vowel_of(measure: str) -> str | None:
    if measure in _RULE_VOWEL:
        return _RULE_VOWEL[measure]
    if ":" in measure:  # "aperture:a", "aperture:a emphasized/standard"
        return measure.split(":", 1)[1].split(" ", 1)[0] or None
    return None


def sheet_marks(
    rows: Sequence[Mapping[str, str]], *, condition: str, clips: Sequence[str]
) -> SheetMarks:
    """The marks for ``condition``'s sheet from ``stimulus_checks.csv`` rows (strings):
    the banner counts every judged row of the condition and the avatar (clip or condition
    empty) and names the failed and warned measures; the vowel marks come from the
    articulation rows of ``clips`` (the clips the sheet shows)."""
    marks = SheetMarks()
    mine = [r for r in rows if r.get("condition") in (condition, "")]
    judged = [(r, _status(r)) for r in mine if _status(r) is not None]
    failed = [r for r, s in judged if s == FAILED]
    warned = [r for r, s in judged if s == WARNED]
    passed = sum(s == PASSED for _, s in judged)
    head = f"checks: {passed} of {len(judged)} passed"
    if not failed and not warned:
        marks.banner.append((head, PASSED))
    for group, colour, word in ((failed, FAILED, "failed"), (warned, WARNED, "warned")):
        if group:
            names = list(dict.fromkeys(f"{r['check']} {r['measure']}" for r in group))
            more = f" (+{len(names) - 3} more)" if len(names) > 3 else ""
            lead = f"{head}; " if head else ""
            marks.banner.append(
                (f"{lead}{len(group)} {word}: {', '.join(names[:3])}{more}", colour)
            )
            head = ""
    for r in rows:
        if r.get("check") != "articulation" or r.get("condition") != condition:
            continue
        if r.get("clip") not in clips:
            continue
        vowel = _vowel_of(r.get("measure", ""))
        if vowel is None:
            continue
        status = _status(r)
        if status is None:
            kind = r["measure"].split(":", 1)[0]
            if r.get("value"):
                text = f"{kind} {float(r['value']):.3g}"
                marks.measures[vowel] = " ".join(filter(None, (marks.measures.get(vowel), text)))
            continue
        word = {FAILED: "\u2717", WARNED: "!", PASSED: "\u2713"}[status]  # ✗ ! ✓
        value = f"{float(r['value']):.2f}" if r.get("value") else "not measured"
        marks.rules.setdefault(vowel, []).append(
            (f"{word} {r['measure']} {value} ({r['threshold']})", status)
        )
    return marks


def contact_sheets(protocol: Protocol, *, protocol_path: Path, out: Path) -> list[Path]:
    """One PNG per condition: the face at the centre of each vowel of the vowel stimulus; a
    protocol without a vowel stimulus gets one PNG of every condition at its strongest frame
    (``contact_conditions.png``). Marked with the checks when ``out`` holds
    ``stimulus_checks.csv``. The sheets frame the face themselves (any render size)."""
    from PIL import Image, ImageDraw

    base_dir = protocol_path.parent
    checks = read_stimulus_checks(out) or []
    if not any(st.expected_vowels for s in protocol.stimulus_sets for st in s.stimuli):
        return [_peak_sheet(protocol, base_dir=base_dir, out=out, checks=checks)]
    avatar = load_avatar(protocol, base_dir=base_dir)
    font, small = sheet_font(28), sheet_font(17)
    paths = []
    out.mkdir(parents=True, exist_ok=True)
    peaks = vowel_peaks(protocol, base_dir=base_dir, avatar=avatar)
    shown = _vowel_clips(protocol, out)
    with Renderer(avatar, face_closeup(avatar, size_px=TILE_PX)) as renderer:
        for cond in protocol.conditions:
            marks = sheet_marks(checks, condition=cond.id, clips=shown.get(cond.id, ()))
            footer = max([(v in marks.measures) + len(marks.rules.get(v, []))
                          for v in "aiueo"] + [0])  # fmt: skip
            tiles = []
            for peak in (p for p in peaks if p.condition == cond.id):
                img = Image.fromarray(renderer.frame(peak.weights))
                title = f"{peak.vowel}  t={peak.t:.2f}s"
                tiles.append(_mark_tile(img, peak.vowel, title, marks, font, small, footer=footer))
            top = 56 + 30 * len(marks.banner)
            height = tiles[0].height + top
            sheet = Image.new("RGB", (sum(t.width for t in tiles), height), (40, 40, 40))
            for i, t in enumerate(tiles):
                sheet.paste(t, (i * t.width, top))
            label = cond.label.get("en") or next(iter(cond.label.values()))
            draw = ImageDraw.Draw(sheet)
            draw.text((16, 12), f"{cond.id}: {label} ({cond.method} {cond.params})",
                      fill=(255, 255, 255), font=font)  # fmt: skip
            for k, (text, colour) in enumerate(marks.banner):
                draw.text((16, 52 + 30 * k), text, fill=colour, font=small)
            path = out / f"contact_{cond.id}.png"
            sheet.save(path)
            paths.append(path)
    return paths


def _mark_tile(img, vowel: str, title: str, marks: SheetMarks, font, small, *, footer: int):
    """The tile with its title, and below it a footer of ``footer`` lines: the vowel's
    measures and rule marks; a frame in the worst rule's colour."""
    from PIL import Image, ImageDraw

    tile = Image.new("RGB", (img.width, img.height + 22 * footer + 8), (20, 20, 20))
    tile.paste(img, (0, 0))
    draw = ImageDraw.Draw(tile)
    draw.text((16, 10), title, fill=(255, 255, 255), font=font)
    lines = [(marks.measures[vowel], (255, 255, 255))] if vowel in marks.measures else []
    lines += marks.rules.get(vowel, [])
    for k, (text, colour) in enumerate(lines):
        draw.text((12, img.height + 4 + 22 * k), text, fill=colour, font=small)
    worst = [c for _, c in marks.rules.get(vowel, []) if c != PASSED]
    if worst:
        colour = FAILED if FAILED in worst else WARNED
        draw.rectangle((0, 0, tile.width - 1, tile.height - 1), outline=colour, width=6)
    return tile


def _vowel_clips(protocol: Protocol, out: Path) -> dict[str, list[str]]:
    """{condition: clip ids of the first stimulus with expected_vowels} from ``clips.csv``
    (empty when the clips are not there yet)."""
    stim_set, stim = next(
        ((s.id, st.id) for s in protocol.stimulus_sets for st in s.stimuli if st.expected_vowels),
        (None, None),
    )
    try:
        rows = read_manifest(out, need=("clip_id", "stimulus_set", "stimulus", "condition"))
    except FormatError:  # no manifest yet: a sheet without vowel marks
        return {}
    shown: dict[str, list[str]] = {}
    for r in rows:
        if r["stimulus_set"] == stim_set and r["stimulus"] == stim:
            shown.setdefault(r["condition"], []).append(r["clip_id"])
    return shown


#: tiles per row of ``contact_conditions.png``
SHEET_COLUMNS = 6


def _peak_sheet(
    protocol: Protocol, *, base_dir: Path, out: Path, checks: Sequence[Mapping[str, str]]
) -> Path:
    """Every condition on the first stimulus its blocks show, at the frame where its mouth
    moves most (the sum of its jaw, mouth and viseme weights, silence's viseme left out),
    side by side, each with its checks' banner."""
    from PIL import Image, ImageDraw

    avatar = load_avatar(protocol, base_dir=base_dir)
    jobs: dict[str, ClipJob] = {}
    for job in plan(protocol):
        jobs.setdefault(job.condition, job)
    font, small = sheet_font(20), sheet_font(13)
    tiles = []
    twin_of = {i: g for g in protocol.offset_twins() for i in g}  # one picture: one tile
    drawn: set[str] = set()
    with Renderer(avatar, face_closeup(avatar, size_px=400)) as renderer:
        for cond in protocol.conditions:
            job = jobs.get(cond.id)
            if job is None or cond.id in drawn:
                continue
            twins = [i for i in twin_of.get(cond.id, [cond.id]) if i in jobs]
            drawn.update(twins)
            speech = speech_for(
                job.stimulus, base_dir=base_dir, sample_rate=protocol.rendering.audio_sample_rate
            )
            bs = _blendshapes(
                protocol, job, speech, tracks_for(job.stimulus, speech), base_dir, avatar
            )
            mouth = [
                k for k, n in enumerate(bs.names)
                if n.startswith(("jaw", "mouth", "viseme_")) and n != "viseme_sil"
            ]  # fmt: skip
            moving = bs.weights[:, mouth] if mouth else bs.weights
            peak = float(bs.times[int(np.argmax(moving.sum(axis=1)))])
            img = Image.fromarray(renderer.frame(weights_at(bs, avatar, t=peak)))
            draw = ImageDraw.Draw(img)
            name = cond.id if len(twins) == 1 else (
                f"{cond.series_id}: {len(twins)} audio offsets")  # fmt: skip
            draw.text((10, 8), f"{name}  t={peak:.2f}s", fill=(255, 255, 255), font=font)
            banner: list = []
            for c in twins if checks else []:  # each twin's lines once, at most six
                banner += sheet_marks(checks, condition=c, clips=()).banner
            banner = list(dict.fromkeys(banner))[:6]
            for k, (text, colour) in enumerate(banner):
                draw.text((10, img.height - 20 * (len(banner) - k) - 6), text[:60], fill=colour,
                          font=small)  # fmt: skip
            tiles.append(img)
    if not tiles:
        raise StageError("no condition is shown by any block: nothing to draw")
    per_row = min(len(tiles), SHEET_COLUMNS)
    rows = -(-len(tiles) // per_row)
    w, h = tiles[0].width, tiles[0].height
    sheet = Image.new("RGB", (per_row * w, rows * h), (40, 40, 40))
    for i, t in enumerate(tiles):
        sheet.paste(t, ((i % per_row) * w, (i // per_row) * h))
    out.mkdir(parents=True, exist_ok=True)
    path = out / "contact_conditions.png"
    sheet.save(path)
    return path


def sheet_font(size: int):
    """A TrueType font of ``size`` px for sheet labels (DejaVu Sans from matplotlib, else
    Noto Sans CJK, else Pillow's default)."""
    import matplotlib
    from PIL import ImageFont

    for name in (
        Path(matplotlib.get_data_path()) / "fonts" / "ttf" / "DejaVuSans.ttf",
        Path("/usr/share/fonts/opentype/noto/NotoSansCJK-Regular.ttc"),
    ):
        if name.exists():
            return ImageFont.truetype(str(name), size)
    return ImageFont.load_default()
