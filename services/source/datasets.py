"""Recorded datasets as lazy, indexed frame sources: KITTI odometry (official and flat clip
layouts), stereo pair folders (``left/``+``right/`` or NuBot's ``{k}L.ppm``/``{k}R.ppm``), an
image folder and a video file. Images are read on access (pykitti's habit, STYLE.md);
``start``/``stop``/``step`` select a subset like a slice, and ``seq`` keeps the dataset's own
frame number so a skipped frame leaves a visible gap."""

from __future__ import annotations

import dataclasses
import logging
import operator
import re
from pathlib import Path
from typing import Iterator, Sequence

import cv2
import numpy as np

from services.common.frames import Camera, Frame, SourceError
from services.source.calibration import read_calibration, read_kitti_calibration

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".ppm", ".pgm", ".bmp", ".tif", ".tiff", ".webp"})
# Datasets without timestamps are stamped seq / fps; KITTI odometry runs at 10 Hz.
DEFAULT_FPS = 10.0
# A frame number is the last run of digits in a file's stem: 000012.png, img_12.jpg.
NUMBERED = re.compile(r"(?:.*\D)?(\d+)")


def read_image(path: Path, grey: bool = False) -> np.ndarray:
    """An 8-bit image, H×W grey or H×W×3 BGR (``grey`` converts colour with ITU-R 601 luma)."""
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except FileNotFoundError:
        raise SourceError(f"{path}: image not found") from None
    except OSError as error:
        raise SourceError(f"{path}: cannot read image: {error.strerror or error}") from None
    image = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_ANYCOLOR) if data.size else None
    if image is None:
        raise SourceError(f"{path}: not a readable image")
    return image


def numbered_images(folder: Path, suffix_pattern: str = "") -> dict[int, Path]:
    """Image files of ``folder`` by frame number (the last digits of the stem, which must be
    followed by ``suffix_pattern``, e.g. ``L`` for NuBot's ``12L.ppm``)."""
    pattern = re.compile(NUMBERED.pattern + suffix_pattern)
    files: dict[int, Path] = {}
    for path in folder.iterdir():
        match = pattern.fullmatch(path.stem)
        if match and path.suffix.lower() in IMAGE_SUFFIXES:
            files[int(match.group(1))] = path
    return files


def read_table(path: Path, columns: int, rows: int, what: str) -> np.ndarray:
    """A whitespace-separated numeric file of ``rows`` lines of ``columns`` values."""
    try:
        lines = [line for line in path.read_text().splitlines() if line.strip()]
    except (OSError, UnicodeDecodeError) as error:
        raise SourceError(f"{path}: cannot read {what}: {error}") from None
    table = np.empty((len(lines), columns))
    for number, line in enumerate(lines, start=1):
        fields = line.split()
        if len(fields) != columns:
            raise SourceError(f"{path}: line {number}: {len(fields)} values, expected {columns} ({what})")
        try:
            table[number - 1] = [float(field) for field in fields]
        except ValueError:
            raise SourceError(f"{path}: line {number}: not a number ({what})") from None
    if len(lines) != rows:
        raise SourceError(f"{path}: {len(lines)} lines of {what} for {rows} images (one line per image)")
    return table


