"""The offline map build (`gridslam map build`, `map sweep`): the loop-closure and
experience-map stages on a source or an image folder and a motion file,
the same cores as the services (view templates, the paper's consistency rule, the experience
map and its log) driven frame by frame in one process, so a dataset's evidence (docs/mapping.md)
is reproducible without a Zenoh network: the paper's Fig. 10 (template and experience ids over
frames), the confirmed closures, the map before and after correction, and a sweep of the match
threshold that shows which closures the consistency rule rejects.

A closure is judged against a reference path (by default the odometry): it is true when the
two frames' reference positions are within `same_place_radius` metres. NuBot has no ground
truth, but its LIBVISO2 loop ends 0.13 m from its start, so its dead reckoning tells places
apart far better than a metre; when noise is added to the map's odometry, the closures are
still judged on the noiseless dead reckoning.
"""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.common.errors import DataError
from services.evaluation import metrics
from services.evaluation.motion_io import add_noise, load_motion
from services.evaluation.plots import new_figure, save
from services.evaluation.results import write_json
from services.evaluation.trajectory import Trajectory, write_tum
from services.expmap.export import corrected_trajectory, graph_dict, odometry_trajectory
from services.expmap.graph import ExperienceMap, MapParams, MapState
from services.expmap.links import ClosureInput, Link
from services.expmap.store import MapStore, Step
from services.loopclosure.detector import Confirmed, LoopClosureDetector
from services.offline.integration import run_deadreckoning, run_grid

log = logging.getLogger(__name__)

CLOSURE_COLUMNS = ("frame", "matched_frame", "matched_template", "votes", "place_distance_m", "same_place")
FRAME_COLUMNS = ("frame", "template_id", "is_new", "distance", "matched_frame", "possible_closure", "loop_closure", "experience")


class EvidenceError(DataError):
    """Inputs of an offline map build that do not fit together."""


@dataclass(eq=False)
class OfflineMap:
    """Everything an offline build saw, per frame, and the final map."""

    frames: np.ndarray              # (N,) frame indices
    template_ids: np.ndarray        # (N,)
    is_new: np.ndarray              # (N,) bool
    distances: np.ndarray           # (N,) match distance
    matched_frames: np.ndarray      # (N,) frame at which the matched template was stored
    possible: np.ndarray            # (N,) bool: a match of a non-recent template (a possible closure)
    experiences: np.ndarray         # (N,) the experience the robot is at
    closures: list[Confirmed]
    experience_map: ExperienceMap
    template_count: int
    steps: list[Step]               # the map's inputs (odometry pose, template, closure), as its log holds them
    before: MapState | None = None  # the map just before the first loop-closure link
    reference: Trajectory | None = None   # (N poses) the path closures are judged on (None: the odometry)
    files: dict[str, Path] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._row = {int(f): i for i, f in enumerate(self.frames)}
        self.odometry = np.array([step.odometry for step in self.steps])   # (N, 3) x, y, heading

    def place_distance(self, frame: int, matched_frame: int) -> float:
        """Distance between where two frames were taken on the reference path, m."""
        positions = self.odometry if self.reference is None else self.reference.positions
        a, b = positions[self._row[frame]], positions[self._row[matched_frame]]
        return float(math.hypot(a[0] - b[0], a[1] - b[1]))

    def odometry_trajectory(self) -> Trajectory:
        return odometry_trajectory(self.steps)

    def corrected_trajectory(self) -> Trajectory:
        return corrected_trajectory(self.experience_map, self.steps)

    def closure_rows(self, radius: float) -> list[dict]:
        rows = []
        for closure in self.closures:
            distance = self.place_distance(closure.frame, closure.matched_frame)
            rows.append({"frame": closure.frame, "matched_frame": closure.matched_frame,
                         "matched_template": closure.matched_template, "votes": closure.votes,
                         "place_distance_m": distance, "same_place": distance <= radius})
        return rows

    def summary(self, radius: float) -> dict:
        """Counts and closures; "elsewhere" means between frames more than `radius` apart."""
        possible = [(int(f), int(m)) for f, m, p in zip(self.frames, self.matched_frames, self.possible) if p]
        possible_far = [(f, m) for f, m in possible if self.place_distance(f, m) > radius]
        rows = self.closure_rows(radius)
        true_rows = [row for row in rows if row["same_place"]]
        odometry, corrected = self.odometry_trajectory(), self.corrected_trajectory()
        links = self.experience_map.links
        errors = {}
        if self.reference is not None:   # e.g. noisy odometry against the noiseless path (SE(2)-aligned)
            for name, traj in (("odometry", odometry), ("corrected", corrected)):
                ate = metrics.ate(traj, self.reference, align="se2")
                errors[f"{name}_error_vs_reference_m"] = {"mean": ate["mean"], "max": ate["max"], "rmse": ate["rmse"]}
        return errors | {
            "frames": len(self.frames),
            "view_templates": self.template_count,
            "experiences": len(self.experience_map),
            "links": len(links),
            "loop_closure_links": sum(link.loop_closure for link in links),
            "closures_accepted": self.experience_map.closures["accepted"],
            "closures_rejected": self.experience_map.closures["rejected"],
            "closures_unmeasured": self.experience_map.closures["unmeasured"],
            "possible_closures": len(possible),
            "possible_closures_elsewhere": len(possible_far),
            "possible_closures_elsewhere_frames": possible_far,
            "confirmed_closures": len(rows),
            "confirmed_closures_elsewhere": len(rows) - len(true_rows),
            "first_confirmed": rows[0] if rows else None,
            "confirmed_frames": [min((r["frame"] for r in rows), default=None), max((r["frame"] for r in rows), default=None)],
            "matched_frames": sorted({r["matched_frame"] for r in rows}),
            "same_place_radius_m": radius,
            "odometry_end_to_start_m": metrics.end_to_start_gap(odometry),
            "corrected_end_to_start_m": metrics.end_to_start_gap(corrected),
            "odometry_path_m": odometry.path_length(),
            "corrected_path_m": corrected.path_length(),
        }


