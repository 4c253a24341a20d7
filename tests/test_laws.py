"""Contact laws are one object (estim.forward.laws), and the native kernels say what they run.

A second law is written here as a new class, as a user would: restitution that falls with
the impact speed, declared not summable. It runs through ``estim.simulate`` bounce by
bounce on the closed-form path and on the ODE path (vacuum and air), against bounce
sequences computed by hand from the physics (a parabola between bounces; for a vertical
drop in air with quadratic drag, the closed forms of that motion), and the native kernels
refuse it, leaving it to the JAX planner with the same results. The seed's factor law,
run bounce by bounce, gives the bounces of its own summed series. And the constants the
kernels are built with are those of ``estim/forward/_constants.py``.
"""

from __future__ import annotations

import math
import pathlib
import re

import diffrax
import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import ROOT, jax_path

import estim
from estim.forward import _constants, _native, _ode, _solver, _trajectory
from estim.forward._contact import inner
from estim.forward.laws import AbstractContactLaw, FactorLaw, law_of

G = 9.81
DROP = ROOT / "data" / "scenes" / "drop.xml"


class SpeedDependentLaw(AbstractContactLaw):
    """Restitution that falls with the impact speed s: ``e(s) = e s / (s + s0)``, so the
    rebound of an impact at s is ``e s^2 / (s + s0)``: quadratic in s once s << s0, and a
    ball comes to rest after finitely many bounces. The tangential velocity is scaled by
    mu_t. Its series have no closed form here: not summable."""

    s0: float = eqx.field(static=True, default=1.0)

    def coefficients(self, params):
        return (params.e, params.mu_t)

    def reset(self, v, n, c):
        _, mu_t = c
        vn = inner(v, n)
        return mu_t * (v - vn * n) + self.rebound(v, n, c) * n

    def rebound(self, v, n, c):
        e, _ = c
        s = -inner(v, n)
        return e * s * s / (s + self.s0)

    def settle(self, tangential, c):
        _, mu_t = c
        return tangential * jnp.where(mu_t == 1.0, 1.0, 0.0)


class BounceByBounceFactorLaw(AbstractContactLaw):
    """The seed's factor law without its closed-form series: every bounce a segment."""

    def coefficients(self, params):
        return FactorLaw().coefficients(params)

    def reset(self, v, n, c):
        return FactorLaw().reset(v, n, c)

    def rebound(self, v, n, c):
        return FactorLaw().rebound(v, n, c)

    def settle(self, tangential, c):
        return FactorLaw().settle(tangential, c)


def test_the_laws_say_what_they_are():
    assert FactorLaw().summable and not SpeedDependentLaw().summable
    scene = estim.load_scene(DROP)
    assert isinstance(law_of(scene), FactorLaw)  # the scene names none: the seed's law
    law = SpeedDependentLaw(s0=2.0)
    assert law_of(scene.with_law(law)) is law
    assert isinstance(law_of(scene.with_law("factor")), FactorLaw)  # a name, as MJCF declares it
    with pytest.raises(ValueError, match="unknown contact law 'sticky'"):
        law_of(scene.with_law("sticky"))
    with pytest.raises(TypeError, match="contact law"):
        law_of(scene.with_law(FactorLaw))  # the class, not a law


def hand_drop(h0, vx, e, mu, s0, rest=_constants.REST_SPEED):
    """The bounces of a ball dropped at rest from h0 (its centre above the contact height)
    with horizontal velocity vx on a horizontal plane in a vacuum, under
    SpeedDependentLaw, from the physics alone: impact k at speed s_k, rebound
    ``e s_k^2 / (s_k + s0)``, a flight of ``2 w / g`` to the next impact at the same speed.
    Returns (t, x, pre normal speed, post normal speed, post vx) per contact; the last
    contact's rebound is below REST_SPEED (the ball comes to rest)."""
    t, x, s, u = math.sqrt(2 * h0 / G), vx * math.sqrt(2 * h0 / G), math.sqrt(2 * h0 * G), vx
    out = []
    while True:
        w = e * s * s / (s + s0)
        u = u * mu
        out.append((t, x, s, w, u))
        if w <= rest:
            return out
        t, x, s = t + 2 * w / G, x + u * 2 * w / G, w


