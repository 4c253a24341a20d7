"""estim.fit against known truth: synthetic recovery (with a Zeno ball), a far start, the
loss gradient against finite differences, identifiability, and the real table drops.

Speed: a fit compiles once per shape (number of balls, padded samples, free, loss, steps).
Every synthetic fit here uses the stairs scene, 3 balls, 60 fps over 2.3 s (139 frames,
dropped frames emulated by NaN rows so that n stays 139) and the default options, so the
whole module compiles the fit once (~20 s) and each further fit takes < 1 s.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import estim
from estim import _config
from estim._json import dumps
from estim.fitting import _fit
from estim.fitting import _registry as registry
from estim.fitting._fit import PARAMETERS, _plan_at, _Problem, _residuals
from estim.fitting._loss import ROBUST_LOSSES, robust_curvature, robust_loss, robust_weight
from estim.forward._constants import ROLL
from estim.forward._trajectory import IMPACT, REST

ROOT = Path(__file__).resolve().parents[1]
STAIRS = ROOT / "data" / "scenes" / "stairs.xml"
DROP = ROOT / "data" / "scenes" / "drop.xml"
REALDATA = ROOT.parent / "shared" / "realdata" / "pingpong_drop_nicofighter45"
BALLS = ("bocce", "golf", "pingpong")
T_END, FPS = 2.3, 60.0
NOISES = (0.001, 0.002, 0.003)


@pytest.fixture(scope="module")
def stairs():
    return estim.load_scene(STAIRS)


def _events(scene, ball, truth):
    """(t, face label, kind) of the exact events of one ball over [0, T_END]."""
    spec = scene.ball(ball)
    p = estim.Params(truth["e"], truth["mu_t"], spec.radius, spec.position, (truth["vx0"], 0.0, 0.0))
    ev = estim.simulate(scene, p, T_END).events
    return [(float(ev.t[i]), scene.face_label(int(ev.face[i])), int(ev.kind[i])) for i in range(int(ev.count))]


def _near_an_edge(scene, ball, truth):
    """Whether the ball's path (on the seed's staircase, 1 ms samples) comes within r of a
    tread's edge in the L1 sense, beyond two faces at once: where the staircase's former
    45-degree bevels would have met it. The truths of this module were drawn clear of
    them, and stay the same draws."""
    spec = scene.ball(ball)
    p = estim.Params(truth["e"], truth["mu_t"], spec.radius, spec.position, (truth["vx0"], 0.0, 0.0))
    q = np.asarray(estim.simulate(scene, p, T_END, ts=np.linspace(0.0, T_END, 2301), throw=False).position)
    excess = np.maximum(np.abs(q[:, None, :] - np.asarray(scene.box_centre)) - np.asarray(scene.box_half), 0.0)
    corner = np.sum(excess > 0, axis=-1) >= 2
    return bool(np.any(corner & (np.sum(excess, axis=-1) < spec.radius)))


def random_truth(rng):
    """One draw of the three balls' (e, mu_t, vx0), well away from the fit's defaults;
    bocce slow and lossy."""
    return {
        "bocce": dict(e=rng.uniform(0.45, 0.55), mu_t=rng.uniform(0.88, 0.92), vx0=rng.uniform(0.3, 0.8)),
        "golf": dict(e=rng.uniform(0.5, 0.9), mu_t=rng.uniform(0.88, 0.99), vx0=rng.uniform(0.9, 1.4)),
        "pingpong": dict(e=rng.uniform(0.5, 0.9), mu_t=rng.uniform(0.88, 0.99), vx0=rng.uniform(0.9, 1.4)),
    }


def _draw_truth(scene, seed):
    """Parameters well away from the fit's defaults, drawn from the seed; bocce slow and
    lossy so that it goes Zeno (comes to rest on a tread) before T_END. Redrawn while any
    trajectory comes near a tread's edge (``_near_an_edge``): on the seed's staircase, which
    has no edges, it would pass through it."""
    rng = np.random.default_rng(seed)
    for _ in range(100):
        truth = random_truth(rng)
        events = {b: _events(scene, b, truth[b]) for b in BALLS}
        bevel = any(_near_an_edge(scene, b, truth[b]) for b in BALLS)
        zeno = any(kind == REST for (_, _, kind) in events["bocce"])
        if not bevel and zeno:
            return truth, events
    raise RuntimeError(f"no admissible truth drawn for seed {seed}")


def _data(scene, truth, seed, noise, drop=0.05):
    """Synthetic tracks with all 139 frames kept as rows; 5% of the rows (never row 0) set
    to NaN to emulate dropped frames, 3 outliers per ball, 1% lost coordinates."""
    tracks = estim.synthesize_tracks(scene, truth, t_end=T_END, frame_rate=FPS, noise=noise,
                                     drop_fraction=0.0, n_outliers=3, seed=seed)
    rng = np.random.default_rng(1000 + seed)
    data = {}
    for b in BALLS:
        t, p = tracks.t[b].copy(), tracks.position[b].copy()
        assert t.size == 139
        rows = rng.choice(np.arange(1, t.size), size=int(round(drop * t.size)), replace=False)
        p[rows] = np.nan
        data[b] = (t, p)
    return data


# Each of the later seeds failed before one change of the pipeline (docs/pages/fitting.md):
# 4, a Zeno ball's robust scale read from a run that had stopped far from its optimum; 18,
# outliers counted as inliers at too wide a scale; 11 and 47, no bounce resolved in 3 mm
# noise (the flight splitter stopped at the first low flight), and a local minimum; 46,
# restarts from a start of mu_t at 1, where the sigmoid holds mu_t still (and
# test_restarts_start_mu_t_below_one).
@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4, 5, 11, 18, 46, 47])
def test_recovery_synthetic(stairs, seed):
    truth, events = _draw_truth(stairs, seed)
    noise = NOISES[seed % 3]
    # bocce goes Zeno: a settle event on a tread before T_END
    assert any(k == REST and label == "+z" and t < T_END for t, (_, label), k in events["bocce"])
    result = estim.fit(stairs, _data(stairs, truth, seed, noise))
    assert result.converged
    for b in BALLS:
        bf = result.balls[b]
        e, se = bf.values["e"], bf.stderr["e"]
        assert bf.converged, (b, bf.notes)
        assert math.isfinite(se) and se > 0, b
        assert abs(e - truth[b]["e"]) < 0.01, (b, e, truth[b]["e"])
        assert abs(e - truth[b]["e"]) < 3 * se, (b, e, truth[b]["e"], se)
        for k in ("mu_t", "vx0"):
            v, s = bf.values[k], bf.stderr[k]
            assert math.isfinite(s), (b, k)
            assert abs(v - truth[b][k]) < max(3 * s, 0.01 if s < 1e-3 else 0.0), (b, k, v, truth[b][k], s)
        # rms of the inliers at the true noise level (within 10%)
        assert abs(bf.rms_m / noise - 1) < 0.10, (b, bf.rms_m, noise)
        assert bf.at_noise_floor
        assert bf.n_obs >= 139 - 7 - 3  # NaN rows out; lost coordinates leave the row


def test_restarts_start_mu_t_below_one(stairs):
    """Seed 181's ping-pong ball starts from mu_t = 0.992 (read from its bounces; truth
    0.966) and ended at mu_t = 1 with rms 5.5 mm for 2 mm noise, restarts included, when
    they kept that start: the sigmoid's slope mu (1 - mu) is 0.008 there. Restarts now
    start mu_t at 0.95. (Its bocce ball's mu_t is not identifiable: not checked here.)"""
    truth, _ = _draw_truth(stairs, 181)
    bf = estim.fit(stairs, _data(stairs, truth, 181, NOISES[181 % 3])).balls["pingpong"]
    assert bf.converged and bf.at_noise_floor, bf.notes
    for k in ("e", "mu_t", "vx0"):
        assert abs(bf.values[k] - truth["pingpong"][k]) < 3 * bf.stderr[k], (k, bf.values[k], truth["pingpong"][k])


@pytest.mark.parametrize(("seed", "ball", "n_true"), [(47, "golf", 5), (50, "pingpong", 3)])
def test_start_resolves_low_flights(stairs, seed, ball, n_true):
    """In 3 mm noise the splitter resolves the bounces before the flights drop below ~2 cm
    (the true times, from the exact events, to one frame), and reads e and mu_t from them;
    it used to stop at the first flight lower than 18 noise levels (no bounce resolved)."""
    from estim.fitting._initial import initial_guess

    truth, events = _draw_truth(stairs, seed)
    t, pos = _data(stairs, truth, seed, 0.003)[ball]
    init = initial_guess(t, pos[:, 0], pos[:, 2], float(stairs.gravity))
    true_times = [te for te, _, _ in events[ball]][:n_true]
    assert len(init.bounces) == n_true
    assert np.allclose(init.bounces, true_times, atol=1 / FPS)
    assert abs(init.e - truth[ball]["e"]) < 0.03
    assert abs(init.mu_t - truth[ball]["mu_t"]) < 0.03


def test_stderr_calibrated(stairs):
    """Over several seeds the errors divided by their standard errors have rms ~ 1."""
    z = []
    for seed in range(9):
        truth, _ = _draw_truth(stairs, seed)
        result = estim.fit(stairs, _data(stairs, truth, seed, NOISES[seed % 3]))
        for b in BALLS:
            bf = result.balls[b]
            z += [(bf.values[k] - truth[b][k]) / bf.stderr[k] for k in ("e", "mu_t", "vx0")]
    z = np.array(z)
    print("z-scores rms", np.sqrt(np.mean(z**2)), "max", np.abs(z).max())
    assert np.all(np.isfinite(z))
    assert 0.6 < np.sqrt(np.mean(z**2)) < 1.6
    assert np.mean(np.abs(z) > 3) < 0.05


def test_noise_read_from_data(stairs):
    ratios = []
    for seed in (0, 1, 3):
        truth, _ = _draw_truth(stairs, seed)
        noise = NOISES[seed % 3]
        result = estim.fit(stairs, _data(stairs, truth, seed, noise))
        ratios += [(result.balls[b].noise_m / noise, sum(f.n for f in result.balls[b].initial.flights))
                   for b in BALLS]
    print("noise_m / noise, samples in flights", ratios)
    # The noise is read from the spread about each flight's parabola (x and z): within 25%
    # from 100 samples in flights (the MAD of 200 residuals has a relative spread of ~8%);
    # a ball that soon rests gives few, and then the larger of two estimates (a factor 2 at
    # most).
    for ratio, n in ratios:
        assert abs(ratio - 1) < (0.25 if n >= 100 else 1.0), (ratio, n)


def _far_start_fit(stairs, e0):
    truth, _ = _draw_truth(stairs, 0)
    truth["pingpong"] = dict(truth["pingpong"], e=0.85)
    data = _data(stairs, truth, 0, 0.002)
    return truth, estim.fit(stairs, data, fixed={"pingpong": {"e": e0}})


@pytest.mark.parametrize("e0", [
    0.7,
    0.5,
])
def test_far_start(stairs, e0):
    """pingpong e = 0.85, started at e0 (``fixed`` sets the starting value of a free
    parameter: in estim.fit it overrides the data-driven start)."""
    truth, result = _far_start_fit(stairs, e0)
    bf = result.balls["pingpong"]
    assert bf.initial.e == pytest.approx(0.85, abs=0.03)  # the data-driven start, overridden
    assert abs(bf.values["e"] - 0.85) < 0.01, bf.values
    assert bf.converged and bf.at_noise_floor
    for b in ("bocce", "golf"):  # the other balls are unaffected
        assert abs(result.balls[b].values["e"] - truth[b]["e"]) < 0.01


def test_missing_physics_is_reported(stairs):
    """Data the model cannot represent (a steady 3 cm/s drift of z, as a tilted camera
    would add) must come back flagged above the noise floor, not as a confident fit."""
    truth, _ = _draw_truth(stairs, 0)
    data = _data(stairs, truth, 0, 0.002)
    t, p = data["golf"]
    p = p.copy()
    p[:, 2] += 0.03 * t
    data["golf"] = (t, p)
    bf = estim.fit(stairs, data).balls["golf"]
    assert not bf.at_noise_floor
    assert any("above the noise level" in n for n in bf.notes), bf.notes


def test_late_clock_is_pointed_out(stairs):
    """A track whose clock starts 5 s after the release (a video's clock) cannot be fitted
    with the release at t = 0; the fit says so, and says why."""
    truth, _ = _draw_truth(stairs, 0)
    data = _data(stairs, truth, 0, 0.002)
    t, p = data["golf"]
    data["golf"] = (t + 5.0, p)
    balls = estim.fit(stairs, data).balls
    assert not balls["golf"].at_noise_floor
    assert any("the first sample is 5.00 s after the release" in n for n in balls["golf"].notes), balls["golf"].notes
    for b in ("bocce", "pingpong"):  # tracks that start at the release get no such note
        assert not any("after the release" in n for n in balls[b].notes), balls[b].notes


def test_loss_gradient_matches_finite_differences(stairs):
    truth, events = _draw_truth(stairs, 1)
    ball = "golf"
    data = _data(stairs, {b: truth[b] for b in BALLS}, 1, 0.002)
    t, pos = data[ball]
    spec = stairs.ball(ball)
    # a point away from the optimum (so that the gradient is not ~0), t0 < 0 so that no
    # sample sits on the release kink; every event time away from the samples
    values = {"e": truth[ball]["e"] + 0.01, "mu_t": truth[ball]["mu_t"] - 0.005, "mu": 0.25,  # (mu: the friction law's)
              "e_slope": 0.0, "compression": 0.0,
              "vx0": truth[ball]["vx0"] + 0.02, "x0": spec.position[0] + 0.003,
              "z0": spec.position[2] - 0.002, "vz0": 0.05, "t0": -0.004, "y0": spec.position[1],
              "vy0": 0.0, "drag_coefficient": 0.47,  # drag and spin: no effect in a vacuum
              "lift_factor": 1.0, "spin_x": 0.0, "spin_y": 0.0, "spin_z": 0.0, "pixel_scale": 1.0,
              "dt_camera2": 0.0, "dt_camera3": 0.0, "dt_camera4": 0.0}  # (the clocks of image fits' cameras)
    phi0 = registry.pack(values)
    assert set(values) == set(PARAMETERS)
    mask = np.isfinite(pos)
    problem = _Problem(t=jnp.asarray(t), obs=jnp.asarray(np.nan_to_num(pos)), mask=jnp.asarray(mask),
                       radius=jnp.asarray(spec.radius), mass=jnp.asarray(spec.mass),
                       inertia=jnp.asarray(spec.inertia), fixed=jnp.asarray(phi0), scale=jnp.asarray(0.002),
                       anchor=jnp.zeros(3), size=jnp.asarray(len(t)))

    @jax.jit
    def loss(phi):
        pl, n_used = _plan_at(stairs, phi, problem, 48)  # the model's structure at phi
        r, _ = _residuals(stairs, phi, problem, pl, n_used, rolls=True)
        return jnp.sum(robust_loss(r / problem.scale, "cauchy"))

    grad = np.asarray(jax.jit(jax.grad(loss))(jnp.asarray(phi0)))
    h = 1e-6
    fd = np.zeros_like(phi0)
    for k in range(len(phi0)):
        d = np.zeros_like(phi0)
        d[k] = h
        fd[k] = (float(loss(jnp.asarray(phi0 + d))) - float(loss(jnp.asarray(phi0 - d)))) / (2 * h)
    print(dict(zip(PARAMETERS, zip(grad, fd, strict=True), strict=True)))
    assert np.all(np.isfinite(grad))
    # the parameters with data (y is not observed; drag and spin act only in air)
    observed = registry.index(("e", "mu_t", "vx0", "x0", "z0", "vz0", "t0"))
    assert np.abs(grad[observed]).min() > 0
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-9 * np.abs(grad).max())


