"""``facelab bench visemes``: accuracy, speed and latency of the viseme analyser (JSON)."""

from __future__ import annotations

import importlib.util
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from stimuli.speech import synthesize
from stimuli.viseme_training import (
    HELDOUT_VARIANTS,
    TRAIN_VARIANTS,
    build_pylipsync_templates,
    corpus,
    evaluate,
)
from stimuli.visemes import StreamingAnalyzer, analyze, default_model

__all__ = ["bench_visemes"]


def bench_visemes(*, runs: int = 5, quick: bool = False) -> dict:
    """Held-out sentences x held-out voice variants; see stimuli/viseme_training.py."""
    model = default_model()
    train_sentences, held = corpus()
    sentences = held[:4] if quick else held
    variants = HELDOUT_VARIANTS[:2] if quick else HELDOUT_VARIANTS
    with tempfile.TemporaryDirectory(prefix="facelab-pylipsync-") as tmp:
        templates = None
        if importlib.util.find_spec("pylipsync") is not None:
            templates = build_pylipsync_templates(
                Path(tmp), sentences=train_sentences[:20], variants=TRAIN_VARIANTS
            )
        result = evaluate(
            model, sentences=sentences, variants=variants, pylipsync_templates=templates
        )
    if templates is None:
        result["pylipsync"] = "not installed (pip install 'facelab[bench]')"

    # speed: median of several runs on one long utterance (scipy.fft runs on one thread)
    long = synthesize("".join(held[:6]))
    analyze(long.samples, sample_rate=long.sample_rate, model=model)
    times = []
    for _ in range(max(1, runs)):
        t0 = time.perf_counter()
        analyze(long.samples, sample_rate=long.sample_rate, model=model)
        times.append(time.perf_counter() - t0)
    result["facelab"]["real_time_factor_offline"] = round(
        long.duration_s / statistics.median(times), 1
    )
    result["facelab"]["real_time_factor_runs"] = [round(long.duration_s / t, 1) for t in times]
    result["facelab"]["timed_audio_s"] = round(long.duration_s, 2)

    # streaming: 10 ms chunks give the same frames as offline analysis
    stream = StreamingAnalyzer(sample_rate=long.sample_rate, model=model)
    chunk = long.sample_rate // 100
    parts = [stream.feed(long.samples[i : i + chunk]) for i in range(0, len(long.samples), chunk)]
    parts.append(stream.flush())
    streamed = np.vstack([p.weights for p in parts])
    offline = analyze(long.samples, sample_rate=long.sample_rate, model=model).weights
    result["facelab"]["streaming"] = {
        "algorithmic_latency_ms": round(1000 * stream.latency_s, 1),
        "of_which_window_half_ms": 16.0,
        "of_which_smoothing_lag_ms": round(1000 * model.lag_s, 1),
        "chunk_ms": 10,
        "max_abs_difference_to_offline": float(np.max(np.abs(streamed - offline))),
    }
    result["machine"] = {"python": platform.python_version(), "cpus": os.cpu_count()}
    result["targets"] = {
        "vowel_accuracy_cores": ">= 0.95",
        "vowel_accuracy_all_frames": ">= 0.90",
        "real_time_factor_offline": ">= 200",
        "streaming_latency_ms": "<= 40",
        "vowel_energy_lag_ms": "within +-10",
    }
    return result