@pytest.mark.parametrize("path", ["closed form", "ode"])
def test_a_law_that_is_not_summable_runs_bounce_by_bounce(path):
    """The speed-dependent law on a table, on the closed-form path (every bounce a segment)
    and on the ODE path forced on the vacuum: the same contacts as the hand-computed
    sequence (times, places, speeds before and after, so the energy after each bounce),
    then the ball at rest on the table."""
    scene = estim.load_scene(DROP).with_law(SpeedDependentLaw(s0=1.0))
    r, z0, vx, e, mu = 0.02, 0.5, 0.3, 0.9, 0.8
    truth = hand_drop(z0 - r, vx, e, mu, 1.0)
    assert 6 <= len(truth) <= 12  # rebounds, then one below REST_SPEED (8 contacts)
    params = estim.Params(e, mu, r, (0.0, 0.0, z0), (vx, 0.0, 0.0))
    kw = {"solver": diffrax.Tsit5()} if path == "ode" else {}
    traj = estim.simulate(scene, params, 2.0, ts=jnp.linspace(0.0, 2.0, 41), **kw)
    ev = traj.events
    n = int(ev.count)
    assert n == len(truth)
    if path == "closed form":  # no summed series: a flight per bounce, then the rest
        kinds = np.asarray(traj.solution.structure.kind)
        assert not np.any(kinds == _constants.TRAIN)
        assert np.sum(kinds == _constants.FLIGHT) == len(truth)
    # Flights are parabolas, which the RK steps integrate to rounding: the same tolerance.
    tol = 1e-12 if path == "closed form" else 1e-9
    t, x, pre, post, u = (np.array(c) for c in zip(*truth, strict=True))
    np.testing.assert_allclose(ev.t[:n], t, rtol=tol, atol=tol)
    np.testing.assert_allclose(ev.position[:n, 0], x, rtol=tol, atol=tol)
    np.testing.assert_allclose(ev.position[:n, 2], r, atol=tol)
    np.testing.assert_allclose(-ev.velocity_pre[:n, 2], pre, rtol=tol, atol=tol)
    # After the last impact the ball rests: the law's settle drops the tangential velocity
    # (mu_t < 1), and the rebound below REST_SPEED is no flight.
    post_v = np.where(np.arange(n) < n - 1, post, 0.0)
    post_u = np.where(np.arange(n) < n - 1, u, 0.0)
    np.testing.assert_allclose(ev.velocity_post[:n, 2], post_v, rtol=tol, atol=tol)
    np.testing.assert_allclose(ev.velocity_post[:n, 0], post_u, rtol=tol, atol=tol)
    energy = 0.5 * np.sum(np.asarray(ev.velocity_post[:n]) ** 2, axis=1)
    np.testing.assert_allclose(energy, 0.5 * (post_v**2 + post_u**2), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(traj.final.position, [x[-1], 0.0, r], atol=tol)
    np.testing.assert_allclose(traj.final.velocity, 0.0, atol=tol)


def air_drop(h0, e, s0, vt, n):
    """The first n contacts of a ball dropped at rest from h0 on a horizontal face in air
    with quadratic drag only (``a = -g - (g / vt^2) |v| v``, vt the terminal speed), under
    SpeedDependentLaw: closed forms of the vertical motion. Falling from rest through H
    takes ``(vt / g) acosh(exp(g H / vt^2))`` and ends at ``vt sqrt(1 - exp(-2 g H / vt^2))``;
    rising at u reaches ``H = (vt^2 / 2g) log(1 + u^2 / vt^2)`` after ``(vt / g) atan(u / vt)``.
    Returns (t, pre speed, post speed) per contact."""

    def fall(height):  # (acosh(1 + y) = log1p(y + sqrt(y (y + 2))), accurate for small y)
        y = math.expm1(G * height / vt**2)
        return vt / G * math.log1p(y + math.sqrt(y * (y + 2))), vt * math.sqrt(-math.expm1(-2 * G * height / vt**2))

    t, s = fall(h0)
    out = []
    for _ in range(n):
        w = e * s * s / (s + s0)
        out.append((t, s, w))
        height = vt**2 / (2 * G) * math.log1p(w * w / vt**2)
        t_fall, s = fall(height)
        t = t + vt / G * math.atan(w / vt) + t_fall
    return out


def test_a_law_that_is_not_summable_runs_on_the_ode_path_in_air():
    """A ping-pong ball dropped on a table through air with quadratic drag (no viscosity,
    no spin: no Magnus), under the speed-dependent law: its contacts follow the closed
    forms of vertical motion with quadratic drag, to the ODE's tolerance, and it comes to
    rest on the table."""
    scene = estim.load_scene(DROP).with_air(estim.Air(density=1.2)).with_law(SpeedDependentLaw(s0=1.0))
    r, m, cd, z0, e = 0.02, 0.0027, 0.47, 0.5, 0.9
    k = 1.2 * cd * math.pi * r * r / (2 * m)
    vt = math.sqrt(G / k)
    truth = air_drop(z0 - r, e, 1.0, vt, 6)
    params = estim.Params(e, 0.8, r, (0.0, 0.0, z0), (0.0, 0.0, 0.0), mass=m, drag_coefficient=cd)
    traj = estim.simulate(scene, params, 2.0, rtol=1e-10, atol=1e-12)
    ev = traj.events
    t, pre, post = (np.array(c) for c in zip(*truth, strict=True))
    # The air slows the first fall by 2 % (3.07 -> 3.01 m/s): the drag is measured, not
    # negligible, against a tolerance of 1e-7.
    assert abs(pre[0] - math.sqrt(2 * G * (z0 - r))) > 0.05
    np.testing.assert_allclose(ev.t[:6], t, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(-ev.velocity_pre[:6, 2], pre, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(ev.velocity_post[:6, 2], post, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(ev.position[:6, :2], 0.0, atol=1e-12)  # straight down
    assert bool(traj.complete)
    np.testing.assert_allclose(traj.final.position, [0.0, 0.0, r], atol=1e-9)
    np.testing.assert_allclose(traj.final.velocity, 0.0, atol=1e-9)


def test_bounce_by_bounce_gives_the_bounces_of_the_summed_series():
    """The factor law without its closed-form series (a segment per bounce, ending where the
    rebound falls below REST_SPEED) lists the bounces of the summed series (to rounding:
    a sum of flights against the closed form of the sum) and comes to rest where the
    series accumulates."""
    drop = estim.load_scene(DROP)
    params = estim.Params(0.5, 0.9, 0.02, (0.0, 0.0, 0.5), (0.4, 0.1, 0.0))
    summed = estim.simulate(drop, params, 2.0)
    one_by_one = estim.simulate(drop.with_law(BounceByBounceFactorLaw()), params, 2.0, max_segments=64)
    n = int(summed.events.count) - 1  # the listed bounces, then the settle
    assert n >= 15 and int(summed.events.kind[n]) == _constants.REST
    for name in ("t", "position", "velocity_pre", "velocity_post"):
        np.testing.assert_allclose(getattr(one_by_one.events, name)[:n], getattr(summed.events, name)[:n],
                                   rtol=1e-12, atol=1e-12, err_msg=name)
    # The last bounces of the one-by-one run are shorter than 1 us (not listed by the sum);
    # what they travel is below 1e-8 m.
    np.testing.assert_allclose(one_by_one.final.position, summed.final.position, atol=1e-8)
    np.testing.assert_allclose(one_by_one.final.velocity, 0.0, atol=1e-12)


def test_the_kernels_refuse_a_law_they_do_not_implement():
    """The kernels support the factor law without air (in either geometry), and say so;
    another law runs on the JAX planner, with the result of the JAX path, bit for bit, and
    the kernels' own entry points refuse it."""
    exact = estim.load_scene(DROP)
    assert _native.supports(FactorLaw(), exact)
    drop = exact.with_geometry("seed")
    toy = drop.with_law(SpeedDependentLaw())
    assert _native.supports(FactorLaw(), drop)
    assert not _native.supports(SpeedDependentLaw(), drop)
    assert not _native.supports(FactorLaw(), drop.with_air(estim.Air(density=1.2)))
    if _native.active():
        assert _native.runs(drop) and not _native.runs(toy)
    params = estim.Params(jnp.array([0.9, 0.6]), 0.8, 0.02, (0.0, 0.0, 0.5), (0.3, 0.0, 0.0))
    ts = jnp.linspace(0.0, 2.0, 9)
    traj = estim.simulate(toy, params, 2.0, ts=ts)
    with jax_path():
        ref = estim.simulate(toy, params, 2.0, ts=ts)
    assert traj.layout == ref.layout
    np.testing.assert_array_equal(traj.record, ref.record)
    np.testing.assert_array_equal(traj.flags, ref.flags)
    with pytest.raises(ValueError, match="do not support the contact law SpeedDependentLaw"):
        _native.plan(toy, params, 2.0, 16)
    # The sensitivities and a derivative run on the JAX planner too.
    s = estim.event_sensitivities(lambda th: estim.Params(th[0], 0.8, 0.02, (0.0, 0.0, 0.5), (th[1], 0.0, 0.0)),
                                  jnp.array([0.9, 0.3]), 1.0, scene=toy)
    ok = np.asarray(s.valid)
    assert ok.sum() >= 3
    np.testing.assert_allclose(np.asarray(s.autodiff)[ok], np.asarray(s.implicit)[ok], rtol=1e-8, atol=1e-10)


def test_an_explicit_factor_law_is_the_default():
    """``Scene.law = FactorLaw()`` is the scene's default law: the same trajectory, bit for
    bit, on the kernels."""
    drop = estim.load_scene(DROP)
    params = estim.Params(jnp.array([0.9, 0.6, 1.0]), jnp.array([0.8, 1.0, 0.5]), 0.02, (0.0, 0.0, 0.5),
                          (0.3, 0.1, 0.0))
    a = estim.simulate(drop, params, 1.5, throw=False)
    b = estim.simulate(drop.with_law(FactorLaw()), params, 1.5, throw=False)
    np.testing.assert_array_equal(a.record, b.record)
    np.testing.assert_array_equal(a.flags, b.flags)


# --- The constants the kernels share with Python -------------------------------------------

KERNELS = pathlib.Path(estim.__file__).parent / "forward" / "_kernels.cc"


def test_the_kernels_are_built_with_pythons_constants():
    """``_kernels.constants()`` (compiled from the header setup.py writes from
    estim/forward/_constants.py) equals the Python values, every one: a stale build (the
    file changed, the kernels not rebuilt) fails here, and estim does not use it."""
    if not _native.available() and _native._kernels is None:
        pytest.skip("the native kernels were not built")
    built = _native._kernels.constants()
    ours = {name: float(value) for name, value in _constants.exported().items()}
    assert built == ours, f"rebuild the kernels (pip install -e .): {_native.stale_constants()}"
    assert _native.stale_constants() == {}


def test_the_kernel_source_copies_no_shared_constant():
    """The C++ source defines none of the shared names and writes none of the shared
    tolerances as a number (they come from the generated header): what is left are the
    kernels' own numbers (BROAD_MARGIN) and the formulas' (0.5, 2.0, ...)."""
    code = re.sub(r"//[^\n]*", "", KERNELS.read_text())  # comments may name them
    for name in _constants.exported():
        assert not re.search(rf"\b(constexpr|enum)\b[^;{{]*\b{name}\s*=", code), name
        assert not re.search(rf"\benum\b[^;]*{{[^}}]*\b{name}\b", code), name
    shared = {v for v in _constants.exported().values() if isinstance(v, float)}
    # Numbers in exponent form (1e-12) and long ones (4503599627370496.0), line by line.
    found = [(line.strip(), float(literal)) for line in code.splitlines()
             for literal in re.findall(r"(?<![\w.])(\d+\.?\d*[eE][-+]?\d+|\d{7,}\.?\d*)(?![\w.])", line)]
    copied = [line for line, value in found if value in shared]
    # The scan sees the one number of this kind the kernels keep as their own (the margin
    # of their broad phase, 1e-6, which happens to equal SERIES_GAP), and no other.
    assert copied == ["constexpr double BROAD_MARGIN = 1e-6;"], "\n".join(copied)


def test_python_reads_the_face_table_columns_and_kinds_from_one_place():
    """The modules that number segment kinds, end reasons, ODE steps and event kinds take
    them from estim.forward._constants: the ODE's mode SLIDE is the planner's SLIDE."""
    assert _ode.SLIDE == _solver.SLIDE == _constants.SLIDE
    assert _ode.FLIGHT == _solver.FLIGHT == _constants.FLIGHT
    assert _trajectory.REST == _constants.REST and _trajectory.IMPACT == _constants.IMPACT
    assert (_ode.STEP_UNUSED, _solver.UNUSED) == (5, 3)
    for name in ("STEP_PLAIN", "STEP_CONTACT", "STEP_ZENO"):
        assert getattr(_ode, name) == getattr(_constants, name)
    assert not hasattr(_ode, "FLY") and not hasattr(_ode, "ZENO")