def odometry_from_motion(path, integrator: str = "deadreckoning", decoder: str = "subpixel", velocity_scale: float = 1.0,
                         noise_trans: float = 0.0, noise_rot_deg: float = 0.0, seed: int = 0) -> Trajectory:
    """The odometry of a motion file (e.g. NuBot's LIBVISO2 table) integrated as the gridcells
    service would: dead reckoning, or the grid-cell network with `decoder` and `velocity_scale`
    (network units per metre); optional Gaussian noise on the increments (motion_io.add_noise)."""
    motion = add_noise(load_motion(path), noise_trans, noise_rot_deg, seed)
    if integrator == "deadreckoning":
        return run_deadreckoning(motion).trajectory
    if integrator == "grid":
        return run_grid(motion, decoder, velocity_scale).trajectory
    raise EvidenceError(f"unknown integrator {integrator!r} (grid or deadreckoning)")


def closure_input(closure: Confirmed, seq: int) -> ClosureInput:
    """The map's input of a closure confirmed at frame ``seq``."""
    m = closure.measurement
    return ClosureInput(closure.matched_template, closure.matched_frame, m.method if m.method != "none" else "", m.forward,
                        m.left, m.yaw, m.covariance, closure.votes, m.inliers, m.error,
                        closure.frame if closure.frame != seq else -1)


def build_map(images: Iterable, odometry: Trajectory, detector: LoopClosureDetector, map_params: MapParams,
              store: Path | None = None, reference: Trajectory | None = None) -> OfflineMap:
    """Run the loop-closure detector and the experience map over `images` (frames with `seq`,
    `stamp`, `left`, and optionally `right` and `camera`: a source's frames, or a list of them);
    odometry row k is the pose at frame k. With `store`, the map's inputs are written to that log
    as the expmap service writes them (so `gridslam map export` reads it). Closures are judged on
    `reference` (row k at frame k; None: the odometry)."""
    x, y, heading = odometry.planar()
    experience_map = ExperienceMap(map_params)
    map_store = MapStore(store, map_params) if store is not None else None
    if map_store is not None and map_store.steps:
        map_store.close()
        raise EvidenceError(f"{store}: already holds a map; choose a new file")
    columns: dict[str, list] = {name: [] for name in ("frames", "template_ids", "is_new", "distances", "matched_frames",
                                                      "possible", "experiences")}
    closures: list[Confirmed] = []
    steps: list[Step] = []
    before = None
    try:
        for frame in images:
            seq = int(frame.seq)
            if seq >= len(x):
                raise EvidenceError(f"frame {seq}: the odometry has only {len(x)} poses")
            observed = detector.observe(seq, frame.left, getattr(frame, "right", None), getattr(frame, "camera", None))
            match = observed.match
            pose = (float(x[seq]), float(y[seq]), float(heading[seq]))
            own = next((closure_input(c, seq) for c in observed.closures if c.frame == seq), None)
            earlier = tuple(closure_input(c, seq) for c in observed.closures if c.frame != seq)
            step = Step(seq, float(frame.stamp), pose, match.template_id, own, earlier=earlier)
            if map_store is not None:
                map_store.append(step)
            steps.append(step)
            state = experience_map.snapshot() if before is None else None
            result = step.apply(experience_map)
            if before is None and any(link.loop_closure and link.accepted for link in result.new_links):
                before = state
            closures += observed.closures
            for name, value in (("frames", seq), ("template_ids", match.template_id), ("is_new", match.is_new),
                                ("distances", match.distance), ("matched_frames", match.matched_frame),
                                ("possible", observed.vote is not None),
                                ("experiences", result.experience)):
                columns[name].append(value)
    finally:
        if map_store is not None:
            map_store.close()
    if not columns["frames"]:
        raise EvidenceError("no frames to build a map from")
    arrays = {name: np.array(values) for name, values in columns.items()}
    if reference is not None:
        if len(reference) < len(x):
            raise EvidenceError(f"the reference path has {len(reference)} poses, the odometry {len(x)}")
        reference = reference.select(arrays["frames"])
    return OfflineMap(**arrays, closures=closures, experience_map=experience_map, template_count=len(detector.places),
                      steps=steps, before=before, reference=reference)


