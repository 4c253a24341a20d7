"""Priors of a fit (``estim.fit(prior=...)``, a scene's ``estim:prior:NAME``, ``estim fit
--prior``): the posterior against the product of two Gaussians, the note where the prior
holds a parameter, and every refusal with its message."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

import estim
from estim.app._cli import main
from estim.fitting import _registry as registry

ROOT = Path(__file__).resolve().parents[1]
STAIRS = ROOT / "data" / "scenes" / "stairs.xml"
TABLE = ROOT / "data" / "scenes" / "table_tennis.xml"
DEMO_CSV = str(ROOT / "data" / "tracks" / "stairs_demo.csv")
TRUTH = {"bocce": dict(e=0.5, mu_t=0.9, vx0=0.5), "golf": dict(e=0.7, mu_t=0.95, vx0=1.1),
         "pingpong": dict(e=0.8, mu_t=0.95, vx0=1.2)}


@pytest.fixture(scope="module")
def stairs():
    return estim.load_scene(STAIRS)


@pytest.fixture(scope="module")
def data(stairs):
    tracks = estim.synthesize_tracks(stairs, TRUTH, t_end=2.3, frame_rate=60.0, noise=0.003, drop_fraction=0.0,
                                     n_outliers=0, seed=3)
    return {b: (tracks.t[b], tracks.position[b]) for b in tracks.balls}


@pytest.fixture(scope="module")
def alone(stairs, data):
    """The fit without a prior (l2: a Gaussian likelihood), golf's e and its standard error."""
    bf = estim.fit(stairs, data, loss="l2").balls["golf"]
    assert bf.converged and not bf.prior
    return bf.values["e"], bf.stderr["e"]


def test_posterior_is_the_product_of_two_gaussians(stairs, data, alone):
    """A Gaussian prior N(m, s_p^2) on e times the data's N(e_hat, s_d^2) (locally linear,
    l2 loss) is N((e_hat / s_d^2 + m / s_p^2) / (1 / s_d^2 + 1 / s_p^2), 1 / (1 / s_d^2 +
    1 / s_p^2)): with s_p = s_d and m two standard errors away, the mean moves by one
    standard error and the standard error shrinks by sqrt(2)."""
    e_hat, s_d = alone
    bf = estim.fit(stairs, data, loss="l2", prior={"e": (e_hat + 2 * s_d, s_d)}).balls["golf"]
    assert bf.converged
    assert bf.prior == {"e": (pytest.approx(e_hat + 2 * s_d), pytest.approx(s_d))}
    print("e", e_hat, s_d, "->", bf.values["e"], bf.stderr["e"])
    assert abs(bf.values["e"] - (e_hat + s_d)) < 0.2 * s_d
    assert bf.stderr["e"] == pytest.approx(s_d / math.sqrt(2), rel=0.1)
    assert not any("prior" in n for n in bf.notes)  # the data still say as much as the prior
    assert bf.to_json()["prior"] == {"e": {"mean": bf.prior["e"][0], "sd": bf.prior["e"][1]}}


def test_a_narrow_prior_holds_the_parameter(stairs, data, alone):
    """A prior ten times narrower than the data's standard error: the fit sits on its mean,
    its standard error is the prior's (1 / sqrt(1 + 1/100) of it), and a note says so."""
    e_hat, s_d = alone
    m, s_p = e_hat - 3 * s_d, 0.1 * s_d
    bf = estim.fit(stairs, data, loss="l2", prior={"e": (m, s_p)}).balls["golf"]
    assert abs(bf.values["e"] - m) < 0.1 * s_d
    assert bf.stderr["e"] == pytest.approx(s_p / math.sqrt(1.01), rel=0.05)
    assert any("held by its prior" in n for n in bf.notes), bf.notes


def test_scene_declares_priors(tmp_path):
    scene = estim.load_scene(TABLE)
    assert dict((n, (m, s)) for n, m, s in scene.priors) == {"e": (0.88, 0.05), "mu": (0.25, 0.1),
                                                             "drag_coefficient": (0.5, 0.2), "spin": (0.0, 1000.0)}
    assert scene.with_geometry("seed").priors == scene.priors
    assert estim.load_scene(STAIRS).priors == ()
    assert registry.priors(scene, {"mu": None, "spin": (0.0, 300.0), "e_slope": None}) == {
        "e": (0.88, 0.05), "drag_coefficient": (0.5, 0.2), "spin_x": (0.0, 300.0), "spin_y": (0.0, 300.0),
        "spin_z": (0.0, 300.0)}
    text = TABLE.read_text()
    for data, words in (("0.9", "two finite numbers"), ("0.9 0", "standard deviation"), ("0.9 0.1 3", "two")):
        bad = tmp_path / "bad.xml"
        bad.write_text(text.replace('name="estim:prior:e" data="0.88 0.05"', f'name="estim:prior:e" data="{data}"'))
        with pytest.raises(ValueError, match=words):
            estim.load_scene(bad)


