"""Synthetic world (work in progress: the renderer follows in the next commit)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class WorldConfig:
    """Settings of the synthetic world (docs/sources.md)."""

    seed: int = 0
    length: float = 12.0
    breadth: float = 8.0
    corridor_width: float = 3.0
    wall_height: float = 2.6
    camera_height: float = 1.2
    laps: int = 2
    speed: float = 0.1
    frames_per_lap: int = 0
    fps: float = 10.0
    wander: float = 0.1
    pillar_spacing: float = 4.0
    noise: float = 2.0
    exposure_jitter: float = 0.02
