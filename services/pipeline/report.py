"""Evaluation of a recorded run: trajectories of every stage in TUM and KITTI formats, metrics
per stage against the ground truth, and the plots (issue 6, "Results folder")."""

from __future__ import annotations

import collections
import json
import logging
import math
from pathlib import Path

import numpy as np

from services.common.errors import DataError
from services.common.layout import METRICS, session_of
from services.evaluation import metrics, plots
from services.evaluation.results import write_json, write_trajectory_files
from services.evaluation.revisits import TRUE_CLOSURE_M, same_place
from services.evaluation.trajectory import Trajectory, camera_to_planar, integrate_increments
from services.pipeline.recorder import Recording

log = logging.getLogger(__name__)

RPE_DISTANCES_M = (1.0, 10.0, 100.0)
# Stage → the topic whose arrival times give its latency and throughput. `map_online` is the pose
# expmap published at each frame; `map` is every frame placed on the final, relaxed map, rebuilt
# from the map's journal once the run is over: no topic, so no latency or throughput of its own.
STAGE_TOPICS = {"egomotion": "egomotion", "gridcells": "grid/pose", "map_online": "map/pose", "map": None}


def percentiles(values) -> dict[str, float | None]:
    values = np.asarray(list(values), dtype=float)
    if values.size == 0:
        return {"p50": None, "p99": None}
    return {"p50": float(np.percentile(values, 50)), "p99": float(np.percentile(values, 99))}


def trajectories(recording: Recording) -> dict[str, Trajectory]:
    """One planar trajectory per stage that published (and the ground truth when known), each
    over the frames that stage published, in frame order."""
    stamps = recording.stamps
    result: dict[str, Trajectory] = {}
    seqs = sorted(recording.increments)
    if seqs:
        forward, left, yaw = (np.array([recording.increments[s][i] for s in seqs]) for i in range(3))
        result["egomotion"] = integrate_increments(forward, left, yaw, [stamps.get(s, 0.1 * s) for s in seqs])
    for name, poses in (("gridcells", recording.grid_poses), ("map_online", recording.map_poses),
                        ("map", recording.final_map)):
        seqs = sorted(poses)
        if seqs:
            x, y, heading = (np.array([poses[s][i] for s in seqs]) for i in range(3))
            result[name] = Trajectory.from_planar([stamps.get(s, 0.1 * s) for s in seqs], x, y, heading)
    seqs = sorted(recording.ground_truth)
    if seqs:
        result["groundtruth"] = camera_to_planar(Trajectory.from_matrices(
            [stamps[s] for s in seqs], np.stack([recording.ground_truth[s] for s in seqs])))
    return result


def _seqs(recording: Recording, name: str) -> list[int]:
    source = {"egomotion": recording.increments, "gridcells": recording.grid_poses, "map_online": recording.map_poses,
              "map": recording.final_map, "groundtruth": recording.ground_truth}[name]
    return sorted(source)


def stage_metrics(estimate: Trajectory, reference: Trajectory) -> dict:
    """ATE after SE(2) and Sim(3) alignment, RPE over fixed distances, KITTI drift, endpoint error."""
    length = reference.path_length()
    result = {
        "path_length_m": estimate.path_length(),
        "ate_se2": metrics.ate(estimate, reference, align="se2"),
        "ate_sim3": metrics.ate(estimate, reference, align="sim3"),
        "endpoint": metrics.endpoint_error(estimate, reference),
        "rpe": {f"{d:g}m": metrics.rpe(estimate, reference, d) for d in RPE_DISTANCES_M if d < length},
        "kitti_drift": metrics.kitti_drift(estimate, reference),
    }
    return result