class IndexedSource:
    """Shared machinery of the recorded sources: subset selection, indexed access, and
    iteration that warns about and skips an unreadable frame. Subclasses implement
    ``_read(seq) -> Frame``. Opening reads the first selected frame, so a source that cannot
    be read at all fails at once with one clear line."""

    live = False

    def __init__(self, name: str, seqs: Sequence[int], camera: Camera | None, start: int, stop: int | None, step: int):
        if start < 0 or (stop is not None and stop < 0) or step < 1:
            raise SourceError(f"{name}: invalid frame selection start={start} stop={stop} step={step} (start, stop >= 0; step >= 1)")
        self.name = name
        self.camera = camera
        self._seqs = tuple(seqs[start:stop:step])
        if not self._seqs:
            raise SourceError(f"{name}: start={start} stop={stop} step={step} selects none of its {len(seqs)} frames")
        self._size: tuple[int, int] | None = None  # (height, width) of every image, from the first frame
        self.unreadable: list[tuple[int, str]] = []   # frames iteration skipped: (seq, why)
        first = self._read(self._seqs[0])
        height, width = first.left.shape[:2]
        if camera is not None and camera.width and (camera.width, camera.height) != (width, height):
            raise SourceError(
                f"{name}: images are {width}×{height} but the calibration is for {camera.width}×{camera.height}"
            )
        self._size = (height, width)
        if camera is not None and not camera.width:
            self.camera = dataclasses.replace(camera, width=width, height=height)

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) of the images, from the first frame."""
        return self._size[1], self._size[0]

    @property
    def seqs(self) -> tuple[int, ...]:
        """The dataset frame numbers this source yields, in order."""
        return self._seqs

    def __len__(self) -> int:
        return len(self._seqs)

    def __getitem__(self, i: int) -> Frame:
        return self._read(self._seqs[operator.index(i)])

    def __iter__(self) -> Iterator[Frame]:
        return self.iterate()

    def iterate(self, first: int = 0) -> Iterator[Frame]:
        """Iteration from the `first`-th selected frame on (a source resuming mid-run)."""
        for seq in self._seqs[first:]:
            try:
                frame = self._read(seq)
            except SourceError as error:
                self._skipped(seq, error)
                continue
            yield frame

    def _skipped(self, seq: int, error: SourceError) -> None:
        log.warning("frame %d skipped: %s", seq, error)
        self.unreadable.append((seq, str(error)))

    def close(self) -> None:
        """Release what the source holds open (nothing for image files)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r}, {len(self)} frames)"

    def _read(self, seq: int) -> Frame:
        raise NotImplementedError

    def _check_size(self, image: np.ndarray, path: Path) -> None:
        if self._size is not None and image.shape[:2] != self._size:
            height, width = self._size
            raise SourceError(f"{path}: image is {image.shape[1]}×{image.shape[0]}, the sequence's images are {width}×{height}")

    def _read_pair(self, left_path: Path, right_path: Path | None, grey: bool) -> tuple[np.ndarray, np.ndarray | None]:
        left = read_image(left_path, grey)
        self._check_size(left, left_path)
        if right_path is None:
            return left, None
        right = read_image(right_path, grey)
        if right.shape != left.shape:
            raise SourceError(
                f"{right_path}: right image {right.shape[1]}×{right.shape[0]} does not match "
                f"left image {left_path.name} {left.shape[1]}×{left.shape[0]}"
            )
        return left, right


def _existing_folder(path: Path, what: str) -> Path:
    if not path.is_dir():
        raise SourceError(f"{path}: {what} not found" if not path.exists() else f"{path}: {what} is not a folder")
    return path


def _kitti_sequence_folder(path: Path) -> Path:
    """The sequence folder of ``path``: itself, or the only sequence of a dataset root."""
    _existing_folder(path, "KITTI folder")
    if (path / "sequences").is_dir():
        sequences = sorted(p.name for p in (path / "sequences").iterdir() if p.is_dir())
        if len(sequences) != 1:
            raise SourceError(
                f"{path}: choose one sequence, e.g. kitti:{path / 'sequences' / (sequences[0] if sequences else '00')}"
                f" (found {', '.join(sequences) or 'none'})"
            )
        return path / "sequences" / sequences[0]
    return path