def test_no_bounce_not_identifiable(stairs):
    """pingpong seen only over its first 0.15 s (it lands at 0.226 s): e and mu_t are not
    identifiable, vx0 still is. Padded into the same 3-ball shape as the other fits."""
    truth, _ = _draw_truth(stairs, 0)
    data = _data(stairs, truth, 0, 0.002)
    t, p = data["pingpong"]
    keep = t <= 0.15 + 1e-9
    data["pingpong"] = (t[keep], p[keep])
    result = estim.fit(stairs, data)
    bf = result.balls["pingpong"]
    assert bf.n_bounces == 0
    for k in ("e", "mu_t"):
        assert math.isnan(bf.stderr[k]), (k, bf.stderr)
        assert any(k in n and "not identifiable" in n for n in bf.notes), bf.notes
    for k in ("vx0", "x0", "z0"):
        assert math.isfinite(bf.stderr[k]) and bf.stderr[k] > 0, (k, bf.stderr)
    assert abs(bf.values["vx0"] - truth["pingpong"]["vx0"]) < max(3 * bf.stderr["vx0"], 0.01)
    js = result.to_json()["balls"]["pingpong"]
    assert js["stderr"]["e"] is None and js["stderr"]["vx0"] is not None
    # fit.json is strict JSON: the correlations of e are undefined, written as null.
    text = dumps(result.to_json())
    assert "NaN" not in text
    corr = json.loads(text)["balls"]["pingpong"]["correlation"]
    i, j = corr["names"].index("e"), corr["names"].index("vx0")
    assert corr["matrix"][i][j] is None and corr["matrix"][j][j] == 1.0
    # the other balls are fitted as usual
    for b in ("bocce", "golf"):
        assert abs(result.balls[b].values["e"] - truth[b]["e"]) < 0.01