def evaluate(recording: Recording, statuses: dict[str, dict], restarts: dict[str, int], frames_expected: int | None,
             wall_time_s: float) -> tuple[dict, dict[str, Trajectory]]:
    """metrics.json's content and the trajectories it was computed from."""
    trajs = trajectories(recording)
    reference = trajs.get("groundtruth")
    sent = sorted(recording.stamps)
    stages: dict[str, dict] = {}
    for name, topic in STAGE_TOPICS.items():
        if name not in trajs:
            continue
        seqs = _seqs(recording, name)
        stage = {"frames": len(seqs), "missing_frames": len(set(sent) - set(seqs))}
        if topic is not None:
            arrivals = recording.arrivals[topic]
            frame_arrivals = recording.arrivals["camera/frame"]
            latencies_ms = [1e3 * (arrivals[s] - frame_arrivals[s]) for s in seqs if s in frame_arrivals and s in arrivals]
            times = sorted(arrivals.values())
            stage["latency_ms"] = percentiles(latencies_ms)
            stage["throughput_fps"] = ((len(times) - 1) / (times[-1] - times[0])
                                       if len(times) > 1 and times[-1] > times[0] else None)
        if reference is not None:
            common = sorted(set(seqs) & set(_seqs(recording, "groundtruth")))
            if len(common) >= 3:
                index = {s: i for i, s in enumerate(seqs)}
                ref_index = {s: i for i, s in enumerate(_seqs(recording, "groundtruth"))}
                stage.update(stage_metrics(trajs[name].select([index[s] for s in common]),
                                           reference.select([ref_index[s] for s in common])))
        stages[name] = stage
    summary = {
        "frames_expected": frames_expected,
        "frames_sent": len(sent),
        "frames_unreadable": int(statuses.get("source", {}).get("extra", {}).get("frames_unreadable", 0)),
        "wall_time_s": wall_time_s,
        "loop_closures": [dict(zip(("frame", "matched_frame", "matched_template", "votes"), c))
                          for _, c in sorted(recording.closures.items())],
        "map_closures": map_closures(recording, trajs.get("groundtruth")),
        **({"localization": localization(recording, trajs.get("groundtruth"))}
           if recording.frame_base or any(not pose[4] for pose in recording.map_poses.values()) else {}),
        "view_templates": 1 + max((t for t, _ in recording.templates.values()), default=-1),
        "experiences": 1 + max((m[3] for m in recording.map_poses.values()), default=-1),
        "groundtruth_path_length_m": reference.path_length() if reference is not None else None,
        "recorder_decode_errors": recording.decode_errors,
    }
    services = {name: {**status, "restarts": restarts.get(name, 0)} for name, status in sorted(statuses.items())}
    for name, count in restarts.items():
        services.setdefault(name, {"restarts": count})
    return {"summary": summary, "stages": stages, "services": services}, trajs


def map_closures(recording: Recording, truth: Trajectory | None) -> dict:
    """What the final map made of the confirmed closures: accepted, rejected, unmeasured (its
    geometry failed); with ground truth, each fate split into true closures (the two frames
    within TRUE_CLOSURE_M of each other) and false ones, and the largest distance accepted."""
    counts: dict = collections.Counter(fate for _, _, fate in recording.map_decisions)
    result = {fate: counts.get(fate, 0) for fate in ("accepted", "rejected", "unmeasured", "unmatched")}
    if truth is not None and recording.map_decisions:
        position = truth_positions(recording, truth)
        judged = [(fate, same_place(position[f], position[m]), math.dist(position[f], position[m]))
                  for f, m, fate in recording.map_decisions if f in position and m in position]
        for fate in ("accepted", "rejected", "unmeasured"):
            result[f"{fate}_true"] = sum(true for x, true, _ in judged if x == fate)
            result[f"{fate}_false"] = sum(not true for x, true, _ in judged if x == fate)
        result["accepted_largest_distance_m"] = max((d for x, _, d in judged if x == "accepted"), default=None)
    return result


def truth_positions(recording: Recording, truth: Trajectory) -> dict[int, tuple[float, float]]:
    """The true position of every frame the map's closures may name: this run's frames (by their
    number in the map) and a saved map's (services/common/layout.py)."""
    position = dict(recording.saved_truth)
    for row, seq in enumerate(_seqs(recording, "groundtruth")):
        position[recording.frame_base + seq] = tuple(truth.positions[row, :2])
    return position