class KittiSequence(IndexedSource):
    """A KITTI odometry sequence.

    Official layout: ``sequences/NN/image_0/`` (left), ``image_1/`` (right), ``calib.txt``,
    ``times.txt``, and ground truth ``poses/NN.txt`` beside ``sequences/`` (also found inside
    the sequence folder). Flat clip layout: ``image_l/``, optional ``image_r/``, ``calib.txt``,
    ``poses.txt``, optional ``times.txt``. ``path`` is the sequence or clip folder, or a
    dataset root holding a single sequence. Ground truth is re-anchored to the first selected
    frame (identity there), so a run that starts mid-sequence starts at the origin.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        start: int = 0,
        stop: int | None = None,
        step: int = 1,
        camera: Camera | None = None,
        fps: float = DEFAULT_FPS,
        grey: bool = False,
        mono: bool = False,
        origin: int | None = None,
    ):
        folder = _kitti_sequence_folder(Path(path))
        if (folder / "image_0").is_dir():
            left_dir, right_dir = folder / "image_0", folder / "image_1"
            pose_files = [folder.parent.parent / "poses" / f"{folder.name}.txt", folder / "poses" / f"{folder.name}.txt"]
        elif (folder / "image_l").is_dir():
            left_dir, right_dir = folder / "image_l", folder / "image_r"
            pose_files = [folder / "poses.txt"]
        else:
            raise SourceError(f"{folder}: not a KITTI sequence (no image_0/ or image_l/ folder)")
        self._left = numbered_images(left_dir)
        if not self._left:
            raise SourceError(f"{left_dir}: no images")
        self._right = numbered_images(right_dir) if right_dir.is_dir() and not mono else None
        self._right_dir = right_dir
        self._grey = grey
        count = max(self._left) + 1  # line k of times.txt and poses belongs to image k
        calib = folder / "calib.txt"
        if camera is None:
            camera = read_kitti_calibration(calib)
        times = folder / "times.txt"
        self._stamps = read_table(times, 1, count, "timestamps")[:, 0] if times.is_file() else np.arange(count) / fps
        pose_file = next((p for p in pose_files if p.is_file()), None)
        self._poses = None
        if pose_file is not None:
            rows = read_table(pose_file, 12, count, "poses (12 values of a 3×4 [R|t])")
            self._poses = np.tile(np.eye(4), (count, 1, 1))
            self._poses[:, :3, :] = rows.reshape(count, 3, 4)
        seqs = range(min(self._left), count)
        selected = seqs[start:stop:step]
        # Ground truth is relative to `origin` (a source restarted mid-run keeps its run's origin).
        anchor = origin if origin is not None else (selected[0] if selected else None)
        self._anchor = np.linalg.inv(self._poses[anchor]) if self._poses is not None and anchor is not None else np.eye(4)
        super().__init__(str(folder), seqs, camera, start, stop, step)

    def _read(self, seq: int) -> Frame:
        left_path = self._left.get(seq)
        if left_path is None:
            raise SourceError(f"{self.name}: image {seq:06d} is missing")
        right_path = None
        if self._right is not None:
            right_path = self._right.get(seq)
            if right_path is None:
                raise SourceError(f"{self._right_dir}: no right image for {left_path.name}")
        left, right = self._read_pair(left_path, right_path, self._grey)
        truth = self._anchor @ self._poses[seq] if self._poses is not None else None
        return Frame(seq=seq, stamp=float(self._stamps[seq]), left=left, right=right, camera=self.camera, ground_truth=truth)


class StereoFolder(IndexedSource):
    """Rectified stereo pairs: ``left/`` and ``right/`` folders of numbered images (matched by
    number), or one folder of NuBot's original ``{k}L.ppm``/``{k}R.ppm``. The calibration is
    ``camera``, else a ``calibration.toml`` in the folder (our format), else unknown (None).
    Optional ``times.txt`` (one time in seconds per frame number); otherwise seq / fps."""

    def __init__(
        self,
        path: str | Path,
        *,
        start: int = 0,
        stop: int | None = None,
        step: int = 1,
        camera: Camera | None = None,
        fps: float = DEFAULT_FPS,
        grey: bool = False,
        mono: bool = False,
    ):
        folder = _existing_folder(Path(path), "stereo folder")
        if (folder / "left").is_dir():
            self._left = numbered_images(folder / "left")
            right_dir = _existing_folder(folder / "right", "right image folder")
            self._right = numbered_images(right_dir)
            empty = folder / "left"
        else:
            self._left = numbered_images(folder, "L")
            self._right = numbered_images(folder, "R")
            right_dir = empty = folder
        if not self._left:
            raise SourceError(f"{empty}: no stereo images (expected left/ and right/ folders, or {{k}}L.ppm and {{k}}R.ppm files)")
        if not self._right:
            raise SourceError(f"{right_dir}: no right images")
        if mono:
            self._right = None
        self._right_dir = right_dir
        self._grey = grey
        if camera is None and (folder / "calibration.toml").is_file():
            camera = read_calibration(folder / "calibration.toml")
        first, count = min(self._left), max(self._left) + 1
        times = folder / "times.txt"
        self._stamps = read_table(times, 1, count, "timestamps")[:, 0] if times.is_file() else np.arange(count) / fps
        super().__init__(str(folder), range(first, count), camera, start, stop, step)

    def _read(self, seq: int) -> Frame:
        left_path = self._left.get(seq)
        if left_path is None:
            raise SourceError(f"{self.name}: no left image numbered {seq}")
        right_path = None
        if self._right is not None:
            right_path = self._right.get(seq)
            if right_path is None:
                raise SourceError(f"{self._right_dir}: no right image for {left_path.name}")
        left, right = self._read_pair(left_path, right_path, self._grey)
        return Frame(seq=seq, stamp=float(self._stamps[seq]), left=left, right=right, camera=self.camera)


def _natural_key(path: Path) -> list:
    """Sort key putting img2 before img10."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


