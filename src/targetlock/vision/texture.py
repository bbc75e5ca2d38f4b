"""Procedural target textures: a mucosa-like surface, an ArUco marker patch and a calibration dot.

Every texture is generated deterministically from a seed (no image files, so no licence
questions). A texture is an (N, N, 4) uint8 array: B, G, R colour and a **height** channel
(0..255) that the renderer turns into surface slopes for specular highlights; height 0 marks
matte material (no highlights, e.g. a printed marker), glossiness ramps up to full at 16. Texel (u, v) has
its centre at integer coordinates, u to the right, v down (OpenCV convention).
"""
from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

_log = logging.getLogger(__name__)

__all__ = ["mucosa_texture", "aruco_texture", "add_dot", "with_height", "ARUCO_DICTIONARIES", "texture_cache_dir",
           "photo_texture", "PHOTOS"]

ARUCO_DICTIONARIES = ("DICT_4X4_50", "DICT_5X5_50", "DICT_6X6_50", "DICT_APRILTAG_36h11")


def _value_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Smooth noise in [0, 1]: a ``cells`` x ``cells`` random grid interpolated to ``size`` px."""
    grid = rng.random((cells + 3, cells + 3)).astype(np.float32)
    work = min(size, 16 * cells)  # coarse noise is computed small, then upsampled
    big = cv2.resize(grid, (work + 3 * work // cells,) * 2, interpolation=cv2.INTER_CUBIC)
    off = work // cells  # drop the border cells, whose cubic interpolation is one-sided
    out = big[off:off + work, off:off + work]
    return out if work == size else cv2.resize(out, (size, size), interpolation=cv2.INTER_LINEAR)


def _fractal(rng: np.random.Generator, size: int, cells: tuple[int, ...], persistence: float) -> np.ndarray:
    out = np.zeros((size, size), np.float32)
    amp, total = 1.0, 0.0
    for c in cells:
        out += amp * _value_noise(rng, size, c)
        total += amp
        amp *= persistence
    out /= total
    out -= out.min()
    out /= max(float(out.max()), 1e-6)
    return out


def _vessel_layer(rng: np.random.Generator, size: int, n_trees: int, width: tuple[float, float],
                  steps: tuple[int, int], blur: float) -> np.ndarray:
    """Float mask in [0, 1] of branching, meandering vessels drawn as anti-aliased polylines."""
    scale = 16  # cv2 drawing with 4 fractional bits
    canvas = np.zeros((size, size), np.uint8)
    stack = []
    for _ in range(n_trees):
        stack.append((rng.uniform(0, size, 2), rng.uniform(0, 2 * np.pi), rng.uniform(*width), 0))
    step_len = size / 256.0
    while stack:
        start, heading, w, depth = stack.pop()
        n = int(rng.integers(*steps) / (1 + depth))
        if n < 3 or w < 0.6:
            continue
        turns = np.cumsum(rng.normal(0.0, 0.18, n)) + heading
        pts = start + np.cumsum(np.stack([np.cos(turns), np.sin(turns)], 1) * step_len, axis=0)
        pts = np.vstack([start, pts])
        cv2.polylines(canvas, [np.round(pts * scale).astype(np.int32)], False, 255,
                      thickness=max(1, int(round(w))), lineType=cv2.LINE_AA, shift=4)
        for _ in range(int(rng.integers(0, 3))):  # side branches, thinner
            k = int(rng.integers(1, n))
            stack.append((pts[k], turns[k - 1] + rng.choice([-1, 1]) * rng.uniform(0.5, 1.2),
                          w * rng.uniform(0.5, 0.8), depth + 1))
    mask = canvas.astype(np.float32) / 255.0
    if blur > 0:
        mask = cv2.GaussianBlur(mask, (0, 0), blur)
    return mask


def texture_cache_dir() -> Path | None:
    """Folder of the on-disk texture cache, or None when disabled.

    ``$TARGETLOCK_CACHE_DIR`` if set (empty or ``off``: no disk cache), else
    ``$XDG_CACHE_HOME/targetlock`` (``~/.cache/targetlock``; ``%LOCALAPPDATA%\\targetlock`` on Windows).
    """
    env = os.environ.get("TARGETLOCK_CACHE_DIR")
    if env is not None:
        return None if env.strip().lower() in ("", "off", "0", "none") else Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or (os.environ.get("LOCALAPPDATA") if os.name == "nt" else None)
    return (Path(base) if base else Path.home() / ".cache") / "targetlock"


@lru_cache(maxsize=1)
def _generator_key() -> str:
    """Changes whenever the generator or the libraries it relies on change (stale files are ignored)."""
    h = hashlib.sha256(Path(__file__).read_bytes())
    h.update(f"numpy {np.__version__} opencv {cv2.__version__}".encode())
    return h.hexdigest()[:16]


def _disk_cached(name: str, shape: tuple[int, ...], make) -> np.ndarray:
    """``make()`` through an .npy file ``name`` in :func:`texture_cache_dir` (generated once per
    machine: a 4096^2 mucosa takes seconds, loading it ~0.1 s). Any cache problem (unwritable
    folder, corrupt file) falls back to generating."""
    folder = texture_cache_dir()
    path = None if folder is None else folder / f"{name}-{_generator_key()}.npy"
    if path is not None and path.is_file():
        try:
            arr = np.load(path, allow_pickle=False)
            if arr.shape == shape and arr.dtype == np.uint8:
                return arr
            _log.warning("texture cache %s has the wrong shape; regenerating", path)
        except (OSError, ValueError) as exc:
            _log.warning("texture cache %s unreadable (%s); regenerating", path, exc)
    arr = make()
    if path is not None:
        tmp = None
        try:
            folder.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=folder, suffix=".tmp")
            with os.fdopen(fd, "wb") as fh:
                np.save(fh, arr, allow_pickle=False)
            os.replace(tmp, path)  # atomic: a parallel run never reads half a file
        except OSError as exc:
            _log.info("texture cache %s not written (%s)", folder, exc)
            if tmp is not None:
                Path(tmp).unlink(missing_ok=True)
    return arr


@lru_cache(maxsize=4)
def _mucosa_cached(seed: int, size: int) -> np.ndarray:
    out = _disk_cached(f"mucosa-{seed}-{size}", (size, size, 4), lambda: _mucosa_generate(seed, size))
    out.setflags(write=False)
    return out


def _mucosa_generate(seed: int, size: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    s = size / 2048.0
    low = _fractal(rng, size, (3, 6, 12), 0.6)
    mid = _fractal(rng, size, (24, 48, 96), 0.6)
    fine = _fractal(rng, size, (160, 320, 640), 0.7)
    deep = _vessel_layer(rng, size, 14, (8 * s, 16 * s), (60, 160), 6.0 * s)
    cap = _vessel_layer(rng, size, 45, (3 * s, 6 * s), (40, 140), 0.8 * s)
    cap = np.maximum(cap, _vessel_layer(rng, size, 160, (1.0 * s, 2.5 * s), (15, 60), 0.6 * s))
    # Base colour (BGR): pale pink to deeper red, driven by low-frequency noise, times mottling
    # and a fine granular surface (pit pattern); deep vessels tint bluish, capillaries red.
    pale = (120.0, 135.0, 225.0)
    red = (70.0, 80.0, 190.0)
    deep_tint = (0.3, 0.7, 0.6)
    cap_tint = (0.7, 0.9, 0.35)
    shade = (0.82 + 0.36 * mid) * (0.88 + 0.24 * fine)
    out = np.empty((size, size, 4), np.uint8)
    for c in range(3):
        ch = (pale[c] + (red[c] - pale[c]) * low) * shade
        ch *= 1.0 - (0.35 * deep_tint[c]) * deep
        ch *= 1.0 - (0.65 * cap_tint[c]) * cap
        out[..., c] = np.clip(ch, 0, 255).astype(np.uint8)
    height = 0.8 * mid + 0.12 * fine + 0.08 * cap  # smooth relief: glints form blobs, not dust
    height = (height - height.min()) / max(float(np.ptp(height)), 1e-6)
    out[..., 3] = np.clip(16.0 + height * 239.0, 0, 255).astype(np.uint8)  # >= 16: glossy everywhere
    return out


def mucosa_texture(seed: int = 0, size: int = 2048) -> np.ndarray:
    """Deterministic mucosa-like BGR+height texture (size x size x 4, uint8) for ``seed``.

    Pink-red base with low-frequency colour variation, mottling, a fine granular pattern,
    bluish deep vessels and sharp red capillaries; the height channel drives specular glints.
    The result is cached in memory and on disk (:func:`texture_cache_dir`, keyed by seed, size
    and generator version) and read-only; copy it before drawing on it.
    """
    if not 64 <= size <= 8192:
        raise ValueError(f"size = {size} px; allowed: [64, 8192] px")
    return _mucosa_cached(int(seed), int(size))


def with_height(image: np.ndarray, height: np.ndarray | None = None) -> np.ndarray:
    """BGR (or gray) image -> BGR+height texture; flat (128) height unless ``height`` is given."""
    img = np.asarray(image)
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise ValueError(f"texture must be HxW, HxWx3 or HxWx4, got shape {img.shape}")
    if img.dtype != np.uint8:
        raise ValueError(f"texture must be uint8, got {img.dtype}")
    if img.shape[2] == 4 and height is None:
        return img
    out = np.empty(img.shape[:2] + (4,), np.uint8)
    out[..., :3] = img[..., :3]
    out[..., 3] = 128 if height is None else height
    return out


def aruco_texture(marker_id: int = 0, dictionary: str = "DICT_4X4_50", size: int = 2048,
                  marker_fraction: float = 0.12, seed: int = 0) -> np.ndarray:
    """Mucosa texture with an ArUco marker (white quiet zone of one cell) at its centre.

    ``marker_fraction`` is the marker's side (black border included) as a fraction of the
    texture side, so on a plane of side ``w`` m the marker is ``marker_fraction * w`` m wide.
    """
    if dictionary not in ARUCO_DICTIONARIES:
        raise ValueError(f"dictionary = {dictionary!r}; allowed: {', '.join(ARUCO_DICTIONARIES)}")
    if not 0.01 <= marker_fraction <= 0.8:
        raise ValueError(f"marker_fraction = {marker_fraction}; allowed: [0.01, 0.8]")
    tex = mucosa_texture(seed, size).copy()
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    side = int(round(marker_fraction * size))
    cells = d.markerSize + 2
    side_cells = max(cells, side // cells * cells)  # whole texels per cell: crisp edges
    if (size - side_cells) % 2 and side_cells > cells:
        side_cells -= cells                           # odd cell count: keep the margins equal
    if (size - side_cells) % 2:
        raise ValueError(f"cannot centre a {dictionary} marker on a {size} px texture; choose another size")
    marker = cv2.aruco.generateImageMarker(d, int(marker_id), side_cells)
    q = side_cells // cells                           # quiet zone: one cell of white
    # Centre on texel position (size - 1) / 2, the plane's centre: equal margins on both sides.
    lo = (size - side_cells) // 2
    tex[lo - q:lo + side_cells + q, lo - q:lo + side_cells + q, :3] = 255
    tex[lo:lo + side_cells, lo:lo + side_cells, :3] = marker[..., None]
    tex[lo - q:lo + side_cells + q, lo - q:lo + side_cells + q, 3] = 0  # height 0: matte print
    return tex


def add_dot(texture: np.ndarray, point_m: tuple[float, float], size_m: tuple[float, float],
            radius_m: float, value: int = 255) -> np.ndarray:
    """Copy of ``texture`` with a bright Gaussian dot (sigma = ``radius_m``/2) at plane point ``point_m``.

    Plane point (x, y) in metres, origin at the plane centre, x right, y down, as used by
    :class:`~targetlock.vision.render.PlanarTarget`. Used to check the renderer's geometry.
    """
    tex = np.array(texture, copy=True)
    h, w = tex.shape[:2]
    u = (point_m[0] + size_m[0] / 2) * w / size_m[0] - 0.5
    v = (point_m[1] + size_m[1] / 2) * h / size_m[1] - 0.5
    sig = 0.5 * radius_m * w / size_m[0]
    r = int(np.ceil(4 * sig)) + 1
    u0, v0 = int(round(u)), int(round(v))
    ys, xs = np.mgrid[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1]
    g = np.exp(-((xs - u) ** 2 + (ys - v) ** 2) / (2 * sig * sig))
    patch = tex[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1, :3].astype(np.float32)
    patch = patch * (1 - g[..., None]) + value * g[..., None]
    tex[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1, :3] = np.clip(np.round(patch), 0, 255).astype(np.uint8)
    if tex.shape[2] == 4:
        tex[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1, 3] = 128
    return tex


# Real photographs shipped inside the scikit-image wheel (no download at run time), with their
# licences as scikit-image's skimage.data documents them.
PHOTOS = {
    "retina": "fundus photograph of a normal left eye, M. Haggstrom (Wikimedia Commons), CC0 1.0",
    "coffee": "cup of coffee, Rachel Michetti, CC0",
    "astronaut": "astronaut Eileen Collins, NASA Great Images, public domain",
    "chelsea": "Chelsea the cat, Stefan van der Walt, CC0",
    "rocket": "SpaceX Falcon 9 launch, SpaceX, public domain",
}


@lru_cache(maxsize=4)
def photo_texture(name: str, size: int = 2048) -> np.ndarray:
    """BGR+height texture (size x size x 4, uint8, read-only) of a real photograph from
    scikit-image's bundled data (:data:`PHOTOS`, licences there). The largest centred square is
    used (for ``retina``, the square inside the round fundus image), resized to ``size``; the
    height channel is the smoothed brightness (glints form on the bright, raised parts)."""
    if name not in PHOTOS:
        raise ValueError(f"photo = {name!r}; allowed: {', '.join(PHOTOS)}")
    if not 64 <= size <= 8192:
        raise ValueError(f"size = {size} px; allowed: [64, 8192] px")
    try:
        import skimage.data
    except ImportError as exc:  # optional: only the real-image evaluation needs it
        raise ImportError("real-image textures need scikit-image: pip install 'scikit-image>=0.22,<1'") from exc
    rgb = np.asarray(getattr(skimage.data, name)())
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[..., None], 3, axis=2)
    h, w = rgb.shape[:2]
    side = min(h, w)
    if name == "retina":  # the fundus is a disc on black: the square inscribed in it
        side = int(side * 0.68)
    y0, x0 = (h - side) // 2, (w - side) // 2
    bgr = cv2.cvtColor(np.ascontiguousarray(rgb[y0:y0 + side, x0:x0 + side, :3]), cv2.COLOR_RGB2BGR)
    bgr = cv2.resize(bgr, (size, size), interpolation=cv2.INTER_CUBIC if size > side else cv2.INTER_AREA)
    grey = cv2.GaussianBlur(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(np.float32), (0, 0), size / 256.0)
    height = 16.0 + 239.0 * (grey - grey.min()) / max(float(np.ptp(grey)), 1e-6)
    out = with_height(bgr, np.clip(height, 0, 255).astype(np.uint8))
    out.setflags(write=False)
    return out