def test_fit_3d_throw_along_y():
    """A ping-pong ball thrown along y on the drop scene's table (estim.simulate from known
    parameters, 120 fps, 1 mm noise in x, y and z): the fit estimates the release state in
    3D (y0 and vy0 besides x0, z0, vx0, by default for tracks with y), from starts read in
    the ball's plane of travel, and recovers every known parameter within 3 standard
    errors at the noise floor."""
    scene = estim.load_scene(DROP)
    truth = dict(e=0.82, mu_t=0.9, x0=0.05, y0=-0.6, z0=0.5, vx0=0.0, vy0=0.9)
    params = estim.Params.for_ball(scene, "pingpong", e=truth["e"], mu_t=truth["mu_t"],
                                   position=(truth["x0"], truth["y0"], truth["z0"]),
                                   velocity=(truth["vx0"], truth["vy0"], 0.0))
    t = np.arange(0.0, 1.2 + 1e-9, 1 / 120)
    exact = np.asarray(estim.simulate(scene, params, 1.2, ts=jnp.asarray(t)).position)
    obs = exact + np.random.default_rng(3).normal(0.0, 1e-3, exact.shape)
    result = estim.fit(scene, {"pingpong": (t, obs)})
    bf = result.balls["pingpong"]
    assert set(bf.names) == {"e", "mu_t", "x0", "y0", "z0", "vx0", "vy0"}
    assert bf.converged and bf.at_noise_floor, bf.notes
    # The surfaces it bounced on, in order: those of the truth's own simulation.
    events = estim.simulate(scene, params, 1.2).events
    kinds, faces = np.asarray(events.kind)[:int(events.count)], np.asarray(events.face)[:int(events.count)]
    assert bf.n_bounces == 2 and bf.contacts == tuple(scene.face_label(int(f)) for f in faces[kinds == IMPACT])
    assert bf.initial.vy0 == pytest.approx(truth["vy0"], abs=0.01)  # the start, along y
    for k, v in truth.items():
        s = bf.stderr[k]
        assert math.isfinite(s) and 0 < s < 2e-3, (k, s)
        assert abs(bf.values[k] - v) < 3 * s, (k, bf.values[k], v, s)
    assert bf.rms_m == pytest.approx(1e-3, rel=0.1)
    # the table shows the lateral release speed that was fitted
    assert "vy0 (m/s)" in result.format_table().splitlines()[0]


