"""View templates and the paper's loop-closure consistency rule (services/loopclosure)."""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from services.benchmarks.loopclosure import make_store, query_frames, random_scenes
from services.common.config import load_config
from services.loopclosure.consistency import ConsistencyParams, ConsistencyRule
from services.loopclosure.service import LoopClosureConfig
from services.loopclosure.templates import TemplateParams, ViewTemplates

NUBOT_FRAMES = 205


# --- the consistency rule -------------------------------------------------------------------
def feed(rule: ConsistencyRule, matches) -> list:
    """(frame, template, is_new, matched_frame) in order → the closures confirmed, by frame."""
    return [(frame, rule.update(frame, template, is_new, matched)) for frame, template, is_new, matched in matches]


def test_a_true_closure_is_confirmed_at_the_seventh_consistent_vote():
    # Frames 100.. replay the stretch first seen at frames 10.. (templates 3.. stored there).
    rule = ConsistencyRule(ConsistencyParams())
    results = feed(rule, [(100 + k, 3 + k // 2, False, 10 + 2 * (k // 2)) for k in range(10)])
    confirmed = [(frame, closure) for frame, closure in results if closure is not None]
    assert [frame for frame, _ in results[:6] if _ is not None] == []      # six votes: not yet
    first_frame, first = confirmed[0]
    assert first_frame == 106 and first.votes == 7                       # the 7th vote confirms
    assert (first.frame, first.matched_frame, first.matched_template) == (106, 16, 6)
    assert [frame for frame, _ in confirmed] == list(range(106, 110))    # and every vote after it


def test_a_lone_match_is_not_a_closure():
    rule = ConsistencyRule(ConsistencyParams())
    matches = [(100 + k, 50 + k, True, 100 + k) for k in range(20)]       # new views ...
    matches[7] = (107, 3, False, 10)                                      # ... but one old place
    assert all(closure is None for _, closure in feed(rule, matches))


def test_six_votes_in_ten_frames_are_not_enough():
    rule = ConsistencyRule(ConsistencyParams())
    matches = [(100 + k, 3, False, 10) if k % 10 < 6 else (100 + k, 60 + k, True, 100 + k) for k in range(30)]
    assert all(closure is None for _, closure in feed(rule, matches))


def test_matches_jumping_between_unrelated_places_are_not_a_closure():
    rule = ConsistencyRule(ConsistencyParams())
    places = [10, 80, 40, 150, 25, 120, 60, 5, 95, 140]                  # a burst of possible closures, all over
    assert all(closure is None for _, closure in feed(rule, [(200 + k, k, False, m) for k, m in enumerate(places)]))


def test_matched_frames_going_backwards_are_not_a_closure():
    # A tolerance wide enough that only the order rule can reject the burst.
    params = ConsistencyParams(tolerance=50)
    backwards = [(100 + k, 9 - k, False, 40 - 2 * k) for k in range(10)]
    assert all(closure is None for _, closure in feed(ConsistencyRule(params), backwards))
    forwards = [(100 + k, k, False, 22 + 2 * k) for k in range(10)]       # the same stretch, forwards
    assert any(closure is not None for _, closure in feed(ConsistencyRule(params), forwards))


def test_an_early_outlier_inside_the_tolerance_does_not_hide_the_run_after_it():
    # Matched frames [14, 10, 11, 12, ..., 18] at frames 100..109: the first vote's offset (86) is
    # within the tolerance of the newest's (91) but its matched frame is ahead of the next eight.
    # A greedy count takes 14 first and keeps only 14..18 (six votes); the longest run is 10..18.
    matched = [14] + list(range(10, 19))
    results = feed(ConsistencyRule(ConsistencyParams()), [(100 + k, 3 + k, False, m) for k, m in enumerate(matched)])
    confirmed = [closure for _, closure in results if closure is not None]
    assert confirmed and confirmed[-1].votes == 9 and confirmed[-1].matched_frame == 18
    assert confirmed[0].frame == 107 and confirmed[0].votes == 7      # 10..16: the seventh vote in order


def test_the_newest_vote_must_end_the_run():
    # Eight votes in order (offset 90), then a newest one whose matched frame goes back to 14
    # (offset 94, inside the tolerance): the run that ends at it is 10..14, 14: six votes, no
    # closure against frame 14 (a greedy count would confirm one with all eight).
    matched = list(range(10, 18)) + [14]
    results = feed(ConsistencyRule(ConsistencyParams()), [(100 + k, 3 + k, False, m) for k, m in enumerate(matched)])
    assert results[-1][1] is None and results[-2][1] is not None


def test_recent_templates_are_not_closures():
    rule = ConsistencyRule(ConsistencyParams(recent_frames=30))
    # The robot stands still for 20 frames matching the template it stored at frame 40.
    assert all(closure is None for _, closure in feed(rule, [(41 + k, 5, False, 40) for k in range(20)]))
    # The same matches 30 frames later are old enough.
    rule = ConsistencyRule(ConsistencyParams(recent_frames=30, tolerance=9))
    assert any(closure is not None for _, closure in feed(rule, [(70 + k, 5, False, 40) for k in range(10)]))


def test_a_robot_standing_still_at_the_revisited_place_needs_the_tolerance_of_min_votes_minus_one():
    # Its votes all match one template while the frames advance: offsets 0..6 frames apart.
    still = [(180 + k, 0, False, 5) for k in range(10)]
    assert all(c is None for _, c in feed(ConsistencyRule(ConsistencyParams(tolerance=5)), still))
    confirmed = [f for f, c in feed(ConsistencyRule(ConsistencyParams(tolerance=6)), still) if c is not None]
    assert confirmed[0] == 186


def test_invalid_consistency_parameters_are_rejected():
    from services.common.errors import ConfigError
    with pytest.raises(ConfigError, match="min_votes"):
        ConsistencyRule(ConsistencyParams(window=5, min_votes=7))


# --- view templates -------------------------------------------------------------------------
def panorama(seed: int = 0) -> np.ndarray:
    """A wide textured scene (120×1200, 8-bit grey) with detail at the scale of a template
    column (10 pixels)."""
    scene = random_scenes(1, 12, 120, np.random.default_rng(seed))[0]
    return (cv2.resize(scene, (1200, 120), interpolation=cv2.INTER_CUBIC).clip(0, 1) * 255).astype(np.uint8)


@pytest.mark.parametrize("pixels", [30, -20, 0])
def test_a_horizontally_shifted_view_matches_with_its_relative_angle_and_sign(pixels):
    params = TemplateParams(width=64, height=12, shift_range=6, fov_deg=64.0)
    scene = panorama()
    x0 = 300
    templates = ViewTemplates(params)
    first = templates.observe(scene[:, x0:x0 + 640], frame=0)
    # The camera turned left by `pixels` (10 px per template column): it sees the scene further
    # left, so the content moves right in the image.
    turned = templates.observe(scene[:, x0 - pixels:x0 - pixels + 640], frame=1)
    assert first.is_new and not turned.is_new and turned.template_id == first.template_id
    assert turned.shift == pixels // 10
    assert turned.relative_angle == pytest.approx(math.radians(64.0) / 64 * (pixels // 10))
    assert np.sign(turned.relative_angle) == np.sign(pixels)              # positive: turned left
    assert turned.matched_frame == 0


def test_a_different_view_becomes_a_new_template():
    templates = ViewTemplates(TemplateParams())
    a = templates.observe(panorama(1)[:, :640], frame=0)
    b = templates.observe(panorama(2)[:, :640], frame=1)
    assert (a.template_id, a.is_new) == (0, True)
    assert (b.template_id, b.is_new, b.matched_frame) == (1, True, 1)
    assert b.distance > templates.params.match_threshold
    assert len(templates) == 2 and templates.frames == [0, 1]


@pytest.mark.parametrize("order", ["bright left first", "bright right first"])
def test_a_tie_goes_to_the_oldest_template(order):
    # Two stored views at exactly the same distance from a plain grey view: half bright, half dark.
    left_bright = np.full((100, 640), 102, np.uint8)
    left_bright[:, :320] = 153
    views = [left_bright, left_bright[:, ::-1].copy()]
    if order == "bright right first":
        views.reverse()
    templates = ViewTemplates(TemplateParams())
    stored = [templates.observe(view, frame) for frame, view in enumerate(views)]
    assert [m.is_new for m in stored] == [True, True]
    match = templates.observe(np.full((100, 640), 127, np.uint8), frame=5)
    assert not match.is_new
    assert match.template_id == 0 and match.matched_frame == 0


def test_template_size_crop_and_normalisation():
    params = TemplateParams(crop=(0.25, 0.75, 0.5, 1.0), width=20, height=4, normalisation=0.4)
    image = np.zeros((100, 200), np.uint8)
    image[50:, 50:150] = 200                                              # exactly the crop is bright
    patch = ViewTemplates(params).template_of(image)
    assert patch.shape == (4, 20)
    assert patch == pytest.approx(np.full((4, 20), 0.4))                  # scaled to the mean intensity
    colour = ViewTemplates(params).template_of(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
    assert colour == pytest.approx(patch)


def compare_with_exhaustive(templates: ViewTemplates, patches) -> tuple[list, list]:
    fast = [templates.best_match(p) for p in patches]
    exhaustive_params = replace(templates.params, matcher="exhaustive")
    saved, templates.params = templates.params, exhaustive_params
    try:
        slow = [templates.best_match(p) for p in patches]
    finally:
        templates.params = saved
    return fast, slow


def test_the_index_finds_the_exhaustive_best_match_on_random_views():
    rng = np.random.default_rng(3)
    templates = make_store(1000, TemplateParams(), rng)
    frames = query_frames(templates, 25, rng)
    fast, slow = compare_with_exhaustive(templates, [templates.template_of(image) for _, image in frames])
    assert [f[0] for f in fast] == [s[0] for s in slow] == [t for t, _ in frames]
    assert [f[2] for f in fast] == [s[2] for s in slow]
    assert [f[1] for f in fast] == pytest.approx([s[1] for s in slow])


@pytest.fixture(scope="module")
def nubot_images(shared_data):
    folder = shared_data / "nubot_scene1" / "left"
    return [cv2.imread(str(folder / f"{k:06d}.png"), cv2.IMREAD_GRAYSCALE) for k in range(NUBOT_FRAMES)]


def nubot_config() -> LoopClosureConfig:
    return load_config(LoopClosureConfig, "loopclosure", preset="nubot")


def test_the_index_matches_like_the_exhaustive_search_on_nubot(nubot_images):
    config = nubot_config()
    fast = ViewTemplates(config.template_params())
    exhaustive = ViewTemplates(replace(config.template_params(), matcher="exhaustive"))
    fast_matches = [fast.observe(image, k) for k, image in enumerate(nubot_images)]
    slow_matches = [exhaustive.observe(image, k) for k, image in enumerate(nubot_images)]
    assert fast_matches == slow_matches
    # Every frame against every template (also the far ones a frame does not match), with an
    # index search so narrow that it must rank the right template among its best two per shift.
    fast.params = replace(fast.params, candidates=2)
    patches = [fast.template_of(image) for image in nubot_images]
    quick, full = compare_with_exhaustive(fast, patches)
    matched = [q for q, f in zip(quick, full) if f[1] <= config.match_threshold]
    assert len(matched) > NUBOT_FRAMES // 2
    assert [(q[0], q[2]) for q, f in zip(quick, full) if f[1] <= config.match_threshold] == \
        [(f[0], f[2]) for f in full if f[1] <= config.match_threshold]


def test_nubot_closes_its_loop_at_the_end_and_nowhere_else(nubot_images):
    """The robot comes back to its start in frames ~180..204 (data README): the preset confirms
    that closure, against a frame of the start, and no closure anywhere else."""
    config = nubot_config()
    templates, rule = ViewTemplates(config.template_params()), ConsistencyRule(config.consistency_params())
    closures = []
    for k, image in enumerate(nubot_images):
        match = templates.observe(image, k)
        closure = rule.update(k, match.template_id, match.is_new, match.matched_frame)
        if closure is not None:
            closures.append(closure)
    assert closures, "the true loop closure was not confirmed"
    assert all(178 <= c.frame <= 204 for c in closures)
    assert all(c.matched_frame <= 20 for c in closures)
    assert min(c.frame for c in closures) <= 190
    assert all(c.votes >= config.min_votes for c in closures)
