"""Target trackers: follow a selected image point from frame to frame.

One interface, :class:`Tracker`: ``select(frame, point_px, window_px)`` chooses the target,
``update(frame)`` returns a :class:`TrackResult` per frame. Two implementations:

:class:`FeatureTracker` (natural tissue texture)
    Corner features in a window around the target are followed with pyramidal Lucas-Kanade
    optical flow (forward-backward checked) **twice** per frame: from the last accepted frame
    (the chain: short baseline, robust to fast appearance change) and from a **keyframe** (no
    drift), the latter through the current region warped by the predicted keyframe -> frame
    similarity, so scale and in-plane rotation are compensated inside every flow window. A
    RANSAC affine rejects outlying features (highlights, instruments, blur); an iteratively
    reweighted local affine of the inliers, weighted towards the target, maps the target point.
    A frame is accepted only if both estimates agree (the chain X_{n-1} -> X_n composed with the
    stored keyframe -> X_{n-1} must equal keyframe -> X_n: the report's consistency check) and
    the target has not jumped away from its constant-velocity prediction (a false jump).
    Keyframes are renewed when scale or rotation drift too far or the match weakens, only from
    well-supported frames, and not from an edge-like target window (a rim, a fold: it locates the
    target across the edge only, and along it the chain and the keyframe slide together) that lost
    the 2-D texture of its sharpest keyframe (motion blur along the edge); the selection keyframe
    (the anchor) is tried again whenever the view returns close to it and overrules a drifted chain.
    When too few corners follow the keyframe (weak texture, blur, noise), a **dense** ECC alignment of the keyframe's high-passed target
    window stands in for them, accepted only when it agrees with the chain. The view's scale and
    rotation change per frame by at most a plausible step when only the chain or a few keyframe
    features measure them (features along one edge determine them poorly); a chain beyond it is
    suspect and corroborates no dense match. A rejected frame is
    **retried** on local-mean-free images (an exposure step that clips or unclips large areas
    changes the region's normalisation) before it counts as a miss; over misses the prediction
    coasts on the last velocity. The confidence scales with the share of the target window
    inside the field of view (a target at the edge is tracked on the features that remain).
    Under strong sensor noise the selection counts only corners above the noise and the regions
    are smoothed before the flow.
    After ``max_misses`` consecutive rejected frames the target is **lost**; it is then (the
    searches taking turns, about one per frame) re-acquired locally (keyframe flow, the selection
    keyframe first), over the whole
    frame (the field of view's bounding box) by a **dense search** of the
    keyframes' band-passed target windows (weak texture, where ORB finds no keypoints; glints
    filled and their halo left out, a candidate must lead every other place and be found again on
    the next frame where the tissue around it went; a best place that does not stand out seeds the
    local keyframe re-lock instead, when near where the target was last seen), or, every few frames,
    by ORB matching
    against the keyframes, verified with RANSAC and by the optical-flow keyframe check. While it is
    lost the tracker also follows the **scene's own motion** (the median optical flow of the corners
    nearest to the target's predicted place) from where it lost the target: a target that left the
    view is looked for where the scene carries it back in, once that place is half a window inside
    the view (not for an edge-like or a large window). In the normal case
    only a region of interest around the prediction is processed (a ~200 px square for an 80 px
    window).

:class:`MarkerTracker` (ArUco marker on the target)
    ``cv2.aruco.ArucoDetector`` in a region around the prediction (whole frame when lost); the
    target is a fixed point in marker coordinates (by default the marker centre).

Preprocessing: grayscale of the region only; the round field of view's black border and the
specular highlights are masked out of feature detection (and neutralised for the optical flow);
the feature tracker normalises the region's brightness and contrast over tissue pixels, so a
lighting change does not break brightness constancy.

Units: pixels (x right, y down, origin top-left, pixel centres at integers), frames.
"""
from __future__ import annotations

import abc
import functools
import math
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np

from ..config import param, validate
from ..model.camera import CameraParams, project, unproject
from ..rig.base import Observation
from .texture import ARUCO_DICTIONARIES

__all__ = ["TrackResult", "Tracker", "FrameClock", "TrackerSettings", "FeatureTracker", "MarkerSettings", "MarkerTracker",
           "make_tracker", "to_observation", "field_of_view_mask"]


@dataclass(frozen=True)
class TrackResult:
    """What a tracker reports for one frame."""
    position_px: np.ndarray
    """Target position (px, x right, y down, image origin top-left). When ``valid`` is False it is
    the last accepted/predicted position (still finite) unless ``lost``, where it is NaN."""
    confidence: float
    """In [0, 1]; 0 when not valid."""
    valid: bool
    """The position was measured on this frame and passed every consistency check."""
    lost: bool
    """The target has been missed for more than ``max_misses`` frames in a row (re-acquiring)."""


def to_observation(result: TrackResult, capture_time: float, cx: float, cy: float, *,
                   frame_index: int = -1, truth_px: np.ndarray | None = None) -> Observation:
    """Loop-side :class:`~targetlock.rig.base.Observation` of a result: offset from (cx, cy) in px,
    NaN when not valid; ``truth_px`` (twin only) becomes the ground-truth offset."""
    centre = np.array([cx, cy], float)
    off = np.asarray(result.position_px, float) - centre if result.valid else np.full(2, np.nan)
    truth = None if truth_px is None else np.asarray(truth_px, float) - centre
    return Observation(capture_time=float(capture_time), offset=off, valid=bool(result.valid),
                       confidence=float(result.confidence) if result.valid else 0.0,
                       frame_index=int(frame_index), truth=truth)


class Tracker(abc.ABC):
    """Common interface of all trackers."""

    lost: bool = True
    """The target is lost (not selected yet, or missed too long): the tracker is searching."""
    failure: str | None = None
    """Why the last :meth:`select` failed (one line a console can show), None after a success."""
    warning: str | None = None
    """After a successful :meth:`select`, what may make the chosen target hard to follow (one line a
    console can show, e.g. texture that runs one way only); None when there is nothing to say."""

    @abc.abstractmethod
    def fresh(self) -> "Tracker":
        """A new tracker of the same kind and settings, with nothing selected (to try a selection
        without losing the target being tracked)."""

    @abc.abstractmethod
    def select(self, frame_bgr: np.ndarray, point_px, window_px: int) -> bool:
        """Choose the target at ``point_px`` (x, y px) using a square template of side
        ``window_px`` px around it. Returns False when the region holds too little structure
        to track (the tracker is then lost; :attr:`failure` says why)."""

    @abc.abstractmethod
    def update(self, frame_bgr: np.ndarray, capture_time: float | None = None) -> TrackResult:
        """Track the target into ``frame_bgr`` (the next frame, BGR uint8). ``capture_time`` (s, any
        monotonic clock): when given, motion prediction and jump limits follow the real interval
        since the last frame (dropped frames); else frames are taken as evenly spaced."""

    @property
    @abc.abstractmethod
    def footprint_px(self) -> float | None:
        """Half side (px) of the square about the target's predicted place (its last position plus
        its last motion) within which the next :meth:`update` reads the frame, while the target is
        tracked and moves as predicted; None when it may read the whole frame (lost, not selected).
        A caller that renders or copies only part of a frame (partial frames in the loop) must give
        at least this, shifted inside the frame as the tracker's own crops are."""


