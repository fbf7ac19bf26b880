"""loopclosure: RatSLAM view templates of every frame and the paper's loop-closure rule."""

from __future__ import annotations

import argparse
import base64
import collections
import csv
import logging
from pathlib import Path

import numpy as np

from pydantic import BaseModel, ConfigDict, Field

from schemas import CameraFrame, LoopClosure, ViewTemplate
from services.common.config import load_config
from services.common.errors import PersistenceError
from services.common.convert import image_from_msg
from services.common.runtime import RuntimeConfig
from services.common.journal import Journal
from services.common.service import REPLAY_FRAMES, Service
from services.loopclosure.consistency import Closure, ConsistencyParams, ConsistencyRule
from services.loopclosure.templates import TemplateParams, ViewMatch, ViewTemplates

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
    store: Path | None = Field(
        None, description="Journal of templates and matches, appended every frame; a restarted service resumes from it.")

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
        # Frames already handled (from the journal after a restart), to answer a re-sent frame again.
        self.recent: collections.OrderedDict[int, tuple[ViewMatch, Closure | None]] = collections.OrderedDict()
        self.last_frame: int | None = None
        self.journal = None
        if config.store is not None:
            params = config.model_dump(mode="json", exclude={"out", "store"})
            self.journal = Journal(config.store, {"format": "gridslam-view-templates", "version": 1, "params": params})
            for record in self.journal.records:
                self._replay(record)
            if self.journal.records:
                log.info("loopclosure resumed from %s: %d frames, %d templates", config.store,
                         len(self.journal.records), len(self.templates))

    def setup(self) -> None:
        self.subscribe("camera/frame", self.on_frame)

    def teardown(self) -> None:
        if self.journal is not None:
            self.journal.close()

    def on_frame(self, message: CameraFrame) -> None:
        seq = message.header.seq
        if self.last_frame is not None and seq <= self.last_frame:
            if seq in self.recent:   # handled before a restart: answer it again from the journal
                self._publish(message.header, *self.recent[seq])
            return
        image = image_from_msg(message.left)
        match = self.templates.observe(image, seq)
        closure = self.rule.update(seq, match.template_id, match.is_new, match.matched_frame)
        if closure is not None:
            self.closures += 1
            log.info("loop closure confirmed at frame %d: frame %d (template %d), %d votes", seq, closure.matched_frame,
                     closure.matched_template, closure.votes)
            if self.csv_path is not None:
                try:
                    with open(self.csv_path, "a", newline="") as handle:
                        csv.writer(handle).writerow((seq, closure.matched_frame, closure.matched_template, closure.votes))
                except OSError as error:
                    raise PersistenceError(f"{self.csv_path}: cannot append ({error.strerror or error})") from None
        self._publish(message.header, match, closure)
        # Journaled after publishing: a crash in between re-handles the frame, never loses it.
        if self.journal is not None:
            patch = self.templates.patch(match.template_id) if match.is_new else None
            self.journal.append({"frame": seq, "template": match.template_id, "new": match.is_new,
                                 "distance": match.distance, "angle": match.relative_angle, "matched_frame": match.matched_frame,
                                 "shift": match.shift, "patch": base64.b64encode(patch.tobytes()).decode() if patch is not None else None})
        self._remember(seq, match, closure)

    def _publish(self, header, match: ViewMatch, closure: Closure | None) -> None:
        if closure is not None:
            self.publish("loop/closure", LoopClosure(header=header, frame=closure.frame, matched_frame=closure.matched_frame,
                                                     matched_template=closure.matched_template, votes=closure.votes))
        self.publish("view/template", ViewTemplate(
            header=header, template_id=match.template_id, is_new=match.is_new, distance=match.distance,
            relative_angle=match.relative_angle, matched_frame=match.matched_frame, template_count=len(self.templates),
            loop_closure=closure is not None))

    def _replay(self, record: dict) -> None:
        """Rebuild the templates and the consistency window from one journal record."""
        frame = record["frame"]
        if record["new"]:
            shape = (self.config.height, self.config.width)
            self.templates.add(np.frombuffer(base64.b64decode(record["patch"]), dtype=np.float32).reshape(shape), frame)
        match = ViewMatch(record["template"], record["new"], record["distance"], record["angle"], record["matched_frame"],
                          record["shift"])
        closure = self.rule.update(frame, match.template_id, match.is_new, match.matched_frame)
        self.closures += closure is not None
        self._remember(frame, match, closure)

    def _remember(self, frame: int, match: ViewMatch, closure: Closure | None) -> None:
        self.last_frame = frame
        self.recent[frame] = (match, closure)
        while len(self.recent) > REPLAY_FRAMES:
            self.recent.popitem(last=False)

    def extra_counters(self) -> dict[str, float]:
        return {**super().extra_counters(), "templates": len(self.templates), "loop_closures": self.closures}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", help="view-template parameters for a dataset: synthetic, nubot, kitti, stlucia")
    parser.add_argument("--match-threshold", type=float, help="template match distance threshold")
    parser.add_argument("--out", type=Path, help="folder for loop_closures.csv")
    parser.add_argument("--store", type=Path, help="journal of templates; a restart resumes from it")


def main(runtime: RuntimeConfig, args: argparse.Namespace) -> int:
    config = load_config(LoopClosureConfig, "loopclosure", preset=args.preset, config_file=args.config,
                         overrides={"match_threshold": args.match_threshold, "out": args.out, "store": args.store})
    return LoopClosureService(runtime, config, args.instance).run()