def test_a_track_that_rolls_over_an_edge_is_fitted_with_the_roll():
    """A golf ball that bounces out on a tread of the exact staircase, slides to its edge,
    rolls over it and does so again one tread down (``ROLL`` segments in the truth's
    plan), 100 fps, 1 mm noise: the fit's program without rolls meets them in its plans
    and the fit runs with them (``estim.fitting._fit.fit_program``). The fitted model's
    positions are ``estim.simulate``'s at the fitted values (those of the program without
    rolls are its flights carried on through the rolls, centimetres off), and every known
    parameter lies within 3 standard errors at the noise floor."""
    scene = estim.load_scene(ROOT / "data" / "scenes" / "stairs_exact.xml")
    truth = dict(e=0.5, x0=0.6, z0=1.32, vx0=0.4)

    def params(v):
        return estim.Params.for_ball(scene, "golf", e=v["e"], mu_t=1.0, position=(v["x0"], v.get("y0", 0.0), v["z0"]),
                                     velocity=(v["vx0"], v.get("vy0", 0.0), 0.0))

    t = np.arange(0.0, 2.5 + 1e-9, 1 / 100)
    traj = estim.simulate(scene, params(truth), 2.5, ts=jnp.asarray(t), keep=("samples", "solution"))
    assert np.sum(np.asarray(traj.solution.structure.kind) == ROLL) == 2
    obs = np.asarray(traj.position) + np.random.default_rng(0).normal(0.0, 1e-3, (t.size, 3))
    bf = estim.fit(scene, {"golf": (t, obs)}, free=tuple(truth), fixed={"golf": {"mu_t": 1.0}}).balls["golf"]
    assert bf.converged and bf.at_noise_floor, bf.notes
    model = estim.simulate(scene, params(bf.values), 2.5, ts=jnp.asarray(bf.model_t)).position
    np.testing.assert_allclose(bf.model_position, np.asarray(model), rtol=0, atol=1e-12)
    for k, v in truth.items():
        assert abs(bf.values[k] - v) < 3 * bf.stderr[k], (k, bf.values[k], v, bf.stderr[k])