def field_of_view_mask(frame_bgr: np.ndarray, margin_px: int = 6, threshold: int = 12) -> np.ndarray:
    """uint8 mask (255 inside) of the endoscope's round field of view, shrunk by ``margin_px``.

    Finds the largest bright region and its enclosing circle; when the image has no dark border
    (a plain camera), the whole image minus the margin is returned.
    """
    gray = cv2.cvtColor(frame_bgr, cv2.COLOR_BGR2GRAY) if frame_bgr.ndim == 3 else frame_bgr
    h, w = gray.shape
    mask = np.zeros((h, w), np.uint8)
    bright = (gray > threshold).astype(np.uint8)
    corners = [bright[:8, :8], bright[:8, -8:], bright[-8:, :8], bright[-8:, -8:]]
    if sum(float(c.mean()) for c in corners) / 4 > 0.5:  # no dark border: a rectangular image
        mask[margin_px:h - margin_px, margin_px:w - margin_px] = 255
        return mask
    bright = cv2.morphologyEx(bright, cv2.MORPH_CLOSE, np.ones((15, 15), np.uint8))
    contours, _ = cv2.findContours(bright, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return mask
    (cx, cy), r = cv2.minEnclosingCircle(max(contours, key=cv2.contourArea))
    cv2.circle(mask, (int(round(cx)), int(round(cy))), max(0, int(r) - margin_px), 255, -1)
    return mask


class FrameClock:
    """Frame intervals between successive frames from their capture times (dropped frames).

    :meth:`tick` returns how many typical frame intervals lie between the previous frame and this
    one: 1 normally, ~2 after one dropped frame. Without (finite, increasing) capture times every
    frame counts as one interval. The typical interval follows the observed ones slowly and a
    long interval only a little (a drop is not the new normal).
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._t: float | None = None   # capture time of the last frame (s)
        self.interval_s: float | None = None  # typical frame interval (s)

    def tick(self, capture_time: float | None) -> float:
        t = math.nan if capture_time is None else float(capture_time)
        if self._t is None or not math.isfinite(t) or t <= self._t:
            self._t = t if math.isfinite(t) else None
            return 1.0
        dt, self._t = t - self._t, t
        if self.interval_s is None:
            self.interval_s = dt
            return 1.0
        steps = max(1.0, dt / self.interval_s)
        self.interval_s = 0.9 * self.interval_s + 0.1 * min(dt, 1.5 * self.interval_s)
        return steps


# ----------------------------------------------------------------------------- 2-D transforms
def _h(t: np.ndarray) -> np.ndarray:
    return np.vstack([t, [0.0, 0.0, 1.0]])


def _apply(t: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return np.asarray(pts, float) @ t[:2, :2].T + t[:2, 2]


def _inv(t: np.ndarray) -> np.ndarray:
    """Inverse of a 2-D affine transform given as 3x3."""
    a, b, c, d, e, f = t[0, 0], t[0, 1], t[0, 2], t[1, 0], t[1, 1], t[1, 2]
    det = a * e - b * d
    ia, ib, id_, ie = e / det, -b / det, -d / det, a / det
    return np.array([[ia, ib, -(ia * c + ib * f)], [id_, ie, -(id_ * c + ie * f)], [0.0, 0.0, 1.0]])


def _translation(d: np.ndarray) -> np.ndarray:
    return np.array([[1.0, 0.0, d[0]], [0.0, 1.0, d[1]], [0.0, 0.0, 1.0]])


def _scale_angle(t: np.ndarray) -> tuple[float, float]:
    """Scale and rotation (rad) of the similarity closest to the linear part of ``t``."""
    a, b, c, d = t[0, 0], t[0, 1], t[1, 0], t[1, 1]
    return math.sqrt(abs(a * d - b * c)), math.atan2(c - b, a + d)


def _similarity(t: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The similarity (3x3) with the scale and rotation of ``t``'s linear part that maps
    ``centre`` where ``t`` does (the best local stand-in for ``t`` around ``centre``)."""
    sc, ang = _scale_angle(t)
    c, s_ = sc * math.cos(ang), sc * math.sin(ang)
    lin = np.array([[c, -s_], [s_, c]])
    off = _apply(t, centre) - lin @ np.asarray(centre, float)
    return np.array([[c, -s_, off[0]], [s_, c, off[1]], [0.0, 0.0, 1.0]])


def _weighted_affine(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> np.ndarray | None:
    """Weighted least-squares 2-D affine (3x3) mapping src -> dst, or None if degenerate."""
    x = np.column_stack([src, np.ones(len(src))])
    xw = x * w[:, None]
    a = xw.T @ x
    if abs(np.linalg.det(a)) < 1e-9 * max(float(np.trace(a)), 1.0) ** 3:
        return None
    sol = np.linalg.solve(a, xw.T @ dst)
    return np.vstack([sol.T, [0.0, 0.0, 1.0]])


def _detail(gray: np.ndarray) -> np.ndarray:
    """High-passed float32 gray (Gaussian sigma 6 px removed): texture without the light fall-off."""
    f = gray.astype(np.float32)
    return f - cv2.GaussianBlur(f, (0, 0), 6.0)


def _band(img: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Band-passed float32 image (Gaussians of sigma ``lo`` minus ``hi`` px): texture without noise and
    without the slow shading (light fall-off, smoothly filled glints)."""
    f = img.astype(np.float32)
    return cv2.GaussianBlur(f, (0, 0), lo) - cv2.GaussianBlur(f, (0, 0), hi)


def _masked_ncc(a: np.ndarray, b: np.ndarray) -> float:
    """Normalised correlation of two equal-sized templates over the pixels both use (non-zero)."""
    ok = (a != 0) & (b != 0)
    if np.count_nonzero(ok) < 16:
        return 0.0
    x, y = a[ok] - a[ok].mean(), b[ok] - b[ok].mean()
    den = math.sqrt(float(np.dot(x, x)) * float(np.dot(y, y)))
    return float(np.dot(x, y)) / den if den > 0 else 0.0


def _halved(img: np.ndarray) -> np.ndarray:
    """``img`` at half its resolution (area average; an odd side rounds up, so a window keeps a centre)."""
    h, w = img.shape[:2]
    return cv2.resize(img, ((w + 1) // 2, (h + 1) // 2), interpolation=cv2.INTER_AREA)


def _peaks(score: np.ndarray, radius: int) -> tuple[tuple[int, int], float, float]:
    """Best place (x, y) of a correlation map, its score and the best score farther than ``radius``."""
    _, top, _, loc = cv2.minMaxLoc(score)
    other = score.copy()
    cv2.circle(other, loc, radius, -2.0, -1)
    _, second, _, _ = cv2.minMaxLoc(other)
    return loc, float(top), float(second)


class _Spectrum:
    """One image prepared for :meth:`match`: ``cv2.matchTemplate(img, tpl, cv2.TM_CCOEFF_NORMED)`` of
    several templates by DFT, with the image's spectrum and window statistics made once for all of
    them and each template's spectrum once (:class:`_SpectralTemplate`), not once per search (the
    whole-frame dense search correlates the same templates with every lost frame). Scores equal
    OpenCV's up to float rounding (~1e-6) except in windows without content (std < 1e-3 levels:
    the zeroed parts of a band-passed image), which score 0: OpenCV's own round-off there (0/0)
    reads up to 0.8."""

    _EMPTY = 1e-3  # std (levels) of a window without content

    def __init__(self, img: np.ndarray) -> None:
        h, w = img.shape
        self.img = img
        self.size = (cv2.getOptimalDFTSize(h), cv2.getOptimalDFTSize(w))
        pad = cv2.copyMakeBorder(img, 0, self.size[0] - h, 0, self.size[1] - w, cv2.BORDER_CONSTANT, value=0)
        self.spectrum = cv2.dft(pad)
        self._inv: dict = {}  # template shape -> 1 / sqrt(sum of squared deviations) per window, 0 if empty

    def _inv_spread(self, th: int, tw: int) -> np.ndarray:
        out = self._inv.get((th, tw))
        if out is None:
            h, w = self.img.shape
            n = th * tw
            # window sums by box filters (double accumulators inside), the valid part
            box = dict(ddepth=cv2.CV_32F, ksize=(tw, th), anchor=(0, 0), normalize=False,
                       borderType=cv2.BORDER_CONSTANT)
            s = cv2.boxFilter(self.img, **box)[:h - th + 1, :w - tw + 1]
            q = cv2.sqrBoxFilter(self.img, **box)[:h - th + 1, :w - tw + 1]
            var = cv2.subtract(q, cv2.multiply(s, s, scale=1.0 / n))
            floor = self._EMPTY ** 2 * n
            empty = var < floor
            out = 1.0 / cv2.sqrt(cv2.max(var, floor))  # (the floor also keeps denormals out: slow)
            out[empty] = 0.0
            self._inv[(th, tw)] = out
        return out

    def match(self, tpl: "_SpectralTemplate") -> np.ndarray:
        """The TM_CCOEFF_NORMED map (float32, (h - th + 1, w - tw + 1)) of ``tpl`` over the image."""
        th, tw = tpl.shape
        h, w = self.img.shape
        if tpl.norm < np.finfo(float).eps:
            return np.ones((h - th + 1, w - tw + 1), np.float32)
        num = cv2.idft(cv2.mulSpectrums(self.spectrum, tpl.spectrum(self.size), 0, conjB=True),
                       flags=cv2.DFT_REAL_OUTPUT)[:h - th + 1, :w - tw + 1]
        # the inverse DFT's 1 / (rows x cols) folded into the template's norm
        score = cv2.multiply(num, self._inv_spread(th, tw), scale=1.0 / (tpl.norm * self.size[0] * self.size[1]))
        lo, hi, _, _ = cv2.minMaxLoc(score)
        if hi >= 1.0 or lo <= -1.0:  # round-off beyond +-1 (OpenCV: +-1 up to 1.125, else 0)
            over = np.abs(score) >= 1.0
            v = score[over]
            score[over] = np.where(np.abs(v) < 1.125, np.sign(v), 0.0)
        return score


class _SpectralTemplate:
    """A fixed template for :meth:`_Spectrum.match`: mean-free, its norm, and its spectrum per DFT
    size, made on first use."""

    def __init__(self, tpl: np.ndarray) -> None:
        self.shape = tpl.shape
        t = tpl.astype(np.float64)
        t -= t.mean()
        self.norm = float(math.sqrt(float(np.sum(t * t))))
        self._tpl = t.astype(np.float32)
        self._spectra: dict = {}

    def spectrum(self, size: tuple[int, int]) -> np.ndarray:
        out = self._spectra.get(size)
        if out is None:
            th, tw = self.shape
            pad = cv2.copyMakeBorder(self._tpl, 0, size[0] - th, 0, size[1] - tw, cv2.BORDER_CONSTANT, value=0)
            out = self._spectra[size] = cv2.dft(pad)
        return out


def _match_around(img: np.ndarray, tpl: np.ndarray, centre: np.ndarray, r: int) -> tuple[np.ndarray, float] | None:
    """Best place (px of ``img``, sub-pixel) of the square template ``tpl`` (odd side) within ``r`` px of
    ``centre`` (px of ``img``), and its normalised correlation; None when that neighbourhood leaves ``img``."""
    half = tpl.shape[0] // 2
    c = np.round(centre).astype(int)
    x0, y0 = c[0] - half - r, c[1] - half - r
    side = tpl.shape[0] + 2 * r
    if x0 < 0 or y0 < 0 or y0 + side > img.shape[0] or x0 + side > img.shape[1]:
        return None
    score = cv2.matchTemplate(img[y0:y0 + side, x0:x0 + side], tpl, cv2.TM_CCOEFF_NORMED)
    _, top, _, loc = cv2.minMaxLoc(score)
    return _subpixel(score, loc) + [x0 + half, y0 + half], float(top)


def _subpixel(score: np.ndarray, loc: tuple[int, int]) -> np.ndarray:
    """Peak ``loc`` (x, y) of a correlation map refined by a parabola through its neighbours (px)."""
    x, y = loc
    out = np.array([x, y], float)
    for k, (a, b) in enumerate(((score[y, x - 1:x], score[y, x + 1:x + 2]), (score[y - 1:y, x], score[y + 1:y + 2, x]))):
        if a.size and b.size:
            den = float(a[0]) - 2.0 * float(score[y, x]) + float(b[0])
            if den < 0.0:
                out[k] += float(np.clip(0.5 * (float(a[0]) - float(b[0])) / den, -0.5, 0.5))
    return out


# ----------------------------------------------------------------------------- feature tracker
@dataclass(frozen=True)
class TrackerSettings:
    """Settings of :class:`FeatureTracker`."""
    max_features: int = param(40, lo=4, hi=1000, doc="most corner features followed in the window")
    feature_quality: float = param(0.005, lo=1e-5, hi=0.5, doc="goodFeaturesToTrack quality level (fraction of best corner)")
    min_feature_distance_px: float = param(4.0, unit="px", lo=1.0, hi=100.0, doc="least distance between features")
    lk_window_px: int = param(11, unit="px", lo=5, hi=61, doc="Lucas-Kanade window side (odd)")
    lk_levels: int = param(3, lo=0, hi=6, doc="Lucas-Kanade pyramid levels, frame-to-frame flow")
    key_levels: int = param(2, lo=0, hi=6, doc="Lucas-Kanade pyramid levels, keyframe flow (prediction-aligned)")
    key_flow_local: bool = param(False, doc="the keyframe flow runs on the regions with their local mean removed "
                                           "(Gaussian, sigma 5 px): removes the bias of faint texture's flow as the "
                                           "tip approaches (most likely the light changing across the window); off: "
                                           "it raised false locks on glints (docs/vision.md)")
    fb_max_px: float = param(1.0, unit="px", lo=0.01, hi=20.0, doc="largest forward-backward flow error of a kept feature")
    ransac_px: float = param(2.0, unit="px", lo=0.1, hi=20.0, doc="RANSAC inlier distance")
    min_inliers: int = param(8, lo=3, hi=500, doc="fewest RANSAC inliers for a valid motion estimate")
    selection_margin: float = param(3.0, lo=1.0, hi=20.0,
                                    doc="select() takes the first 1.5x or 2x window that holds this x min_inliers "
                                        "corners when the requested one holds fewer (else the first with half as "
                                        "many); a selection with fewer corners than that warns")
    min_inlier_ratio: float = param(0.5, lo=0.0, hi=1.0,
                                    doc="least fraction of the successfully followed features that are RANSAC inliers")
    consistency_px: float = param(3.0, unit="px", lo=0.1, hi=100.0,
                                  doc="largest disagreement of the chained and the keyframe estimate")
    keyframe_correction_px: float = param(9.0, unit="px", lo=0.0, hi=1000.0,
                                          doc="a strong match (>= 2 min_inliers, around the target) of a keyframe "
                                              "other than the selection overrules a chain that disagrees by up to "
                                              "this much (the selection's: by any amount), unless the sensor is "
                                              "noisy (denoise_px in use); 0: only the selection's")
    chain_keyframe_corrects: bool = param(False, doc="let a keyframe made from a frame the chain alone carried "
                                                     "correct the chain (keyframe_correction_px); unsafe: it holds "
                                                     "the chain's own error (for comparison)")
    max_jump_px: float = param(30.0, unit="px", lo=1.0, hi=1000.0,
                               doc="largest distance from the constant-velocity prediction (else: false jump)")
    max_view_scale_step: float = param(0.06, lo=0.0, hi=10.0,
                                       doc="largest change of the view's scale (log) per frame interval believed from "
                                           "the frame-to-frame features (beyond it they move the view by translation "
                                           "only) or from fewer than 2 min_inliers keyframe features (beyond it "
                                           "limited to this)")
    max_view_rotation_step_deg: float = param(5.0, unit="deg", lo=0.0, hi=180.0,
                                              doc="largest rotation of the view per frame interval believed from the "
                                                  "frame-to-frame features or a few keyframe features (as "
                                                  "max_view_scale_step)")
    max_misses: int = param(4, lo=0, hi=10000, doc="consecutive rejected frames before the target is declared lost")
    search_margin_px: float = param(40.0, unit="px", lo=0.0, hi=1000.0,
                                    doc="margin of the region of interest around the window at the predicted position")
    keyframes: int = param(6, lo=1, hi=64, doc="recent keyframes kept besides the selection (anchor) keyframe")
    keyframe_scale: float = param(0.3, lo=0.01, hi=2.0, doc="scale range of a keyframe (relative); a new one is made at half of it")
    keyframe_rotation_deg: float = param(40.0, unit="deg", lo=0.5, hi=90.0,
                                         doc="rotation range of a keyframe; a new one is made at half of it")
    keyframe_min_confidence: float = param(0.3, lo=0.0, hi=1.0,
                                           doc="a frame whose match confidence (share and number of inliers) is lower "
                                               "is a weak match for making keyframes")
    weak_keyframes: int = param(0, lo=0, hi=1000,
                                doc="most keyframes made in a row from weak matches (each hands its error on)")
    highlight_margin_px: int = param(3, unit="px", lo=0, hi=50,
                                     doc="highlights are grown by this margin before masking and filling")
    saturation_level: int = param(190, lo=1, hi=255,
                                  doc="least 8-bit gray level of a highlight (raised towards 250 on bright tissue: "
                                      "mean + 3 std of the region)")
    highlight_max_chroma: float = param(0.25, lo=0.0, hi=1.0,
                                        doc="largest colour saturation (1 - min/max of B, G, R) of a highlight pixel")
    highlight_max_blob_px: int = param(1500, unit="px", lo=1, hi=1000000,
                                       doc="largest bright blob that is a glint; larger bright areas: only clipped pixels")
    highlight_max_share: float = param(0.25, lo=0.0, hi=1.0,
                                       doc="largest share of a region masked as highlight (the brightest are kept)")
    large_window_px: float = param(100.0, unit="px", lo=8.0, hi=4096.0,
                                   doc="a window this large or larger, as asked for (select()'s window_px), is large: "
                                       "its features are kept highlight_clearance_px clear of highlights and its "
                                       "dense re-acquisition templates are its central dense_template_max_px")
    context_isotropy: float = param(0.15, lo=0.0, hi=1.0,
                                    doc="a window smaller than large_window_px whose texture isotropy (see "
                                        "edge_isotropy) is below this is widened 1.5x, else 2x, for more context around "
                                        "the target: the first that reaches it, else the most isotropic; 0: never "
                                        "(see docs/vision.md: seeds 0-30 tracked +1.5-2 %, fewer false locks in all)")
    edge_like_dense: bool = param(False, doc="let the dense alignment of the keyframe window carry a frame (when too few "
                                             "corners match it) also in a window that stays edge-like after the "
                                             "context widening (isotropy below context_isotropy at its largest): such a "
                                             "template locates the target across its edge only and slides along it")
    highlight_clearance_px: int = param(5, unit="px", lo=0, hi=50,
                                        doc="in a large window (large_window_px), a feature is neither detected nor "
                                            "followed within this distance of a highlight (the reach of the "
                                            "Lucas-Kanade window, lk_window_px // 2): a glint's halo reaches beyond "
                                            "its mask, and a corner whose flow window sees it follows the glint, "
                                            "which slides over the tissue; 0: only features on highlights are left out")
    corner_noise_floor: float = param(4.0, lo=0.0, hi=1000.0,
                                      doc="a corner whose strength (smallest eigenvalue of the 5 px structure tensor of "
                                          "the normalised gray) is below this x the region's noise variance is noise "
                                          "(twice the strongest that pure noise makes); 0: every corner counts")
    corner_noise_level: float = param(3.0, unit="levels", lo=0.0, hi=255.0,
                                      doc="sensor noise (std, 8-bit gray levels of the frame) above which the "
                                          "selection counts only corners above corner_noise_floor")
    denoise_px: float = param(1.0, unit="px", lo=0.0, hi=10.0,
                              doc="Gaussian sigma the regions are smoothed with before the optical flow when the "
                                  "sensor noise at selection is above corner_noise_level; 0: never")
    patch_reject_ncc: float = param(0.2, lo=-1.0, hi=1.0,
                                    doc="a frame whose target patch correlates less with the keyframe's is rejected (covered)")
    patch_keyframe_ncc: float = param(0.75, lo=-1.0, hi=1.0,
                                      doc="least target-patch correlation for full confidence and for making a keyframe")
    patch_override_px: float = param(3.0, unit="px", lo=0.0, hi=100.0,
                                     doc="a target patch that decorrelated (below patch_reject_ncc) does not reject the "
                                         "frame when the chain and the keyframe's features agree within this distance "
                                         "and at least 2 of those features lie within 0.3 window of the target (or a "
                                         "dense match agrees with the chain and 2 of the chain's features lie there; "
                                         "accepted with low confidence, no keyframe); 0: always reject")
    chain_after_reported: bool = param(True, doc="a frame after rejected frames that were all reported from a strong "
                                                 "chain whose target patch matched the keyframe's (a dense match "
                                                 "disputed it) may be carried by a strong chain alone, as after an "
                                                 "accepted frame")
    patch_energy_ratio: float = param(1.6, lo=1.0, hi=100.0,
                                      doc="target-patch texture energy ratio (either way) beyond which a decorrelated "
                                          "patch counts as covered")
    dense_min_ecc: float = param(0.6, lo=0.0, hi=1.0,
                                 doc="least ECC correlation of the dense keyframe match (weak texture) that agrees with the chain")
    dense_min_ncc: float = param(0.35, lo=0.0, hi=1.0,
                                 doc="least correlation of the dense keyframe match (weak texture; band-passed) that "
                                     "agrees with the chain (band-passed, glints' halo left out; tried when ECC fails)")
    dense_radius_px: float = param(8.0, unit="px", lo=1.0, hi=100.0,
                                   doc="the dense keyframe match searches this far around the prediction")
    patch_blur_ncc: float = param(0.3, lo=-1.0, hi=1.0,
                                  doc="a target patch with less texture energy, evenly spread, that still correlates "
                                      "this much is the same tissue blurred (weak texture under motion blur), not covered")
    patch_blur_energy: float = param(0.2, lo=0.0, hi=1.0,
                                     doc="least texture-energy ratio (current / keyframe) of such a blurred target patch")
    edge_isotropy: float = param(0.05, lo=0.0, hi=1.0,
                                 doc="a target window whose texture isotropy (smaller / larger eigenvalue of its "
                                     "structure tensor, sensor noise removed) is below this is edge-like: it locates "
                                     "the target across the edge only; 0: no edge rule")
    edge_texture_loss: float = param(0.75, lo=0.0, hi=1.0,
                                     doc="an edge-like target window that keeps less than this share of the 2-D "
                                         "texture (isotropy) of the sharpest keyframe it descends from (compared keyframe "
                                         "to keyframe at the same tissue area and scale, over pixels clear of highlights "
                                         "in both) lost the texture that held the target along the edge (motion blur): "
                                         "no keyframe is made from it")
    reacquire: bool = param(True, doc="search the whole frame for the target once it is lost")
    orb_features: int = param(1000, lo=50, hi=50000, doc="ORB features detected over the frame when re-acquiring")
    reacquire_every: int = param(8, lo=1, hi=1000, doc="while lost, search the whole frame with ORB on every n-th "
                                                          "frame (the (n+1)-th, (2n+1)-th, ... lost frame)")
    reacquire_min_inliers: int = param(12, lo=4, hi=1000, doc="fewest ORB RANSAC inliers to accept a re-acquisition")
    reacquire_ratio: float = param(0.8, lo=0.1, hi=1.0, doc="Lowe ratio for ORB descriptor matches")
    dense_reacquire: bool = param(True, doc="while lost, also search the frame densely for the keyframes' band-passed "
                                            "target window (weak texture, where ORB finds no keypoints)")
    dense_reacquire_every: int = param(2, lo=1, hi=1000,
                                       doc="while lost, search the frame densely on every n-th frame (and on the "
                                           "frame after a candidate was found)")
    dense_reacquire_ncc: float = param(0.35, lo=0.0, hi=1.0,
                                       doc="least normalised correlation of a dense re-acquisition candidate")
    dense_template_max_px: float = param(80.0, unit="px", lo=8.0, hi=4096.0,
                                         doc="largest side of a large window's (large_window_px) dense "
                                             "re-acquisition templates (a keyframe's target window): its central part")
    dense_reacquire_lead: float = param(1.7, lo=1.0, hi=100.0,
                                        doc="least ratio of the candidate's correlation to the best other place's")
    dense_unique_ncc: float = param(0.6, lo=-1.0, hi=1.0,
                                    doc="a keyframe whose band-passed target window correlates this much with its own "
                                        "region a quarter window or more away (an edge, a repeated texture) is not "
                                        "searched for densely")
    dense_energy_ratio: float = param(2.0, lo=1.0, hi=1000.0,
                                      doc="a later keyframe whose band-passed target window has more than this times "
                                          "the selection's texture energy and correlates less than dense_agree_ncc "
                                          "with it (something new and strong, e.g. an instrument's edge) is not "
                                          "searched for densely")
    dense_agree_ncc: float = param(0.3, lo=-1.0, hi=1.0,
                                   doc="see dense_energy_ratio")
    scene_relock: bool = param(True, doc="while lost, follow the scene's motion over the whole view from where the "
                                         "target was predicted, and try the local keyframe re-lock where it puts the "
                                         "target")
    scene_relock_depth: float = param(0.5, lo=0.0, hi=10.0,
                                      doc="the scene re-lock is tried only where the target is at least this many "
                                          "windows inside the field of view (at its edge the lens distortion bends a "
                                          "keyframe made nearer the centre: re-locks there were several px off)")
    dense_anchor_ncc: float = param(0.15, lo=-1.0, hi=1.0,
                                    doc="a dense candidate of a later keyframe is dropped unless the selection's own "
                                        "band-passed window correlates at least this much within 4 px of it; -1: "
                                        "never dropped")
    dense_presearch: bool = param(True, doc="pre-search the frame densely at quarter resolution: a template is "
                                            "searched at half resolution (which alone decides) only where it "
                                            "stands out there (saves CPU time while lost)")
    dense_presearch_ncc: float = param(0.3, lo=0.0, hi=1.0,
                                       doc="least quarter-resolution correlation for a template's half-resolution search")
    dense_presearch_lead: float = param(1.15, lo=1.0, hi=100.0,
                                        doc="least quarter-resolution lead (best place / best other place) for a "
                                            "template's half-resolution search")
    dense_confirm_px: float = param(3.0, unit="px", lo=0.1, hi=100.0,
                                    doc="a dense candidate is accepted when the next frame finds it again where the "
                                        "tissue around it moved, within this distance")
    dense_streak_lead: float = param(1.3, lo=1.0, hi=100.0,
                                     doc="a dense candidate leading every other place by less than "
                                         "dense_reacquire_lead but at least this much is accepted once it has been "
                                         "found again, where the tissue around it moved, on dense_streak_frames "
                                         "consecutive frames")
    phase_dense: bool = param(True, doc="just selected or re-acquired on the selection keyframe and no corner "
                                        "follows: a dense match of the selection keyframe placed by the region's "
                                        "phase correlation and agreeing with it carries the frame")
    survivor_seed: bool = param(True, doc="just selected or re-acquired (no velocity known) and the chain failed: "
                                          "when at least 3 corners passed the flow's checks and moved together (within "
                                          "3 px), their motion seeds one more attempt (fast motion that blurred the "
                                          "rest and left the phase correlation without a peak)")
    relock_central: bool = param(True, doc="while lost near the edge of the view (the tracked scale or rotation "
                                           "10 % or 10 degrees off the one the target had near the centre), the "
                                           "local keyframe re-lock a quarter window inside the view first tries the "
                                           "scale and rotation the lens distortion gives there (interpolated with the "
                                           "distance from the centre between the central ones and those at the loss); "
                                           "not for a window of large_window_px or more")
    chain_only_jump_px: float = param(10.0, unit="px", lo=0.0, hi=1000.0,
                                      doc="a frame carried by the chain alone (keyframe unmatched) lies at most this "
                                          "far from the constant-velocity prediction, per frame interval")
    local_seed_px: float = param(50.0, unit="px", lo=0.0, hi=1000.0,
                                 doc="while lost, the local keyframe re-lock is also tried where the selection's "
                                     "band-passed window correlates best within this distance of the last position "
                                     "(0: off; further is the whole-frame searches' job)")
    seeded_relock_px: float = param(120.0, unit="px", lo=0.0, hi=10000.0,
                                    doc="while lost, the whole-frame dense search's best place, when within this "
                                        "distance of where the target was last seen, seeds a local keyframe re-lock "
                                        "(0: off)")
    dense_streak_frames: int = param(4, lo=2, hi=100, doc="see dense_streak_lead")
    dense_agree_px: float = param(8.0, unit="px", lo=0.0, hi=100.0,
                                  doc="a weak dense candidate (dense_streak_lead) of a later keyframe counts only "
                                      "within this distance of the selection keyframe's best place")
    dense_central_radius: float = param(0.4, lo=0.0, hi=1.0,
                                        doc="while lost, the dense templates are also searched at the scale and "
                                            "rotation of the last accepted frame with the target within this "
                                            "fraction of the round view's radius from its centre (near the edge the "
                                            "lens distortion shrinks the tracked scale, to 0.56 on a `leave`)")
    dense_streak_any_keyframe: bool = param(False, doc="let a weak dense candidate of a later keyframe count without "
                                                       "the selection keyframe's agreement (dense_agree_px); unsafe: "
                                                       "a later keyframe may hold an instrument's edge (for comparison)")

    def check(self, prefix: str = "") -> None:
        if self.lk_window_px % 2 == 0:
            from ..config import ConfigError
            raise ConfigError(f"{prefix}lk_window_px = {self.lk_window_px} must be odd")


@dataclass(eq=False)
class _View:
    """Preprocessed region of one frame: normalised gray, local -> frame transform (3x3),
    highlight mask, raw gray."""
    gray: np.ndarray
    to_frame: np.ndarray
    sat: np.ndarray
    raw: np.ndarray
    fov: np.ndarray          # field-of-view mask of the region (uint8, 255 inside)
    zero: float = 0.0        # level of ``gray`` that a black raw pixel maps to (gray = gain * raw + zero)
    flat: np.ndarray | None = None  # gray with the local mean removed (exposure retry), made on first use
    high: np.ndarray | None = None  # high-passed gray (phase correlation, ECC), made on first use
    sigma: float | None = None      # sensor noise of ``gray`` (levels), estimated on first use
    gain: float = 1.0               # gray = gain * raw + zero
    near_sat: np.ndarray | None = None  # ``sat`` grown by the highlight clearance, made on first use

    _LAPLACE = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)

    def noise(self) -> float:
        """Standard deviation (levels of ``gray``) of the sensor noise around the region's centre:
        the median absolute response of a second-difference kernel that cancels smooth texture
        (Immerkaer's), robust to the texture's edges; it reads low rather than high."""
        if self.sigma is None:
            h, w = self.gray.shape
            q = min(h, w) // 4
            box = self.gray[h // 2 - q:h // 2 + q, w // 2 - q:w // 2 + q].astype(np.float32)
            resp = cv2.filter2D(box, -1, self._LAPLACE)[1:-1, 1:-1]
            # for white noise of std s the response has std 6 s; median |N(0, 1)| = 0.6745
            # every 4th: enough samples; the median by partition (np.median's NaN handling costs 2x)
            a = np.abs(resp[::2, ::2]).ravel()
            k1, k2 = (a.size - 1) // 2, a.size // 2
            a = np.partition(a, (k1, k2)) if a.size else a
            self.sigma = float((a[k1] + a[k2]) / 2) / (6.0 * 0.6745) if a.size else math.nan
        return self.sigma

    def detail(self) -> np.ndarray:
        """:func:`_detail` of ``gray``, made once (a region is correlated again on an exposure retry,
        a keyframe's on every ECC match)."""
        if self.high is None:
            self.high = _detail(self.gray)
        return self.high

    def local(self) -> np.ndarray:
        """``gray`` with its local mean (Gaussian, sigma 5 px) removed, around 128: brightness
        constancy holds across an exposure step even where the region's normalisation changed
        (clipped pixels, glare that came or went)."""
        if self.flat is None:
            f = self.gray.astype(np.float32)
            self.flat = cv2.convertScaleAbs(f - cv2.GaussianBlur(f, (0, 0), 5.0), alpha=1.5, beta=128.0)
        return self.flat


@dataclass(eq=False)
class _Keyframe:
    view: _View
    pts: np.ndarray          # features (N, 2), frame coordinates of that frame (px)
    target: np.ndarray       # target position in that frame (px)
    from_anchor: np.ndarray  # 3x3 similarity anchor-frame -> this frame
    orb_pts: np.ndarray | None = None
    orb_desc: np.ndarray | None = None
    orb_src: tuple | None = None  # what orb_pts/orb_desc are described from on first use (see
    # FeatureTracker._orb_features): (frame crop, crop origin px)
    sharp: bool = True       # not made from a blurred view (used for whole-frame re-acquisition)
    by_chain: bool = False   # made from a frame the chain alone carried (no keyframe or dense match): it
    # holds the chain's own error and cannot correct it
    unseen: int = 0          # made from a target patch that could not be compared (mostly glare): how
    # many such keyframes in a row led to it (0: its target patch was compared)
    patch: tuple | None = None  # the target's own patch (band-passed gray, not-highlight mask, local
    # energy), made on first use
    patch_wide: tuple | None = None  # the same of the whole target window (a patch under glare), on first use
    band: tuple | None = None  # band-passed gray and its valid mask (dense re-acquisition), made on first use
    texture: float = 1.0     # share of the 2-D texture of its lineage's sharpest keyframe its edge-like target
    # window still shows (1 when the window is not edge-like; see FeatureTracker._edge_smeared)
    self_ncc: float | None = None  # best match of its band-passed target window in its own region away from
    # the target (an edge or a repeated texture matches elsewhere too), made on first use


# corners whose median motion carries a lost target's predicted place (see FeatureTracker._scene_motion)
SCENE_NEIGHBOURS = 12
# px beyond a corner search window whose pixels still change the corners found in it (FeatureTracker._corners)
_CORNER_REACH = 5


class FeatureTracker(Tracker):
    """Keyframe-checked optical-flow feature tracker with re-acquisition (see module docstring)."""

    def __init__(self, settings: TrackerSettings | None = None) -> None:
        self.settings = validate(settings or TrackerSettings())
        s = self.settings
        self._win = (s.lk_window_px, s.lk_window_px)
        self._lk_crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 10, 0.03)
        self._orb = cv2.ORB_create(nfeatures=s.orb_features, scaleFactor=1.2, nlevels=6, edgeThreshold=31,
                                   patchSize=31, fastThreshold=10)
        self._orb_tpl = cv2.ORB_create(nfeatures=400, scaleFactor=1.2, nlevels=6, edgeThreshold=31,
                                       patchSize=31, fastThreshold=10)
        self._clahe: dict = {}
        self._ecc_crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-4)
        k = 2 * s.highlight_margin_px + 1  # highlight mask grown by this margin
        self._dilate = np.ones((k, k), np.uint8)
        c = 2 * s.highlight_clearance_px + 1
        self._clearance = np.ones((c, c), np.uint8)
        self._clear = False  # features are kept clear of highlights (a large window, see select)
        self._tpl_side = math.inf  # largest side of a dense re-acquisition template (px; see select)
        self._edge_like = False    # the window stayed edge-like after the context widening (see select)
        self._halo = np.ones((9, 9), np.uint8)  # reach of the target patch's band-pass (sigma 4 px) beyond a highlight
        self._fov: np.ndarray | None = None
        self._hann: np.ndarray | None = None
        self._anchor: _Keyframe | None = None
        self.lost = True
        self.stats = {"frames": 0, "misses": 0, "reacquisitions": 0, "keyframes": 0, "false_jumps": 0,
                      "inconsistent": 0, "outside": 0, "corrections": 0, "covered": 0, "dense": 0, "edge_like_dense": 0,
                      "retried": 0, "dense_reacquisitions": 0, "lost_frames": 0, "local_searches": 0,
                      "orb_searches": 0, "dense_searches": 0, "dense_presearch_skips": 0,
                      "similarity_dropped": 0, "similarity_limited": 0, "covered_overruled": 0, "edge_smeared": 0,
                      "seeded_relocks": 0, "phase_dense": 0, "dense_anchor_disagrees": 0, "scene_relocks": 0,
                      "survivor_seeds": 0}
        self._chain_only = 0
        self._verified_misses = False  # every miss since the last accepted frame was reported (see _update)
        self._lost_frames = 0
        self._vel_known = False
        self._clock = FrameClock()
        self._retry = False  # the optical flow runs on local-mean-free images (exposure retry)
        self._unretried: np.ndarray | None = None  # where this frame's first attempt's strong chain put the target (px)
        self._coasted: TrackResult | None = None  # a rejected frame's chain-only report (see _track)
        self._dense_tpl: list | None = None  # dense re-acquisition templates of the current loss
        self._cand: tuple | None = None      # dense candidate awaiting confirmation on the next frame
        self._dense_seed: np.ndarray | None = None  # the last dense search's best place (px), standing out or not
        self._scene: tuple[np.ndarray, np.ndarray] | None = None  # while lost: (last half-res grey, where the scene's
        # motion since the loss puts the target (px)); None when not lost or the scene's motion was lost too
        self._fov_half: np.ndarray | None = None
        self._fov_half_inner: np.ndarray | None = None  # _band_inner of _fov_half
        self._smooth = 0.0  # Gaussian sigma (px) the regions' gray is smoothed with (noisy sensor)
        self._fov_quarter: np.ndarray | None = None
        self._fov_full: np.ndarray | None = None  # a region's field-of-view mask when wholly inside (_warped_fov)
        self._box: tuple[int, int, int, int] | None = None  # whole-frame searches: (x0, y0, x1, y1) px
        self._per_frame: dict | None = None  # what is made of the frame being updated: its preprocessed
        # regions by (x0, y0, smoothing), "shift": (last accepted view, its phase-correlation shift)
        self.selection: dict | None = None
        """How the last successful :meth:`select` found its features (window, quality, masking)."""

    # ------------------------------------------------------------------ views
    def _highlights(self, bgr: np.ndarray, gray: np.ndarray, fov: np.ndarray) -> np.ndarray:
        """Specular highlights (bool) of a region, grown by ``highlight_margin_px``.

        A glint is near-saturated, white and a small local blob; pale but textured tissue is bright
        too, so brightness alone is not enough. Candidates: gray >= ``saturation_level`` and colour
        saturation <= ``highlight_max_chroma`` (reddish tissue is never white). A connected blob of
        candidates is a glint (with its halo) when it has at most ``highlight_max_blob_px`` pixels
        and reaches near saturation relative to the region's exposure (mean + 3 std of its gray,
        within [200, 245]); elsewhere only clipped pixels (>= 250, no texture left) are. The masked
        share of the region is capped at ``highlight_max_share`` (the brightest pixels are kept),
        so a bright frame never masks the target away.
        """
        s = self.settings
        _, cand = cv2.threshold(gray, s.saturation_level - 1, 255, cv2.THRESH_BINARY)
        cand = cv2.bitwise_and(cand, fov)
        out = np.zeros(gray.shape, bool)
        x, y, w, h = cv2.boundingRect(cand)
        if w == 0:
            return out
        mean, std = cv2.meanStdDev(gray, mask=fov)
        peak = min(245.0, max(200.0, float(mean[0, 0]) + 3.0 * float(std[0, 0])))
        box = (slice(y, y + h), slice(x, x + w))  # the rest only where there are candidates
        c, g = cand[box], gray[box]
        if bgr.ndim == 3:
            ch = cv2.split(np.ascontiguousarray(bgr[box]))  # a contiguous copy first: 2x faster split
            lo, hi = cv2.min(cv2.min(ch[0], ch[1]), ch[2]), cv2.max(cv2.max(ch[0], ch[1]), ch[2])
            # colour saturation 1 - lo/hi <= highlight_max_chroma
            white = cv2.compare(lo.astype(np.float32), (1.0 - s.highlight_max_chroma) * hi.astype(np.float32),
                                cv2.CMP_GE)
            c = cv2.bitwise_and(c, white)
        n, labels, st, _ = cv2.connectedComponentsWithStats(c, connectivity=8, ltype=cv2.CV_16U)
        cpos = c > 0
        glint = np.zeros(n, bool)  # small blobs that reach near saturation
        glint[labels[cpos & (g >= peak)]] = True
        glint &= st[:, cv2.CC_STAT_AREA] <= s.highlight_max_blob_px
        glint[0] = False
        sat = cpos & (g >= 250)
        if n > 1:
            sat |= glint[labels]
        n_sat = int(np.count_nonzero(sat))
        cap = int(s.highlight_max_share * cv2.countNonZero(fov)) if n_sat else 0
        if n_sat > cap:  # keep the brightest, up to the cap
            k = cap
            vals = g[sat]
            q = np.partition(vals, len(vals) - k - 1)[len(vals) - k - 1] if k > 0 else 256
            sat &= g > q
        # grown within the candidates' box and the margin only (nothing outside it to grow)
        r = s.highlight_margin_px
        gy0, gx0 = max(0, y - r), max(0, x - r)
        gy1, gx1 = min(gray.shape[0], y + h + r), min(gray.shape[1], x + w + r)
        grow = np.zeros((gy1 - gy0, gx1 - gx0), np.uint8)
        grow[y - gy0:y - gy0 + h, x - gx0:x - gx0 + w] = sat.view(np.uint8)
        out[gy0:gy1, gx0:gx1] = cv2.dilate(grow, self._dilate) > 0
        return out

    def _avoided(self, view: _View) -> np.ndarray:
        """Where (bool, region px) no feature is detected or followed: on highlights, and in a large
        window also within ``highlight_clearance_px`` of them (:meth:`select`)."""
        if not self._clear:
            return view.sat
        if view.near_sat is None:
            view.near_sat = cv2.dilate(view.sat.view(np.uint8), self._clearance) > 0
        return view.near_sat

    def _normalise(self, raw: np.ndarray, fov: np.ndarray, sat: np.ndarray, to_frame: np.ndarray) -> _View:
        """Normalised gray (mean 128, fixed contrast, statistics over tissue only), neutral outside
        the field of view and smoothly filled on highlights: the static black border and the
        moving glints then add no edges that would pull the optical flow."""
        x, y, bw, bh = cv2.boundingRect(sat.view(np.uint8))
        tissue = fov
        if bw > 0:  # the statistics over tissue only, unless highlights cover all of it
            tissue = fov.copy()
            tissue[sat] = 0
            if not tissue.any():
                tissue = fov
        mean, std = cv2.meanStdDev(raw, mask=tissue)
        std = max(float(std[0, 0]), 2.0)
        alpha = 40.0 / std
        norm = cv2.convertScaleAbs(raw, alpha=alpha, beta=128.0 - alpha * float(mean[0, 0]))
        if cv2.countNonZero(fov) < fov.size:  # most regions lie wholly inside the view
            norm[fov == 0] = 128
        if bw > 0:  # fill highlights smoothly from their surroundings (normalised convolution)
            hh, ww = sat.shape
            x0, y0, x1, y1 = max(0, x - 6), max(0, y - 6), min(ww, x + bw + 6), min(hh, y + bh + 6)
            sub, m = norm[y0:y1, x0:x1], sat[y0:y1, x0:x1]
            keep = (~m).astype(np.float32)
            num = cv2.blur(sub.astype(np.float32) * keep, (11, 11))
            den = cv2.blur(keep, (11, 11))
            fill = num / np.maximum(den, 1e-3)
            fill[den < 1e-3] = 128.0
            sub[m] = fill[m].astype(np.uint8)
        return _View(norm, to_frame, sat, raw, fov, 128.0 - alpha * float(mean[0, 0]), gain=alpha)

    def _crop(self, frame: np.ndarray, centre: np.ndarray) -> _View:
        """Square region of side ``self._side`` around ``centre``, shifted to lie inside the frame
        (pyramidal LK needs equal-sized images)."""
        h, w = frame.shape[:2]
        side = self._side
        x0 = int(min(max(0, round(centre[0] - side / 2)), w - side))
        y0 = int(min(max(0, round(centre[1] - side / 2)), h - side))
        key = (x0, y0, self._smooth)
        if self._per_frame is not None and key in self._per_frame:
            return self._per_frame[key]
        bgr = frame[y0:y0 + side, x0:x0 + side]
        raw = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY) if bgr.ndim == 3 else np.ascontiguousarray(bgr)
        fov = self._fov[y0:y0 + side, x0:x0 + side]
        view = self._smoothed(self._normalise(raw, fov, self._highlights(bgr, raw, fov), _translation((x0, y0))))
        if self._per_frame is not None:
            self._per_frame[key] = view
        return view

    def _smoothed(self, view: _View) -> _View:
        """``view`` with its gray smoothed when the sensor is noisy (``denoise_px``, set at selection)."""
        if self._smooth > 0.0:
            view.gray = cv2.GaussianBlur(view.gray, (0, 0), self._smooth)
        return view

    def _warp(self, base: _View, local_to_frame: np.ndarray) -> _View:
        """The preprocessed region ``base`` resampled through ``local_to_frame`` (3x3), so it lines
        up with a keyframe region: the optical flow then only has to absorb the prediction error,
        and scale/rotation are compensated within every flow window."""
        m = (_inv(base.to_frame) @ local_to_frame)[:2]
        size = (self._side, self._side)
        inv = cv2.WARP_INVERSE_MAP
        raw = cv2.warpAffine(base.raw, m, size, flags=cv2.INTER_LINEAR | inv, borderMode=cv2.BORDER_REPLICATE)
        if base.sat.any():
            sat = cv2.warpAffine(base.sat.view(np.uint8), m, size, flags=cv2.INTER_NEAREST | inv,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0
        else:  # no highlights: nothing to resample (a nearest-neighbour warp costs as much as the gray's)
            sat = np.zeros((self._side, self._side), bool)
        return self._smoothed(self._normalise(raw, self._warped_fov(local_to_frame), sat, local_to_frame.copy()))

    def _warped_fov(self, local_to_frame: np.ndarray) -> np.ndarray:
        """The field-of-view mask (uint8, 255 inside) resampled onto a region of side ``self._side``
        through ``local_to_frame`` (3x3). A region whose footprint (with 2 px to spare for the
        nearest-neighbour rounding) lies wholly inside the field of view is all inside: a shared,
        read-only mask instead of a warp (most regions away from the rim of the view)."""
        side = self._side
        h, w = self._fov.shape
        c = _apply(local_to_frame, ((0.0, 0.0), (side - 1.0, 0.0), (0.0, side - 1.0), (side - 1.0, side - 1.0)))
        x0, y0 = (math.floor(v) - 2 for v in c.min(axis=0))
        x1, y1 = (math.ceil(v) + 3 for v in c.max(axis=0))  # exclusive
        if x0 >= 0 and y0 >= 0 and x1 <= w and y1 <= h:
            ii = self._fov_sum
            if int(ii[y1, x1] - ii[y0, x1] - ii[y1, x0] + ii[y0, x0]) == (x1 - x0) * (y1 - y0):
                if self._fov_full is None or self._fov_full.shape[0] != side:
                    self._fov_full = np.full((side, side), 255, np.uint8)
                    self._fov_full.flags.writeable = False
                return self._fov_full
        return cv2.warpAffine(self._fov, local_to_frame[:2], (side, side), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def _features(self, view: _View, centre: np.ndarray, half: float, quality: float | None = None,
                  masked: bool = True) -> np.ndarray:
        """Corners (frame px) within a square of half-side ``half`` px around ``centre`` in a crop view
        (``quality``: goodFeaturesToTrack level, default the setting; ``masked``: not on highlights);
        only those above the sensor noise when there are enough of them (:meth:`_corners`)."""
        return self._corners(view, centre, half, quality, masked)[0]

    def _corners(self, view: _View, centre: np.ndarray, half: float, quality: float | None = None,
                 masked: bool = True) -> tuple[np.ndarray, int]:
        """:meth:`_features` and how many of them stand above the sensor noise: a corner whose
        Shi-Tomasi strength (smallest eigenvalue) is below ``corner_noise_floor`` x the noise
        variance of the region is what noise alone makes (fresh on every frame, nothing the flow
        can follow; on a smooth target under strong noise nearly every corner found is one). When
        at least 1.5 x ``min_inliers`` corners are above it, only those are returned; else all (weak
        texture: the corners there are all that can be followed)."""
        s = self.settings
        h, w = view.gray.shape
        off = view.to_frame[:2, 2]
        c = centre - off
        x0, y0 = int(max(0, c[0] - half)), int(max(0, c[1] - half))
        x1, y1 = int(min(w, c[0] + half + 1)), int(min(h, c[1] + half + 1))
        if x1 <= x0 or y1 <= y0:
            return np.zeros((0, 2), np.float32), 0
        # Detected on the window and a margin only, not the whole region (5-10x less work): a corner's
        # strength reaches 3 px (3x3 Sobel, 5x5 block), its non-maximum suppression 1 px more, so the
        # corners found in the window are the same as on the whole region.
        cx0, cy0 = max(0, x0 - _CORNER_REACH), max(0, y0 - _CORNER_REACH)
        cx1, cy1 = min(w, x1 + _CORNER_REACH), min(h, y1 + _CORNER_REACH)
        mask = np.zeros((cy1 - cy0, cx1 - cx0), np.uint8)
        ox, oy = int(off[0]), int(off[1])
        mask[y0 - cy0:y1 - cy0, x0 - cx0:x1 - cx0] = self._fov[oy + y0:oy + y1, ox + x0:ox + x1]
        if masked:
            mask[self._avoided(view)[cy0:cy1, cx0:cx1]] = 0
        pts = cv2.goodFeaturesToTrack(view.gray[cy0:cy1, cx0:cx1], s.max_features, quality or s.feature_quality,
                                      s.min_feature_distance_px, mask=mask, blockSize=5)
        if pts is None:
            return np.zeros((0, 2), np.float32), 0
        pts = pts.reshape(-1, 2) + np.float32((cx0, cy0))
        if s.corner_noise_floor <= 0.0 or view.noise() < s.corner_noise_level * view.gain:
            return pts + off.astype(np.float32), len(pts)
        # the corner strength where the corners are (the window plus the 3 px the 5 px block reaches)
        bx0, by0 = max(0, x0 - 3), max(0, y0 - 3)
        eig = cv2.cornerMinEigenVal(view.gray[by0:min(h, y1 + 3), bx0:min(w, x1 + 3)].astype(np.float32), 5, 3)
        q = np.round(pts).astype(int) - (bx0, by0)
        strong = eig[q[:, 1], q[:, 0]] > s.corner_noise_floor * view.noise() ** 2
        return pts + off.astype(np.float32), int(np.count_nonzero(strong))

    # ------------------------------------------------------------- estimation
    def _flow(self, a: _View, b: _View, pts: np.ndarray, guess: np.ndarray, levels: int, local: bool = False):
        """Pyramidal LK of points ``pts`` (frame px of view a) into view b, starting from ``guess``
        (frame px of view b), with a forward-backward check; points that end on a highlight are
        dropped. Returns (src, dst) frame coordinates of the kept points."""
        if len(pts) == 0:
            return pts, pts
        p0 = _apply(_inv(a.to_frame), pts).astype(np.float32).reshape(-1, 1, 2)
        g = _apply(_inv(b.to_frame), guess).astype(np.float32).reshape(-1, 1, 2)
        ga, gb = (a.local(), b.local()) if local else (a.gray, b.gray)
        if self._retry:  # local-mean-free, and only fine levels: large areas that clipped or came
            # out of clipping change the coarse levels most
            ga, gb, levels = a.local(), b.local(), min(levels, 1)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(ga, gb, p0, g, winSize=self._win, maxLevel=levels,
                                             criteria=self._lk_crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        back = p1 - (g - p0)  # backward search starts from the predicted motion, not from the answer
        pb, st2, _ = cv2.calcOpticalFlowPyrLK(gb, ga, p1, back, winSize=self._win, maxLevel=levels,
                                              criteria=self._lk_crit, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        fb = np.linalg.norm((pb - p0).reshape(-1, 2), axis=1)
        ok = (st.ravel() == 1) & (st2.ravel() == 1) & (fb < self.settings.fb_max_px)
        q = p1.reshape(-1, 2)
        h, w = b.gray.shape
        ok &= (q[:, 0] >= 0) & (q[:, 1] >= 0) & (q[:, 0] <= w - 1) & (q[:, 1] <= h - 1)
        if ok.any():  # on a highlight (in a large window: near one) in either image: biased, drop it
            idx = np.flatnonzero(ok)
            qi = np.round(q[ok]).astype(int)
            pi = np.clip(np.round(p0.reshape(-1, 2)[ok]).astype(int), 0, [w - 1, h - 1])
            ok[idx[self._avoided(b)[qi[:, 1], qi[:, 0]] | self._avoided(a)[pi[:, 1], pi[:, 0]]]] = False
        return pts[ok], _apply(b.to_frame, q[ok])

    @staticmethod
    def _common_motion(src: np.ndarray, dst: np.ndarray, least: int = 3, spread_px: float = 3.0) -> np.ndarray | None:
        """The median translation (px) of at least ``least`` followed points (``src`` -> ``dst``, frame
        px) if every one of them moved within ``spread_px`` of it (motion blur and the lens distortion
        spread a fast motion by a few px), else None."""
        if len(src) < least:
            return None
        d = np.asarray(dst, float) - np.asarray(src, float)
        m = np.median(d, axis=0)
        return m if float(np.max(np.linalg.norm(d - m, axis=1))) <= spread_px else None

    def _motion(self, src: np.ndarray, dst: np.ndarray, centre: np.ndarray):
        """RANSAC affine (lens distortion and perspective make the local motion anisotropic), then
        a least-squares affine of the inliers weighted towards ``centre``. Returns (affine 3x3,
        closest similarity 3x3, inlier mask, inlier count) or None."""
        s = self.settings
        if len(src) < max(s.min_inliers, 3):
            return None
        aff0, inl = cv2.estimateAffine2D(src.astype(np.float32), dst.astype(np.float32), method=cv2.RANSAC,
                                         ransacReprojThreshold=s.ransac_px, maxIters=300, confidence=0.995,
                                         refineIters=10)
        if aff0 is None:
            return None
        inl = inl.ravel().astype(bool)
        n_in = int(inl.sum())
        if n_in < s.min_inliers or n_in < s.min_inlier_ratio * len(src):
            return None
        half = 0.5 * self._window
        si, di = src[inl].astype(float), dst[inl].astype(float)
        w0 = 1.0 / (1.0 + np.sum((si - centre) ** 2, axis=1) / (half * half))
        aff = _h(aff0)
        for _ in range(2):  # iteratively reweighted: Cauchy weights on the residuals (0.5 px scale)
            r2 = np.sum((_apply(aff, si) - di) ** 2, axis=1)
            fit = _weighted_affine(si, di, w0 / (1.0 + r2 / 0.25))
            if fit is None:
                break
            aff = fit
        if aff is None or np.abs(aff[:2, :2] - aff0[:, :2]).max() > 0.25:  # no blow-up from few points
            aff = _h(aff0)
        return aff, _similarity(aff, centre), inl, n_in

    def _orb_prep(self, bgr: np.ndarray, fov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gray for ORB (local contrast equalised with tiles of ~90 x 72 px, slightly smoothed:
        repeatable keypoints on low-contrast tissue) and the detection mask (field of view, no
        highlights) of an image region ``bgr`` whose field-of-view mask is ``fov``."""
        gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY) if bgr.ndim == 3 else np.ascontiguousarray(bgr)
        mask = fov.copy()
        if bgr.ndim == 3:
            mask[self._highlights(bgr, gray, mask)] = 0
        grid = (max(1, round(bgr.shape[1] / 90)), max(1, round(bgr.shape[0] / 72)))
        clahe = self._clahe.get(grid)
        if clahe is None:
            clahe = self._clahe[grid] = cv2.createCLAHE(clipLimit=2.0, tileGridSize=grid)
        return cv2.GaussianBlur(clahe.apply(gray), (0, 0), 1.0), mask

    def _orb_source(self, frame: np.ndarray, centre: np.ndarray) -> tuple:
        """What :meth:`_orb_features` describes a keyframe with target at ``centre`` (px) from: a copy
        of the frame's region within the window + 32 px of it (the frame may be a reused buffer) and
        the region's origin (px). The field of view and the window are the selection's, as then."""
        half = self._window + 32
        h, w = frame.shape[:2]
        x0, y0 = int(max(0, centre[0] - half)), int(max(0, centre[1] - half))
        x1, y1 = int(min(w, centre[0] + half + 1)), int(min(h, centre[1] + half + 1))
        return frame[y0:y1, x0:x1].copy(), (x0, y0)

    def _orb_features(self, kf: _Keyframe) -> tuple[np.ndarray | None, np.ndarray | None]:
        """ORB keypoints (frame px) and descriptors of keyframe ``kf`` within its window of its
        target, described on first use: only the whole-frame re-acquisition needs them, and only
        of the anchor and the latest sharp keyframe (most keyframes are never searched for)."""
        if kf.orb_src is not None:
            bgr, (x0, y0) = kf.orb_src
            kf.orb_src = None
            gray, mask = self._orb_prep(bgr, self._fov[y0:y0 + bgr.shape[0], x0:x0 + bgr.shape[1]])
            kps, desc = self._orb_tpl.detectAndCompute(gray, mask)
            if desc is not None and len(kps) >= 4:
                pts = np.array([k.pt for k in kps], np.float32) + [x0, y0]
                near = np.max(np.abs(pts - kf.target), axis=1) <= self._window
                kf.orb_pts, kf.orb_desc = pts[near], desc[near]
        return kf.orb_pts, kf.orb_desc

    def _make_keyframe(self, frame: np.ndarray, view: _View, target: np.ndarray,
                       from_anchor: np.ndarray, pts: np.ndarray | None = None, sharp: bool = True) -> _Keyframe | None:
        """A keyframe of ``view`` (target at ``target`` px); ``sharp``: its view is not a blurred one
        (only sharp keyframes are matched over the whole frame when re-acquiring)."""
        if pts is None:
            pts = self._features(view, target, 0.5 * self._window)
        if len(pts) < self.settings.min_inliers:
            return None
        kf = _Keyframe(view, pts.astype(np.float32), np.array(target, float), from_anchor, sharp=sharp)
        if self.settings.reacquire and sharp:
            kf.orb_src = self._orb_source(frame, target)
        self.stats["keyframes"] += 1
        return kf

    # -------------------------------------------------------------------- API
    @property
    def footprint_px(self) -> float | None:
        # the flow's region (side ``_side`` about the prediction) and a new keyframe's description
        # (the window + 32 px about the target, see _orb_source); the window is the selection's,
        # which may have grown beyond the side asked for (weak or one-way texture)
        if self.lost or self._anchor is None:
            return None
        return max(0.5 * self._side, self._window + 32.0)

    def fresh(self) -> "FeatureTracker":
        return FeatureTracker(self.settings)

    def select(self, frame_bgr: np.ndarray, point_px, window_px: int) -> bool:
        """Select the target; when the window holds too few usable corners, fall back in turn to a
        1.5x and 2x larger window, to a 10x lower corner quality level, and to corners on
        highlights too. ``failure`` says why it still failed; ``selection`` how it succeeded."""
        s = self.settings
        if not 8 <= int(window_px) <= 2048:
            raise ValueError(f"window_px = {window_px}; allowed: [8, 2048] px")
        self.failure = None
        self.warning = None
        self.selection = None
        self._anchor = None
        self.lost = True
        self._fov = field_of_view_mask(frame_bgr, margin_px=s.lk_window_px // 2 + 2)
        p = np.asarray(point_px, float).reshape(2)
        h, w = frame_bgr.shape[:2]
        if not np.all(np.isfinite(p)) or not (0 <= p[0] < w and 0 <= p[1] < h):
            self.failure = f"point {p.round(1).tolist()} px is outside the {w}x{h} image"
            return False
        if not self._fov.any():
            self.failure = "no image content: the frame is dark (no field of view found)"
            return False
        self._fov_half = self._fov_quarter = None
        self._box = None
        self._smooth = 0.0
        self._pos = p.copy()
        if not self._in_view(p):
            self.failure = "point is outside the endoscope's field of view (or on its edge)"
            return False
        best = 0
        attempts = [(1.0, None, True), (1.5, None, True), (2.0, None, True),
                    (2.0, 0.1 * s.feature_quality, True), (2.0, 0.1 * s.feature_quality, False)]
        # Few corners (fewer than selection_margin x min_inliers: a smooth or dark target) leave no
        # margin for the ones lost to motion blur or noise on the next frames: a larger window
        # (same quality, same masking) is then taken if it has that margin. On vision-eval seeds 0-12
        # windows with fewer than 3 x min_inliers were tracked on 0.55 of their in-view frames, the
        # rest 0.95; seeds 0-20, margin 1.5 -> 3 (with the exposure-retry rule in _track): in-view
        # frames tracked 0.933 -> 0.937, false-lock frames 73 -> 56.
        # The first window with that margin is taken, else the first with half of it (the rule's
        # margin before 2026-12-03: 1.5 x min_inliers), else the requested one.
        margins = (math.ceil(s.selection_margin * s.min_inliers), math.ceil(0.5 * s.selection_margin * s.min_inliers))
        found = None
        reached: dict[int, tuple] = {}  # margin -> the first window whose strong corners reach it
        for grow, quality, masked in attempts:
            if found is not None and (quality is not None or not masked):
                break
            window = min(2048.0, grow * float(window_px))
            self._setup_window(frame_bgr, window)
            self._clear = False  # the window is chosen on the corners' count alone (see below)
            view = self._crop(frame_bgr, p)
            pts, n_strong = self._corners(view, p, 0.5 * self._window, quality, masked)
            best = max(best, len(pts))
            if len(pts) >= s.min_inliers:
                candidate = (window, quality, masked, view, pts, n_strong)
                found = found or candidate
                for m in margins:
                    if n_strong >= m:
                        reached.setdefault(m, candidate)
            if margins[0] in reached:
                break
        found = next((reached[m] for m in margins if m in reached), found)
        if found is not None and s.context_isotropy > 0.0 and window_px < s.large_window_px:
            before = found[0]
            found, isotropy = self._with_context(frame_bgr, p, float(window_px), found)
            context = found[0] > before
        else:
            isotropy, context = None, False
        self._edge_like = isotropy is not None and isotropy < s.context_isotropy
        if found is not None:
            window, quality, masked, view, pts, _ = found
            if window != self._window:
                self._setup_window(frame_bgr, window)
            # A window the user chose large (not one widened here for want of corners, which needs every
            # corner it has and whose periphery is what makes the target distinctive) holds plenty far from
            # the target, which the checks do not see through:
            # - A glint's halo reaches beyond its mask, and a corner whose flow window sees it follows the
            #   glint, which slides over the tissue as the view turns. In a large window such corners near
            #   the target are outnumbered by true ones farther out, and the RANSAC affine bends to fit both
            #   groups: the chain and the keyframe then agree on a position the glints dragged along (seed
            #   2's coffee `specular` at 160 px: 8-21 px off on 89 % of the frames, corners on the glints'
            #   rims 2-15 px off, the spoon's 80-105 px away within 0.3 px). Its features are kept clear of
            #   highlights. In the default 80 px window there is no far group to hide behind (the chain and
            #   the keyframe disagree, the frame is rejected); leaving them out there tracked more (seeds
            #   0-6: +0.0-0.04) but changed which weak-texture drifts the checks catch (new false locks on
            #   four seeds). The clearance does not choose the window (fewer corners clear of the glints
            #   kept seed 3's coffee `noise` at 80 px instead of 160, and it was lost).
            # - The dense re-acquisition looks for the target's surroundings, not the window's periphery,
            #   where e.g. an instrument coming over the target already showed in the last keyframe (seed
            #   0's mucosa `occlusion` at 160 px: the search found its edge and re-locked 184 px off).
            # - A window widened for context (context_isotropy) is large too: it has corners enough, and on
            #   the plain surface it was widened for, the glints' rims are the corners nearest the target
            #   (seeds 0-8 without it: false locks on 0.9 % of the frames, 7 times as many as with it, up to
            #   78 % of seed 5's coffee `blur`, trailing the target by 11-20 px; with the whole window, not
            #   its centre, as the dense template: seed 5's doubled).
            large = window_px >= s.large_window_px or context
            self._tpl_side = s.dense_template_max_px if large else math.inf
            if large and masked and s.highlight_clearance_px > 0:
                self._clear = True
                clear = self._features(view, p, 0.5 * self._window, quality, masked)
                if len(clear) >= s.min_inliers:
                    pts = clear
                else:
                    self._clear = False
            if s.denoise_px > 0.0 and view.noise() >= s.corner_noise_level * view.gain:
                # A noisy sensor: every region is smoothed before the flow (the noise is fresh on
                # every frame, nothing to follow); the corners are taken from the smoothed view.
                self._smooth = s.denoise_px
                smooth = self._crop(frame_bgr, p)
                spts = self._features(smooth, p, 0.5 * self._window, quality, masked)
                if len(spts) >= s.min_inliers:
                    view, pts = smooth, spts
                else:
                    self._smooth = 0.0
            kf = self._make_keyframe(frame_bgr, view, p, np.eye(3), pts)
            self.selection = {"window_px": self._window, "quality": quality or s.feature_quality,
                              "highlights_masked": masked, "features": len(pts), "isotropy": isotropy}
            self.warning = self._selection_warning(len(pts), isotropy)
        else:
            sat = float(view.sat.mean())
            why = (f"{sat:.0%} of the region is saturated or glare" if sat > 0.3 else
                   "the region is featureless (too little texture)")
            self.failure = (f"too few trackable corners around the point ({best} < {s.min_inliers}) even in a "
                            f"{self._window:.0f} px window: {why}")
            return False
        self._anchor = self._key = kf
        self._from_anchor = np.eye(3)   # anchor frame -> last accepted frame (similarity)
        self._central_from_anchor = np.eye(3)  # ... the last accepted with the target near the view's centre
        self._central_at = float(np.hypot(*(p - self._fov_centre)))  # px from the view's centre it was then
        self._prev = view               # last accepted frame's region ...
        self._prev_pts = kf.pts.copy()  # ... and the features to follow from it
        self.lost = False
        return True

    def _selection_warning(self, n_features: int, isotropy: float | None) -> str | None:
        """What may make a selected target hard to follow (one line), None if nothing. On vision-eval
        seeds 0-12 (468 sequences, in-view frames tracked, mean per sequence): windows with fewer than
        3x min_inliers corners (``selection_margin``, the count select() widens a window for) 0.55 (15
        sequences), more 0.95; windows still edge-like after the context widening 0.86 (61), the rest 0.95."""
        notes = []
        s = self.settings
        if n_features < math.ceil(s.selection_margin * s.min_inliers):
            notes.append(f"only {n_features} trackable corners in its {self._window:.0f} px window: blur or fast "
                         f"motion may lose it (a larger window or a spot with more texture holds better)")
        if self._edge_like and isotropy is not None:
            notes.append(f"its texture runs one way (isotropy {isotropy:.2f}): it may slide along that edge or rim")
        return "; ".join(notes) or None

    def _with_context(self, frame_bgr: np.ndarray, p: np.ndarray, window_px: float, found: tuple) -> tuple[tuple, float]:
        """The selection window ``found`` (window, quality, masked, view, corners, strong corners), or a
        1.5x or 2x larger one around ``p`` (px) when its texture is edge-like or flat: isotropy below
        ``context_isotropy``. A point on a smooth rim, a cup's plain glaze or a dark band is located by its
        80 px window along one direction only, and motion blur along it leaves nothing to follow (seeds 0-8:
        the 41 photograph windows of 80 px with isotropy below 0.1 were tracked on 75 % of their frames, 90 %
        when selected at 160 px, and half of the frames the photographs lost were theirs); the surroundings
        hold corners in other directions. The first larger window that reaches the isotropy is taken, else
        the most isotropic; each needs ``min_inliers`` corners at the same quality and masking. Returns the
        window and its isotropy."""
        s = self.settings
        window, quality, masked = found[:3]
        if self._window != window:
            self._setup_window(frame_bgr, window)
        best, best_iso = found, self._window_isotropy(found[3], p)
        for grow in (1.5, 2.0):
            if best_iso >= s.context_isotropy:
                break
            w = min(2048.0, grow * window_px)
            if w <= window:
                continue
            self._setup_window(frame_bgr, w)
            view = self._crop(frame_bgr, p)
            pts, n_strong = self._corners(view, p, 0.5 * w, quality, masked)
            if len(pts) < s.min_inliers:
                continue
            iso = self._window_isotropy(view, p)
            if iso > best_iso:
                best, best_iso = (w, quality, masked, view, pts, n_strong), iso
        return best, best_iso

    def _window_isotropy(self, view: _View, p: np.ndarray) -> float:
        """Isotropy (:meth:`_isotropy`) of the current window's texture around ``p`` (px) in ``view``."""
        iso = self._isotropy(view, p, view, np.eye(3), 1.0, int(round(0.5 * self._window)))
        return 1.0 if iso is None else iso

    def _setup_window(self, frame_bgr: np.ndarray, window_px: float) -> None:
        s = self.settings
        self._window = float(window_px)
        k = max(3, int(self._window // 2) | 1)
        self._fov_inner = cv2.erode(self._fov, np.ones((k, k), np.uint8))  # keyframes only from here
        self._fov_depth = cv2.distanceTransform(self._fov, cv2.DIST_L2, 3)  # px from the view's edge
        h, w = self._fov.shape
        self._scene_mask = cv2.resize(self._fov_inner, (w // 2, h // 2), interpolation=cv2.INTER_NEAREST)
        self._scene = None
        x, y, bw, bh = cv2.boundingRect(self._fov)
        self._fov_centre, self._fov_radius = np.array([x + 0.5 * bw, y + 0.5 * bh]), 0.5 * max(bw, bh, 1)
        self._fov_sum = cv2.integral(self._fov // 255)  # for the share of a window inside the view
        self._vel = np.zeros(2)
        self._vel_known = False
        self._misses = 0
        self._recent: deque[_Keyframe] = deque(maxlen=s.keyframes)
        self._weak_keys = 0  # keyframes made in a row from weak matches
        self._side = int(min(frame_bgr.shape[0], frame_bgr.shape[1],
                             math.ceil(1.3 * self._window + 2 * (s.search_margin_px + s.lk_window_px // 2 + 1))))
        self._hann = None
        self._clock.reset()
        self._steps = 1.0             # frame intervals from the last frame to this one
        self._gap = 0.0               # frame intervals from the last accepted frame to the last frame

    def _close(self, kf: _Keyframe, anchor_to_pred: np.ndarray, frac: float) -> bool:
        """The predicted view differs from keyframe ``kf`` by less than ``frac`` of the renewal limits."""
        sc, ang = _scale_angle(anchor_to_pred @ _inv(kf.from_anchor))
        return (abs(math.log(sc)) < math.log1p(frac * self.settings.keyframe_scale) and
                abs(math.degrees(ang)) < frac * self.settings.keyframe_rotation_deg)

    def _keyframe_candidates(self, anchor_to_pred: np.ndarray, relock: bool = False) -> list[tuple[_Keyframe, int]]:
        """(keyframe, fewest inliers to accept it) to try in order: every few frames the anchor
        (if the view is back close to it: no accumulated error), then the current keyframe, then
        the most recent other keyframe close to the predicted view. While lost (``relock``) the
        anchor comes first on every attempt, on the re-lock's own evidence (1.5 ``min_inliers``):
        the later keyframes may hold what made the target lost (seed 0's coffee `occlusion`: made as
        the instrument came near, 1-6 of their 22-24 corners matched when the target came back, the
        selection's 13 of 20, within 0.5 px)."""
        out = []
        if self._key is not self._anchor and (relock or self.stats["frames"] % 5 == 0) and \
                self._close(self._anchor, anchor_to_pred, 0.5):
            out.append((self._anchor, 0 if relock else 2 * self.settings.min_inliers))
        out.append((self._key, 0))
        for kf in reversed(self._recent):
            if kf is not self._key and self._close(kf, anchor_to_pred, 0.7):
                out.append((kf, 0))
                break
        return out

    def _view_share(self, p: np.ndarray) -> float:
        """Share (0..1) of the target window centred at ``p`` (px) that lies inside the field of view."""
        h, w = self._fov.shape
        half = 0.5 * self._window
        x0, y0 = min(max(round(p[0] - half), 0), w), min(max(round(p[1] - half), 0), h)
        x1, y1 = min(max(round(p[0] + half), 0), w), min(max(round(p[1] + half), 0), h)
        ii = self._fov_sum
        inside = float(ii[y1, x1] - ii[y0, x1] - ii[y1, x0] + ii[y0, x0])
        return min(1.0, inside / max(1.0, (2 * half) ** 2))

    @staticmethod
    def _scene_gray(frame: np.ndarray) -> np.ndarray:
        """The whole frame's grey at half resolution (what :meth:`_scene_motion` compares)."""
        g = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame
        return cv2.resize(g, (g.shape[1] // 2, g.shape[0] // 2), interpolation=cv2.INTER_AREA)

    def _scene_motion(self, prev: np.ndarray, cur: np.ndarray, at: np.ndarray) -> np.ndarray | None:
        """How far (px) the scene around ``at`` (frame px) moved from ``prev`` to ``cur`` (half-resolution
        greys of two frames): the median motion of the nearest corners that optical flow follows there
        and back (to within 1 px), over the view clear of its edge (which does not move). Local, not one
        motion for the whole view: the lens distortion slows the motion towards the edge, where a
        target leaves and comes back (a similarity fitted to the whole view ran ahead of it there,
        ~90 px over the 17 frames of a return). None when too few corners follow (a featureless or
        wholly changed view)."""
        # A low quality level: it is relative to the strongest corner, which a glint or the optic disc
        # makes so strong that a 1 % level left 3 corners on the fundus photograph (120 at 0.1 %).
        pts = cv2.goodFeaturesToTrack(prev, 120, 0.001, 8, mask=self._scene_mask)
        if pts is None or len(pts) < 12:
            return None
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(prev, cur, pts, None, winSize=(15, 15), maxLevel=3)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(cur, prev, nxt, None, winSize=(15, 15), maxLevel=3)
        pts, nxt, back = (v.reshape(-1, 2) for v in (pts, nxt, back))
        ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(back - pts, axis=1) < 1.0)
        if np.count_nonzero(ok) < 10:
            return None
        pts, flow = 2.0 * pts[ok], 2.0 * (nxt[ok] - pts[ok])
        near = np.argsort(np.linalg.norm(pts - at, axis=1))[:SCENE_NEIGHBOURS]
        return np.median(flow[near], axis=0)

    def _scene_relock(self, frame: np.ndarray) -> TrackResult | None:
        """While lost: carry the target's predicted place on by the scene's motion around it since the
        last frame, and once it lies ``scene_relock_depth`` windows inside the view (and away from where
        the local re-lock already looks), try the local keyframe re-lock there. A target that left the
        view comes back where the scene carries it, often far from where it was last seen, beyond the
        local searches' reach; in a lost stretch (blur, glare) the scene's motion says where the target
        went. The re-lock still needs the keyframe's corners around the target and its own patch, as
        every re-lock does."""
        prev, where = self._scene
        cur = self._scene_gray(frame)
        step = self._scene_motion(prev, cur, where)
        if step is None:
            self._scene = None  # nothing to carry the prediction on any more
            return None
        where = where + step
        self._scene = (cur, where)
        x, y = int(round(where[0])), int(round(where[1]))
        h, w = self._fov_depth.shape
        if not (0 <= x < w and 0 <= y < h) or self._fov_depth[y, x] < self.settings.scene_relock_depth * self._window \
                or np.hypot(*(where - self._pos)) <= 8.0:
            return None
        self.stats["scene_relocks"] += 1
        return self._track(frame, relock=True, seed=where)

    def _in_view(self, p: np.ndarray, inner: bool = False) -> bool:
        """``p`` (px) lies inside the (shrunk) field of view; ``inner``: a quarter window further in."""
        x, y = int(round(p[0])), int(round(p[1]))
        m = self._fov_inner if inner else self._fov
        h, w = m.shape
        return 0 <= x < w and 0 <= y < h and m[y, x] > 0

    def _coarse_shift(self, frame: np.ndarray) -> np.ndarray | None:
        """Translation (px) of the last accepted region into ``frame``, by phase correlation (once per
        update: the exposure retry asks again)."""
        cache = self._per_frame if self._per_frame is not None else {}
        hit = cache.get("shift")
        if hit is None or hit[0] is not self._prev:
            hit = cache["shift"] = (self._prev, self._phase_shift(frame))
        return None if hit[1] is None else hit[1].copy()

    def _phase_shift(self, frame: np.ndarray) -> np.ndarray | None:
        off = self._prev.to_frame[:2, 2]
        same = self._crop(frame, off + self._side / 2)
        if np.any(same.to_frame[:2, 2] != off):
            return None
        if self._hann is None:
            self._hann = cv2.createHanningWindow((self._side, self._side), cv2.CV_32F)
        # The window also fades out smoothly towards the (static) border of the field of view,
        # which would otherwise pull the correlation peak to zero shift.
        x0, y0 = int(off[0]), int(off[1])
        fov = self._fov[y0:y0 + self._side, x0:x0 + self._side].astype(np.float32)
        win = self._hann * cv2.blur(cv2.erode(fov, np.ones((9, 9), np.uint8)), (17, 17)) * (1.0 / 255.0)
        # high-pass: the static light fall-off would also peak at zero shift
        (dx, dy), response = cv2.phaseCorrelate(self._prev.detail(), same.detail(), win)
        if response < 0.05 or math.hypot(dx, dy) > self._side / 3:
            return None
        return np.array([dx, dy])

    _NOISE_BAND = 0.05  # variance of white noise (std 1) after the patch's resampling and band-pass (measured)

    def _patch_similarity(self, view: _View, kf: _Keyframe, key_to_frame: np.ndarray,
                          motion_px: np.ndarray | None = None) -> tuple[float, bool, bool]:
        """How well the target's own patch (side ~0.4 window) in ``view``, mapped by
        ``key_to_frame`` (3x3), still matches keyframe ``kf``: the normalised cross-correlation of
        both band-passed patches without highlight pixels (their halo neither), the sensor noise
        taken out of both energies and the current patch scaled to the keyframe's contrast, or
        ``patch_keyframe_ncc`` when their
        texture energies agree within ``patch_energy_ratio`` (the same tissue, slightly blurred or
        misregistered, not covered) or the energy is evenly lower (down to ``patch_blur_energy``)
        and it still correlates ``patch_blur_ncc`` (weak texture, blurred); 0 for a uniform patch,
        1 when the keyframe's patch itself is uniform or mostly glare (nothing to compare). Also
        returns whether the patch passed only as a blurred view (a keyframe made from it is not
        used to re-acquire) and whether it was seen at all (False: mostly glare, the target
        itself unverified). ``motion_px``: the target's motion per frame interval (px); a patch
        that decorrelated is then also compared with the keyframe's smeared along it (motion blur),
        and passing that way scores just below ``patch_keyframe_ncc`` (accepted, no keyframe)."""
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP

        def sample(v: _View, m: np.ndarray, side: int) -> tuple[np.ndarray, np.ndarray]:
            g = cv2.warpAffine(v.gray, m[:2], (side, side), flags=flags, borderMode=cv2.BORDER_REPLICATE)
            sat = cv2.warpAffine(v.sat.view(np.uint8), m[:2], (side, side), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                                 borderMode=cv2.BORDER_REPLICATE)
            # band-pass: noise smoothed away, and so is the slow shading (light fall-off, the smooth
            # fill of glints), which changes with the view and is not the target's appearance.
            # Highlights and their halo are left out (a filled blob still leaves a ring in the
            # band-pass). Also the patch's brightness (gray levels above black): texture energies
            # are compared relative to it (contrast), which neither the light's gain nor the
            # region's normalisation (what else is in the region) changes.
            ok = cv2.dilate(sat, self._halo) == 0
            level = float(np.mean(g[ok])) - v.zero if ok.any() else 0.0
            return _band(g, 1.0, 4.0), ok, level

        def patches(half: int, wide: bool):
            """(keyframe's patch: band-passed, usable mask, local energy, noise variance, level; this
            frame's: band-passed in the keyframe's contrast, noise variance; both usable) of side 2 half + 1."""
            side = 2 * half + 1
            to_patch = _translation(kf.target - half)
            # Sensor noise is in both band-passed patches' energy but not in their covariance: it is
            # taken out, so strong noise on weak texture does not read as another texture.
            cached = kf.patch_wide if wide else kf.patch
            if cached is None:
                ref, ok_ref, level = sample(kf.view, _inv(kf.view.to_frame) @ to_patch, side)
                nv_ref = self._NOISE_BAND * kf.view.noise() ** 2
                local = cv2.blur(ref * ref, (9, 9))
                cached = ref, ok_ref, np.maximum(local - nv_ref, 0.25 * local) + 1.0, nv_ref, level
                if wide:
                    kf.patch_wide = cached
                else:
                    kf.patch = cached
            ref, ok_ref, ref_local, nv_ref, ref_level = cached
            cur, ok_cur, level = sample(view, _inv(view.to_frame) @ key_to_frame @ to_patch, side)
            gain = ref_level / level if ref_level > 1.0 and level > 1.0 else 1.0  # in the keyframe's contrast
            return ref, ref_local, nv_ref, cur * np.float32(gain), self._NOISE_BAND * (gain * view.noise()) ** 2, \
                ok_ref & ok_cur

        ref, ref_local, nv_ref, cur, nv_cur, ok = patches(max(7, int(round(0.2 * self._window))), False)
        if np.count_nonzero(ok) < 0.3 * ok.size:
            # Mostly glare: the target itself cannot be compared (the glare test is elsewhere). Its
            # whole window still can: when that matches the keyframe's, this view is registered
            # where the keyframe was (a keyframe made from it hands on no error); else it stays
            # unverified (coffee `leave`: the target on a glossy spoon, under glints for 10 frames,
            # made no keyframe after the second such one, and the keyframe flow, distorted towards
            # the edge of the view, lost it while the chain still followed it).
            wide = patches(int(0.5 * self._window), True)
            usable = wide[5]
            # its own correlation (not the energy rules' pass), and only a textured window (band-passed
            # std >= 2 of 40: a smooth one would "match" anywhere)
            seen = (np.count_nonzero(usable) >= 0.3 * usable.size and float(np.std(wide[0][usable])) >= 2.0 and
                    self._patch_score(*wide)[2] >= self.settings.patch_keyframe_ncc)
            return 1.0, False, seen
        out = (*self._patch_score(ref, ref_local, nv_ref, cur, nv_cur, ok)[:2], True)
        if out[0] >= self.settings.patch_keyframe_ncc or motion_px is None:
            return out
        # Motion blur smears the patch along the motion (up to the whole frame interval's motion
        # with a long exposure): the band-passed texture across it is gone, so the patch
        # decorrelates although it is the same tissue. Compare with the keyframe's patch smeared the
        # same way (a covered patch does not match that either).
        s = self.settings
        d = np.linalg.solve(key_to_frame[:2, :2], np.asarray(motion_px, float))  # in keyframe px
        length = float(np.hypot(*d))
        if length < 3.0:
            return out
        for frac in (0.5, 1.0):
            n = int(round(frac * length))
            if n < 2:
                continue
            k = np.zeros((n | 1, n | 1), np.float32)
            c = (n | 1) // 2
            u = d / length
            for t in np.linspace(-0.5 * n, 0.5 * n, 2 * n + 1):
                k[int(round(c + t * u[1])), int(round(c + t * u[0]))] = 1.0
            k /= k.sum()
            refb = cv2.filter2D(ref, -1, k, borderType=cv2.BORDER_REPLICATE)
            local = cv2.blur(refb * refb, (9, 9))
            ref_local_b = np.maximum(local - nv_ref, 0.25 * local) + 1.0
            score, _, ncc = self._patch_score(refb, ref_local_b, nv_ref, cur, nv_cur, ok)
            if score < s.patch_keyframe_ncc:
                continue
            # The same tissue smeared: accepted, but no keyframe is made from it (its own
            # correlation may be low: it is not registered well enough to hand on).
            return min(max(ncc, s.patch_reject_ncc), 0.99 * s.patch_keyframe_ncc), True, True
        return out

    def _patch_score(self, ref: np.ndarray, ref_local: np.ndarray, nv_ref: float, cur: np.ndarray, nv_cur: float,
                     ok: np.ndarray) -> tuple[float, bool, float]:
        """The target-patch comparison of :meth:`_patch_similarity` of the band-passed patches
        ``ref`` and ``cur`` (noise variances ``nv_ref``, ``nv_cur``) over ``ok``: its score, whether it
        passed only as a blurred view, and the patches' own correlation (1 for a textureless target)."""
        a, b = ref[ok], cur[ok]
        a = a - a.mean()
        b = b - b.mean()
        e_ref = float(np.dot(a, a))
        e_ref = max(e_ref - nv_ref * a.size, 0.25 * e_ref)
        if e_ref < 4.0 * a.size:  # the target itself has no texture (std < 2 of 40): no check
            return 1.0, False, 1.0
        e_cur = float(np.dot(b, b))
        e_cur = max(e_cur - nv_cur * b.size, 0.25 * e_cur)
        den = math.sqrt(e_cur * e_ref)
        ncc = min(1.0, float(np.dot(a, b)) / den) if den > 1e-3 else 0.0
        # Decorrelated *and* with another texture energy, or with texture gone from part of the
        # patch: something else is there (an instrument's edge adds structure, its smooth body
        # removes it). Decorrelation at equal, evenly spread energy is only a slightly
        # misregistered or blurred view of the same tissue; so is an even loss of energy that still
        # correlates (weak texture under motion blur), while a covered patch does not correlate.
        local = cv2.blur(cur * cur, (9, 9))[ok]
        local = np.maximum(local - nv_cur, 0.25 * local) / ref_local[ok]
        k = int(0.9 * (len(local) - 1))
        vanished = float(np.mean(local < 0.1 * np.partition(local, k)[k]))
        ratio = e_cur / e_ref
        if vanished < 0.25 and 1.0 / self.settings.patch_energy_ratio <= ratio <= self.settings.patch_energy_ratio:
            return max(ncc, self.settings.patch_keyframe_ncc), False, ncc
        if vanished < 0.25 and self.settings.patch_blur_energy <= ratio < 1.0 and ncc >= self.settings.patch_blur_ncc:
            return max(ncc, self.settings.patch_keyframe_ncc), ncc < self.settings.patch_keyframe_ncc, ncc
        return ncc, False, ncc

    def _match_keyframe(self, base: _View, kf: _Keyframe, key_to_pred: np.ndarray):
        """Optical flow keyframe -> this frame's region ``base``, warped by the predicted transform.
        Returns (motion or None, kept keyframe points, their matches, the warped region)."""
        wv = self._warp(base, key_to_pred @ kf.view.to_frame)
        ksrc, kdst = self._flow(kf.view, wv, kf.pts, _apply(key_to_pred, kf.pts), self.settings.key_levels,
                                local=self.settings.key_flow_local)
        return self._motion(ksrc, kdst, kf.target), ksrc, kdst, wv

    def _match_ecc(self, kf: _Keyframe, key_to_pred: np.ndarray, wv: _View) -> tuple[np.ndarray, float] | None:
        """Dense fallback when too few of keyframe ``kf``'s corners can be followed (weak texture,
        blur, noise, an exposure step): the keyframe's high-passed target window (this frame's
        highlights left out) is aligned with this frame's region ``wv`` (already warped by the
        prediction ``key_to_pred``) by ECC, a correlation that is invariant to gain and offset.
        Returns (keyframe frame -> this frame, 3x3; the correlation) or None when it does not
        converge or correlates less than ``dense_min_ecc``; then :meth:`_match_dense` tries."""
        s = self.settings
        half = int(0.5 * self._window)
        t = np.round(kf.target - kf.view.to_frame[:2, 2]).astype(int)
        h, w = kf.view.gray.shape
        x0, y0 = max(0, t[0] - half), max(0, t[1] - half)
        x1, y1 = min(w, t[0] + half + 1), min(h, t[1] + half + 1)
        if x1 - x0 < 16 or y1 - y0 < 16:
            return None
        box = (slice(y0, y1), slice(x0, x1))
        if np.count_nonzero(kf.view.sat[box]) > 0.5 * (y1 - y0) * (x1 - x0):
            return None
        warp = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0]], np.float32)
        try:  # high-passed (the light fall-off moves with the camera, not with the tissue); the
            # mask (of the input region) leaves this frame's highlights out
            rho, warp = cv2.findTransformECC(kf.view.detail()[box], wv.detail(), warp, cv2.MOTION_TRANSLATION,
                                             self._ecc_crit, (~wv.sat).view(np.uint8), 5)
        except cv2.error:  # did not converge
            return None
        d = warp[:, 2].astype(float) - (x0, y0)  # shift in the keyframe's (and the warped region's) pixels
        if not rho >= s.dense_min_ecc or np.hypot(*d) > s.search_margin_px:
            return None
        return key_to_pred @ _translation(d), float(rho)

    def _match_dense(self, kf: _Keyframe, key_to_pred: np.ndarray, wv: _View) -> tuple[np.ndarray, float] | None:
        """Dense fallback when too few of keyframe ``kf``'s corners can be followed (weak texture,
        blur, noise, an exposure step): the keyframe's band-passed target window is correlated
        (normalised, so invariant to gain and offset) with this frame's region ``wv`` (already
        warped by the prediction ``key_to_pred``) within ``dense_radius_px``; highlights and their
        halo are left out of both. Returns (keyframe frame -> this frame, 3x3; the correlation) or
        None when the best place correlates less than ``dense_min_ncc``."""
        s = self.settings
        bp, valid = self._kf_band(kf)
        half = int(0.5 * self._window)
        r = int(math.ceil(s.dense_radius_px))
        t = np.round(kf.target - kf.view.to_frame[:2, 2]).astype(int)
        h, w = bp.shape
        x0, y0 = max(r, t[0] - half), max(r, t[1] - half)
        x1, y1 = min(w - r, t[0] + half + 1), min(h - r, t[1] + half + 1)
        if x1 - x0 < 16 or y1 - y0 < 16:
            return None
        ok = valid[y0:y1, x0:x1] > 0
        if np.count_nonzero(ok) < 0.3 * ok.size:
            return None
        tpl = np.where(ok, bp[y0:y1, x0:x1], np.float32(0.0))
        img = _band(wv.gray[y0 - r:y1 + r, x0 - r:x1 + r], *self._BAND_FULL)
        near = self._band_valid(wv.fov[y0 - r:y1 + r, x0 - r:x1 + r], wv.sat[y0 - r:y1 + r, x0 - r:x1 + r], 1.0)
        img[near == 0] = 0.0
        score = cv2.matchTemplate(img, tpl, cv2.TM_CCOEFF_NORMED)
        _, top, _, loc = cv2.minMaxLoc(score)
        if not top >= s.dense_min_ncc:
            return None
        d = _subpixel(score, loc) - r  # shift in the keyframe's (and the warped region's) pixels
        return key_to_pred @ _translation(d), float(top)

    def update(self, frame_bgr: np.ndarray, capture_time: float | None = None) -> TrackResult:
        # The same region of this frame is often preprocessed twice (the exposure retry, the
        # phase correlation's region), and the retry repeats the phase correlation: made once per
        # frame (the frame may be a reused buffer, so never across frames).
        self._per_frame = {}
        self._coasted = None
        try:
            return self._update(frame_bgr, capture_time)
        finally:
            self._per_frame = None

    def _update(self, frame_bgr: np.ndarray, capture_time: float | None) -> TrackResult:
        s = self.settings
        self.stats["frames"] += 1
        if self._anchor is None:
            return TrackResult(np.full(2, np.nan), 0.0, False, True)
        self._steps = self._clock.tick(capture_time)
        if self.lost:
            self._lost_frames += 1
            k = self._lost_frames
            # The searches take turns (a lost frame costs about one of them): the whole-frame dense
            # search every ``dense_reacquire_every`` frames and on the frame after it found a
            # candidate (which that frame must confirm), ORB every ``reacquire_every`` frames but not
            # on the first lost frame, the local keyframe re-lock on the first two lost frames and then
            # on every 4th. No ORB on the first lost frame (the dearest search): the target was just
            # missed on several frames in a row (left the view, covered, blurred) and is rarely back
            # at once; on 4680 frames of seeds 0 and 1 ORB never re-locked there.
            dense = s.reacquire and s.dense_reacquire and (
                self._cand is not None or k % s.dense_reacquire_every == 1 % s.dense_reacquire_every)
            self.stats["lost_frames"] += 1
            res = self._scene_relock(frame_bgr) if self._scene is not None else None
            if res is not None:
                return res
            if k <= 2 or k % 4 == 0:
                self.stats["local_searches"] += 1
                res = self._track(frame_bgr, relock=True)
                if res is None and s.local_seed_px > 0:
                    # The same, seeded where the selection's band-passed window correlates best around
                    # the last position (no uniqueness asked: a seed only; the whole-frame dense search
                    # skips windows that match their own surroundings or have little texture).
                    res = self._seeded_relock(frame_bgr, self._local_seed(frame_bgr), s.local_seed_px)
            if res is None and s.reacquire and k > 1 and k % s.reacquire_every == 1 % s.reacquire_every:
                self.stats["orb_searches"] += 1
                res = self._reacquire(frame_bgr)
            if res is None and dense:
                self.stats["dense_searches"] += 1
                res = self._reacquire_dense(frame_bgr)
                # A target that moved while it was lost (covered, blurred) is rarely within the optical
                # flow's reach of where it was last seen (seed 0's coffee `occlusion`: 25 px, and the
                # local re-lock there never found it). The dense search's best place, even one that
                # does not stand out enough to be accepted on its own, seeds the local re-lock, which
                # still needs a keyframe's corners around it and the target's own patch.
                if res is None:
                    res = self._seeded_relock(frame_bgr, self._dense_seed, s.seeded_relock_px)
            if res is not None:
                self._dense_tpl = self._cand = None
            if res is None:
                return TrackResult(np.full(2, np.nan), 0.0, False, True)
            return res
        res = self._track(frame_bgr, relock=False)
        if res is None:
            # Rejected: an exposure step (or glare that came or went) may have changed the region's
            # normalisation. Retry on local-mean-free images before counting a miss.
            self._retry = True
            try:
                res = self._track(frame_bgr, relock=False)
            finally:
                self._retry = False
            if res is not None:
                self.stats["retried"] += 1
        if res is not None:
            return res
        coasted, self._coasted = self._coasted, None
        # misses that were all reported from a chain whose target patch matched the keyframe's
        self._verified_misses = coasted is not None and (self._misses == 0 or self._verified_misses)
        self._misses += 1
        self.stats["misses"] += 1
        # The target keeps moving while frames are rejected (blur, a glint, a covered moment): the
        # prediction coasts on the last velocity over the whole gap since the last accepted frame.
        self._gap += self._steps
        if self._misses > s.max_misses:
            self.lost = True
            # From here the scene's own motion carries the prediction (see _scene_relock). Not for an
            # edge-like window (a rim): its re-lock may lie anywhere along the edge, and under motion
            # blur the chain then slides along it (seed 24's coffee `blur`: re-locked that way, then 14
            # frames 8-20 px off; left lost, nothing is reported). Nor for a large window: near the
            # edge of the view the lens distortion bends its motion away from the point's, and its
            # keyframes made there keep that error (seed 6's mucosa `leave` at 160 px: re-locked 8.2 px
            # off from one).
            self._scene = (self._scene_gray(frame_bgr), self._pos + self._vel * self._gap) \
                if s.scene_relock and not self._edge_like and self._window < s.large_window_px else None
            self._vel[:] = 0.0
            self._vel_known = False
            self._gap = 0.0
            self._lost_frames = 0
            self._dense_tpl = self._cand = None
            return TrackResult(np.full(2, np.nan), 0.0, False, True)
        return coasted or TrackResult(self._pos.copy(), 0.0, False, False)

    def _track(self, frame: np.ndarray, relock: bool, seed: np.ndarray | None = None) -> TrackResult | None:
        """One step from the last accepted frame; None if this frame is rejected. ``relock``: the
        target is lost and this is a cheap local attempt (keyframe evidence required), around
        ``seed`` (px) if given, else where it was last seen."""
        s = self.settings
        steps = self._steps + self._gap  # frame intervals since the last accepted frame
        # velocity in px per typical frame interval; a re-lock may be seeded elsewhere (px)
        pred = self._pos + self._vel * steps if seed is None else np.asarray(seed, float)
        moving = pred.copy()  # where the target's own motion puts it (pred may follow a coarse shift below)
        tried_shift = False
        phased = None  # the target's place by this frame's phase-correlation shift, when no velocity is known (px)
        if not relock and not self._vel_known:
            # No velocity yet (just selected or re-acquired): predict by phase correlation.
            shift = self._coarse_shift(frame)
            tried_shift = True
            if shift is not None:
                pred = phased = self._pos + shift
        view = self._crop(frame, pred)
        # 1) chain: last accepted frame -> this frame
        src, dst = self._flow(self._prev, view, self._prev_pts, self._prev_pts + (pred - self._pos), s.lk_levels)
        chain = self._motion(src, dst, self._pos)
        if chain is None and not relock:
            # Unexpected motion: a second attempt seeded by the coarse shift from phase correlation
            # of the same region in both frames (or, if that seeded the first one, by no motion).
            survivors = (src, dst)
            shift = np.zeros(2) if tried_shift else self._coarse_shift(frame)
            if shift is not None and np.hypot(*(self._pos + shift - pred)) > 2.0:
                pred = self._pos + shift
                view = self._crop(frame, pred)
                src, dst = self._flow(self._prev, view, self._prev_pts, self._prev_pts + shift, s.lk_levels)
                chain = self._motion(src, dst, self._pos)
            common = self._common_motion(*survivors) if chain is None and not self._vel_known and s.survivor_seed \
                else None
            if common is not None and np.hypot(*(self._pos + common - pred)) > 2.0:
                # Just selected or re-acquired (no velocity to predict from) in fast motion: the blur
                # left most corners beyond the forward-backward check and the phase correlation found
                # no peak, but the few corners that passed moved together: their motion seeds one more
                # attempt (seed 5's retina `fast`, 17 px per frame from the first frame: 5 of 40 corners
                # passed, all within 3 px of the true motion; the phase correlation's peak was 0.01).
                # Not once a velocity is known: a jump away from it is not believed, and a frame of
                # displaced texture moves every corner together too.
                pred = self._pos + common
                view = self._crop(frame, pred)
                src, dst = self._flow(self._prev, view, self._prev_pts, self._prev_pts + common, s.lk_levels)
                chain = self._motion(src, dst, self._pos)
                self.stats["survivor_seeds"] += 1
        suspect = False  # the chain's own scale/rotation were implausible: it is no corroboration
        if chain is not None:
            chain, suspect = self._steady(chain, steps)
        step = chain[1] if chain is not None else _translation(pred - self._pos)
        anchor_to_pred = step @ self._from_anchor
        # 2) keyframe -> this frame, predicted through the chain
        key = None
        current = None  # (key_to_pred, warped region) of the current keyframe, for the dense fallback
        views = self._relock_views(anchor_to_pred, pred) if relock else [anchor_to_pred]
        for kf, least, key_to_pred in [(kf, least, a2p @ _inv(kf.from_anchor))
                                       for a2p in views for kf, least in self._keyframe_candidates(a2p, relock)]:
            km, ksrc, kdst, wv = self._match_keyframe(view, kf, key_to_pred)
            if kf is self._key:
                current = (key_to_pred, wv)
            # while lost, a keyframe alone needs 1.5 min_inliers (below): a weaker match leaves the next
            # keyframe or view to try
            if km is not None and km[3] >= (max(least, 1.5 * s.min_inliers) if relock else least):
                key = (kf, km, kdst)
                break
        est_chain = _apply(chain[0], self._pos) if chain is not None else None
        if not self._retry:
            self._unretried = est_chain if chain is not None and chain[3] >= 2 * s.min_inliers else None
        agree = math.inf  # how closely the chain and a keyframe's features agree (px)
        if key is not None and chain is None and key[1][3] < 1.5 * s.min_inliers:
            key = None  # a keyframe alone, on a few features only: not trusted (while lost: the loop above)
        dense = None
        disputed = False  # a dense match disagreed with the chain (on the retry)
        if key is None and chain is None and phased is not None and not relock and s.phase_dense \
                and self._key is self._anchor:
            # Just selected or re-acquired (no velocity yet) and no corner followed (fast motion blurred
            # them all: seed 4's coffee `fast`, 17 px per frame, lost from the first frame), but the
            # region's phase correlation measured its motion: the keyframe's window aligned densely
            # there, agreeing with it, stands in for the chain. Not once a velocity is known: then
            # the phase correlation follows whatever moves most, and an instrument crossing the target
            # or the view's edge agreed with a dense match (false locks on 5 of 9 seeds' `occlusion`
            # and `leave` sequences). Nor from a later keyframe: one made as an instrument came near
            # holds its outline, and right after a re-lock the phase correlation followed the receding
            # instrument and that keyframe's dense match agreed (held-out seed 15's retina `occlusion`:
            # 27 px off on the frame after a correct re-lock, then 140-148 px on the instrument).
            sel = self._anchor  # the selection keyframe: anchor -> anchor is the identity
            pview = view if np.hypot(*(pred - phased)) < 1e-9 else self._crop(frame, phased)
            sel_to_ph = _translation(phased - self._pos) @ self._from_anchor
            wv = self._warp(pview, sel_to_ph @ sel.view.to_frame)
            dense = self._match_ecc(sel, sel_to_ph, wv) or self._match_dense(sel, sel_to_ph, wv)
            if dense is not None and np.hypot(*(_apply(dense[0], sel.target) - phased)) <= s.consistency_px:
                est_chain, pred, view = phased, phased, pview
                self.stats["phase_dense"] += 1
            else:
                dense = None
        if key is None and current is not None and chain is not None and not relock and not suspect:
            # ECC first; the band-passed correlation when ECC finds nothing (it leaves the glints'
            # halo out, which on weak texture can outweigh the tissue). An ECC match that
            # disagrees with the chain is a warning kept: the frame is rejected below.
            dense = self._match_ecc(self._key, *current)
            if dense is None:
                dense = self._match_dense(self._key, *current)
            if self._retry and self._smooth == 0.0 and dense is not None and \
                    np.hypot(*(_apply(dense[0], self._key.target) - est_chain)) > s.consistency_px:
                # ECC starts from the warp the view's similarity predicts, and weak keyframe matches
                # (few corners, all near the target) can leave that similarity off: on seed 0's coffee
                # `tip` 15 % in scale, and ECC converged 17-30 px off on frames where the chain (20+
                # inliers) was within 2 px. Such a frame is still rejected (the tracker's state stays
                # at the last accepted frame), but a strong chain whose target patch matches the
                # keyframe's may report it. Not under strong sensor noise (denoised regions), where
                # the chain drifts.
                self.stats["inconsistent"] += 1
                dense, disputed = None, True
        if key is not None:
            kf, (aff, sim, inl, n_in), kdst = key
            est = _apply(aff, kf.target)
            conf = min(1.0, n_in / max(len(kf.pts), 1) / 0.8) * min(1.0, n_in / (2.0 * s.min_inliers))
            if self._retry and self._unretried is not None and n_in < 2 * s.min_inliers and self._smooth == 0.0 and \
                    (est_chain is None or np.hypot(*(est_chain - self._unretried)) > s.consistency_px):
                # The exposure retry is for flow the exposure change broke, not for a strong chain that
                # a weak keyframe match disputed: a retry chain that moved to that match is another fit of
                # the same corners, not a better one (seed 14's coffee `folds` grown to 120 px on the
                # deforming surface: the first chain 0.3 px from the target, the keyframe's 10 inliers
                # 4.8 px off; the retry's chain agreed with them 5 px off, made a keyframe there and
                # held 5-10 px off for the rest of the sequence). Not under strong sensor noise
                # (denoised regions), where the first chain drifts and the retry repairs it (seed 3's
                # coffee `noise` at 80 px: tracked on 0.23 of 40 frames with the rule there, 0.6+ without).
                self.stats["inconsistent"] += 1
                return None
            if est_chain is not None:
                agree = float(np.hypot(*(est - est_chain)))
                if agree > s.consistency_px:
                    inl_pts = kdst[inl]
                    around = bool(np.all(est > inl_pts.min(axis=0)) and np.all(est < inl_pts.max(axis=0)))
                    # A later keyframe: only a correction of what the chain may have inherited, and
                    # not under strong sensor noise (denoised regions), where keyframes are made from
                    # noisy matches and carry their own error (seeds 3 and 4, coffee `noise`: later
                    # keyframes 5-12 px off "corrected" chains 2-5 px off, 10 frames of false lock).
                    # Nor from a keyframe made where the chain alone carried the frame: it holds the chain's
                    # own error (seed 2's coffee `leave` at 160 px: one made 3.5 px off near the edge of the
                    # view, where the lens distortion bends the two feature sets' extrapolations apart,
                    # "corrected" the next frame's chain from 3.4 to 6.8 px off, then 8 px for five frames).
                    within = kf is self._anchor or (agree <= s.keyframe_correction_px and self._smooth == 0.0
                                                    and (not kf.by_chain or s.chain_keyframe_corrects))
                    if n_in < 2 * s.min_inliers or not around or not within:
                        self.stats["inconsistent"] += 1  # X_n-1 -> X_n disagrees with keyframe -> X_n
                        return None
                    # A strong match of a keyframe overrules the chain: drift corrected; not from
                    # features on one side of the target only (an extrapolation: under noise, anchor
                    # features along one rim slid along it and "corrected" a right chain 2 -> 20 px
                    # off in 6 frames, seed 4's coffee `noise`). The chain starts from the last
                    # accepted position and hands its error on: on the photographs of seeds 0 and 1
                    # every such strong, surrounding match of a later keyframe that disagreed with
                    # the chain (11 frames, 3-7 px apart) was the closer one (0.4-4 px from the
                    # target, the chain 3-7 px), and rejecting those frames lost the target.
                    self.stats["corrections"] += 1
                    est_chain = est
                # Both agree: average them by their inlier counts. The keyframe keeps the chain
                # from drifting; the chain smooths the keyframe estimate when few features match.
                n_c = chain[3]
                est = (n_in * est + n_c * est_chain) / (n_in + n_c)
            new_from_anchor = sim @ kf.from_anchor
            if n_in < 2 * s.min_inliers and not self._plausible(new_from_anchor @ _inv(self._from_anchor), steps):
                # A few keyframe features determine the view's scale and rotation poorly (as the
                # chain's, see _steady), but a keyframe may also correct the chain's drift: the
                # position is taken, the view's scale and rotation change by at most the plausible
                # step (a real correction then takes a few frames).
                self.stats["similarity_limited"] += 1
                new_from_anchor = self._limited(new_from_anchor, steps, est)
            next_pts = kdst[inl]
        elif dense is not None:
            # Too few corners matched the keyframe, but its whole target window aligns densely.
            kf = self._key
            aff, rho = dense
            est = _apply(aff, kf.target)
            n_in = 0
            if np.hypot(*(est - est_chain)) > s.consistency_px:
                self.stats["inconsistent"] += 1
                return None
            if self._edge_like and not s.edge_like_dense:
                # A template with structure across one direction only aligns along its edge as well as
                # anywhere: under motion blur the chain and this match slid together along a plain rim
                # (seed 17's coffee `fast`, widened to 160 px at isotropy 0.07: 8-20 px off on 63 % of
                # the frames). Not the target's place: a miss.
                self.stats["edge_like_dense"] += 1
                return None
            est = 0.5 * (est + est_chain)
            self.stats["dense"] += 1
            conf = 0.5 * rho
            new_from_anchor = _similarity(aff, kf.target) @ kf.from_anchor
            next_pts = dst[chain[2]] if chain is not None else self._features(view, est, 0.5 * self._window)
        elif (chain is not None and not suspect and not relock and self._chain_only < 3 and chain[3] >= 2 * s.min_inliers
              and (self._misses == 0 or disputed or (self._verified_misses and s.chain_after_reported))
              # Only near the motion the target had: a chain alone that suddenly jumps follows something
              # else (seed 8's retina `occlusion`: corners re-detected on an instrument's outline as it
              # reached the target, then a 24 px jump with it while the target drifted 0.5 px per frame,
              # and 47 and 68 px off on the next frames; on seeds 0, 1 and 8 every other frame carried by
              # the chain alone was within 6 px of the prediction). The region's phase correlation that
              # seeds a second attempt follows whatever moves most, the instrument too: not the reference.
              and (not self._vel_known or np.hypot(*(est_chain - moving)) <= s.chain_only_jump_px * steps)):
            aff, sim, inl, n_in = chain  # keyframe unmatched: a few frames on the chain alone
            est = est_chain
            conf = 0.5 * min(1.0, n_in / max(len(self._prev_pts), 1) / 0.8)
            new_from_anchor = sim @ self._from_anchor
            next_pts = dst[inl]
        else:
            return None
        if np.hypot(*(est - pred)) > s.max_jump_px * (3.0 if relock else steps):
            self.stats["false_jumps"] += 1  # moved too far from the prediction: not believed
            return None
        if not self._in_view(est):
            self.stats["outside"] += 1  # left the field of view: cannot be measured any more
            return None
        # The target's own patch must still look like the keyframe's: the surrounding features
        # alone cannot tell that an instrument (or blood, smoke) now covers the target itself.
        if key is not None or dense is not None:
            ref, ref_to_frame = kf, aff.copy()  # the local affine: follows the lens distortion too
        else:
            ref = self._key
            ref_to_frame = new_from_anchor @ _inv(ref.from_anchor)
        ref_to_frame[:2, 2] += est - _apply(ref_to_frame, ref.target)
        ncc, blurred, seen = self._patch_similarity(view, ref, ref_to_frame, (est - self._pos) / steps)
        if disputed:  # reported (if its patch confirms it), but not taken as the next frames' base
            if seen and ncc >= s.patch_keyframe_ncc:
                self._coasted = TrackResult(est.copy(), float(conf * self._view_share(est)), True, False)
            return None
        if ncc < s.patch_reject_ncc:
            # The patch decorrelated: something may cover the target. Not when the keyframe's own
            # features right around the target (within 0.3 window) still follow it and the chain
            # agrees (patch_override_px), or a dense match of the keyframe's window agrees with the
            # chain and the chain's features right around the target follow it: a covered
            # target's surroundings are covered too, or they disagree.
            # On the photographs (seeds 0 and 1) 36 of 37 frames rejected as covered were visible
            # and tracked within 2 px (an exposure change, motion blur, noise or sliding glare
            # decorrelated the band-passed patch; the 37th was a covered target, within 1.6 px).
            # Such a frame is accepted with a low confidence and makes no keyframe.
            near = 0
            if not suspect and ((key is not None and agree <= s.patch_override_px) or
                                (key is None and dense is not None and s.patch_override_px > 0.0)):
                d = np.abs(next_pts - est)
                near = int(np.count_nonzero(np.max(d, axis=1) <= 0.3 * self._window))
            if near < 2:
                self.stats["covered"] += 1
                return None
            self.stats["covered_overruled"] += 1
            ncc = s.patch_reject_ncc
        # A dense match of a window that is mostly glare measures the glare and the window's
        # edges, not the target: against a keyframe that is itself twice removed from a verified
        # target it is not believed (on seed 2's coffee `rotation` such matches agreed with the
        # chain for 11 frames while both drifted 4 -> 20 px off the target).
        if key is None and dense is not None and not seen and ref.unseen >= 2:
            self.stats["inconsistent"] += 1
            return None
        match_conf = conf  # the evidence of the match itself
        conf *= min(1.0, ncc / s.patch_keyframe_ncc)
        # One-sided support (inliers only on one side: the rest covered or out of view) is an
        # extrapolation: less confident.
        surrounded = len(next_pts) > 0 and bool(np.all(est > next_pts.min(axis=0)) and np.all(est < next_pts.max(axis=0)))
        if not surrounded:
            conf *= 0.5
        # At the edge of the view (or of the image) only part of the window has image: the
        # features there carry the estimate, with confidence in proportion to the window's share.
        conf *= self._view_share(est)
        # Accept.
        self._chain_only = 0 if (key is not None or dense is not None) else self._chain_only + 1
        self._vel_known = not relock
        self._vel = (est - self._pos) / steps if self._vel_known else np.zeros(2)
        self._gap = 0.0
        self._pos = est
        self._misses = 0
        self.lost = False
        self._set_from_anchor(new_from_anchor, est)
        self._prev = view
        if len(next_pts) < s.max_features // 2:
            extra = self._features(view, est, 0.5 * self._window)
            next_pts = np.vstack([next_pts, extra]) if len(extra) else next_pts
        self._prev_pts = next_pts.astype(np.float32)
        # A new keyframe when the one used drifted in scale/rotation or matched poorly.
        renew = key is None
        if key is not None:
            sc, ang = _scale_angle(sim)
            renew = (abs(math.log(sc)) > math.log1p(0.5 * s.keyframe_scale) or
                     abs(math.degrees(ang)) > 0.5 * s.keyframe_rotation_deg or
                     n_in < max(2 * s.min_inliers, 0.4 * len(kf.pts)))
            self._key = kf
        # Only from a well-supported estimate: features on all sides of the target (no
        # extrapolation, which drifts at the edge of the view), its own patch unchanged.
        # A weak match (few of the keyframe's features) hands its error on to the next keyframe:
        # renewing from such frames one after another drifts off the target, so at most
        # ``weak_keyframes`` in a row (default none: more keep weak texture tracked longer, but
        # drifted into false locks on unseen sequences).
        # A target under glare is unverified (its patch could not be compared): a keyframe made
        # from it takes the surroundings' word for where the target is. Two such in a row are
        # fine (mucosa `leave`: < 1 px), a third is not made: on seed 2's coffee `rotation`
        # (target under a glint while the tissue turns) keyframes made that way on frames 3, 5
        # and 8 handed a 0.6 px/frame drift on, 1 -> 13 px in 16 frames, reported valid with
        # confidence up to 0.8.
        weak = match_conf < s.keyframe_min_confidence
        supported = (surrounded and self._in_view(est, inner=True)
                     and ncc >= s.patch_keyframe_ncc and (not weak or self._weak_keys < s.weak_keyframes)
                     and (seen or ref.unseen < 2))
        # Renew only when chain and keyframe both support this frame (or the chain strongly). Under
        # strong sensor noise (denoised regions) a dense match of the keyframe's window that agrees
        # with a plausible chain is the keyframe's support too: the keyframe's corners stop matching
        # as the view moves on (seed 2's retina `noise`: 1-9 of 40 on frames 16-28), only dense
        # matches carry the frames, and without a renewal the stale keyframe failed for good on
        # frame 24 (lost for 30 frames with the target in view, 0.9-1.7 px before). Not on a quiet
        # sensor: there such keyframes cost more than they kept (seed 0's coffee `lighting` 0.69 ->
        # 0.37, one frame > 8 px off on seed 2's retina `leave`).
        by_key = key is not None or (dense is not None and self._smooth > 0.0)
        strong = (by_key and chain is not None) or (key is None and n_in >= 3 * s.min_inliers)
        # A target window whose texture is an edge (a rim, a fold) locates the target only across it:
        # along it the chain and the keyframe's features slide together (the consistency check
        # cannot see it) and only faint texture holds them. When that texture is smeared away (motion
        # blur along the edge), a keyframe made there hands the slide on: on seed 3's coffee `blur`
        # keyframes made in the smear were 2.4 and 10.1 px off and 31 % of the frames were reported
        # 9-17 px off; on seed 4's coffee `rotation` 5-6.5 px off ones drifted to a false lock.
        renew = renew and not relock and supported and strong
        texture = self._edge_smeared(view, est, ref, ref_to_frame) if renew else None
        if texture is not None and texture < s.edge_texture_loss:
            self.stats["edge_smeared"] += 1
            renew = False
        if renew:
            kf_new = self._make_keyframe(frame, view, est, new_from_anchor, sharp=not blurred)
            if kf_new is not None:
                kf_new.texture = 1.0 if texture is None else texture
                kf_new.unseen = 0 if seen else ref.unseen + 1
                kf_new.by_chain = key is None and dense is None
                self._recent.append(kf_new)
                self._key = kf_new
                self._weak_keys = self._weak_keys + 1 if weak else 0
        if relock:
            self.stats["reacquisitions"] += 1
        return TrackResult(est.copy(), float(conf), True, False)

    @staticmethod
    @functools.lru_cache(maxsize=64)
    def _grad_noise(sigma: float) -> float:
        """What white noise of std 1 adds to each diagonal term of the structure tensor of
        :meth:`_isotropies` (gray smoothed with ``sigma`` px, then Sobel / 8)."""
        r = int(math.ceil(4 * sigma)) + 2
        delta = np.zeros((2 * r + 1, 2 * r + 1), np.float32)
        delta[r, r] = 1.0
        gx = cv2.Sobel(cv2.GaussianBlur(delta, (0, 0), sigma), cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
        return float(np.sum(gx.astype(np.float64) ** 2))

    def _isotropies(self, view: _View, est: np.ndarray, ref: _Keyframe, ref_to_frame: np.ndarray) -> tuple[float, float]:
        """How two-dimensional the texture of the target window is in ``view`` (target at ``est`` px)
        and in keyframe ``ref`` (mapped into this frame by ``ref_to_frame``, 3x3): the smaller over the
        larger eigenvalue of each window's structure tensor (Gaussian-weighted towards the target,
        sigma a quarter window), the sensor noise's share taken out of both (0: an edge or nothing,
        1: isotropic texture). Each is measured on its own pixel grid (resampling would blur the fine
        texture this measures), at the same scale on the tissue (the finer view smoothed more: a view
        that zoomed out shows less fine texture, which is no blur) and only where both frames are
        inside the field of view and clear of highlights (a clipped area has no texture in either:
        an exposure step that clips part of the window changes neither)."""
        sc = _scale_angle(ref_to_frame)[0]  # this frame's px per keyframe px
        parts = []
        for v, centre, other, to_other, k in ((view, est, ref.view, _inv(ref_to_frame), max(1.0, sc)),
                                              (ref.view, ref.target, view, ref_to_frame, max(1.0, 1.0 / sc))):
            # the same area of tissue in both (the keyframe's px are 1 / sc of this frame's), smoothed to
            # the same scale on it: the finer view by its px per the other's (k)
            half = int(round(0.5 * self._window * (1.0 if v is view else 1.0 / sc)))
            iso = self._isotropy(v, centre, other, to_other, k, half)
            if iso is None:  # too little usable texture to compare: no verdict
                return 1.0, 1.0
            parts.append(iso)
        return parts[0], parts[1]

    def _isotropy(self, v: _View, centre: np.ndarray, other: _View, to_other: np.ndarray, sigma: float,
                  half: int) -> float | None:
        """Isotropy of the texture in ``v`` within ``half`` px of ``centre`` (px), smoothed by ``sigma``
        px, where ``v`` and ``other`` (``v``'s frame -> ``other``'s frame: ``to_other``, 3x3) are both
        inside the field of view and clear of highlights (see :meth:`_isotropies`); None when too little
        of the window is usable."""
        near = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
        m = int(math.ceil(3 * sigma)) + 2  # the smoothing's and the derivative's reach
        side = 2 * (half + m) + 1
        c = np.round(np.asarray(centre, float) - v.to_frame[:2, 2]) - (half + m)  # window origin, local px
        crop = np.array([[1.0, 0.0, c[0]], [0.0, 1.0, c[1]], [0.0, 0.0, 1.0]])
        g = cv2.warpAffine(v.gray, crop[:2], (side, side), flags=near, borderMode=cv2.BORDER_REPLICATE)
        own = cv2.warpAffine(v.sat.view(np.uint8) | (v.fov == 0).view(np.uint8), crop[:2], (side, side), flags=near,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=1)
        mp = _inv(other.to_frame) @ to_other @ v.to_frame @ crop
        theirs = cv2.warpAffine(other.sat.view(np.uint8) | (other.fov == 0).view(np.uint8), mp[:2], (side, side),
                                flags=near, borderMode=cv2.BORDER_CONSTANT, borderValue=1)
        usable = cv2.dilate(own | theirs, np.ones((2 * m - 1, 2 * m - 1), np.uint8))[m:-m, m:-m] == 0
        g1 = cv2.getGaussianKernel(2 * half + 1, 0.5 * half, cv2.CV_32F)
        w = (g1 @ g1.T) * usable
        if float(w.sum()) < 0.1:
            return None
        w /= w.sum()
        g = cv2.GaussianBlur(g.astype(np.float32), (0, 0), sigma)
        gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)[m:-m, m:-m]
        gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)[m:-m, m:-m]
        a, b, d = float(np.sum(w * gx * gx)), float(np.sum(w * gx * gy)), float(np.sum(w * gy * gy))
        mean, r = 0.5 * (a + d), math.sqrt(0.25 * (a - d) ** 2 + b * b)
        nz = self._grad_noise(round(sigma, 2)) * v.noise() ** 2
        lo, hi = mean - r - nz, mean + r - nz
        return max(lo, 0.0) / hi if hi > 1e-6 else 0.0

    def _edge_smeared(self, view: _View, est: np.ndarray, ref: _Keyframe, ref_to_frame: np.ndarray) -> float | None:
        """For a keyframe from this frame: None when the target window (at ``est`` px in ``view``) is not
        edge-like (isotropy at least ``edge_isotropy``), else the share of 2-D texture it keeps of the
        sharpest keyframe it descends from (its isotropy over keyframe ``ref``'s, :meth:`_isotropies`,
        times ``ref.texture``); below ``edge_texture_loss`` it is smeared (no keyframe). Compared along
        the lineage, so a slow smear over several keyframes adds up. None under strong sensor noise
        (denoised regions), where the fine texture cannot be measured."""
        s = self.settings
        if self._smooth > 0.0 or s.edge_isotropy <= 0.0:
            return None
        cur, key = self._isotropies(view, est, ref, ref_to_frame)
        if cur >= s.edge_isotropy:
            return None
        return min(1.0, (cur / key if key > 0.0 else 1.0) * ref.texture)

    def _steady(self, chain: tuple, steps: float) -> tuple[tuple, bool]:
        """The frame-to-frame motion ``chain`` with its scale and rotation kept only when they are
        plausible for ``steps`` frame intervals (``max_view_scale_step``, ``max_view_rotation_step_deg``).
        Few features, or features along one edge (a rim, a fold), leave them poorly determined: a
        wrong 20 % / 15 deg step once taken into the view's similarity misaligned every later
        keyframe warp, and the keyframe flow then found nothing (the target was lost with the chain
        still following it). The position (the affine at the target) is kept, but such a chain is
        suspect (also returned): it still predicts and is checked against a keyframe's features,
        but it no longer corroborates a dense match or carries a frame alone (on seed 2's coffee
        `specular` a suspect chain and an ECC match agreed frame after frame while both drifted
        6 -> 19 px off the target)."""
        if self._plausible(chain[1], steps):
            return chain, False
        self.stats["similarity_dropped"] += 1
        return (chain[0], _translation(_apply(chain[0], self._pos) - self._pos), chain[2], chain[3]), True

    def _limited(self, new_from_anchor: np.ndarray, steps: float, est: np.ndarray) -> np.ndarray:
        """``new_from_anchor`` with its change of scale and rotation from the current view limited to
        what is plausible in ``steps`` frame intervals, mapping the anchor's target to ``est``."""
        s = self.settings
        sc, ang = _scale_angle(new_from_anchor @ _inv(self._from_anchor))
        ls = float(np.clip(math.log(sc), -s.max_view_scale_step * steps, s.max_view_scale_step * steps))
        lim = math.radians(s.max_view_rotation_step_deg * steps)
        a = float(np.clip(ang, -lim, lim))
        r = math.exp(ls) * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        out = np.eye(3)
        out[:2, :2] = r @ self._from_anchor[:2, :2]
        out[:2, 2] = est - out[:2, :2] @ self._anchor.target
        return out

    def _plausible(self, step: np.ndarray, steps: float) -> bool:
        """Similarity ``step`` (3x3) changes scale and rotation no more than believable in ``steps``
        frame intervals."""
        s = self.settings
        sc, ang = _scale_angle(step)
        return (abs(math.log(sc)) <= s.max_view_scale_step * steps and
                abs(math.degrees(ang)) <= s.max_view_rotation_step_deg * steps)

    def _reacquire(self, frame: np.ndarray) -> TrackResult | None:
        """Whole-frame ORB search for any keyframe, verified by RANSAC and by the optical-flow
        keyframe check seeded with the ORB transform."""
        s = self.settings
        # One matching pass for the anchor and the most recent keyframe together; none of them
        # with enough descriptors (weak texture): the frame's ORB search would be wasted.
        sharp = [k for k in self._recent if k.sharp][-1:]  # the latest not made from a blurred view
        kfs = [k for k in [self._anchor, *sharp]
               if (desc := self._orb_features(k)[1]) is not None and len(desc) >= s.reacquire_min_inliers]
        if not kfs:
            return None
        box = self._search_box()
        gray, mask = self._orb_prep(frame[box[1]:box[3], box[0]:box[2]], self._fov[box[1]:box[3], box[0]:box[2]])
        kps, desc = self._orb.detectAndCompute(gray, mask)
        if desc is None or len(kps) < s.reacquire_min_inliers:
            return None
        pts = np.array([k.pt for k in kps], np.float32) + np.float32(box[:2])
        owner = np.concatenate([np.full(len(k.orb_desc), i) for i, k in enumerate(kfs)])
        query = np.concatenate([k.orb_desc for k in kfs])
        qpts = np.concatenate([k.orb_pts for k in kfs])
        # The two nearest frame descriptors of each keyframe descriptor (what BFMatcher.knnMatch
        # computes, by the same function), as arrays: no DMatch objects to build and unpack.
        dist, nearest = cv2.batchDistance(query, desc, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=2)
        ratio_ok = (nearest[:, 1] >= 0) & (dist[:, 0] < s.reacquire_ratio * dist[:, 1].astype(float))
        good = np.column_stack([np.flatnonzero(ratio_ok), nearest[ratio_ok, 0]]).astype(int).reshape(-1, 2)
        best = None
        for i, kf in enumerate(kfs):
            g = good[owner[good[:, 0]] == i] if len(good) else good
            if len(g) < s.reacquire_min_inliers:
                continue
            sim, inl = cv2.estimateAffinePartial2D(qpts[g[:, 0]], pts[g[:, 1]], method=cv2.RANSAC,
                                                   ransacReprojThreshold=3.0, maxIters=1000, confidence=0.995)
            if sim is None:
                continue
            n_in = int(inl.sum())
            if n_in >= s.reacquire_min_inliers and (best is None or n_in > best[0]):
                best = (n_in, kf, _h(sim))
        if best is None:
            return None
        _, kf, key_to_cur = best
        est0 = _apply(key_to_cur, kf.target)
        base = self._crop(frame, est0)
        km, ksrc, kdst, _ = self._match_keyframe(base, kf, key_to_cur)
        if km is None or km[3] < 1.5 * s.min_inliers:
            return None
        aff, sim, inl, n_in = km
        est = _apply(aff, kf.target)
        if np.hypot(*(est - est0)) > 6.0:
            return None
        conf = min(1.0, n_in / max(len(kf.pts), 1) / 0.8) * min(1.0, n_in / (2.0 * s.min_inliers))
        return self._relocked(est, kf, sim, base, kdst[inl], conf)

    # ------------------------------------------------------- dense re-acquisition
    _BAND_FULL = (1.0, 6.0)  # band-pass sigmas (px) at full resolution; at half resolution half of them

    def _band_valid(self, fov: np.ndarray, sat: np.ndarray, scale: float,
                    inner: np.ndarray | None = None) -> np.ndarray:
        """uint8 mask (255: usable) of a band-passed region at ``scale``: inside the field of view and
        clear of highlights by the band-pass's reach (a glint's filled blob still leaves a ring of
        its halo there, which would match any bright blob, e.g. a glint that stays put). ``inner``:
        :meth:`_band_inner` of ``fov``, when already made."""
        k = self._band_reach(scale)
        near = cv2.dilate(sat.view(np.uint8), np.ones((k, k), np.uint8))
        if inner is None:
            inner = self._band_inner(fov, scale)
        return cv2.bitwise_and(inner, cv2.bitwise_not(near * 255))

    def _band_inner(self, fov: np.ndarray, scale: float) -> np.ndarray:
        """The part of ``fov`` (uint8 mask) beyond the band-pass's reach (at ``scale``) from its edge."""
        k = self._band_reach(scale)
        return cv2.erode(fov, np.ones((k, k), np.uint8))

    def _band_reach(self, scale: float) -> int:
        """Side (px, odd) of the square the band-pass at ``scale`` reaches across (1.5 of its wide sigma)."""
        return 2 * int(math.ceil(1.5 * self._BAND_FULL[1] * scale)) + 1

    def _kf_band(self, kf: _Keyframe) -> tuple[np.ndarray, np.ndarray]:
        """Band-passed gray of keyframe ``kf``'s region and its usable mask (:meth:`_band_valid`)."""
        if kf.band is None:
            kf.band = _band(kf.view.gray, *self._BAND_FULL), self._band_valid(kf.view.fov, kf.view.sat, 1.0)
        return kf.band

    def _dense_template(self, kf: _Keyframe, scale: float, from_anchor: np.ndarray,
                        valid: np.ndarray | None = None) -> tuple[np.ndarray, float] | None:
        """Band-passed target window of keyframe ``kf`` (side = window; a large one's centre, see select),
        resampled at ``scale`` (1 or 0.5) to the scale and rotation of the view ``from_anchor`` (anchor ->
        that view); highlights and what lies outside the field of view are zero (neutral for the
        correlation). Returns (template, its texture energy per valid pixel) or None when too little of
        it is usable. ``valid``: another usable mask of the keyframe's region (uint8, 255: usable)."""
        bp, usable = self._kf_band(kf)
        valid = usable if valid is None else valid
        rel = from_anchor @ _inv(kf.from_anchor)   # keyframe -> that view
        lin_inv = np.linalg.inv(_similarity(rel, kf.target)[:2, :2]) / scale
        half = int(round(0.5 * min(self._window, self._tpl_side) * scale))  # a large window: its centre (select)
        side = 2 * half + 1
        t_local = kf.target - kf.view.to_frame[:2, 2]
        m = np.hstack([lin_inv, (t_local - lin_inv @ np.array([half, half], float))[:, None]])
        flags = cv2.WARP_INVERSE_MAP
        tpl = cv2.warpAffine(bp, m, (side, side), flags=cv2.INTER_LINEAR | flags, borderValue=0)
        ok = cv2.warpAffine(valid, m, (side, side), flags=cv2.INTER_NEAREST | flags, borderValue=0) > 0
        n_ok = int(np.count_nonzero(ok))
        if n_ok < 0.3 * ok.size:
            return None
        tpl[~ok] = 0.0
        return tpl, float(np.dot(tpl.ravel(), tpl.ravel())) / n_ok

    def _search_box(self) -> tuple[int, int, int, int]:
        """(x0, y0, x1, y1) px, even: the part of the frame the whole-frame searches look at, the
        field of view's bounding box with a margin that holds a template window and the band-pass's
        and ORB's reach beyond it (outside the round view there is nothing to find; a round view
        in a 4:3 frame leaves about a quarter of it black)."""
        if self._box is None:
            h, w = self._fov.shape
            x, y, bw, bh = cv2.boundingRect(self._fov)
            m = int(0.5 * self._window) + 8  # the window (centred in the view), ORB's 31 px edge
            x0, y0 = max(0, x - m) // 2 * 2, max(0, y - m) // 2 * 2
            x1, y1 = min(w, x + bw + m), min(h, y + bh + m)
            self._box = x0, y0, x0 + (x1 - x0) // 2 * 2, y0 + (y1 - y0) // 2 * 2
        return self._box

    def _dense_image(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The frame's :meth:`_search_box` at half resolution, normalised, highlights filled,
        band-passed (zero near highlights and the field of view's edge), its field-of-view mask and
        the box's origin (x, y px of the full frame)."""
        x0, y0, x1, y1 = self._search_box()
        w, h = x1 - x0, y1 - y0
        if self._fov_half is None:
            self._fov_half = cv2.resize(self._fov[y0:y1, x0:x1], (w // 2, h // 2), interpolation=cv2.INTER_NEAREST)
            self._fov_half_inner = self._band_inner(self._fov_half, 0.5)  # the same on every frame
        small_bgr = cv2.resize(frame[y0:y1, x0:x1], (w // 2, h // 2), interpolation=cv2.INTER_AREA)
        gray = cv2.cvtColor(small_bgr, cv2.COLOR_BGR2GRAY) if small_bgr.ndim == 3 else small_bgr
        fov = self._fov_half
        view = self._normalise(gray, fov, self._highlights(small_bgr, gray, fov), np.eye(3))
        img = _band(view.gray, 0.5 * self._BAND_FULL[0], 0.5 * self._BAND_FULL[1])
        img[self._band_valid(fov, view.sat, 0.5, self._fov_half_inner) == 0] = 0.0
        return img, fov, np.array([x0, y0], float)

    def _self_similarity(self, kf: _Keyframe) -> float:
        """How well keyframe ``kf``'s band-passed target window matches its own surroundings (the
        keyframe's region, half resolution) more than a quarter window away from itself: a window
        whose texture is one edge (a rim, a fold) or repeats matches there too, and a dense search
        of the whole frame would find another place along that edge as readily as the target
        (coffee `lighting`: a window on a cup's rim re-acquired 82 px along the rim)."""
        if kf.self_ncc is None:
            bp, valid = self._kf_band(kf)
            img = _halved(np.where(valid > 0, bp, np.float32(0.0)))
            half = int(round(0.25 * self._window))
            t = np.round(0.5 * (kf.target - kf.view.to_frame[:2, 2])).astype(int)
            h, w = img.shape
            if not (half <= t[0] < w - half and half <= t[1] < h - half):
                kf.self_ncc = 0.0
                return kf.self_ncc
            tpl = img[t[1] - half:t[1] + half + 1, t[0] - half:t[0] + half + 1]
            score = cv2.matchTemplate(img, tpl, cv2.TM_CCOEFF_NORMED)
            cv2.circle(score, (int(t[0] - half), int(t[1] - half)), max(3, half // 2), -2.0, -1)
            kf.self_ncc = float(score.max())
        return kf.self_ncc

    def _dense_search(self, frame: np.ndarray) -> tuple[np.ndarray, _Keyframe, float, bool, np.ndarray] | None:
        """Best place (frame px) of the keyframes' dense templates in the whole frame (half
        resolution, refined at full resolution), with its keyframe, correlation, whether it is
        strong, and the view similarity its template was resampled to, if it stands out:
        correlation >= ``dense_reacquire_ncc`` and ``dense_streak_lead`` times that of any other
        place (strong: ``dense_reacquire_lead`` times). Glints are filled smoothly before
        band-passing, so a glint (which stays put in the image while the tissue moves) cannot be
        matched. The best place found, standing out or not, is left in ``_dense_seed`` (half
        resolution, else quarter: the finest searched) for a seeded local re-lock (see _update)."""
        s = self.settings
        self._dense_seed = None
        if self._dense_tpl is None:
            kfs = [self._anchor] + [k for k in self._recent if k.sharp][-1:]
            self._dense_tpl = []
            views = [self._from_anchor]
            if self._central_offset() is not None:
                # lost near the edge, where the distortion shrank the tracked scale: the target may
                # come back at either scale (still compressed at the edge, as it was near the centre)
                views.append(self._central_from_anchor)
            for view_sim in views:
                anchor = None
                for kf in dict.fromkeys(kfs):  # unique, in order
                    small, full = self._dense_template(kf, 0.5, view_sim), self._dense_template(kf, 1.0, view_sim)
                    if kf is self._anchor:
                        anchor = full
                    # too weak a texture to tell the target from anything else (band-passed std < 1.5 of 40)
                    if small is None or full is None or full[1] < 2.25 or self._self_similarity(kf) >= s.dense_unique_ncc:
                        continue
                    # A later keyframe's window with much more texture than the selection's that does
                    # not look like it (both seen at the view's scale and rotation) holds something new
                    # and strong: an instrument's edge coming over the target (its outline then
                    # dominates a weak template, and the search finds the instrument: seed 3's retina
                    # `occlusion`, 2.5x the energy, correlation 0.15, re-locked 160 px off on it). A
                    # sharp view of a blurred selection has more texture too, but correlates with it
                    # (0.65, seed 4's retina `blur`); a view near the edge of the field of view
                    # (`leave`) correlates little (-0.1-0.4) but has no more texture.
                    if kf is not self._anchor and anchor is not None and full[1] > s.dense_energy_ratio * anchor[1] \
                            and _masked_ncc(anchor[0], full[0]) < s.dense_agree_ncc:
                        continue
                    self._dense_tpl.append((kf, _SpectralTemplate(small[0]), full[0],
                                            _SpectralTemplate(_halved(small[0])), view_sim))
        if not self._dense_tpl:
            return None
        img, fov, origin = self._dense_image(frame)
        tpls = self._dense_tpl
        seed = None  # (place px, correlation) of the best peak at the finest resolution searched
        if s.dense_presearch:
            # Pre-search at quarter resolution (a third of a template's cost): a template that
            # stands out nowhere there is not searched at half resolution, whose search alone
            # decides what is a candidate (a coarse score would let wrong places lead: the lead
            # test needs the fine second best). At quarter resolution the fine texture that makes
            # the target lead is partly gone: on 962 lost frames of 18 loss-heavy photograph
            # sequences the candidates correlated >= 0.58 and led >= 1.78 there, but a mucosa
            # candidate leading 1.9 at half resolution led only 1.29; 73 % of the template
            # searches are skipped.
            img_q = _halved(img)
            if self._fov_quarter is None:
                self._fov_quarter = cv2.resize(fov, img_q.shape[::-1], interpolation=cv2.INTER_NEAREST)
            keep = []
            spec_q = _Spectrum(img_q)
            for t in tpls:
                hq = t[3].shape[0] // 2
                score_q = spec_q.match(t[3])
                score_q[self._fov_quarter[hq:hq + score_q.shape[0], hq:hq + score_q.shape[1]] == 0] = -1.0
                loc_q, top_q, second_q = _peaks(score_q, max(2, hq // 2))
                if seed is None or top_q > seed[1]:
                    seed = (4.0 * np.array([loc_q[0] + hq, loc_q[1] + hq], float) + 1.5 + origin, top_q)
                if top_q >= s.dense_presearch_ncc and top_q >= s.dense_presearch_lead * second_q:
                    keep.append(t)
                else:
                    self.stats["dense_presearch_skips"] += 1
            tpls = keep
        peaks = []
        spec = _Spectrum(img) if tpls else None
        for kf, small, full, _, view_sim in tpls:
            half = small.shape[0] // 2
            score = spec.match(small)
            score[fov[half:half + score.shape[0], half:half + score.shape[1]] == 0] = -1.0  # target in view only
            loc, top, second = _peaks(score, max(3, half // 2))
            peaks.append((2.0 * np.array([loc[0] + half, loc[1] + half], float) + 0.5 + origin, kf, top, second, full,
                          view_sim))
        if peaks:
            seed = max(((p[0], p[2]) for p in peaks), key=lambda q: q[1])
        self._dense_seed = None if seed is None else seed[0]
        at_anchor = [p for p, kf, *_ in peaks if kf is self._anchor]
        best = None
        for p, kf, top, second, full, view_sim in peaks:
            strong = top >= s.dense_reacquire_lead * second
            # A weak candidate (dense_streak_lead) of a later keyframe only where the selection's own
            # template peaks too: a later keyframe may hold an instrument's edge, which leads a little,
            # steadily, where the instrument goes (seed 2's coffee `occlusion`: 0.55 leading 1.4 on six
            # consecutive frames, 185 px from the target and from the selection's peak).
            weak = top >= s.dense_streak_lead * second and (
                kf is self._anchor or s.dense_streak_any_keyframe
                or any(np.hypot(*(p - q)) <= s.dense_agree_px for q in at_anchor))
            if top >= s.dense_reacquire_ncc and (strong or weak) and (best is None or top > best[2]):
                best = (p, kf, top, full, strong, view_sim)
        if best is None:
            return None
        p0, kf, top, full, strong, view_sim = best
        # Full resolution, within a few px of the half-resolution peak.
        base = self._crop(frame, p0)
        band = _band(base.gray, *self._BAND_FULL)
        if kf is not self._anchor and s.dense_anchor_ncc > -1.0:
            # A later keyframe's candidate must look like the selection too: a keyframe made as an
            # instrument's tip entered its window holds the tip's outline, which the energy rule above
            # misses on a window of strong texture, and its template finds the instrument wherever it
            # goes (held-out seed 15's retina `occlusion`: 0.94 leading 1.74, 146 px from the covered
            # target, where the selection's window correlated 0.05; re-locked there and reported 54-192 px
            # off on 34 frames). Seeds 0-20: that sequence 0.45 -> 0.69 tracked, no other false lock
            # gained or lost; one `leave` frame each on seeds 0 and 4 re-locks a frame later.
            anchor = self._dense_template(self._anchor, 1.0, view_sim)
            agree = _match_around(band, anchor[0], p0 - base.to_frame[:2, 2], 4) if anchor is not None else None
            if agree is not None and agree[1] < s.dense_anchor_ncc:
                self.stats["dense_anchor_disagrees"] += 1
                return None
        fine = _match_around(band, full, p0 - base.to_frame[:2, 2], 4)
        if fine is None or fine[1] < s.dense_reacquire_ncc:
            # The finest texture is gone (motion blur): the half-resolution place stands (the
            # confirmation on the next frame and the keyframe's refinement follow).
            return p0, kf, top, strong, view_sim
        return fine[0] + base.to_frame[:2, 2], kf, min(top, fine[1]), strong, view_sim

    def _reacquire_dense(self, frame: np.ndarray) -> TrackResult | None:
        """Dense re-acquisition: a candidate from :meth:`_dense_search` is accepted on the next frame
        that finds it again where the tissue around it went (the candidate's own band-passed
        surroundings followed by correlation): one good-looking frame is not enough."""
        s = self.settings
        cand, self._cand = self._cand, None
        # A strong candidate must lead every other place strongly again on the next frame, where the
        # tissue around it went: a lower lead there (1.3 was tried) confirmed a wrong place of the
        # fundus that led 1.70 and then 1.52 (seed 3's retina `leave`, target out of view), as often
        # as it confirmed the target. Weaker leads need a longer streak (dense_streak_frames).
        found = self._dense_search(frame)
        if found is None:
            return None
        p, kf, top, strong, view_sim = found
        streak = 1
        view = self._crop(frame, p)
        img = _band(view.gray, *self._BAND_FULL)
        half = int(round(0.5 * self._window))
        if cand is not None:
            q, patch, cand_streak, cand_strong = cand
            # where the tissue around the previous candidate went (at most a jump away)
            r = int(min(s.max_jump_px * self._steps, s.search_margin_px))
            again = _match_around(img, patch, q - view.to_frame[:2, 2], r)
            followed = again is not None and again[1] >= s.dense_reacquire_ncc and \
                np.hypot(*(again[0] + view.to_frame[:2, 2] - p)) <= s.dense_confirm_px
            if followed:
                streak = cand_streak + 1
            # Accepted after two strong frames, or after a streak of weaker ones: a target coming back
            # through the distorted, dim edge of the view and blurred by its motion leads its
            # surroundings by only 1.3-1.7 for many frames (seed 0's retina `leave`: the top place,
            # within 5 px of the target, on every search of frames 48-54, strong on one of them,
            # re-locked by ORB at frame 64), while a wrong place that once leads strongly rarely
            # keeps the lead on several consecutive frames.
            if followed and ((cand_strong and strong) or streak >= s.dense_streak_frames):
                rel = _similarity(view_sim @ _inv(kf.from_anchor), kf.target)
                key_to_cur = rel.copy()
                key_to_cur[:2, 2] += p - _apply(rel, kf.target)
                # Refined like a tracked frame: the keyframe's corners (affine: follows the lens
                # distortion), else its dense window (ECC); the template's place is only a seed.
                # Without either (too weak a texture), the template's place is followed but not
                # reported until the next frame tracks it (near the edge of the view the lens
                # distortion deforms the template: its place may be several px off).
                km, _, kdst, wv = self._match_keyframe(view, kf, key_to_cur)
                dense = self._match_dense(kf, key_to_cur, wv) if km is None else None
                if km is not None:
                    key_to_cur = km[0]
                elif dense is not None:
                    key_to_cur = dense[0]
                p_ref = _apply(key_to_cur, kf.target)
                if np.hypot(*(p_ref - p)) > s.dense_confirm_px + 4.0 or not self._in_view(p_ref):
                    return None
                p = p_ref
                key_to_cur = _similarity(key_to_cur, kf.target)
                pts = self._features(view, p, 0.5 * self._window, 0.1 * s.feature_quality)
                # the target's own patch must look like the keyframe's (as on every tracked frame)
                ncc, _, _ = self._patch_similarity(view, kf, key_to_cur)
                if ncc < s.patch_reject_ncc:
                    return None
                self.stats["dense_reacquisitions"] += 1
                res = self._relocked(p, kf, key_to_cur, view, pts, 0.5 * top)
                if km is None and dense is None:  # tentative: reported once the next frame tracks
                    # it, lost again at its first miss
                    self._misses = s.max_misses
                    return TrackResult(np.full(2, np.nan), 0.0, False, True)
                return res
        c = np.round(p - view.to_frame[:2, 2]).astype(int)
        if half <= c[0] < img.shape[1] - half and half <= c[1] < img.shape[0] - half:
            self._cand = p, img[c[1] - half:c[1] + half + 1, c[0] - half:c[0] + half + 1].copy(), streak, strong
        return None

    def _seeded_relock(self, frame: np.ndarray, seed: np.ndarray | None, reach: float) -> TrackResult | None:
        """The local keyframe re-lock around ``seed`` (px), if it lies within ``reach`` px of where the
        target was last seen but more than 8 px away (nearer, the re-lock at the last position tries the
        same), and a quarter window inside the view: at its edge the lens distortion bends a keyframe
        made nearer the centre (seed 6's `leave` at 160 px: re-locked 6.7 px off, 8.3 px a few frames
        later); the target is found further in."""
        if seed is None or not 8.0 < np.hypot(*(seed - self._pos)) <= reach or not self._in_view(seed, inner=True):
            return None
        self.stats["seeded_relocks"] += 1
        return self._track(frame, relock=True, seed=seed)

    def _local_seed(self, frame: np.ndarray) -> np.ndarray | None:
        """Where (px) the selection keyframe's band-passed target window, at the view's last scale and
        rotation, correlates best within ``local_seed_px`` of the last position (and the region around
        it), if at least ``dense_reacquire_ncc``."""
        # Highlights left out with only a few px of their halo: a window strewn with small glints
        # (seed 5's mucosa `occlusion`) keeps nothing beyond the whole halo, and this is only a seed.
        def usable(v: _View) -> np.ndarray:  # uint8, 255: in view and 2 px clear of highlights
            return cv2.bitwise_and(v.fov, cv2.bitwise_not(cv2.dilate(v.sat.view(np.uint8), np.ones((5, 5), np.uint8)) * 255))

        made = self._dense_template(self._anchor, 1.0, self._from_anchor, usable(self._anchor.view))
        if made is None:
            return None
        tpl = made[0]
        view = self._crop(frame, self._pos)
        img = _band(view.gray, *self._BAND_FULL)
        img[usable(view) == 0] = 0.0
        r = min((min(img.shape) - tpl.shape[0]) // 2 - 1, int(self.settings.local_seed_px))
        found = _match_around(img, tpl, self._pos - view.to_frame[:2, 2], r) if r > 0 else None
        if found is None or found[1] < self.settings.dense_reacquire_ncc:
            return None
        return found[0] + view.to_frame[:2, 2]

    def _central_offset(self) -> tuple[float, float] | None:
        """Scale and rotation (rad) from the last accepted frame's view to the one when the target was
        last near the view's centre, when they differ by more than 10 % or 10 degrees (lost near the
        edge, where the lens distortion shrinks the tracked scale); else None."""
        sc, ang = _scale_angle(self._central_from_anchor @ _inv(self._from_anchor))
        return (sc, ang) if abs(math.log(sc)) > math.log(1.1) or abs(ang) > math.radians(10.0) else None

    def _relock_views(self, anchor_to_pred: np.ndarray, pred: np.ndarray) -> list[np.ndarray]:
        """The anchor -> this frame transforms a re-lock around ``pred`` (px) tries: when the view's
        scale or rotation at the loss differ from the central ones (:meth:`_central_offset`), first
        the one the lens distortion gives at ``pred``'s distance from the view's centre, interpolated
        (log-scale and angle, linearly in that distance) between the central one and the one at the
        loss, then the last accepted frame's (``anchor_to_pred``: its scale and rotation moved to
        ``pred``). A target lost at the edge of the view, where the distortion had shrunk it, comes
        back towards the centre growing to the scale it had there: the keyframe's corners predicted at
        the edge's scale (0.66 on seed 1's retina `leave`) do not follow (0-1 of 40, the place right to
        0.5 px), at the central scale 8-12 of them do. The central scale further out, where it is as
        wrong the other way, re-locked a large window 7.8 px off (seed 6's mucosa `leave` at 160 px;
        the edge's scale re-locks it 4 frames later within 3.6 px), and a large window's match bent by
        the distortion across it still re-locked 7.6 px off with the interpolated scale: not for a large
        window, and only a quarter window inside the view."""
        s = self.settings
        offset = self._central_offset() if s.relock_central and self._window < s.large_window_px \
            and self._in_view(pred, inner=True) else None
        if offset is None:
            return [anchor_to_pred]
        at_loss = float(np.hypot(*(self._pos - self._fov_centre)))
        r = float(np.hypot(*(pred - self._fov_centre)))
        k = float(np.clip((at_loss - r) / max(at_loss - self._central_at, 1.0), 0.0, 1.0))  # 1: central
        if k < 0.1:
            return [anchor_to_pred]
        sc, ang = offset
        c, sn = sc ** k * math.cos(k * ang), sc ** k * math.sin(k * ang)
        there = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]]) @ self._from_anchor
        there[:2, 2] += pred - _apply(there, self._anchor.target)
        return [there, anchor_to_pred]

    def _set_from_anchor(self, from_anchor: np.ndarray, est: np.ndarray) -> None:
        """Accept ``from_anchor`` (anchor -> this frame) for the target at ``est`` (px); also as the
        central one (:attr:`TrackerSettings.dense_central_radius`) when ``est`` is near the view's centre."""
        self._from_anchor = from_anchor
        if np.hypot(*(est - self._fov_centre)) <= self.settings.dense_central_radius * self._fov_radius:
            self._central_from_anchor = from_anchor
            self._central_at = float(np.hypot(*(est - self._fov_centre)))

    def _relocked(self, est: np.ndarray, kf: _Keyframe, key_to_cur: np.ndarray, view: _View, pts: np.ndarray,
                  conf: float) -> TrackResult:
        """Accept a whole-frame re-acquisition: the target at ``est`` (px), matched to keyframe ``kf``
        by the similarity ``key_to_cur``; ``pts`` (px) are the features to follow from ``view``."""
        if len(pts) < self.settings.max_features // 2:
            extra = self._features(view, est, 0.5 * self._window)
            pts = np.vstack([pts, extra]) if len(extra) else pts
        self._pos = est
        self._vel = np.zeros(2)
        self._vel_known = False
        self._misses = 0
        self.lost = False
        self._set_from_anchor(key_to_cur @ kf.from_anchor, est)
        self._key = kf
        self._prev = view
        self._prev_pts = np.asarray(pts, np.float32).reshape(-1, 2)
        self.stats["reacquisitions"] += 1
        return TrackResult(est.copy(), float(conf), True, False)


# ------------------------------------------------------------------------------ marker tracker
@dataclass(frozen=True)
class MarkerSettings:
    """Settings of :class:`MarkerTracker`."""
    dictionary: str = param("DICT_4X4_50", choices=ARUCO_DICTIONARIES, doc="ArUco dictionary of the marker")
    marker_id: int = param(-1, lo=-1, hi=10000, doc="marker to follow; -1: the one at the selected point")
    max_misses: int = param(4, lo=0, hi=10000, doc="consecutive frames without the marker before it is lost")
    search_margin_px: float = param(40.0, unit="px", lo=0.0, hi=2000.0, doc="margin of the search region around the marker")
    max_jump_px: float = param(60.0, unit="px", lo=1.0, hi=2000.0, doc="largest distance from the prediction")


class MarkerTracker(Tracker):
    """ArUco marker tracker; the target is a fixed point in marker coordinates."""

    # Marker coordinates: side = 1, centre (0, 0), x right, y down; corners in ArUco order.
    _UNIT = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]], np.float32)

    def __init__(self, settings: MarkerSettings | None = None, camera: CameraParams | None = None) -> None:
        """``camera``: intrinsics with lens distortion; when given, the marker's corners are
        undistorted before the marker-to-image homography is fitted, so a point inside a large
        marker near the edge of a distorting lens is placed correctly (else: plain homography)."""
        self.settings = validate(settings or MarkerSettings())
        self.camera = camera
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        params.cornerRefinementWinSize = 4
        params.cornerRefinementMinAccuracy = 0.01
        params.cornerRefinementMaxIterations = 50
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.settings.dictionary))
        self._det = cv2.aruco.ArucoDetector(d, params)
        self._id = None
        self._pos = np.full(2, np.nan)
        self._vel = np.zeros(2)
        self._size = 0.0
        self._misses = 0
        self.lost = True
        self._clock = FrameClock()

    def _detect(self, frame: np.ndarray, roi=None) -> dict[int, np.ndarray]:
        if roi is None:
            crop, off = frame, np.zeros(2)
        else:
            x0, y0, x1, y1 = roi
            crop, off = frame[y0:y1, x0:x1], np.array([x0, y0], float)
        gray = cv2.cvtColor(crop, cv2.COLOR_BGR2GRAY) if crop.ndim == 3 else crop
        corners, ids, _ = self._det.detectMarkers(gray)
        if ids is None:
            return {}
        return {int(i): c.reshape(4, 2).astype(float) + off for i, c in zip(ids.ravel(), corners)}

    def _undistorted(self, px: np.ndarray) -> np.ndarray:
        """Pixels -> undistorted pinhole pixels (identity without a camera)."""
        cam = self.camera
        if cam is None or not (cam.k1 or cam.k2):
            return np.asarray(px, float)
        ray = unproject(np.asarray(px, float), 1.0, cam)
        return project(ray, cam, distort=False)

    def _distorted(self, px: np.ndarray) -> np.ndarray:
        cam = self.camera
        if cam is None or not (cam.k1 or cam.k2):
            return np.asarray(px, float)
        ray = unproject(np.asarray(px, float), 1.0, cam, distort=False)
        return project(ray, cam)

    def _point(self, corners: np.ndarray) -> np.ndarray:
        h = cv2.getPerspectiveTransform(self._UNIT, self._undistorted(corners).astype(np.float32))
        p = cv2.perspectiveTransform(self._offset.reshape(1, 1, 2), h).reshape(2).astype(float)
        return self._distorted(p)

    @property
    def footprint_px(self) -> float | None:
        # the marker search's region about the prediction (see update)
        if self.lost or self._id is None:
            return None
        return self._size + self.settings.search_margin_px + float(np.hypot(*self._vel))

    def fresh(self) -> "MarkerTracker":
        return MarkerTracker(self.settings, self.camera)

    def select(self, frame_bgr: np.ndarray, point_px, window_px: int) -> bool:
        p = np.asarray(point_px, float).reshape(2)
        found = self._detect(frame_bgr)
        self.lost = True
        self.failure = None
        self._clock.reset()
        if self.settings.marker_id >= 0:
            found = {k: v for k, v in found.items() if k == self.settings.marker_id}
        if not found:
            self.failure = ("no ArUco marker found" if self.settings.marker_id < 0
                            else f"marker {self.settings.marker_id} not found")
            return False
        # The marker containing the point, else the nearest centre within the window.
        def dist(c):
            inside = cv2.pointPolygonTest(c.astype(np.float32).reshape(-1, 1, 2), (float(p[0]), float(p[1])), True)
            return -inside if inside >= 0 else np.hypot(*(c.mean(0) - p))
        mid, corners = min(found.items(), key=lambda kv: dist(kv[1]))
        if cv2.pointPolygonTest(corners.astype(np.float32).reshape(-1, 1, 2), (float(p[0]), float(p[1])), False) < 0 \
                and np.hypot(*(corners.mean(0) - p)) > window_px:
            self.failure = f"no marker within {window_px} px of the point"
            return False
        hinv = cv2.getPerspectiveTransform(self._undistorted(corners).astype(np.float32), self._UNIT)
        self._offset = cv2.perspectiveTransform(self._undistorted(p).reshape(1, 1, 2).astype(np.float32),
                                                hinv).reshape(2)
        self._id = mid
        self._pos = p.copy()
        self._vel = np.zeros(2)
        self._size = float(np.sqrt(cv2.contourArea(corners.astype(np.float32))))
        self._misses = 0
        self.lost = False
        return True

    def update(self, frame_bgr: np.ndarray, capture_time: float | None = None) -> TrackResult:
        s = self.settings
        if self._id is None:
            return TrackResult(np.full(2, np.nan), 0.0, False, True)
        steps = self._clock.tick(capture_time)
        corners = None
        vel = self._vel * steps  # px per typical frame interval, over the real interval
        if not self.lost:
            pred = self._pos + vel
            half = self._size + s.search_margin_px + float(np.hypot(*vel))
            h, w = frame_bgr.shape[:2]
            roi = (int(max(0, pred[0] - half)), int(max(0, pred[1] - half)),
                   int(min(w, pred[0] + half + 1)), int(min(h, pred[1] + half + 1)))
            if roi[2] - roi[0] > 16 and roi[3] - roi[1] > 16:
                corners = self._detect(frame_bgr, roi).get(self._id)
        if corners is None:
            corners = self._detect(frame_bgr).get(self._id)
        if corners is not None:
            est = self._point(corners)
            pred = self._pos + vel
            if self.lost or np.hypot(*(est - pred)) <= s.max_jump_px * steps:
                self._vel = (est - self._pos) / steps if (not self.lost and self._misses == 0) else np.zeros(2)
                self._pos = est
                self._size = float(np.sqrt(cv2.contourArea(corners.astype(np.float32))))
                self._misses = 0
                self.lost = False
                return TrackResult(est.copy(), 1.0, True, False)
        self._misses += 1
        self._vel[:] = 0.0
        if self._misses > s.max_misses:
            self.lost = True
            return TrackResult(np.full(2, np.nan), 0.0, False, True)
        return TrackResult(self._pos.copy(), 0.0, False, False)


def make_tracker(kind: str = "feature", settings=None, camera: CameraParams | None = None) -> Tracker:
    """A tracker by name: ``"feature"`` (:class:`FeatureTracker`) or ``"marker"`` (:class:`MarkerTracker`,
    which uses ``camera``'s lens distortion when given)."""
    if kind == "feature":
        return FeatureTracker(settings)
    if kind == "marker":
        return MarkerTracker(settings, camera)
    raise ValueError(f"tracker kind = {kind!r}; allowed: 'feature', 'marker'")