def localization(recording: Recording, truth: Trajectory | None) -> dict:
    """A session on a saved map: from which frame its poses were in the map's frame (placed or
    joined), how many were, the experiences it added, and — with ground truth in the map's frame
    (a saved map of the same source: the truth's origin is its first frame) — the error of those
    poses as they are, without any alignment."""
    seqs = sorted(recording.map_poses)
    localized = [s for s in seqs if recording.map_poses[s][4]]
    new = {e for _, experiences, _ in recording.map_updates for e, _, _ in experiences}
    result = {"frames": len(seqs), "localized_frames": len(localized),
              "first_localized": localized[0] if localized else None,
              "frames_to_localize": (localized[0] - seqs[0]) if localized else None, "experiences_changed": len(new)}
    if truth is not None and localized:
        row = {s: i for i, s in enumerate(_seqs(recording, "groundtruth"))}
        errors = np.array([math.dist(recording.map_poses[s][:2], truth.positions[row[s], :2]) for s in localized if s in row])
        if len(errors):
            result["error_unaligned_m"] = {"max": float(errors.max()), "rmse": float(np.sqrt(np.mean(errors ** 2))),
                                           "mean": float(errors.mean())}
    if truth is not None and recording.saved_truth and recording.whole_map:
        # Every session's frames on the final map against their truth, in the first session's frame.
        position = truth_positions(recording, truth)
        frames = [f for f in sorted(recording.whole_map) if f in position]
        if len(frames) >= 3:
            poses = np.array([recording.whole_map[f] for f in frames])
            estimate = Trajectory.from_planar(np.arange(len(frames), dtype=float), poses[:, 0], poses[:, 1], poses[:, 2])
            reference = np.array([position[f] for f in frames])
            unaligned = np.hypot(*(poses[:, :2] - reference).T)
            result["whole_map"] = {"frames": len(frames), "sessions": len({session_of(f) for f in frames}),
                                   "ate_se2_rmse_m": metrics.ate(estimate, Trajectory.from_planar(
                                       estimate.stamps, reference[:, 0], reference[:, 1], poses[:, 2]), align="se2")["rmse"],
                                   "error_unaligned_rmse_m": float(np.sqrt(np.mean(unaligned ** 2)))}
    return result


def write_report(folder: Path, recording: Recording, result: dict, trajs: dict[str, Trajectory]) -> list[Path]:
    """Trajectory files, metrics.json and the plots; returns the files written."""
    written: list[Path] = []
    for name, traj in trajs.items():
        written.extend(write_trajectory_files(folder, name, traj))
    written.append(write_json(folder / METRICS, result))
    if trajs:
        written.append(plots.plot_trajectories(folder / "trajectories.png", trajs, title="Trajectories of every stage"))
    reference = trajs.get("groundtruth")
    if reference is not None:
        series = {}
        ref_seqs = _seqs(recording, "groundtruth")
        for name in STAGE_TOPICS:
            if name in trajs:
                seqs = _seqs(recording, name)
                common = sorted(set(seqs) & set(ref_seqs))
                if len(common) >= 3:
                    index, ref_index = {s: i for i, s in enumerate(seqs)}, {s: i for i, s in enumerate(ref_seqs)}
                    errors = metrics.position_errors(trajs[name].select([index[s] for s in common]),
                                                     reference.select([ref_index[s] for s in common]), align="se2")
                    series[name] = (np.array(common), errors)
        if series:
            written.append(plots.plot_series(folder / "errors.png", series, "frame", "position error after SE(2) alignment (m)",
                                             title="Error over frames"))
    if recording.templates or recording.map_poses:
        series = {}
        if recording.templates:
            seqs = sorted(recording.templates)
            series["view template"] = (np.array(seqs), np.array([recording.templates[s][0] for s in seqs]))
        if recording.map_poses:
            seqs = sorted(recording.map_poses)
            series["experience"] = (np.array(seqs), np.array([recording.map_poses[s][3] for s in seqs]))
        written.append(plots.plot_series(folder / "templates.png", series, "frame", "id",
                                         title="View templates and experiences over frames (paper Fig. 10)"))
    if recording.lattices:
        seqs = sorted(recording.lattices)
        picks = sorted({seqs[int(i)] for i in np.linspace(0, len(seqs) - 1, min(4, len(seqs)))})
        written.append(plots.plot_heatmaps(folder / "lattice.png", {f"frame {s}": recording.lattices[s] for s in picks},
                                           title="Grid-cell activity (paper Fig. 1)"))
    return [path for path in written if path is not None]   # (a plot is None without matplotlib)


