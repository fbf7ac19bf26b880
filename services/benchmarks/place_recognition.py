"""`gridslam bench place-recognition --source SPEC --ground-truth GT [--radius M]`: how well each
place recognition finds the revisits of a recording, against a ground truth.

For each method (`--methods`, default every one of PLACE_RECOGNITIONS) the loop-closure
detector (services/loopclosure/detector.py, the core the loopclosure service runs, with the
paper's consistency rule and the closure geometry) observes every frame, and the table gives:

- **confirmed closures**, true and false by the ground truth, their **precision**, and the
  **recall** by frame: a revisit frame is found when a confirmed closure joins it to a frame
  the ground truth marks (revisits.py: a mask image, poses within `--radius`, or frame ranges);
- **R@100P**: the recall at 100 % precision of the raw match scores — every frame's best
  older place (bow: its inliers; scanline, sequence: minus the difference), ranked by score:
  the largest share of the revisit frames found above a threshold that no false match reaches;
- **ms/frame**: the median time of the detector's `observe`.

`--out DIR` writes `place_recognition.png` (the precision–recall curves of the raw scores) and
`place_recognition.json`. The ground truth `frames` takes the poses of the source's own frames
(the synthetic worlds), with `--radius`.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.common.config import load_config
from services.common.errors import ConfigError
from services.common.settings import CommandParser
from services.evaluation.revisits import from_poses, read_ground_truth
from services.loopclosure.detector import MemoryKeyframes
from services.loopclosure.places import PLACE_RECOGNITIONS
from services.loopclosure.service import LoopClosureConfig
from services.source.spec import open_source


@dataclass
class MethodResult:
    method: str
    confirmed: list[tuple[int, int]]      # (frame, matched frame) of every confirmed closure
    scores: list[tuple[float, int, int]]  # (score, frame, matched frame): each frame's best older place
    ms: list[float]


def run_method(method: str, frames, preset: str | None, config_file: Path | None) -> MethodResult:
    config = load_config(LoopClosureConfig, "loopclosure", preset=preset, config_file=config_file,
                         overrides={"place_recognition": method})
    detector = config.detector(MemoryKeyframes(limit=10**7))
    recent = config.recent_frames
    result = MethodResult(method, [], [], [])
    for frame in frames:
        started = time.perf_counter()
        observed = detector.observe(frame.seq, frame.left, frame.right, frame.camera)
        result.ms.append(1e3 * (time.perf_counter() - started))
        result.confirmed += [(c.frame, c.matched_frame) for c in observed.closures]
        if observed.candidate is not None and frame.seq - observed.candidate[0] >= recent:
            result.scores.append((observed.candidate[1], frame.seq, observed.candidate[0]))
    return result


def precision_recall(scores: list[tuple[float, int, int]], truth, revisits: set[int]) -> tuple[np.ndarray, np.ndarray]:
    """Precision and recall (by revisit frame) of the raw scores at every threshold, best first."""
    ranked = sorted(scores, key=lambda s: -s[0])
    found: set[int] = set()
    true = 0
    precision, recall = [], []
    for count, (_, frame, matched) in enumerate(ranked, start=1):
        if truth.is_true(frame, matched):
            true += 1
            found.add(frame)
        precision.append(true / count)
        recall.append(len(found & revisits) / max(len(revisits), 1))
    return np.array(precision), np.array(recall)


def recall_at_full_precision(precision: np.ndarray, recall: np.ndarray) -> float:
    """The recall reached before the first false match in score order."""
    full = np.flatnonzero(precision < 1.0)
    stop = full[0] if len(full) else len(precision)
    return float(recall[stop - 1]) if stop else 0.0


def summarise(result: MethodResult, truth, revisits: set[int]) -> dict:
    true = [(f, m) for f, m in result.confirmed if truth.is_true(f, m)]
    found = {f for f, _ in true} & revisits
    precision, recall = precision_recall(result.scores, truth, revisits)
    return {"method": result.method, "confirmed": len(result.confirmed), "true": len(true),
            "false": len(result.confirmed) - len(true), "false_pairs": sorted(set(result.confirmed) - set(true))[:20],
            "precision": len(true) / len(result.confirmed) if result.confirmed else None,
            "found": len(found), "revisit_frames": len(revisits), "recall": len(found) / max(len(revisits), 1),
            "recall_at_100_precision": recall_at_full_precision(precision, recall),
            "ms_per_frame_p50": float(np.median(result.ms)), "curve": (precision.tolist(), recall.tolist())}


def frames_truth(frames, radius: float, recent: int):
    """The ground truth of a source whose frames carry their poses (camera convention)."""
    poses = [frame.ground_truth for frame in frames]
    if any(pose is None for pose in poses):
        raise ConfigError("--ground-truth frames: the source's frames carry no ground truth")
    positions = np.array([(pose[2, 3], -pose[0, 3]) for pose in poses])
    headings = np.array([math.atan2(-pose[0, 2], pose[2, 2]) for pose in poses])
    return from_poses(positions, headings, radius, recent)


def plot(path: Path, rows: list[dict], title: str) -> Path | None:
    from services.evaluation.plots import new_figure, save

    figure = new_figure(figsize=(5.5, 4.5))
    if figure is None:
        return None
    axes = figure.add_subplot(1, 1, 1)
    for row in rows:
        precision, recall = row["curve"]
        axes.plot(recall, precision, label=f"{row['method']} (R@100P {100 * row['recall_at_100_precision']:.0f} %)")
    axes.set_xlabel("recall (revisit frames)")
    axes.set_ylabel("precision")
    axes.set_xlim(0, 1)
    axes.set_ylim(0, 1.02)
    axes.set_title(title)
    axes.legend(loc="lower left")
    return save(figure, path)


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="gridslam bench place-recognition", description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", required=True, help="a source spec, e.g. images:../shared/data/rtabmap_samples/images")
    parser.add_argument("--ground-truth", required=True, metavar="GT",
                        help="a revisit mask image (N×N), a poses file (TUM or KITTI, with --radius), frame ranges "
                             "FIRST-LAST:FIRST-LAST (e.g. 180-204:0-40), or 'frames' (the source's own poses, with --radius)")
    parser.add_argument("--radius", type=float, help="poses: frames this close (m) are one place")
    parser.add_argument("--preset", help="dataset preset of the source and the loop closure (its template settings)")
    parser.add_argument("-c", "--config", type=Path, help="a gridslam TOML config file ([loopclosure] ...)")
    parser.add_argument("--methods", default=",".join(PLACE_RECOGNITIONS), help="comma-separated place recognitions")
    parser.add_argument("--n-frames", type=int, help="only the first N frames")
    parser.add_argument("--laps", type=int, help="synthetic world: laps of its route")
    parser.add_argument("--out", type=Path, help="folder for place_recognition.png and .json")
    parser.add_argument("--title", help="title of the plot (default: the source)")
    args = parser.parse_args(argv)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = sorted(set(methods) - set(PLACE_RECOGNITIONS))
    if unknown:
        raise ConfigError(f"--methods: {unknown[0]!r} is not one of {', '.join(PLACE_RECOGNITIONS)}")
    frames = open_source(args.source, preset=args.preset, stop=args.n_frames, world={"laps": args.laps} if args.laps else None)
    frames = list(frames)
    recent = load_config(LoopClosureConfig, "loopclosure", preset=args.preset, config_file=args.config).recent_frames
    if args.ground_truth == "frames":
        truth = frames_truth(frames, args.radius or 2.0, recent)
    else:
        truth = read_ground_truth(args.ground_truth, args.radius, recent)
    revisits = truth.revisit_frames & {frame.seq for frame in frames}
    rows = [summarise(run_method(method, frames, args.preset, args.config), truth, revisits) for method in methods]
    print(f"{args.source}{f' (preset {args.preset})' if args.preset else ''}: {len(frames)} frames, "
          f"{len(revisits)} revisit frames ({args.ground_truth})")
    print()
    print("| place recognition | confirmed | true / false | precision | revisit frames found | recall | R@100P | ms/frame |")
    print("|:--|--:|--:|--:|--:|--:|--:|--:|")
    for row in rows:
        precision = "—" if row["precision"] is None else f"{100 * row['precision']:.0f} %"
        print(f"| {row['method']} | {row['confirmed']} | {row['true']} / {row['false']} | {precision} | "
              f"{row['found']} of {row['revisit_frames']} | {100 * row['recall']:.0f} % | "
              f"{100 * row['recall_at_100_precision']:.0f} % | {row['ms_per_frame_p50']:.1f} |")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "place_recognition.json").write_text(json.dumps(
            {"source": args.source, "preset": args.preset, "ground_truth": args.ground_truth, "frames": len(frames),
             "results": [{k: v for k, v in row.items() if k != "curve"} for row in rows]}, indent=1))
        png = plot(args.out / "place_recognition.png", rows, args.title or args.source)
        print(f"\nresults: {args.out}" + ("" if png else " (no plot: the plots extra is not installed)"))
    return 0
