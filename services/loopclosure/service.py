"""loopclosure: RatSLAM view templates of every frame and the paper's loop-closure rule."""

from __future__ import annotations

import argparse
import csv
import logging
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field

from schemas import CameraFrame, LoopClosure, ViewTemplate
from services.common.config import load_config
from services.common.convert import image_from_msg
from services.common.runtime import RuntimeConfig
from services.common.service import Service
from services.loopclosure.consistency import ConsistencyParams, ConsistencyRule
from services.loopclosure.templates import TemplateParams, ViewTemplates

log = logging.getLogger(__name__)

CLOSURE_COLUMNS = ("frame", "matched_frame", "matched_template", "votes")


class LoopClosureConfig(BaseModel):
    """Configuration of the loopclosure service (table `[loopclosure]`, env `GRIDSLAM_LOOPCLOSURE_*`, presets)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    crop: tuple[float, float, float, float] = Field((0.0, 1.0, 0.0, 1.0), description="Crop x0, x1, y0, y1 as fractions of the image.")
    width: int = Field(60, ge=4, description="Template columns.")
    height: int = Field(10, ge=1, description="Template rows.")
    normalisation: float = Field(0.4, ge=0, description="Mean intensity each template is scaled to (0: none).")
    shift_range: int = Field(5, ge=0, description="Column shifts tried in each direction.")
    match_threshold: float = Field(0.085, gt=0, description="Distance below which a view matches a stored template.")
    fov_deg: float = Field(53.0, gt=0, le=360, description="Horizontal field of view of the image, degrees.")
    candidates: int = Field(32, ge=1, description="Templates compared in full after the profile prefilter.")
    window: int = Field(10, ge=1, description="Consecutive frames of the consistency rule.")
    min_votes: int = Field(7, ge=1, description="Consistent possible closures needed in the window (paper: more than six).")
    tolerance: int = Field(5, ge=0, description="Frames by which the votes' frame offsets may disagree.")
    recent_frames: int = Field(30, ge=1, description="Templates stored fewer frames ago are not loop closures.")
    out: Path | None = Field(None, description="Folder for loop_closures.csv (none: not written).")

    def template_params(self) -> TemplateParams:
        return TemplateParams(crop=self.crop, width=self.width, height=self.height, normalisation=self.normalisation,
                              shift_range=self.shift_range, match_threshold=self.match_threshold, fov_deg=self.fov_deg,
                              candidates=self.candidates)

    def consistency_params(self) -> ConsistencyParams:
        return ConsistencyParams(window=self.window, min_votes=self.min_votes, tolerance=self.tolerance,
                                 recent_frames=self.recent_frames)


class LoopClosureService(Service):
    name = "loopclosure"

    def __init__(self, runtime: RuntimeConfig, config: LoopClosureConfig, instance: str | None = None):
        super().__init__(runtime, instance)
        self.config = config
        self.templates = ViewTemplates(config.template_params())
        self.rule = ConsistencyRule(config.consistency_params())
        self.closures = 0
        self.csv_path = config.out / "loop_closures.csv" if config.out else None
        if self.csv_path is not None and not self.csv_path.exists():
            self.csv_path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.csv_path, "w", newline="") as handle:
                csv.writer(handle).writerow(CLOSURE_COLUMNS)

    def setup(self) -> None:
        self.subscribe("camera/frame", self.on_frame)

    def on_frame(self, message: CameraFrame) -> None:
        seq = message.header.seq
        match = self.templates.observe(image_from_msg(message.left), seq)
        closure = self.rule.update(seq, match.template_id, match.is_new, match.matched_frame)
        if closure is not None:
            self.closures += 1
            log.info("loop closure confirmed at frame %d: frame %d (template %d), %d votes", seq, closure.matched_frame,
                     closure.matched_template, closure.votes)
            self.publish("loop/closure", LoopClosure(header=message.header, frame=seq, matched_frame=closure.matched_frame,
                                                     matched_template=closure.matched_template, votes=closure.votes))
            if self.csv_path is not None:
                with open(self.csv_path, "a", newline="") as handle:
                    csv.writer(handle).writerow((seq, closure.matched_frame, closure.matched_template, closure.votes))
        self.publish("view/template", ViewTemplate(
            header=message.header, template_id=match.template_id, is_new=match.is_new, distance=match.distance,
            relative_angle=match.relative_angle, matched_frame=match.matched_frame, template_count=len(self.templates),
            loop_closure=closure is not None))

    def extra_counters(self) -> dict[str, float]:
        return {**super().extra_counters(), "templates": len(self.templates), "loop_closures": self.closures}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", help="view-template parameters for a dataset: synthetic, nubot, kitti, stlucia")
    parser.add_argument("--match-threshold", type=float, help="template match distance threshold")
    parser.add_argument("--out", type=Path, help="folder for loop_closures.csv")


def main(runtime: RuntimeConfig, args: argparse.Namespace) -> int:
    config = load_config(LoopClosureConfig, "loopclosure", preset=args.preset, config_file=args.config,
                         overrides={"match_threshold": args.match_threshold, "out": args.out})
    return LoopClosureService(runtime, config, args.instance).run()
