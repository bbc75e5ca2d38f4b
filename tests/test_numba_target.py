"""The numba kernels are compiled for one x86-64 level, so the renderer's frames (fastmath kernels)
and everything measured on them are the same on every machine of that level."""
import hashlib
import os
import subprocess
import sys

import pytest

import targetlock

V3 = targetlock._has_x86_64_v3()


def _cpu_name(env: dict) -> str:
    code = "import os, targetlock; print(os.environ.get('NUMBA_CPU_NAME', 'host'))"
    env = {k: v for k, v in {**os.environ, **env}.items() if v is not None}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return out.stdout.strip()


@pytest.mark.skipif(not V3, reason="not an x86-64-v3 machine")
def test_importing_targetlock_pins_numba_to_x86_64_v3_unless_the_user_chose():
    assert _cpu_name({"NUMBA_CPU_NAME": None}) == "x86-64-v3"
    assert _cpu_name({"NUMBA_CPU_NAME": "generic"}) == "generic"


@pytest.mark.skipif(not V3, reason="the checksum is of frames rendered for x86-64-v3")
def test_rendered_frames_are_the_same_on_every_x86_64_v3_machine():
    """Checksum of the first frames of a rendered sequence. On an Intel Emerald Rapids (AVX-512) the
    kernels compiled for x86-64-v3, haswell or znver2 all give these frames (those the vision tests
    were recorded on, on an earlier machine); compiled for the host itself (``emeraldrapids``) they
    differ. A deliberate change of the renderer changes this checksum: record the new one."""
    from targetlock.vision import PlanarTarget, RenderSettings
    from targetlock.vision.evaluate import EvalSettings, render_sequence
    target = PlanarTarget.mucosa(seed=6, texture_px=RenderSettings().texture_px)
    h = hashlib.md5()
    for f in render_sequence("leave", EvalSettings(photos=()), seed=6, target=target)[:12]:
        h.update(f.image.tobytes())
    assert h.hexdigest() == CHECKSUM


CHECKSUM = "eff0c08c3536e24d3833433dce0ff2bf"