def summary_rows(result: dict) -> list[tuple[str, object, str]]:
    """The Metric | Value | Unit table printed at the end of a run."""
    summary = result["summary"]
    rows: list[tuple[str, object, str]] = [
        ("frames sent", summary["frames_sent"], "frames"),
        *([("frames unreadable, skipped", summary["frames_unreadable"], "frames (logs/source.log names them)")]
          if summary.get("frames_unreadable") else []),
        ("wall time", summary["wall_time_s"], "s"),
        ("ground-truth path", summary["groundtruth_path_length_m"], "m"),
        ("view templates", summary["view_templates"], ""),
        ("experiences", summary["experiences"], ""),
        ("confirmed loop closures", len(summary["loop_closures"]), ""),
    ]
    closures = summary["map_closures"]
    if summary["loop_closures"]:
        rows.append(("closures accepted / rejected / unmeasured by the map",
                     f"{closures['accepted']} / {closures['rejected']} / {closures['unmeasured']}", ""))
    located = summary.get("localization")
    if located:
        rows.append(("in the map's frame from frame", "—" if located["first_localized"] is None else
                     f"{located['first_localized']} ({located['frames_to_localize']} frames in)", ""))
        rows.append(("frames in the map's frame", f"{located['localized_frames']} of {located['frames']}", "frames"))
        rows.append(("experiences added or moved", located["experiences_changed"], ""))
        if "error_unaligned_m" in located:
            error = located["error_unaligned_m"]
            rows.append(("map pose error, no alignment: max / RMSE", f"{error['max']:.4g} / {error['rmse']:.4g}", "m"))
        if "whole_map" in located:
            whole = located["whole_map"]
            rows.append((f"whole map ({whole['sessions']} sessions, {whole['frames']} frames): ATE RMSE (SE(2)) / "
                         "no alignment", f"{whole['ate_se2_rmse_m']:.4g} / {whole['error_unaligned_rmse_m']:.4g}", "m"))
    if "accepted_false" in closures:
        rows.append(("closures accepted: true / false", f"{closures['accepted_true']} / {closures['accepted_false']}",
                     f"false: frames > {TRUE_CLOSURE_M:g} m apart"))
        rows.append(("closures rejected: true / false", f"{closures['rejected_true']} / {closures['rejected_false']}", ""))
    stages = result["stages"]
    for name in sorted(stages, key=list(STAGE_TOPICS).index):   # pipeline order (metrics.json sorts them by name)
        stage = stages[name]
        rows.append((f"{name}: frames", stage["frames"], "frames"))
        if "ate_se2" in stage:
            rows.append((f"{name}: ATE RMSE (SE(2))", stage["ate_se2"]["rmse"], "m"))
            rows.append((f"{name}: ATE RMSE (Sim(3))", stage["ate_sim3"]["rmse"], "m"))
            rows.append((f"{name}: endpoint error", stage["endpoint"]["percent_of_path"], "% of path"))
        if "latency_ms" in stage:   # (not the final map: it is rebuilt after the run)
            rows.append((f"{name}: latency p50 from frame", stage["latency_ms"]["p50"], "ms"))
            rows.append((f"{name}: latency p99 from frame", stage["latency_ms"]["p99"], "ms"))
            rows.append((f"{name}: throughput", stage["throughput_fps"], "frames/s"))
    for name, service in result["services"].items():
        for counter in ("decode_errors", "gaps", "restarts"):
            if service.get(counter):
                rows.append((f"{name}: {counter.replace('_', ' ')}", service[counter], ""))
    return rows


def read_metrics(folder: Path) -> dict:
    """A results folder's metrics.json."""
    path = Path(folder) / METRICS
    if not path.is_file():
        raise DataError(f"{path}: not found (a results folder of `gridslam run` or `demo` holds it)")
    try:
        result = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise DataError(f"{path}: not readable JSON ({error})") from None
    if not isinstance(result, dict) or not {"summary", "stages", "services"} <= result.keys():
        raise DataError(f"{path}: not a run's metrics (summary, stages and services expected)")
    return result