# --- plots ------------------------------------------------------------------------------------
def plot_ids_over_frames(png_path, run: OfflineMap, radius: float, title: str = "") -> Path | None:
    """The paper's Fig. 10: view-template id and experience id against frame, with the
    possible closures (matches of non-recent templates) and the confirmed ones marked."""
    figure = new_figure(figsize=(8.0, 6.0), layout="constrained")
    if figure is None:
        return None
    top, bottom = figure.subplots(2, 1, sharex=True)
    top.step(run.frames, run.template_ids, where="post", color="C0", linewidth=1.2, label="view template")
    bottom.step(run.frames, run.experiences, where="post", color="C1", linewidth=1.2, label="experience")
    near = np.array([run.place_distance(int(f), int(m)) <= radius for f, m in zip(run.frames, run.matched_frames)])
    for axes, ids in ((top, run.template_ids), (bottom, run.experiences)):
        for mask, colour, label in ((run.possible & near, "C2", f"possible closure (same place, ≤ {radius:g} m)"),
                                    (run.possible & ~near, "C3", f"possible closure elsewhere (> {radius:g} m)")):
            if mask.any():
                axes.plot(run.frames[mask], ids[mask], "o", markersize=4, color=colour, label=label)
        confirmed = np.array([c.frame for c in run.closures])
        if len(confirmed):
            rows = np.searchsorted(run.frames, confirmed)
            axes.plot(confirmed, ids[rows], "x", color="black", markersize=6, label="confirmed closure")
        axes.grid(True, alpha=0.3)
        axes.legend(loc="upper left", fontsize="small")
    top.set_ylabel("view template id")
    bottom.set_ylabel("experience id")
    bottom.set_xlabel("frame")
    if title:
        top.set_title(title)
    return save(figure, png_path)


def _draw_map(axes, poses: np.ndarray, links: list[Link], odometry: np.ndarray | None, title: str) -> None:
    if odometry is not None:
        axes.plot(odometry[:, 0], odometry[:, 1], color="0.75", linewidth=1.0, label="odometry path")
    for link in links:
        a, b = poses[link.source], poses[link.target]
        axes.plot([a[0], b[0]], [a[1], b[1]], color="C3" if link.loop_closure else "C0",
                  linewidth=2.0 if link.loop_closure and link.accepted else 0.8,
                  linestyle="-" if link.accepted else ":")
    axes.plot(poses[:, 0], poses[:, 1], ".", color="C0", markersize=4, label=f"{len(poses)} experiences")
    axes.plot([], [], color="C0", linewidth=0.8, label="odometric link")
    axes.plot([], [], color="C3", linewidth=2.0, label="loop-closure link")
    if any(not link.accepted for link in links):
        axes.plot([], [], color="C3", linewidth=0.8, linestyle=":", label="closure the map refused")
    axes.plot(poses[0, 0], poses[0, 1], "o", color="black", markersize=6, label="first experience")
    axes.set_aspect("equal", adjustable="datalim")
    axes.grid(True, alpha=0.3)
    axes.set_xlabel("x [m]")
    axes.set_ylabel("y [m]")
    axes.set_title(title, fontsize="medium")
    axes.legend(loc="best", fontsize="x-small")


