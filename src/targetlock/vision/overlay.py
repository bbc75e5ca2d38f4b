"""Draw the tracking state on a frame: image-centre cross, target, error line and text.

Colours (BGR): target green when valid, orange when the frame was rejected (last position),
red "LOST" when lost; the image centre is a white cross; the line from the centre to the target
is the offset the controller drives to zero; ground truth (twin) is a small magenta cross.
"""
from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np

from .tracker import TrackResult

__all__ = ["draw_overlay"]

_GREEN, _ORANGE, _RED = (60, 220, 60), (0, 165, 255), (40, 40, 235)
_WHITE, _YELLOW, _MAGENTA = (255, 255, 255), (0, 230, 255), (255, 60, 255)


def _pt(p) -> tuple[int, int]:
    return int(round(float(p[0]) * 16)), int(round(float(p[1]) * 16))


def _text(img: np.ndarray, text: str, org: tuple[int, int], colour, scale: float = 0.5) -> None:
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)


def draw_overlay(frame_bgr: np.ndarray, result: TrackResult | None = None, *,
                 centre_px: Sequence[float] | None = None, truth_px: Sequence[float] | None = None,
                 lines: Sequence[str] = (), copy: bool = True) -> np.ndarray:
    """Frame with the tracking state drawn on it.

    ``result``: the tracker's output for this frame (None: nothing tracked); ``centre_px``:
    the image centre (px; default: the middle of the frame), from which the offset is measured;
    ``truth_px``: ground-truth target position (px), if known; ``lines``: extra text lines (e.g.
    time, controller state) written top-left. Returns a new image unless ``copy`` is False.
    """
    img = frame_bgr.copy() if copy else frame_bgr
    h, w = img.shape[:2]
    c = np.array(centre_px if centre_px is not None else ((w - 1) / 2, (h - 1) / 2), float)
    cx, cy = _pt(c)
    arm = 12 * 16
    cv2.line(img, (cx - arm, cy), (cx + arm, cy), _WHITE, 1, cv2.LINE_AA, 4)
    cv2.line(img, (cx, cy - arm), (cx, cy + arm), _WHITE, 1, cv2.LINE_AA, 4)
    text = list(lines)
    if truth_px is not None and np.all(np.isfinite(truth_px)):
        tx, ty = _pt(truth_px)
        a = 5 * 16
        cv2.line(img, (tx - a, ty - a), (tx + a, ty + a), _MAGENTA, 1, cv2.LINE_AA, 4)
        cv2.line(img, (tx - a, ty + a), (tx + a, ty - a), _MAGENTA, 1, cv2.LINE_AA, 4)
    if result is not None:
        p = np.asarray(result.position_px, float)
        if result.lost or not np.all(np.isfinite(p)):
            _text(img, "LOST", (w // 2 - 24, 30), _RED, 0.8)
            text.append("target lost")
        else:
            colour = _GREEN if result.valid else _ORANGE
            px, py = _pt(p)
            cv2.line(img, (cx, cy), (px, py), _YELLOW, 1, cv2.LINE_AA, 4)
            cv2.circle(img, (px, py), 10 * 16, colour, 2, cv2.LINE_AA, 4)
            a = 4 * 16
            cv2.line(img, (px - a, py), (px + a, py), colour, 1, cv2.LINE_AA, 4)
            cv2.line(img, (px, py - a), (px, py + a), colour, 1, cv2.LINE_AA, 4)
            d = p - c
            state = "" if result.valid else "  (held: frame rejected)"
            text.append(f"offset dx={d[0]:+6.1f} dy={d[1]:+6.1f} px  |e|={np.hypot(*d):5.1f} px{state}")
            text.append(f"confidence {result.confidence:.2f}")
            if truth_px is not None and np.all(np.isfinite(truth_px)):
                text.append(f"tracking error {np.hypot(*(p - np.asarray(truth_px, float))):.2f} px")
    for i, line in enumerate(text):
        _text(img, line, (10, h - 12 - 20 * (len(text) - 1 - i)), _WHITE)
    return img
