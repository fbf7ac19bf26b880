"""The pipeline bench's stereo folder: the synthetic world written as PNG files reads back as
the same frames through `stereo:FOLDER`, with the camera it was rendered with."""

import numpy as np

from services.benchmarks.pipeline import write_stereo_folder
from services.common.frames import Camera
from services.source.spec import open_source

CAMERA = Camera(fx=120.0, fy=120.0, cx=79.5, cy=59.5, baseline=0.2, width=160, height=120)


def test_stereo_folder_reads_back_the_rendered_frames(tmp_path):
    folder = write_stereo_folder("synthetic:3", "synthetic", CAMERA, 4, tmp_path / "frames")
    with open_source("synthetic:3", preset="synthetic", calibration=CAMERA, stop=4) as rendered, \
            open_source(f"stereo:{folder}") as read:
        pairs = list(zip(rendered, read, strict=True))
    assert len(pairs) == 4
    for original, copy in pairs:
        assert copy.seq == original.seq
        assert copy.camera == CAMERA
        np.testing.assert_array_equal(copy.left, original.left)
        np.testing.assert_array_equal(copy.right, original.right)
