"""Image conversions of pixel arrays (numpy and OpenCV; no wire types): the grey view the
estimators and the closure geometry read, and the displayable, downsampled view and its JPEG
that the viewer and the ROS bridge send."""

from __future__ import annotations

import cv2
import numpy as np


def grey(image: np.ndarray) -> np.ndarray:
    """An 8-bit single-channel view of a frame image (BGR converted with OpenCV's luma)."""
    if image.ndim == 3:
        if image.shape[2] == 1:
            image = image[:, :, 0]
        else:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.dtype != np.uint8:
        image = np.clip(image, 0, 255).astype(np.uint8)
    return image


def display_image(pixels: np.ndarray, encoding: str, max_width: int) -> np.ndarray:
    """An image as uint8 grey or BGR, at most `max_width` wide (area-averaged), for display."""
    if encoding == "rgb8":
        pixels = cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR)
    elif encoding == "mono16":
        pixels = (pixels >> 8).astype(np.uint8)
    elif encoding == "32FC1":
        finite = np.nan_to_num(pixels.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        low, high = float(finite.min()), float(finite.max())
        pixels = np.zeros(finite.shape, np.uint8) if high <= low else ((finite - low) * (255.0 / (high - low))).astype(np.uint8)
    height, width = pixels.shape[:2]
    if width > max_width:
        pixels = cv2.resize(pixels, (max_width, max(1, round(height * max_width / width))), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(pixels)


def encode_camera_jpeg(image: np.ndarray, quality: int = 80) -> bytes:
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return data.tobytes()
