"""``facelab avatar``: inspect an avatar file, draw its contact sheet, write sample files."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from facelab.errors import FacelabError
from facelab.experiment.cli.common import (
    AddCommand,
    force_option,
    output_file,
    picture_suffixes,
    verbs,
    whole,
)

__all__ = ["register"]


def _load(spec: str):
    from facelab.stimuli.avatar import default_head, load

    return default_head() if spec == "default" else load(Path(spec))


def _audit(avatar) -> list[str]:
    """The stimulus checks' avatar audit against the reference study's conditions
    (kato2021): each row that did not pass, in words."""
    import contextlib

    from facelab.errors import AvatarError
    from facelab.protocol import load_protocol
    from facelab.resources import protocol_path
    from facelab.stimuli.avatar.targets import with_viseme_mixes
    from facelab.stimuli.checks.avatar_checks import audit_avatar

    path = protocol_path("kato2021")
    with contextlib.suppress(AvatarError):  # else the viseme methods cannot play (said above)
        avatar = with_viseme_mixes(avatar)
    rows = audit_avatar(avatar, load_protocol(path), base_dir=path.parent)
    return [("warning: " if r.severity != "error" else "") + r.describe()
            for r in rows if r.passed is False]  # fmt: skip


def _cmd_avatar(args: argparse.Namespace) -> int:
    from facelab.stimuli.render.inspect import avatar_report, format_report, write_sheet

    if args.action == "inspect":
        if not args.file:
            raise FacelabError(
                "facelab avatar inspect FILE: give a .glb/.gltf/.vrm file or 'default'"
            )
        sheet = (output_file(args.sheet, option="--sheet", force=args.force,
                             suffixes=picture_suffixes) if args.sheet else None)  # fmt: skip
        avatar = _load(args.file)
        report = avatar_report(avatar)
        report["audit"] = _audit(avatar)
        print(
            json.dumps(report, indent=2, ensure_ascii=False) if args.json else format_report(report)
        )
        if sheet is not None:
            write_sheet(avatar, out=sheet, tile=args.tile)
            print(f"wrote {sheet}")
        return 0
    # sample
    from facelab.stimuli.avatar import default_head, save
    from facelab.stimuli.avatar.samples import KINDS, write_sample

    if not args.out:
        raise FacelabError("facelab avatar sample: --out FILE is required")
    out = output_file(args.out, option="--out", force=args.force)
    if args.vroid and not args.kind.startswith("vrm"):
        raise FacelabError("facelab avatar sample: --vroid goes with --kind vrm0 or vrm1")
    if args.kind == "default":
        save(default_head(), out)
    elif args.kind in KINDS:
        write_sample(out, kind=args.kind, head_rows=args.head_rows, vroid=args.vroid)
    print(f"wrote {out}")
    return 0


def register(add: AddCommand) -> None:
    """Add this family's subcommands."""
    p = add(
        "avatar",
        "inspect an avatar (what it offers, which conditions it can play, a contact sheet) "
        "or write a sample avatar file",
        _cmd_avatar,
    )
    verb = verbs(p)
    v = verb("inspect", "what an avatar file offers and how each animation method plays on it")
    v.add_argument("file", metavar="FILE", help=".glb/.gltf/.vrm or 'default'")
    v.add_argument("--json", action="store_true", help="print JSON")
    v.add_argument("--sheet", metavar="PNG", help="also write a contact sheet")
    v.add_argument("--tile", type=whole(lo=64, hi=4096), default=360,
                   help="contact sheet tile size in pixels")  # fmt: skip
    force_option(v)
    v = verb("sample", "write the default head or a small stand-in avatar")
    v.add_argument(
        "--kind",
        choices=["default", "skinned", "rpm", "vrm0", "vrm1"],
        default="default",
        help="the default head (skinned glTF) or a stand-in for a Ready Player Me, "
        "VRM 0.x / 1.0 or generic skinned export",
    )
    v.add_argument("--head-rows", type=whole(lo=8, hi=400), default=40, help="mesh density")
    v.add_argument(
        "--vroid",
        action="store_true",
        help="with --kind vrm0/vrm1: VRoid Studio's layout (a face of several primitives, "
        "sparse morph targets, MToon materials, an alpha-masked eyelash card, a texture "
        "atlas read through KHR_texture_transform)",
    )
    v.add_argument("--out", required=True, metavar="FILE", help="file to write (.glb, .gltf, .vrm)")
    force_option(v)
