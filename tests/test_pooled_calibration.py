"""Calibration of the shared standard errors of a pooled fit (``estim.fitting._pooled``):
a module of its own, so that under pytest-xdist it runs beside the rest of
``tests/test_pooled.py`` rather than after it."""

from __future__ import annotations

import pytest
from test_pooled import DROP_AIR, drops

import estim
from estim.fitting._pooled import fit_clips


@pytest.mark.slow
def test_shared_standard_errors_are_calibrated():
    """20 repeats of 30 clips in air with known shared e = 0.85 and C_d = 0.5 (per-clip
    release states from 0.3-0.6 m, 0.7 s at 50 Hz, 1 mm noise), all in one program (a group
    per repeat): the truth lies inside the 95% interval in 17 to 20 of the 20 repeats, for
    both."""
    scene = estim.load_scene(DROP_AIR)
    clips = []
    for r in range(20):
        clips += drops(scene, 0.85, 30, 100 + r, rate=50.0, span=0.7, heights=(0.3, 0.6), group=f"r{r}")[0]
    res = fit_clips(scene, clips, shared=("e", "drag_coefficient"), restarts=0, steps=15, joint_steps=20,
                    per_clip=False)
    assert len(res.shared) == 20
    _assert_covered(res)


@pytest.mark.slow
def test_shared_standard_errors_are_calibrated_with_few_clips():
    """As above with 8 clips per repeat (as few as a person films of one ball on one floor)
    and the clips' own estimates (the default): the truth inside the 95% interval in 17 to
    20 of the 20 repeats, for both. (With the IRLS weights as the bread of the sandwich
    and in the noise estimate, the standard errors came out 20% small: 17 of 20, rms z 1.25.)"""
    scene = estim.load_scene(DROP_AIR)
    clips = []
    for r in range(20):
        clips += drops(scene, 0.85, 8, 100 + r, rate=50.0, span=0.7, heights=(0.3, 0.6), group=f"r{r}")[0]
    res = fit_clips(scene, clips, shared=("e", "drag_coefficient"), restarts=0, steps=15, joint_steps=20)
    assert len(res.shared) == 20
    _assert_covered(res)


def _assert_covered(res):
    for name, true in (("e", 0.85), ("drag_coefficient", 0.5)):
        inside = sum(abs(sf.values[name] - true) < 1.96 * sf.stderr[name] for sf in res.shared.values())
        assert 17 <= inside <= 20, (name, inside, [(sf.values[name], sf.stderr[name]) for sf in res.shared.values()])