def plot_map_correction(png_path, run: OfflineMap, title: str = "") -> Path | None:
    """The experience map just before its first loop-closure link (odometry only) beside the
    final relaxed map, and the per-frame trajectory before and after correction."""
    figure = new_figure(figsize=(15.0, 5.2), layout="constrained")
    if figure is None:
        return None
    left, middle, right = figure.subplots(1, 3)
    if run.before is not None:
        _draw_map(left, run.before.poses, run.before.links, run.odometry,
                  f"before the first loop-closure link ({len(run.before.poses)} experiences)")
    else:
        left.set_title("no loop-closure link: the map is the odometry")
    final = run.experience_map
    _draw_map(middle, final.final_poses(), final.links, None, f"the final map (end of run, {len(final)} experiences)")
    corrected = run.corrected_trajectory().positions
    if run.reference is not None:
        right.plot(run.reference.positions[:, 0], run.reference.positions[:, 1], "--", color="black", linewidth=1.0,
                   label="reference (noiseless odometry)")
    right.plot(run.odometry[:, 0], run.odometry[:, 1], color="0.6", label="odometry (uncorrected)")
    right.plot(corrected[:, 0], corrected[:, 1], color="C2", label="frames on the final map (corrected)")
    for positions, colour in ((run.odometry, "0.6"), (corrected, "C2")):
        right.plot(positions[0, 0], positions[0, 1], "o", color=colour)
        right.plot(positions[-1, 0], positions[-1, 1], "s", color=colour)
    right.set_aspect("equal", adjustable="datalim")
    right.grid(True, alpha=0.3)
    right.set_xlabel("x [m]")
    right.set_title("per-frame trajectory, as is (○ start, □ end)", fontsize="medium")
    right.legend(loc="best", fontsize="x-small")
    if title:
        figure.suptitle(title)
    return save(figure, png_path)


# --- results ----------------------------------------------------------------------------------
def write_build(folder: Path, run: OfflineMap, radius: float, config: dict, title: str = "") -> dict[str, Path]:
    """loop_closures.csv, frames.csv, summary.json (with the config), map.tum (corrected),
    odometry.tum, graph.json and the two plots."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    files = {}
    with open(folder / "loop_closures.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=CLOSURE_COLUMNS)
        writer.writeheader()
        writer.writerows(run.closure_rows(radius))
    files["loop_closures"] = folder / "loop_closures.csv"
    with open(folder / "frames.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(FRAME_COLUMNS)
        closed = {c.frame for c in run.closures}
        for i, frame in enumerate(run.frames):
            writer.writerow((int(frame), int(run.template_ids[i]), int(run.is_new[i]), f"{run.distances[i]:.5f}",
                             int(run.matched_frames[i]), int(run.possible[i]), int(frame in closed), int(run.experiences[i])))
    files["frames"] = folder / "frames.csv"
    files["summary"] = write_json(folder / "summary.json", {"config": config, "summary": run.summary(radius)})
    files["map_tum"] = write_tum(folder / "map.tum", run.corrected_trajectory())
    files["odometry_tum"] = write_tum(folder / "odometry.tum", run.odometry_trajectory())
    files["graph"] = write_json(folder / "graph.json", graph_dict(run.experience_map))
    files["ids_plot"] = plot_ids_over_frames(folder / "templates_experiences.png", run, radius, title)
    files["map_plot"] = plot_map_correction(folder / "map_correction.png", run, title)
    run.files.update(files)
    return files


def sweep(images: list, odometry: Trajectory, loopclosure, map_params: MapParams, thresholds: list[float],
          tolerances: list[int], radius: float, reference: Trajectory | None = None) -> list[dict]:
    """One build per (match threshold, tolerance) of the loop-closure config `loopclosure`
    (services.loopclosure.service.LoopClosureConfig): what each finds, true and false."""
    rows = []
    for tolerance in tolerances:
        for threshold in thresholds:
            detector = loopclosure.model_copy(update={"match_threshold": threshold, "tolerance": tolerance}).detector()
            run = build_map(images, odometry, detector, map_params, reference=reference)
            summary = run.summary(radius)
            first = summary["first_confirmed"]
            rows.append({"match_threshold": threshold, "tolerance": tolerance, "view_templates": summary["view_templates"],
                         "possible": summary["possible_closures"], "possible_elsewhere": summary["possible_closures_elsewhere"],
                         "confirmed": summary["confirmed_closures"],
                         "confirmed_elsewhere": summary["confirmed_closures_elsewhere"],
                         "first_confirmed": f"{first['frame']} ↔ {first['matched_frame']}" if first else "-"})
    return rows