def test_a_track_that_starts_on_a_tread_is_fitted_from_there():
    """A golf ball released sliding on step2's top of the seed's staircase (0.4 m/s along
    x, 0.05 along y), off the tread's end after 1 s and down the stairs (60 fps, 2 mm
    noise; the track of tests/test_registry.py's start test). The fit releases it from
    the tread, z0 and vz0 held (``estim.fitting._fit._on_surface``: released any height
    above the tread, the factor law's Zeno series there would stop it dead), and recovers
    every other known parameter within 3 standard errors at the noise floor. The start
    from the first flight's parabola had put the ball 4.9 m under the tread at t = 0,
    thrown up at 9.8 m/s, and the fit ended with z0 2.4 m off, e 0.34 (true 0.5), 2.6 mm
    rms for 2 mm of noise."""
    scene = estim.load_scene(STAIRS)
    truth = dict(e=0.5, mu_t=0.9, x0=0.5, y0=0.1, vx0=0.4, vy0=0.05)
    p = estim.Params.for_ball(scene, "golf", e=0.5, mu_t=0.9, position=(0.5, 0.1, 1.25), velocity=(0.4, 0.05, 0.0))
    t = np.arange(0.0, 2.5, 1 / 60)
    obs = np.asarray(estim.simulate(scene, p, 2.5, ts=jnp.asarray(t)).position)
    obs = obs + np.random.default_rng(0).normal(0.0, 2e-3, obs.shape)
    bf = estim.fit(scene, {"golf": (t, obs)}).balls["golf"]
    assert bf.converged and bf.at_noise_floor, bf.notes
    assert bf.values["z0"] == 1.25 and bf.values["vz0"] == 0.0 and math.isnan(bf.stderr["z0"])
    assert any(n.startswith("z0 = 1.25 held: the track starts with the ball on a surface") for n in bf.notes)
    for k, v in truth.items():
        assert abs(bf.values[k] - v) < 3 * bf.stderr[k], (k, bf.values[k], v, bf.stderr[k])


