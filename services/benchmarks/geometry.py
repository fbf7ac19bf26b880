"""`gridslam bench geometry`: accuracy and cost of metric loop closures (services/loopclosure/geometry.py).

1. Accuracy on the synthetic world (exact ground truth), several seeds: for each, pairs of a
   lap-1 keyframe and a later view of the same place, alternately the lap-2 frame up to 8
   frames (0.8 m) away and a view rendered off the route (±0.3 m sideways, ±0.5 m along,
   ±8°). Stereo: success rate, RMS and largest errors, and the normalised squared errors
   eᵀC⁻¹e (3 on average for a consistent covariance). Mono: yaw and direction errors.
   Pairs of places at least 4 m apart must all be refused.
2. NuBot (when ../shared/data is present): keyframe of frame 0 against frames 184..204, where
   the robot is back at its start and stands still from ~190 on; frames 30..165 (metres away
   on LIBVISO2's path) must be refused.
3. Cost at 640×480 (NuBot's images, else the synthetic world rendered at that size): medians
   of `keyframe` and `relative_pose`, stereo and mono, in one thread, wall clock and thread
   CPU time.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from services.benchmarks.timing import median_ms as timed_medians
from services.common.frames import Camera
from services.common.settings import CommandParser
from services.loopclosure.geometry import ClosureGeometry
from services.source.synthetic import SyntheticWorld, WorldConfig, default_camera

NUBOT = Path(__file__).resolve().parents[3] / "shared" / "data" / "nubot_scene1"
NUBOT_CAMERA = Camera(493.86945, 493.86945, 320.33392, 244.18816, 0.11996, 640, 480)


def relative(p0, p1) -> np.ndarray:
    """Planar pose p1 = (x, y, yaw) in the body frame of p0: (forward, left, yaw)."""
    (x0, y0, h0), (x1, y1, h1) = p0, p1
    c, s = math.cos(h0), math.sin(h0)
    return np.array([c * (x1 - x0) + s * (y1 - y0), -s * (x1 - x0) + c * (y1 - y0), math.remainder(h1 - h0, 2 * math.pi)])


def revisits(world: SyntheticWorld, count: int, seed: int) -> list:
    """``count`` pairs (keyframe's frame, current left image, true relative pose): a lap-1 frame
    and, alternately, the lap-2 frame up to 8 frames away or a view rendered off the route."""
    rng = np.random.default_rng(seed)
    lap = world.frames_per_lap
    pairs = []
    for index, a in enumerate(rng.choice(np.arange(10, lap - 10), count, replace=False)):
        a = int(a)
        if index % 2 == 0:
            b = a + lap + int(rng.integers(-8, 9))
            pairs.append((world[a], world[b].left, relative(world.planar_pose(a), world.planar_pose(b))))
        else:
            x, y, h = world.planar_pose(a)
            forward, left, turn = rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3), math.radians(rng.uniform(-8, 8))
            pose = (x + math.cos(h) * forward - math.sin(h) * left, y + math.sin(h) * forward + math.cos(h) * left, h + turn)
            image, _ = world.render(*pose, exposure=1.05, noise=np.random.default_rng([seed, a]))
            pairs.append((world[a], image, relative(world.planar_pose(a), pose)))
    return pairs


def unrelated(world: SyntheticWorld, count: int, seed: int) -> list:
    """``count`` pairs (keyframe's frame, lap-2 frame) of places at least 4 m apart along the route."""
    rng = np.random.default_rng(seed + 1000)
    lap = world.frames_per_lap
    pairs = []
    for _ in range(count):
        a = int(rng.integers(lap))
        pairs.append((world[a], world[(a + int(rng.integers(40, lap - 40))) % lap + lap]))
    return pairs


def pose_error(result, truth) -> np.ndarray:
    error = np.array([result.forward, result.left, result.yaw]) - truth
    error[2] = math.remainder(error[2], 2 * math.pi)
    return error


def direction_error(result, truth) -> float:
    return abs(math.degrees(math.remainder(math.atan2(result.left, result.forward) - math.atan2(truth[1], truth[0]), 2 * math.pi)))


def accuracy(seeds: list[int], count: int, geometry: ClosureGeometry) -> dict:
    stereo, mono, pairs, refused, tried = [], [], 0, 0, 0
    for seed in seeds:
        world = SyntheticWorld(WorldConfig(seed=seed))
        for frame, image, truth in revisits(world, count, seed):
            pairs += 1
            result = geometry.relative_pose(geometry.keyframe(frame.left, frame.right, frame.camera), image)
            if result.ok:
                error = pose_error(result, truth)
                stereo.append((error, float(error @ np.linalg.solve(result.covariance, error))))
            result = geometry.relative_pose(geometry.keyframe(frame.left, None, frame.camera), image)
            if result.ok:
                yaw_error = math.remainder(result.yaw - truth[2], 2 * math.pi)
                known = (result.forward or result.left) and math.hypot(truth[0], truth[1]) >= 0.2
                mono.append((abs(math.degrees(yaw_error)), direction_error(result, truth) if known else math.nan,
                             yaw_error ** 2 / result.covariance[2, 2]))
        for frame, other in unrelated(world, count // 2, seed):
            tried += 2
            refused += not geometry.relative_pose(geometry.keyframe(frame.left, frame.right, frame.camera), other.left).ok
            refused += not geometry.relative_pose(geometry.keyframe(frame.left, None, frame.camera), other.left).ok
    errors = np.array([e for e, _ in stereo])
    nees = np.array([n for _, n in stereo])
    yaw, direction, z = (np.array(column) for column in zip(*mono))
    direction = direction[np.isfinite(direction)]
    return {
        "stereo_ok": f"{len(stereo)}/{pairs}",
        "stereo_rms_cm": np.sqrt((errors[:, :2] ** 2).mean(axis=0)) * 100,
        "stereo_max_cm": np.abs(errors[:, :2]).max(axis=0) * 100,
        "stereo_yaw_rms_deg": math.degrees(math.sqrt((errors[:, 2] ** 2).mean())),
        "stereo_yaw_max_deg": math.degrees(np.abs(errors[:, 2]).max()),
        "nees": (nees.mean(), np.median(nees), np.percentile(nees, 95), nees.max()),
        "mono_ok": f"{len(mono)}/{pairs}",
        "mono_yaw_deg": (np.median(yaw), np.percentile(yaw, 90), yaw.max()),
        "mono_direction_deg": (np.median(direction), np.percentile(direction, 90), direction.max(), len(direction)),
        "mono_yaw_z2": (np.median(z), z.mean()),
        "refused": f"{refused}/{tried}",
    }


def nubot_image(side: str, frame: int) -> np.ndarray:
    return cv2.imread(str(NUBOT / side / f"{frame:06d}.png"), cv2.IMREAD_GRAYSCALE)


def nubot(geometry: ClosureGeometry) -> dict:
    keyframe = geometry.keyframe(nubot_image("left", 0), nubot_image("right", 0), NUBOT_CAMERA)
    mono = geometry.keyframe(nubot_image("left", 0), None, NUBOT_CAMERA)
    closures = [geometry.relative_pose(keyframe, nubot_image("left", b)) for b in range(184, 205)]
    monos = [geometry.relative_pose(mono, nubot_image("left", b)) for b in range(184, 205)]
    ok = [r for r in closures if r.ok]
    poses = np.array([(r.forward, r.left, math.degrees(r.yaw)) for r in ok])
    still = np.array([(r.forward, r.left, math.degrees(r.yaw)) for b, r in zip(range(184, 205), closures) if r.ok and b >= 190])
    yaw_gap = [abs(math.degrees(a.yaw - m.yaw)) for a, m in zip(closures, monos) if a.ok and m.ok]
    elsewhere = range(30, 166, 5)
    refused = sum(not geometry.relative_pose(keyframe, nubot_image("left", b)).ok for b in elsewhere)
    refused_mono = sum(not geometry.relative_pose(mono, nubot_image("left", b)).ok for b in elsewhere)
    return {
        "ok": f"{len(ok)}/{len(closures)}", "mono_ok": f"{sum(m.ok for m in monos)}/{len(monos)}",
        "mean": poses.mean(axis=0), "still_std": still.std(axis=0),
        "sd": np.sqrt(np.mean([np.diag(r.covariance) for r in ok], axis=0)) * [1, 1, 180 / math.pi],
        "inliers": int(np.median([r.inliers for r in ok])),
        "mono_yaw_gap_deg": (np.median(yaw_gap), max(yaw_gap)),
        "refused": f"{refused}/{len(elsewhere)} stereo, {refused_mono}/{len(elsewhere)} mono",
    }


def timing(geometry: ClosureGeometry, repeats: int) -> dict:
    """Median ms of keyframe/relative_pose at 640×480 (NuBot frames 0 → 190, else synthetic)."""
    if NUBOT.is_dir():
        source = "NuBot frames 0 and 190"
        left, right, current, camera = nubot_image("left", 0), nubot_image("right", 0), nubot_image("left", 190), NUBOT_CAMERA
    else:
        source = "synthetic world at 640×480"
        world = SyntheticWorld(WorldConfig(seed=0), camera=default_camera(640, 480))
        first, later = world[100], world[100 + world.frames_per_lap + 3]
        left, right, current, camera = first.left, first.right, later.left, first.camera

    def median_ms(call) -> tuple[float, float]:
        call()   # a warm-up call, not timed
        return timed_medians(call, repeats)

    stereo = geometry.keyframe(left, right, camera)
    mono = geometry.keyframe(left, None, camera)
    return {
        "source": source,
        "keyframe stereo": median_ms(lambda: geometry.keyframe(left, right, camera)),
        "keyframe mono": median_ms(lambda: geometry.keyframe(left, None, camera)),
        "relative_pose stereo": median_ms(lambda: geometry.relative_pose(stereo, current, camera)),
        "relative_pose mono": median_ms(lambda: geometry.relative_pose(mono, current, camera)),
        "bytes stereo": len(stereo.to_bytes()), "bytes mono": len(mono.to_bytes()),
    }


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="gridslam bench geometry", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="0,1,2,3", help="synthetic worlds (comma-separated seeds)")
    parser.add_argument("--pairs", type=int, default=24, help="revisit pairs per world (half as many unrelated pairs)")
    parser.add_argument("--repeats", type=int, default=30, help="timed calls per case (the median is reported)")
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    geometry = ClosureGeometry()
    seeds = [int(v) for v in args.seeds.split(",") if v.strip()]

    a = accuracy(seeds, args.pairs, geometry)
    print(f"Synthetic world, seeds {args.seeds}, {args.pairs} revisit pairs each (offsets ≤ 0.8 m, ≤ 8°)")
    print()
    print("| | value |")
    print("|:--|--:|")
    print(f"| stereo: measured | {a['stereo_ok']} |")
    print(f"| stereo: RMS error forward, left (cm) | {a['stereo_rms_cm'][0]:.2f}, {a['stereo_rms_cm'][1]:.2f} |")
    print(f"| stereo: largest error forward, left (cm) | {a['stereo_max_cm'][0]:.1f}, {a['stereo_max_cm'][1]:.1f} |")
    print(f"| stereo: RMS, largest yaw error (°) | {a['stereo_yaw_rms_deg']:.2f}, {a['stereo_yaw_max_deg']:.2f} |")
    print("| stereo: eᵀC⁻¹e mean, median, p95, max (χ²₃: 3, 2.37, 7.8) | " + ", ".join(f"{v:.2f}" for v in a["nees"]) + " |")
    print(f"| mono: measured | {a['mono_ok']} |")
    print("| mono: yaw error median, p90, max (°) | " + ", ".join(f"{v:.2f}" for v in a["mono_yaw_deg"]) + " |")
    d = a["mono_direction_deg"]
    print(f"| mono: direction error median, p90, max (°; {d[3]} pairs ≥ 0.2 m apart) | {d[0]:.1f}, {d[1]:.1f}, {d[2]:.1f} |")
    print(f"| mono: yaw e²/σ² median, mean (χ²₁: 0.45, 1) | {a['mono_yaw_z2'][0]:.2f}, {a['mono_yaw_z2'][1]:.2f} |")
    print(f"| places ≥ 4 m apart refused (stereo and mono) | {a['refused']} |")
    print()
    if NUBOT.is_dir():
        n = nubot(geometry)
        print("NuBot scene 1: keyframe of frame 0 against frames 184..204 (back at the start; still from 190)")
        print()
        print("| | value |")
        print("|:--|--:|")
        print(f"| stereo measured | {n['ok']} |")
        print(f"| mean forward, left (m), yaw (°) | {n['mean'][0]:.3f}, {n['mean'][1]:.3f}, {n['mean'][2]:.2f} |")
        print(f"| std over the still frames 190..204 | {n['still_std'][0]:.4f}, {n['still_std'][1]:.4f}, {n['still_std'][2]:.3f} |")
        print(f"| σ from the covariance (RMS) | {n['sd'][0]:.4f}, {n['sd'][1]:.4f}, {n['sd'][2]:.3f} |")
        print(f"| median inliers | {n['inliers']} |")
        print(f"| mono measured; yaw − stereo yaw, median, max (°) | {n['mono_ok']}; {n['mono_yaw_gap_deg'][0]:.2f}, {n['mono_yaw_gap_deg'][1]:.2f} |")
        print(f"| frames 30..165 (every 5th, elsewhere) refused | {n['refused']} |")
        print()
    t = timing(geometry, args.repeats)
    print(f"Cost at 640×480 ({t['source']}), one thread, medians of {args.repeats} calls")
    print()
    print("| call | wall ms | thread CPU ms |")
    print("|:--|--:|--:|")
    for key in ("keyframe stereo", "keyframe mono", "relative_pose stereo", "relative_pose mono"):
        print(f"| {key} | {t[key][0]:.1f} | {t[key][1]:.1f} |")
    print()
    print(f"Keyframe size: {t['bytes stereo']} bytes stereo, {t['bytes mono']} mono "
          f"({t['bytes stereo'] + 16} and {t['bytes mono'] + 16} on disk with the record header: "
          f"{(t['bytes stereo'] + 16) * 1000 / 2**20:.1f} and {(t['bytes mono'] + 16) * 1000 / 2**20:.1f} MiB per 1k keyframes)")
    return 0