class ImageFolder(IndexedSource):
    """A folder of monocular images in natural name order (img2 before img10); seq is the
    position in that order, stamps are seq / fps."""

    def __init__(
        self,
        path: str | Path,
        *,
        start: int = 0,
        stop: int | None = None,
        step: int = 1,
        camera: Camera | None = None,
        fps: float = DEFAULT_FPS,
        grey: bool = False,
    ):
        folder = _existing_folder(Path(path), "image folder")
        self._files = sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=_natural_key)
        if not self._files:
            raise SourceError(f"{folder}: no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
        self._fps = fps
        self._grey = grey
        super().__init__(str(folder), range(len(self._files)), camera, start, stop, step)

    def _read(self, seq: int) -> Frame:
        left, _ = self._read_pair(self._files[seq], None, self._grey)
        return Frame(seq=seq, stamp=seq / self._fps, left=left, camera=self.camera)


class VideoFile(IndexedSource):
    """A video file OpenCV can decode (St Lucia is an .avi). Indexed access seeks; iteration
    decodes sequentially and skips unselected frames with ``grab``. Stamps are seq / fps with
    the container's frame rate (``fps`` when the container has none)."""

    # Frames in a row that fail to decode before iteration decides the stream has ended
    # (containers sometimes over-report their frame count).
    MAX_FAILURES_IN_A_ROW = 5
    # Iteration decodes-and-drops (grab) up to this many frames to reach the next selected one;
    # further away it seeks, which in most codecs means decoding from the previous key frame.
    MAX_GRABS = 60

    def __init__(
        self,
        path: str | Path,
        *,
        start: int = 0,
        stop: int | None = None,
        step: int = 1,
        camera: Camera | None = None,
        fps: float | None = None,
        grey: bool = False,
    ):
        self._path = Path(path)
        if not self._path.is_file():
            raise SourceError(f"{self._path}: video file not found")
        self._capture = cv2.VideoCapture(str(self._path))
        if not self._capture.isOpened():
            raise SourceError(f"{self._path}: OpenCV cannot open this video")
        count = int(self._capture.get(cv2.CAP_PROP_FRAME_COUNT))
        if count <= 0:
            raise SourceError(f"{self._path}: the video reports no frames")
        container_fps = self._capture.get(cv2.CAP_PROP_FPS)
        self._fps = float(fps or (container_fps if container_fps and container_fps > 0 else DEFAULT_FPS))
        self._grey = grey
        self._position = 0  # index of the frame the next read() decodes
        super().__init__(str(self._path), range(count), camera, start, stop, step)

    def _decode(self, seq: int) -> Frame:
        ok, image = self._capture.read()
        self._position = seq + 1
        if not ok or image is None:
            raise SourceError(f"{self._path}: frame {seq} cannot be decoded")
        if self._grey and image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        self._check_size(image, self._path)
        return Frame(seq=seq, stamp=seq / self._fps, left=image, camera=self.camera)

    def _read(self, seq: int) -> Frame:
        if seq != self._position:
            self._capture.set(cv2.CAP_PROP_POS_FRAMES, seq)
        return self._decode(seq)

    def iterate(self, first: int = 0) -> Iterator[Frame]:
        failures = 0
        for seq in self._seqs[first:]:
            if seq < self._position or seq - self._position > self.MAX_GRABS:
                self._capture.set(cv2.CAP_PROP_POS_FRAMES, seq)  # seek when far away, grab when close
                self._position = seq
            while self._position < seq:
                self._capture.grab()
                self._position += 1
            try:
                frame = self._decode(seq)
            except SourceError as error:
                failures += 1
                self._skipped(seq, error)
                if failures >= self.MAX_FAILURES_IN_A_ROW:
                    log.warning("%s: stopped after %d undecodable frames in a row (the stream ended early)", self._path, failures)
                    return
                continue
            failures = 0
            yield frame

    def close(self) -> None:
        self._capture.release()