# ---------------------------------------------------------------------------------------
# Real data: ping-pong drops on a table (shared/realdata beside the checkout)
# ---------------------------------------------------------------------------------------


def _table_files():
    if not (REALDATA / "table").is_dir():
        pytest.skip(f"real data not found at {REALDATA}")
    files = sorted((REALDATA / "table").glob("tracked-*.txt"), key=lambda p: int(p.stem.split("-")[1]))
    assert len(files) == 15
    return files


@pytest.mark.slow
def test_real_table_drops():
    """e per table file with the pixel pipeline (every file padded to 400 samples: one
    compile). The authors found e = 0.821 +- 0.007; only a broad range is asserted."""
    from estim import fit_pixels

    rows = []
    for f in _table_files():
        result, data, mpp, _ = fit_pixels(f, DROP, ball="pingpong", frame_interval=0.01, pad_to=400)
        bf = result.balls["pingpong"]
        rows.append((f.name, bf.values["e"], bf.stderr["e"], bf.rms_m / mpp, bf.noise_m / mpp, mpp, bf.converged))
    for name, e, se, rms_px, noise_px, mpp, conv in rows:
        print(f"{name:15s} e = {e:.4f} +- {se:.4f}  rms {rms_px:.2f} px (noise {noise_px:.2f} px)  "
              f"{mpp * 1e3:.4f} mm/px  converged {conv}")
    es = np.array([r[1] for r in rows])
    print(f"mean e = {es.mean():.4f} +- {es.std(ddof=1) / math.sqrt(len(es)):.4f} (authors 0.821 +- 0.007)")
    for name, e, se, *_ in rows:
        assert 0.6 < e < 0.95, (name, e)
        assert math.isfinite(se) and se > 0, (name, se)