@pytest.mark.parametrize("prior, words", [
    ({"ee": (0.9, 0.1)}, "unknown parameter 'ee'"),
    ({"e": (0.9, 0.0)}, "standard deviation"),
    ({"e": (0.9, math.nan)}, "standard deviation"),
    ({"e": (1.5, 0.1)}, "must lie in [0, 1]"),
    ({"drag_coefficient": (-1.0, 0.1)}, "must be > 0"),
    ({"e": 0.9}, "(mean, standard deviation)"),
])
def test_bad_priors_are_refused(prior, words):
    scene = estim.load_scene(TABLE)
    with pytest.raises(ValueError) as err:
        registry.priors(scene, prior)
    assert words in str(err.value)


def test_a_prior_on_a_held_parameter_is_refused(stairs, data):
    with pytest.raises(ValueError, match=r"a prior on \['vz0'\], which this fit holds"):
        estim.fit(stairs, data, free=registry.default_free(stairs, lateral=False), prior={"vz0": (0.0, 1.0)})


def test_what_has_a_prior_is_fitted_by_default():
    """A fit of a track in metres estimates by default, besides the law's coefficients and
    the release state, every parameter that acts and has a prior (the table-tennis scene's
    drag coefficient), unless the prior is dropped; a parameter that does not act in the
    scene (the drag coefficient in a vacuum) does not join."""
    table = estim.load_scene(TABLE)
    known = registry.priors(table)
    # (The spin's prior adds nothing: the spin is free already, in its place.)
    assert registry.default_free(table, True, known) == ("e", "mu", "drag_coefficient") + registry.expand(
        ("position", "velocity", "spin"))
    assert registry.default_free(table, True, tuple(known) + ("lift_factor",))[3] == "lift_factor"
    assert "drag_coefficient" not in registry.default_free(table, True, registry.priors(table, {"drag_coefficient": None}))
    assert "drag_coefficient" not in registry.default_free(table.with_air(None), True, known)
    assert registry.default_free(table, True) == registry.default_free(table, True, ("e", "mu"))
    stairs = estim.load_scene(STAIRS)
    assert registry.default_free(stairs, False, ("vz0",)) == ("e", "mu_t", "vx0", "x0", "z0", "vz0")


def test_cli_prior(tmp_path, capsys):
    code = main(["fit", DEMO_CSV, "--scene", str(STAIRS), "--json", "--prior", "e=0.7,0.3", "--prior", "mu_t=0.9,0.5"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    balls = json.loads(captured.out)["balls"]
    for fitted in balls.values():
        assert fitted["prior"] == {"e": {"mean": 0.7, "sd": 0.3}, "mu_t": {"mean": 0.9, "sd": 0.5}}
        assert fitted["converged"]
    for argv, words in ((["--prior", "e=0.5"], "NAME=MEAN,SD"), (["--prior", "e=a,b"], "not a number"),
                        (["--prior", "=1,2"], "NAME=MEAN,SD"), (["--prior", "e=0.5,-1"], "standard deviation")):
        assert main(["fit", DEMO_CSV, "--scene", str(STAIRS)] + argv) == 2, argv
        err = capsys.readouterr().err
        assert words in err, (argv, err)


def test_prior_rows_in_noise_units():
    """A prior row is (value - mean) / sd in noise units (the robust scale cancels)."""
    from estim.fitting._fit import _prior_rows

    arrays = registry.prior_arrays({"e": (0.8, 0.05)})
    phi = registry.pack({**registry.defaults(estim.load_scene(STAIRS).ball("golf")), "e": 0.9})

    class P:
        prior = arrays
        scale = 0.003

    rows = np.asarray(_prior_rows(phi, P)) / P.scale
    k = registry.index(("e",))[0]
    assert rows[k] == pytest.approx(2.0)
    assert np.count_nonzero(rows) == 1
