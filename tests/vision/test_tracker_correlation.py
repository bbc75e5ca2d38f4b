"""The feature tracker's spectral template correlation (the lost state's whole-frame dense search):
the template spectra and the image's spectrum are made once and reused, and must score as
``cv2.matchTemplate(..., TM_CCOEFF_NORMED)`` does."""
import cv2
import numpy as np

from targetlock.vision.tracker import _Spectrum, _SpectralTemplate


def _band_image(shape, seed=0):
    rng = np.random.default_rng(seed)
    f = rng.normal(0.0, 40.0, shape).astype(np.float32)
    return cv2.GaussianBlur(f, (0, 0), 1.0) - cv2.GaussianBlur(f, (0, 0), 6.0)


def test_cached_spectra_score_as_match_template():
    img = _band_image((144, 162))
    img[:, 120:] = 0.0  # a zeroed part (field-of-view edge, highlights), where windows reach into it
    tpls = [img[30:51, 40 + 7 * k:61 + 7 * k] + np.float32(k) for k in range(3)]  # an offset does not matter
    spec = _Spectrum(img)
    stpls = [_SpectralTemplate(t) for t in tpls]
    for _ in range(2):  # the second round reuses every cached spectrum and window statistic
        for t, st in zip(tpls, stpls):
            ref = cv2.matchTemplate(img, t, cv2.TM_CCOEFF_NORMED)
            got = spec.match(st)
            assert got.shape == ref.shape and got.dtype == np.float32
            inside = slice(None), slice(0, 120 - 21)  # windows with content
            assert np.abs(got[inside] - ref[inside]).max() < 1e-5
            assert np.unravel_index(np.argmax(got), got.shape) == np.unravel_index(np.argmax(ref), ref.shape)
    # a second image with the same templates (their spectra cached) scores like a fresh template
    img2 = _band_image((144, 162), seed=1)
    assert np.abs(_Spectrum(img2).match(stpls[0]) - _Spectrum(img2).match(_SpectralTemplate(tpls[0]))).max() == 0.0


def test_windows_without_content_score_zero():
    img = _band_image((100, 120))
    img[:, :60] = 0.0
    got = _Spectrum(img).match(_SpectralTemplate(_band_image((21, 21), seed=2)))
    # a window entirely in the zeroed part has no defined correlation: 0 (not round-off)
    assert np.all(got[:, :60 - 21 + 1] == 0.0)
    assert np.abs(got).max() <= 1.0