@pytest.mark.parametrize("kind", ROBUST_LOSSES)
def test_robust_weight_and_curvature_are_the_losss_derivatives(kind):
    """u w(u) = rho'(u) and robust_curvature(u) = rho''(u), against central differences of
    the loss (away from Huber's kink at c, where rho'' jumps)."""
    u = np.concatenate([np.linspace(-9.0, 9.0, 181), [0.0, 1e-3, 2.385, 5.0]])
    u = u[np.abs(np.abs(u) - 1.345) > 1e-2]
    h = 1e-4
    d1 = (robust_loss(u + h, kind) - robust_loss(u - h, kind)) / (2 * h)
    d2 = (robust_loss(u + h, kind) - 2 * robust_loss(u, kind) + robust_loss(u - h, kind)) / h**2
    np.testing.assert_allclose(u * robust_weight(u, kind), d1, rtol=0, atol=1e-7)
    np.testing.assert_allclose(robust_curvature(u, kind), d2, rtol=0, atol=1e-5)



def test_fit_programs_compile_by_path_and_tier_up_on_the_ode_path(monkeypatch):
    """A fit's program is compiled with the closed form's options in a vacuum; in air with
    the quick options for its first ``FIT_ODE_TIER_UP`` calls of one signature, then with
    the optimised ones (``estim._config``), counted per signature, or from the first call
    inside ``estim.optimised_programs``. On exact geometry in a
    vacuum it runs without rolls first, again with them where a plan rolled (the result
    is then the program's with rolls), and with them from then on for that signature."""
    used = []

    def fake_filter_jit(fun, compiler_options=None):
        return lambda *a, **k: used.append((compiler_options, k["rolls"])) or fun(*a, **k)

    monkeypatch.setattr(eqx, "filter_jit", fake_filter_jit)
    # A plan "rolls" where x > 10; the program returns x * n, and whether it had rolls.
    program = _fit.fit_program(lambda scene, x, n, rolls: (x * n, rolls, not rolls and x > 10))
    scenes = Path(__file__).resolve().parents[1] / "data" / "scenes"
    vacuum, air, edges = (estim.load_scene(scenes / f) for f in ("stairs.xml", "drop_air.xml", "drop.xml"))
    n = _config.FIT_ODE_TIER_UP
    closed_form, quick, optimised = (_config.compile_options(o) for o in
                                     (_config.FIT_COMPILE, _config.FIT_ODE_COMPILE, _config.FIT_ODE_OPTIMISED))
    for _ in range(n + 2):
        assert program(vacuum, np.float64(2.0), 3) == (6.0, True)  # (no edges: nothing left out)
    assert used == [(closed_form, True)] * (n + 2)
    used.clear()
    for _ in range(n + 1):
        program(air, np.ones(2), 3)
    program(air, np.ones(3), 3)  # another shape: another signature
    program(air, np.ones(2), 4)  # another static value: another signature
    assert used == [(quick, True)] * n + [(optimised, True)] + [(quick, True)] * 2
    used.clear()
    with _config.optimised_programs():  # a process that will fit many shots: optimised at once
        program(air, np.ones(5), 3)
    program(air, np.ones(5), 3)  # and kept after the block
    program(air, np.ones(6), 3)  # (a signature first seen outside it starts quick)
    assert used == [(optimised, True)] * 2 + [(quick, True)]
    used.clear()
    assert program(edges, np.float64(2.0), 3) == (6.0, False)
    assert program(edges, np.float64(20.0), 3) == (60.0, True)  # a roll: run again, with rolls
    assert program(edges, np.float64(2.0), 3) == (6.0, True)  # that signature keeps them
    assert program(edges, np.float64(2.0), 4) == (8.0, False)  # another does not
    assert [r for _, r in used] == [False, False, True, True, False]
