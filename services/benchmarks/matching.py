"""The place recognition's cost per frame as the map grows, for `gridslam bench mapping`.

`scanline`: N realistic view templates (smooth random scenes, services/benchmarks/loopclosure.py)
and frames that revisit them or show new views (ViewTemplates.observe timed).

`bow` and `sequence`: N places made from the frames of the `campus` world (rendered here: 320×240,
stereo keyframes), its 5000 first frames repeated when N is larger — a map that went round its
route N/5000 times, so every posting list and every candidate set is as long as a map of N
places makes it; the frames timed are half frames of the route (revisits) and half frames of
another world (new places). What is timed is the recogniser's `observe`: the frame's features,
its bag of words or small image, the index, and the verification of the candidates (the
keyframes of new places and the closure geometry are the same at every size and not in it), and
the share of the revisits that vote for a stored copy of their place (`revisits_recognised`).
"""

from __future__ import annotations

import time

import numpy as np

POOL_FRAMES = 5000


class _PoolKeyframes:
    """Keyframes of N places that repeat the pool's."""

    def __init__(self, pool: list):
        self.pool = pool

    def get(self, place: int):
        return self.pool[place % len(self.pool)]


def _frames(spec: str, preset: str, count: int) -> list:
    from services.source.spec import open_source

    source = open_source(spec, preset=preset, stop=count)
    return [source[i] for i in range(len(source))]


def measure_matching(method: str, size: int, frames: int, rng: np.random.Generator) -> dict:
    """Median and p99 ms of one frame's matching with ``size`` places stored, and the memory the
    places take (MiB per 1000)."""
    if method == "scanline":
        return _scanline(size, frames, rng)
    from services.common.config import load_config
    from services.loopclosure.detector import _Frame
    from services.loopclosure.geometry import ClosureGeometry
    from services.loopclosure.places import recogniser
    from services.loopclosure.service import LoopClosureConfig

    config = load_config(LoopClosureConfig, "loopclosure", overrides={"place_recognition": method})
    places = recogniser(method, config.place_params(), config.recent_frames)
    geometry = ClosureGeometry(config.geometry_parameters())
    pool = _frames("synthetic:0", "campus", min(size, POOL_FRAMES))
    keyframes = [geometry.keyframe(f.left, f.right, f.camera) for f in pool] if method == "bow" else []
    store = _PoolKeyframes(keyframes)
    views = [places.sequences.image_of(f.left) for f in pool] if method == "sequence" else []
    before = _places_bytes(places)
    for place in range(size):
        if method == "bow":
            places.bow.add(places.bow.bag(store.get(place).descriptors), place)
        else:
            places.sequences.replay(place, views[place % len(views)], True)
    per_thousand = (_places_bytes(places) - before) / size * 1000 / 2**20
    revisited = [int(i) for i in rng.integers(0, len(pool), frames // 2)]
    new = _frames("synthetic:1", "synthetic", frames - frames // 2)
    order = rng.permutation(len(revisited) + len(new))
    queries = [((pool[revisited[i]], revisited[i]) if i < len(revisited) else (new[i - len(revisited)], None)) for i in order]
    timings, recognised = [], 0
    for index, (frame, pool_index) in enumerate(queries):
        view = _Frame(size + 100 + index, frame.left, frame.right, frame.camera, geometry)
        started = time.perf_counter()
        found = places.observe(view.seq, view, store.get)
        timings.append(1e3 * (time.perf_counter() - started))
        # A revisit is recognised when it votes for one of the stored copies of its place.
        recognised += pool_index is not None and any(place % len(pool) == pool_index for place, _ in found.votes)
    return {"match_ms_p50": float(np.median(timings)), "match_ms_p99": float(np.percentile(timings, 99)),
            "places_mib_per_1k": per_thousand, "places": len(places), "revisits_recognised": recognised / len(revisited)}


def _places_bytes(places) -> int:
    """What the stored places take in memory (their index and what it points to)."""
    if hasattr(places, "bow"):
        return places.bow.index.nbytes + 8 * len(places.bow.frames)
    sequences = places.sequences
    return sequences.nbytes


def _scanline(size: int, frames: int, rng: np.random.Generator) -> dict:
    from services.benchmarks.loopclosure import make_store, query_frames, random_scenes
    from services.loopclosure.templates import TemplateParams

    params = TemplateParams()
    templates = make_store(size, params, rng)
    revisits = query_frames(templates, frames // 2, rng)
    new = random_scenes(frames - frames // 2, 120, 640, rng)
    images = [image for _, image in revisits] + [(scene * 255).astype(np.uint8) for scene in new]
    timings = []
    for i in rng.permutation(len(images)):
        started = time.perf_counter()
        templates.observe(images[i], size + int(i))
        timings.append(1e3 * (time.perf_counter() - started))
    per_thousand = templates._patches[:len(templates)].nbytes / len(templates) * 1000 / 2**20
    return {"match_ms_p50": float(np.median(timings)), "match_ms_p99": float(np.percentile(timings, 99)),
            "places_mib_per_1k": per_thousand, "places": len(templates)}
