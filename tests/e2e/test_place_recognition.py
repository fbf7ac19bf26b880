"""Place recognition on real recordings nobody here made, through the real pipeline with the
defaults (no preset): RTAB-Map's loop-closure samples against their human-marked ground truth,
and NuBot's loop from its left images, held to its golden figures (tests/golden/nubot.json).
And the shipped vocabulary is the one its command makes."""

import json
import subprocess

import numpy as np

from services.evaluation.revisits import RevisitRanges, read_ground_truth
from services.loopclosure.vocabulary import DEFAULT_FILE, Vocabulary
from tests import golden
from tests.netutil import GRIDSLAM, REPO, endpoint, free_port


def run(tmp_path, *args: str) -> dict:
    out = tmp_path / "run"
    done = subprocess.run(GRIDSLAM + ["run", *args, "--listen", endpoint(free_port()), "--out", str(out)], cwd=REPO,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return {"metrics": json.loads((out / "metrics.json").read_text()), "stderr": done.stderr,
            "config": json.loads((out / "config.json").read_text()), "folder": out}


def test_the_rtabmap_samples_close_their_loops_with_the_defaults_and_join_no_unmarked_frames(tmp_path, shared_data):
    folder = shared_data / "rtabmap_samples"
    result = run(tmp_path, "--source", f"images:{folder / 'images'}")
    truth = read_ground_truth(str(folder / "loop_closures_gt.bmp"))
    closures = [(c["frame"], c["matched_frame"]) for c in result["metrics"]["summary"]["loop_closures"]]
    assert all(truth.is_true(frame, matched) for frame, matched in closures), closures
    found = {frame for frame, matched in closures} & truth.revisit_frames
    assert len(found) >= 33, sorted(found)
    # No calibration: a camera was assumed, and the run says so, and that its scale is arbitrary.
    assumed = result["config"]["assumed"]
    assert assumed["camera"].startswith("assumed: a pinhole with a 65°") and not assumed["metric_scale"]
    assert "camera: assumed" in result["stderr"] and "scale arbitrary" in result["stderr"]


def test_nubot_from_its_left_images_closes_its_loop_with_the_defaults_and_nothing_else(tmp_path, shared_data):
    result = run(tmp_path, "--source", f"images:{shared_data / 'nubot_scene1' / 'left'}")
    closures = [(c["frame"], c["matched_frame"]) for c in result["metrics"]["summary"]["loop_closures"]]
    # The loop: frames 180.. back where frames ..40 were. The robot is back within 1.1 m of frame 15
    # from frame 175 on by LIBVISO2's path, so closures of 175..179 are of the same loop.
    loop = RevisitRanges.parse("175-204:0-40")
    assert all(loop.is_true(frame, matched) for frame, matched in closures), closures
    assert len({frame for frame, _ in closures} & set(range(180, 205))) >= 20
    # README.md's figures: the closures counted exactly, the ATE against LIBVISO2 within 2 %.
    golden.check("nubot", result["folder"], shared_data)


def test_the_shipped_vocabulary_is_what_its_command_trains(tmp_path):
    out = tmp_path / "vocabulary.npz"
    done = subprocess.run(GRIDSLAM + ["vocabulary", "--out", str(out)], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    trained, shipped = Vocabulary.load(out), Vocabulary.load(DEFAULT_FILE)
    assert trained.trained_on == shipped.trained_on
    assert all(np.array_equal(a, b) for a, b in zip(trained.levels, shipped.levels))
    assert np.array_equal(trained.idf, shipped.idf)


def kitti_video(shared_data, path) -> None:
    """A 10 s video (5 frames/s) of the KITTI clip's 51 left images: no calibration comes with it."""
    import cv2

    files = sorted((shared_data / "kitti06_clip" / "image_l").glob("*.png"))
    first = cv2.imread(str(files[0]))
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 5.0, (first.shape[1], first.shape[0]))
    for file in files:
        writer.write(cv2.imread(str(file)))
    writer.release()


def test_a_video_without_a_calibration_runs_mono_end_to_end_and_says_what_it_assumed(tmp_path, shared_data):
    from services.evaluation.trajectory import read_tum

    video = tmp_path / "kitti.avi"
    kitti_video(shared_data, video)
    plain = run(tmp_path / "plain", "--source", f"video:{video}", "--egomotion", "mono", "--no-mapping")
    assert "egomotion: mono; scale arbitrary" in plain["stderr"] and "camera: assumed: a pinhole with a 65°" in plain["stderr"]
    assert plain["metrics"]["stages"]["egomotion"]["frames"] == 51
    metric = run(tmp_path / "metric", "--source", f"video:{video}", "--egomotion", "mono", "--fov", "82",
                 "--camera-height", "1.65", "--no-mapping")
    assert metric["config"]["assumed"]["metric_scale"] and "1.65 m, --camera-height" in metric["stderr"]
    truth = 59.9   # the clip's path (poses.txt)
    assert abs(read_tum(tmp_path / "metric" / "run" / "egomotion.tum").path_length() - truth) < 0.1 * truth
