"""The procedural texture is cached on disk, keyed by its parameters, and survives a bad cache."""
import numpy as np

from targetlock.vision import texture


def _fresh(monkeypatch, folder):
    monkeypatch.setenv("TARGETLOCK_CACHE_DIR", str(folder))
    texture._mucosa_cached.cache_clear()


def test_texture_is_cached_on_disk_and_reloaded_identically(tmp_path, monkeypatch):
    _fresh(monkeypatch, tmp_path)
    a = texture.mucosa_texture(seed=3, size=128)
    files = list(tmp_path.glob("mucosa-3-128-*.npy"))
    assert len(files) == 1
    texture._mucosa_cached.cache_clear()
    calls = []
    monkeypatch.setattr(texture, "_mucosa_generate", lambda *a: calls.append(a))
    b = texture.mucosa_texture(seed=3, size=128)
    assert calls == []                      # loaded, not regenerated
    np.testing.assert_array_equal(a, b)
    assert not b.flags.writeable
    texture._mucosa_cached.cache_clear()


def test_other_parameters_get_their_own_file(tmp_path, monkeypatch):
    _fresh(monkeypatch, tmp_path)
    a = texture.mucosa_texture(seed=1, size=64)
    b = texture.mucosa_texture(seed=2, size=64)
    assert len(list(tmp_path.glob("mucosa-*.npy"))) == 2
    assert not np.array_equal(a, b)
    texture._mucosa_cached.cache_clear()


def test_corrupt_or_unwritable_cache_falls_back_to_generating(tmp_path, monkeypatch):
    _fresh(monkeypatch, tmp_path)
    want = texture.mucosa_texture(seed=4, size=64)
    (path,) = tmp_path.glob("mucosa-4-64-*.npy")
    path.write_bytes(b"not an array")
    texture._mucosa_cached.cache_clear()
    np.testing.assert_array_equal(texture.mucosa_texture(seed=4, size=64), want)
    blocker = tmp_path / "file"
    blocker.write_text("x")
    _fresh(monkeypatch, blocker / "sub")    # cannot be created: no cache, still a texture
    np.testing.assert_array_equal(texture.mucosa_texture(seed=4, size=64), want)
    _fresh(monkeypatch, "off")
    assert texture.texture_cache_dir() is None
    texture._mucosa_cached.cache_clear()
