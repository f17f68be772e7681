"""``facelab demo``: the paper's study end to end on the embedded defaults.

1. validate the shipped ``kato2021`` protocol (``facelab protocols`` lists it);
2. render its clips into ``<out>/clips`` (re-used when unchanged);
3. simulate 8 participants with effects in the paper's direction, written through the same
   session log as real sessions, into a new ``<out>/run-<UTC time>/results`` (never over an
   earlier run);
4. analyse them with the one analysis pipeline (``facelab.analysis.run``, as ``facelab
   analyze`` does): for VAS studies the sound repeated-measures analysis and the paper's
   procedure, for task protocols their psychometric, staircase or identification analyses -
   into ``<out>/run-<UTC time>/analysis`` with figures, ``report.html`` and ``report.md``.

The simulated data are labelled as simulated in every session file and in the report.
"""

from __future__ import annotations

import datetime as dt
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from facelab.resources import protocol_path

if TYPE_CHECKING:
    from facelab.experiment.cli.common import GridProgress

__all__ = ["DEFAULT_PROTOCOL", "run_demo"]

DEFAULT_PROTOCOL = protocol_path("kato2021")  # shipped inside the package


def run_demo(
    *,
    out: Path,
    protocol_path: Path = DEFAULT_PROTOCOL,
    participants: int = 8,
    seed: int = 2021,
    size: tuple[int, int] | None = None,
    fps: int | None = None,
    progress: GridProgress | None = None,
    say: Callable[[str], None] = print,
    accept: Sequence[str] = (),
) -> dict[str, Path | float | int]:
    from facelab.analysis import run
    from facelab.experiment.cli.analysis_cmds import print_layout
    from facelab.experiment.cli.common import run_stimulus_checks
    from facelab.experiment.simulate import design_sampler, simulate_study
    from facelab.stimuli.render.build import build_clips, clip_counts, plan, settings_for
    from facelab.stimuli.render.inputs import load_checked_protocol

    t0 = time.perf_counter()
    protocol = load_checked_protocol(protocol_path)
    say(f"[1/4] protocol {protocol_path}: study {protocol.study.id!r} is valid")

    settings = settings_for(protocol)
    if size is not None:
        settings = replace(settings, width=size[0], height=size[1])
    clips = out / "clips"
    t = time.perf_counter()
    if progress is not None:
        progress.start(len(plan(protocol)))
    rows = build_clips(
        protocol,
        protocol_path=protocol_path,
        out=clips,
        settings=settings,
        fps=fps,
        progress=progress,
        log=lambda s: None,
    )
    say(
        f"[2/4] {clip_counts(rows)} at "
        f"{settings.width}x{settings.height}, {fps or protocol.rendering.fps} fps in "
        f"{time.perf_counter() - t:.1f} s -> {clips / 'clips.csv'}"
    )
    run_stimulus_checks(protocol, protocol_path=protocol_path, clips_dir=clips, accept=accept,
                        say=lambda s: say("      " + s), sheets=True)  # fmt: skip

    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%d-%H%M%S")
    run_dir = out / f"run-{stamp}"
    suffix = 1
    while run_dir.exists():
        run_dir = out / f"run-{stamp}-{suffix}"
        suffix += 1
    results = run_dir / "results"
    t = time.perf_counter()
    sessions = simulate_study(
        protocol, protocol_path=protocol_path, results=results, participants=participants, seed=seed
    )
    say(
        f"[3/4] simulated {len(sessions)} participants (seed {seed}; SIMULATED data, effects "
        f"{protocol.simulation.effects}) in {time.perf_counter() - t:.1f} s -> "
        f"{results / protocol.study.id}"
    )

    t = time.perf_counter()
    done = run(
        results, protocol, protocol_path=protocol_path, out=run_dir / "analysis",
        clips=clips, sampler=design_sampler(protocol),
    )  # fmt: skip
    say(
        f"[4/4] analysed {len(done.data)} responses in {time.perf_counter() - t:.1f} s -> "
        f"{done.files.html}"
    )
    for note in done.notes:
        say(f"      note: {note}")
    print_layout(done.results, say=lambda s: say("    " + s))
    total = time.perf_counter() - t0
    say(f"done in {total:.1f} s. Report: {done.files.html}")
    return {
        "clips": clips,
        "results": results,
        "analysis": run_dir / "analysis",
        "report": done.files.html,
        "seconds": total,
        "ratings": len(done.data),
    }
