"""`gridslam bench loopclosure`: cost per frame of ViewTemplates.observe as templates accumulate,
and what the index finds against the exhaustive search.

Cost: with N stored templates (N = 1k, 10k, 50k by default) a frame is observed by the default
matcher (the nearest-neighbour index, then `candidates` per shift compared exactly) and by the
exhaustive one (every template compared patch to patch at every shift, `matcher =
"exhaustive"`). Both get the same store and the same frames; the table gives the medians, their
ratio, and whether both chose the same template.

The stored templates are realistic rather than white noise: smooth random scenes (low-pass
filtered noise plus vertical edges and a brightness gradient), normalised as template_of does.
The frames observed are full-size images whose view is one of the stored templates, seen
shifted by a few columns, re-lit and with sensor noise, so every frame is a match (as on a
revisit).

Recall (`--recall SPEC@PRESET,...`): the loop-closure detector over a whole sequence with each
matcher (no closure geometry: it does not change which closures are confirmed); of the closures
the exhaustive search confirms, how many the index confirms too (the same frame against the
same matched frame).
"""

from __future__ import annotations

import statistics
import time
from dataclasses import replace

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter

from services.common.config import load_config
from services.common.settings import CommandParser
from services.loopclosure.service import LoopClosureConfig
from services.loopclosure.templates import TemplateParams, ViewTemplates


def random_scenes(count: int, height: int, width: int, rng: np.random.Generator) -> np.ndarray:
    """`count` smooth grey scenes in 0..1 (count, height, width), float32."""
    scenes = gaussian_filter(rng.normal(size=(count, height, width)), sigma=(0, height / 12, width / 24))
    scenes /= scenes.std(axis=(1, 2), keepdims=True) + 1e-9
    edges = np.cumsum(rng.random((count, 1, width)) < 8.0 / width, axis=2)   # ~8 vertical edges per view
    scenes += 0.8 * ((edges * 0.61803) % 1.0)                               # a level per segment between edges
    scenes += np.linspace(0, 1, height)[None, :, None] * rng.normal(0, 0.5, (count, 1, 1))
    scenes -= scenes.min(axis=(1, 2), keepdims=True)
    scenes /= scenes.max(axis=(1, 2), keepdims=True) + 1e-9
    return (0.15 + 0.7 * scenes).astype(np.float32)


def _normalised(patches: np.ndarray, params: TemplateParams) -> np.ndarray:
    if params.normalisation > 0:
        patches = patches * (params.normalisation / patches.mean(axis=(1, 2), keepdims=True))
    return patches.astype(np.float32)


def make_store(count: int, params: TemplateParams, rng: np.random.Generator) -> ViewTemplates:
    """A ViewTemplates holding `count` realistic templates."""
    templates = ViewTemplates(params)
    for start in range(0, count, 5000):
        scenes = random_scenes(min(5000, count - start), params.height, params.width, rng)
        for i, patch in enumerate(_normalised(scenes, params)):
            templates.add(patch, start + i)
    return templates


def query_frames(templates: ViewTemplates, frames: int, rng: np.random.Generator, size=(480, 640)) -> list[tuple[int, np.ndarray]]:
    """Full-size images whose view is a stored template (chosen at random) shifted by a few
    columns, re-lit and noisy: (template id, image)."""
    params = templates.params
    h, w = size
    x0, x1, y0, y1 = params.crop
    out = []
    for _ in range(frames):
        template_id = int(rng.integers(len(templates)))
        patch = templates.patch(template_id)
        view = cv2.resize(patch, (int((x1 - x0) * w), int((y1 - y0) * h)), interpolation=cv2.INTER_LINEAR)
        shift = int(rng.integers(-params.shift_range // 2, params.shift_range // 2 + 1)) * view.shape[1] // params.width
        view = np.roll(view, shift, axis=1)
        view = view / view.max() * rng.uniform(0.6, 0.9) + rng.normal(0, 0.01, view.shape)
        image = np.full((h, w), 0.5, np.float32)
        image[int(y0 * h):int(y0 * h) + view.shape[0], int(x0 * w):int(x0 * w) + view.shape[1]] = view
        out.append((template_id, np.clip(image * 255, 0, 255).astype(np.uint8)))
    return out


def time_observe(templates: ViewTemplates, frames: list[tuple[int, np.ndarray]]) -> tuple[float, list[int]]:
    """Median seconds per observe() and the template each frame matched (-1: stored as new)."""
    seconds, matched = [], []
    for index, (_, image) in enumerate(frames):
        started = time.perf_counter()
        match = templates.observe(image, 10**9 + index)
        seconds.append(time.perf_counter() - started)
        matched.append(-1 if match.is_new else match.template_id)
    return statistics.median(seconds), matched


def confirmed_closures(spec: str, preset: str, matcher: str) -> set[tuple[int, int]]:
    """(frame, matched frame) of every closure the detector confirms over a sequence."""
    from services.source.spec import open_source

    config = load_config(LoopClosureConfig, "loopclosure", preset=preset).model_copy(
        update={"matcher": matcher, "closure": "ratslam", "place_recognition": "scanline"})
    detector = config.detector()
    closures = set()
    for frame in open_source(spec, preset=preset, mono=True):
        observed = detector.observe(frame.seq, frame.left)
        closures.update((closure.frame, closure.matched_frame) for closure in observed.closures)
    return closures


def recall(sequences: list[str]) -> None:
    print("| sequence | preset | closures, exhaustive | closures, index | found by both | recall |")
    print("|:--|:--|--:|--:|--:|--:|")
    for item in sequences:
        spec, _, preset = item.partition("@")
        exhaustive, index = (confirmed_closures(spec, preset, matcher) for matcher in ("exhaustive", "index"))
        both = len(exhaustive & index)
        print(f"| {spec} | {preset} | {len(exhaustive)} | {len(index)} | {both} | "
              f"{100.0 * both / len(exhaustive) if exhaustive else 100.0:.1f} % |", flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="gridslam bench loopclosure", description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="nubot", help="loopclosure preset for the template size and shifts (default nubot)")
    parser.add_argument("--sizes", default="1000,10000,50000", help="comma-separated numbers of stored templates")
    parser.add_argument("--frames", type=int, default=15, help="frames observed per size (the median is reported)")
    parser.add_argument("--exhaustive-frames", type=int, default=5, help="frames for the exhaustive matcher")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--recall", metavar="SPEC@PRESET,...",
                        help="instead: closures confirmed with the index against the exhaustive search over these "
                             "sequences, e.g. synthetic:0@synthetic,stereo:../shared/data/nubot_scene1@nubot")
    args = parser.parse_args(argv)
    if args.recall:
        recall([item for item in args.recall.split(",") if item.strip()])
        return 0
    config = load_config(LoopClosureConfig, "loopclosure", preset=args.preset)
    params = config.template_params()
    sizes = [int(v) for v in args.sizes.split(",") if v.strip()]
    rng = np.random.default_rng(args.seed)
    print(f"view templates {params.width}×{params.height}, shifts ±{params.shift_range}, index: {params.candidates} "
          f"nearest per shift (preset {args.preset}); {args.frames} frames per size ({args.exhaustive_frames} exhaustive); medians")
    print()
    print("| stored templates | observe, index (ms) | observe, exhaustive (ms) | exhaustive / index | same match | frames matched right |")
    print("|---:|---:|---:|---:|---:|---:|")
    for size in sizes:
        templates = make_store(size, params, rng)
        frames = query_frames(templates, args.frames, rng)
        templates.observe(frames[0][1], -1)   # warm up (allocations, caches)
        fast, fast_matched = time_observe(templates, frames)
        templates.params = replace(params, matcher="exhaustive")   # the same store, every template compared in full
        slow, slow_matched = time_observe(templates, frames[:args.exhaustive_frames])
        same = sum(a == b for a, b in zip(fast_matched, slow_matched))
        right = sum(m == t for m, (t, _) in zip(fast_matched, frames))
        print(f"| {size:,} | {1e3 * fast:.2f} | {1e3 * slow:.1f} | {slow / fast:.0f}× "
              f"| {same}/{len(slow_matched)} | {right}/{len(frames)} |")
    return 0
