"""The fit's parameters: one registry entry per fittable quantity.

Every quantity a fit can estimate is one :class:`Parameter` in :data:`REGISTRY` (in the
spirit of mujoco's ``sysid`` ``Parameter``): its name, where it lives in
:class:`estim.Params` (a field, and for a vector its components: the release position
``x0 y0 z0``, velocity ``vx0 vy0 vz0`` and spin ``spin_x spin_y spin_z``), the transform to
unconstrained coordinates, its default, how the data gives a start, its unit and a line of
documentation. The fit, the command line, fit.json, the replay and the plots loop over the
registry; nothing indexes the parameters by position. Adding a parameter is one entry.

The flat names (:data:`NAMES`: ``e``, ``mu_t``, ``x0``, ..., ``spin_z``) are the names of
every component, in registry order; they are what ``estim.fit(free=..., fixed=...)``,
``estim fit --also`` and fit.json use. A fit works on two vectors:

- ``phi``, the physical values of every component in the order of :data:`NAMES`
  (:func:`pack`, :func:`unpack`);
- ``theta``, the unconstrained coordinates of the fitted components, in the order of
  ``free``: ``phi_k = T_k(theta_k)`` with ``T`` the component's transform:

      identity:  phi = theta                                  (a position, a speed, t0, spin)
      sigmoid:   phi = 1 / (1 + exp(-theta)),  in (0, 1)      (e, mu_t)
      exp:       phi = exp(theta),             in (0, inf)    (the drag coefficient, the lift factor)

  Constraints hold by reparametrisation, never by clipping; the inverse clips only a start
  that lies on the edge of the range (``logit`` of 0 or 1 is infinite).

Adding a fit parameter is one entry of :data:`REGISTRY`. The ball's radius, say (a field of
:class:`estim.Params`, positive, by default the scene's value, no start from the data)::

    Parameter("radius", field="radius", transform=Exp(), default=lambda ball: (ball.radius,),
              unit="m", doc="ball radius")

With it, ``estim.fit(..., free=(..., "radius"))`` and ``estim fit --also radius`` fit it
(with a standard error), fit.json holds it, ``estim replay`` replays with it, ``estim
simulate --radius`` sets it, and the table and captions show it where it was fitted. A
parameter that acts only in air says ``acts=_in_air``; one the data can start from gives
``start=lambda initial: (...)`` (``estim.fitting._initial.Initial``). A quantity that is not
yet a field of ``Params`` needs that field first (and the forward model to use it).
"""

from __future__ import annotations

import abc
import math
from collections.abc import Callable, Iterable, Mapping
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..forward.laws import law_of, laws_reading
from ..model._params import DRAG_COEFFICIENT, Params
from ..model._scene import LAWS, Ball, Scene
from ._initial import E_DEFAULT, FRICTION_DEFAULT, MU_DEFAULT, Initial
from ._loss import array_namespace

__all__ = [
    "AbstractTransform", "Exp", "Identity", "MAX_CAMERAS", "NAMES", "Parameter", "REGISTRY", "Sigmoid", "acting",
    "check_acting", "component", "default_free", "defaults", "describe", "expand", "index", "pack", "prior_arrays",
    "priors", "shown", "slopes",
    "starting_values", "to_params", "to_physical", "to_theta", "unpack", "value", "values_for",
    "with_values",
]


# --------------------------------------------------------------------------- transforms


class AbstractTransform(eqx.Module):
    """A bijection ``phi = T(theta)`` from the real line onto a parameter's range.

    Each method takes NumPy or JAX arrays and answers in kind (``xp`` is the namespace).
    """

    @abc.abstractmethod
    def physical(self, theta, xp):
        """``phi = T(theta)``."""

    @abc.abstractmethod
    def unconstrained(self, phi, xp):
        """``theta = T^-1(phi)`` (a start on the edge of the range is moved just inside)."""

    @abc.abstractmethod
    def slope(self, phi):
        """``d phi / d theta`` at ``phi`` (the chain rule from theta to the physical value)."""

    @abc.abstractmethod
    def refuse(self, value: float) -> str | None:
        """Why ``value`` cannot be held fixed (outside the closed range), or ``None``."""


class Identity(AbstractTransform):
    """``phi = theta``: any real value."""

    def physical(self, theta, xp):
        return theta

    def unconstrained(self, phi, xp):
        return phi

    def slope(self, phi):
        return 1.0

    def refuse(self, value):
        return None


class Sigmoid(AbstractTransform):
    """``phi = 1 / (1 + exp(-theta))`` in (0, 1); ``theta = log(phi) - log(1 - phi)`` with
    phi clipped to ``[1e-6, 1 - 1e-6]``; ``d phi / d theta = phi (1 - phi)``."""

    def physical(self, theta, xp):
        if xp is jnp:
            return jax.nn.sigmoid(theta)
        with np.errstate(over="ignore"):
            return 1.0 / (1.0 + np.exp(-theta))

    def unconstrained(self, phi, xp):
        phi = xp.clip(phi, 1e-6, 1 - 1e-6)
        return xp.log(phi) - xp.log1p(-phi)

    def slope(self, phi):
        return phi * (1 - phi)

    def refuse(self, value):
        return None if 0.0 <= value <= 1.0 else "must lie in [0, 1]"


class Exp(AbstractTransform):
    """``phi = exp(theta)`` in (0, inf); ``theta = log(max(phi, 1e-6))``;
    ``d phi / d theta = phi``."""

    def physical(self, theta, xp):
        return xp.exp(theta)

    def unconstrained(self, phi, xp):
        return xp.log(xp.maximum(phi, 1e-6))

    def slope(self, phi):
        return phi

    def refuse(self, value):
        return None if value > 0 else "must be > 0"


# --------------------------------------------------------------------------- entries


def _per_component(value, n: int, what: str) -> tuple:
    out = tuple(value) if isinstance(value, (tuple, list)) else (value,) * n
    if len(out) != n:
        raise ValueError(f"Parameter: {what} has {len(out)} items for {n} components")
    return out


class Parameter(eqx.Module):
    """One fittable quantity (a scalar, or a vector with components).

    Attributes:
        name: the entry's name: the component's name for a scalar (``"e"``), the
            :class:`estim.Params` field's for a vector (``"velocity"``).
        field: the field of :class:`estim.Params` that holds it; ``None`` for a quantity of
            the data, not the ball: the release time ``t0`` (the model's t = 0 on the data's
            clock) and ``pixel_scale`` (a factor on a pixel track's scale).
        components: the flat names of its components (``("vx0", "vy0", "vz0")``); a scalar
            has one, its own name.
        transform: to unconstrained coordinates (:class:`Identity`, :class:`Sigmoid`,
            :class:`Exp`).
        default: ``ball -> values`` (one per component) where neither the data nor the
            caller gives one; ``ball`` is the scene's :class:`estim.Ball` (its release
            point, radius and mass).
        start: ``initial -> values`` read from the data (:class:`Initial`, the track's
            flights in the ball's plane of travel), ``None`` for a component the data does
            not give; ``None``: no start from the data.
        hold_start: per component, whether a component that is not fitted is held at the
            data's start (``True``) or at its default (``False``: a release straight from the
            hand, ``vz0 = 0``, unless ``vz0`` is fitted).
        show: per component, ``"always"`` (a column of the fit's table and of the replay's
            captions), ``"fitted"`` (shown where it is fitted) or ``"never"`` (the release
            point: it lies in the plots).
        unit: the unit of every component (``""``: none).
        doc: one line for help texts.
        acts: ``scene -> bool``, whether it changes the motion in ``scene`` (the drag
            coefficient only in air, ``mu_t`` only under a contact law that reads it); a fit
            refuses to estimate it where it does not act, and :func:`to_params` holds it at
            its default there. An entry that can be idle has a default that needs no ball.
        acts_where: where it acts, for messages (``"in a scene with air"``; ``""``: always).
        zero_where_idle: :class:`estim.Params` requires it to be zero where it does not act
            (the spin).
        needs_bounce: the data determines it only through bounces (a note says so when
            none is resolved).
        opt_in: fitted only when asked (``free``, ``--also``), never by default: a
            refinement of the law that a track must show (the restitution's slope with the
            impact speed).
    """

    name: str
    field: str | None
    components: tuple[str, ...]
    transform: AbstractTransform
    default: Callable[[Ball], tuple[float, ...]]
    start: Callable[[Initial], tuple[float | None, ...]] | None
    hold_start: tuple[bool, ...]
    show: tuple[str, ...]
    unit: str
    doc: str
    acts: Callable[[Scene], bool]
    acts_where: str
    zero_where_idle: bool
    needs_bounce: bool
    opt_in: bool

    def __init__(self, name: str, *, field: str | None, default, components: Iterable[str] | None = None,
                 transform: AbstractTransform | None = None, start=None, hold_start=True,
                 show="fitted", unit: str = "", doc: str = "", acts=None, acts_where: str = "",
                 zero_where_idle: bool = False, needs_bounce: bool = False, opt_in: bool = False):
        self.name = name
        self.field = field
        self.components = (name,) if components is None else tuple(components)
        n = len(self.components)
        self.transform = Identity() if transform is None else transform
        if callable(default):
            self.default = default
        else:
            values = _per_component(default, n, "default")
            self.default = lambda ball: values
        self.start = start
        self.hold_start = _per_component(hold_start, n, "hold_start")
        self.show = _per_component(show, n, "show")
        self.unit = unit
        self.doc = doc
        self.acts = _always if acts is None else acts
        self.acts_where = acts_where
        self.zero_where_idle = zero_where_idle
        self.needs_bounce = needs_bounce
        self.opt_in = opt_in

    def __check_init__(self):
        bad = [s for s in self.show if s not in ("always", "fitted", "never")]
        if bad:
            raise ValueError(f"Parameter {self.name!r}: show must be 'always', 'fitted' or 'never', got {bad}")

    def label(self, component: str) -> str:
        """``"vx0 (m/s)"``: the component's name with the unit, for tables and axes."""
        return f"{component} ({self.unit})" if self.unit else component


def _always(scene: Scene) -> bool:
    return True


def _never(scene: Scene) -> bool:
    """Acts through what is observed, not through the scene (the cameras' clocks: an image
    fit admits them itself, estim.fitting._fit)."""
    return False


def _in_air(scene: Scene) -> bool:
    return scene.air is not None


def _spinning(scene: Scene) -> bool:
    """The spin acts through the Magnus force in air, and at impacts under a law that
    couples it to the velocity."""
    return scene.air is not None or law_of(scene).couples_spin


def _read_by_law(field: str) -> Callable[[Scene], bool]:
    """Acts where the scene's contact law reads the :class:`estim.Params` field ``field``
    (``AbstractContactLaw.reads``)."""
    return lambda scene: field in law_of(scene).reads()


# The most cameras an image fit takes: camera 1 and the offsets of the others' clocks
# (``camera_offset``; a fit of other data refuses them, estim.fitting._fit).
MAX_CAMERAS = 4

IN_AIR = "in a scene with air (<option density=...>)"
UNDER_LAW = "under a contact law that reads it (the scene's estim:law)"

REGISTRY: tuple[Parameter, ...] = (
    Parameter("e", field="e", transform=Sigmoid(), default=E_DEFAULT, start=lambda s: (s.e,),
              show="always", needs_bounce=True, acts=_read_by_law("e"), acts_where=UNDER_LAW,
              doc="coefficient of restitution: an impact turns the normal velocity into -e times itself"),
    Parameter("mu_t", field="mu_t", transform=Sigmoid(), default=MU_DEFAULT, start=lambda s: (s.mu_t,),
              show="always", needs_bounce=True, acts=_read_by_law("mu_t"), acts_where=UNDER_LAW,
              doc="tangential coefficient of the factor law: an impact scales the tangential velocity by mu_t"),
    Parameter("mu", field="mu", transform=Sigmoid(), default=FRICTION_DEFAULT, start=lambda s: (s.mu,),
              show="always", needs_bounce=True, acts=_read_by_law("mu"), acts_where=UNDER_LAW,
              doc="Coulomb friction coefficient of the friction law (estim.FrictionLaw), in (0, 1)"),
    Parameter("e_slope", field="e_slope", default=0.0, unit="s/m", needs_bounce=True, opt_in=True,
              acts=_read_by_law("e_slope"), acts_where=UNDER_LAW,
              doc="change of e per m/s of normal impact speed (negative: e falls as impacts get faster), "
                  "about the friction law's reference speed 2.446 m/s (the ITTF drop test's)"),
    Parameter("compression", field="compression", default=0.0, unit="m", needs_bounce=True, opt_in=True,
              doc="how much closer than its radius the ball's centre comes to a surface at a bounce (the "
                  "contact radius is radius - compression; negative: a larger effective contact radius)"),
    Parameter("position", field="position", components=("x0", "y0", "z0"), unit="m",
              default=lambda ball: tuple(ball.position), start=lambda s: s.position, show="never",
              doc="release position of the ball's centre"),
    Parameter("velocity", field="velocity", components=("vx0", "vy0", "vz0"), unit="m/s",
              default=(0.0, 0.0, 0.0), start=lambda s: s.velocity, hold_start=(True, True, False),
              show=("always", "fitted", "fitted"), doc="release velocity"),
    Parameter("t0", field=None, unit="s", default=0.0,
              doc="release time on the data's clock (the model's t = 0)"),
    Parameter("drag_coefficient", field="drag_coefficient", transform=Exp(), default=DRAG_COEFFICIENT,
              acts=_in_air, acts_where=IN_AIR, doc="drag coefficient C_D of the quadratic drag"),
    Parameter("lift_factor", field="lift_factor", transform=Exp(), default=1.0, acts=_in_air, acts_where=IN_AIR,
              doc="factor on the Magnus lift coefficient (1: the textbook curve of Sawicki et al.)"),
    Parameter("spin", field="spin", components=("spin_x", "spin_y", "spin_z"), unit="rad/s",
              default=(0.0, 0.0, 0.0), start=lambda s: s.spin, hold_start=False, acts=_spinning,
              acts_where=f"{IN_AIR} or under a contact law that couples spin (estim:law friction)",
              zero_where_idle=True, doc="angular velocity at release: the Magnus force in flight, the "
                                        "friction law's bounces"),
    Parameter("camera_offset", field=None, components=tuple(f"dt_camera{k}" for k in range(2, MAX_CAMERAS + 1)),
              unit="s", default=0.0, acts=_never, acts_where="in a fit of image tracks seen by several cameras",
              doc="time added to the clock of camera k (2, 3, ...) to put its rows on camera 1's: image tracks "
                  "seen by several cameras (estim.fitting._image)"),
    Parameter("pixel_scale", field=None, transform=Exp(), default=1.0,
              doc="factor on a pixel track's metres per pixel about its surface (1: the scale "
                  "read off the data; fitted per clip where that scale is biased, as by drag)"),
)

# Every component, in registry order: the layout of the fit's vector phi.
NAMES: tuple[str, ...] = tuple(c for p in REGISTRY for c in p.components)
_ENTRY = {c: p for p in REGISTRY for c in p.components}
_INDEX = {c: i for i, c in enumerate(NAMES)}


def _check_registry() -> None:
    """Components are unique, and a vector's name is no component's (``expand`` reads it)."""
    if len(set(NAMES)) != len(NAMES):
        raise ValueError(f"the registry names a component twice: {NAMES}")
    vectors = [p.name for p in REGISTRY if p.components != (p.name,)]
    clash = [n for n in vectors if n in NAMES]
    if clash:
        raise ValueError(f"registry entries named like a component: {clash}")
    fields = [p.field for p in REGISTRY if p.field is not None]
    if len(set(fields)) != len(fields):
        raise ValueError(f"two registry entries write the same Params field: {fields}")


_check_registry()


def component(name: str) -> Parameter:
    """The entry that holds the component ``name``.

    Raises:
        ValueError: an unknown name, listing the known ones.
    """
    try:
        return _ENTRY[name]
    except KeyError:
        raise ValueError(f"unknown parameter {name!r}; the parameters are {NAMES}") from None


def expand(names: Iterable[str]) -> tuple[str, ...]:
    """Flat component names for ``names``, where a vector entry's name stands for all its
    components (``"spin"`` -> ``spin_x, spin_y, spin_z``); order kept, repeats dropped.

    Raises:
        ValueError: an unknown name.
    """
    vectors = {p.name: p.components for p in REGISTRY if p.components != (p.name,)}
    out = []
    for n in names:
        for c in vectors.get(n, (n,)):
            component(c)  # raises for an unknown name
            if c not in out:
                out.append(c)
    return tuple(out)


def index(names: Iterable[str]) -> np.ndarray:
    """Positions of the components ``names`` in the vector phi."""
    return np.array([_INDEX[n] for n in names], dtype=np.int64)


def value(phi, name: str):
    """The component ``name`` of the vector phi."""
    return phi[_INDEX[name]]


def pack(values: Mapping[str, float]) -> np.ndarray:
    """The vector phi of ``values`` (one float64 per name of :data:`NAMES`, all required)."""
    missing = [n for n in NAMES if n not in values]
    if missing:
        raise ValueError(f"no value for {missing}")
    return np.array([values[n] for n in NAMES], dtype=np.float64)


def unpack(phi) -> dict[str, Any]:
    """``name -> phi[k]`` for every component (NumPy or JAX scalars, as phi holds them)."""
    return {n: phi[i] for i, n in enumerate(NAMES)}


class _Bound(NamedTuple):
    """A transform's methods, bound once (:func:`_transform`)."""

    physical: Callable
    unconstrained: Callable
    slope: Callable


def _transform(name: str) -> _Bound:
    """The methods of the transform of the component ``name``. Bound once: an equinox
    Module builds a bound method (itself a Module) at every attribute access, which the
    fits' bookkeeping did thousands of times per fit of many clips."""
    if name not in _BOUND:
        component(name)  # raises, naming the known parameters
    return _BOUND[name]


_BOUND = {n: _Bound(_ENTRY[n].transform.physical, _ENTRY[n].transform.unconstrained, _ENTRY[n].transform.slope)
          for n in NAMES}


def to_physical(theta, free: tuple[str, ...], fixed):
    """phi: ``fixed`` (every component) with the fitted components ``free`` at
    ``T(theta)``; NumPy in, NumPy out (a copy), JAX in, JAX out."""
    xp = array_namespace(theta)
    values = [_transform(n).physical(theta[i], xp) for i, n in enumerate(free)]
    if xp is np:
        out = np.array(fixed, dtype=np.float64)
        out[index(free)] = values
        return out
    return fixed.at[index(free)].set(jnp.stack(values))


def to_theta(phi, free: tuple[str, ...]):
    """theta: the unconstrained coordinates of the components ``free`` of phi."""
    xp = array_namespace(phi)
    return xp.stack([_transform(n).unconstrained(value(phi, n), xp) for n in free])


def slopes(phi, free: tuple[str, ...]) -> np.ndarray:
    """``d phi_k / d theta_k`` for the components ``free`` at phi (NumPy)."""
    return np.array([_transform(n).slope(value(phi, n)) for n in free], dtype=np.float64)


def priors(scene: Scene, given: Mapping[str, Any] | None = None) -> dict[str, tuple[float, float]]:
    """The priors of a fit: ``component -> (mean, standard deviation)``, the scene's
    (``Scene.priors``, as its MJCF file declares them) updated by ``given`` (a name, or a
    vector's name for all its components, to ``(mean, sd)``, or to ``None`` to drop the
    scene's prior on it).

    Raises:
        ValueError: an unknown name, a standard deviation that is not a positive finite
            number, or a mean outside the parameter's range (each message names it).
    """
    out: dict[str, tuple[float, float]] = {}
    for source, items in (("the scene's", [(n, (m, sd)) for n, m, sd in scene.priors]),
                          ("the", list((given or {}).items()))):
        for name, spec in items:
            try:
                names = expand((name,))
            except ValueError as err:
                raise ValueError(f"{source} prior on {name!r}: {err}") from None
            if spec is None:
                for c in names:
                    out.pop(c, None)
                continue
            try:
                mean, sd = (float(v) for v in spec)
            except (TypeError, ValueError):
                raise ValueError(f"{source} prior on {name!r} must be (mean, standard deviation), got {spec!r}") from None
            if not (math.isfinite(mean) and math.isfinite(sd) and sd > 0):
                raise ValueError(f"{source} prior on {name!r} = ({mean}, {sd}): the mean must be finite and "
                                 "the standard deviation a positive finite number")
            for c in names:
                why = component(c).transform.refuse(mean)
                if why:
                    raise ValueError(f"{source} prior on {c!r}: its mean {mean} {why}")
                out[c] = (mean, sd)
    return out


def prior_arrays(priors_: Mapping[str, tuple[float, float]]) -> np.ndarray:
    """``(2, len(NAMES))``: the priors' means and inverse standard deviations in the order
    of phi (weight 0 where a component has no prior)."""
    out = np.zeros((2, len(NAMES)))
    for n, (mean, sd) in priors_.items():
        out[:, _INDEX[n]] = mean, 1.0 / sd
    return out


def defaults(ball: Ball) -> dict[str, float]:
    """Every component's default for the scene's ball ``ball``."""
    out = {}
    for p in REGISTRY:
        out.update(zip(p.components, (float(v) for v in p.default(ball)), strict=True))
    return out


def starting_values(ball: Ball, initial: Initial, free: Iterable[str]) -> dict[str, float]:
    """Every component's starting value: the data's start (``Parameter.start``) for a
    fitted component, and for a fixed one where ``hold_start`` says so; else the default."""
    free = set(free)
    out = {}
    for p in REGISTRY:
        data = p.start(initial) if p.start is not None else (None,) * len(p.components)
        for c, d, s, hold in zip(p.components, p.default(ball), data, p.hold_start, strict=True):
            out[c] = float(s) if s is not None and (hold or c in free) else float(d)
    return out


def _stack(values):
    return jnp.stack(values) if len(values) > 1 else values[0]


def acting(scene: Scene) -> frozenset[str]:
    """The components that change the motion in ``scene`` (``Parameter.acts``)."""
    return frozenset(c for p in REGISTRY if p.acts(scene) for c in p.components)


def where_it_acts(name: str) -> str:
    """Where the component ``name`` acts, for a refusal: its entry's ``acts_where``, and for
    a coefficient that only some contact laws read, those laws and how a scene declares
    one. Asked when a message needs it, not in ``acts_where``: which laws read a field is
    traced (``AbstractContactLaw.reads``), and importing estim or building the CLI's help
    must not start JAX's backend (``jax.distributed.initialize`` comes first)."""
    entry = component(name)
    names = laws_reading(entry.field) if entry.acts_where == UNDER_LAW else LAWS
    if len(names) == len(LAWS):
        return entry.acts_where
    return (f"under a contact law that reads it ({' or '.join(names)}; a scene declares its law with "
            f'<custom><text name="estim:law" data="{names[-1]}"/></custom>, the factor law where it declares none)')


def check_acting(scene: Scene, names: Iterable[str], what: str = "fitting") -> None:
    """Refuse components that do nothing in ``scene``: an estimate of them would be noise,
    a value given for them silently ignored.

    Raises:
        ValueError: naming each and where it acts.
    """
    idle = [n for n in names if not component(n).acts(scene)]
    if idle:
        where = "; ".join(f"{n} acts only {where_it_acts(n)}" for n in idle)
        raise ValueError(f"{what} {idle}: {where}, and this scene's ({type(law_of(scene)).__name__}"
                         f"{', with air' if scene.air is not None else ', no air'}) does not have it")


# Fitted by default for the seed's factor law: the release speed along x, the release point
# in the x-z plane, e and mu_t (the release from the hand: vz0 = 0); for a track with y the
# lateral release state too (``LATERAL``).
FACTOR_FREE = ("e", "mu_t", "vx0", "x0", "z0")
LATERAL = ("y0", "vy0")
# A drop filmed from the side (a pixel track read at one scale) starts with an unknown
# vertical speed; it has no y.
SIDE_VIEW = ("vx0", "vz0", "x0", "z0")


def default_free(scene: Scene, lateral: bool, known: Iterable[str] = ()) -> tuple[str, ...]:
    """What a fit estimates by default in ``scene``: the law's coefficients that act there
    (``e``, and ``mu_t`` or ``mu``) and the release state.

    Under the seed's factor law: ``FACTOR_FREE``, and ``LATERAL`` for a track with y
    (``lateral``). Under a law that couples spin (a ball thrown or hit, as in table
    tennis): the law's coefficients, the release position and velocity (3-vectors) and
    the spin, which the bounce (and in air the Magnus force) reads.

    ``known``: the parameters with a prior (:func:`priors`: the scene's, as a fit of one
    track in metres applies them, ``estim.fit``); those that act join, after the law's
    coefficients. What is known of a parameter, a real ball's drag coefficient say, is
    estimated with that knowledge rather than held at a textbook value."""
    known = tuple(n for n in expand(tuple(known)) if _ENTRY[n].acts(scene))
    if not law_of(scene).couples_spin:
        base = FACTOR_FREE + (LATERAL if lateral else ())
        return base + tuple(n for n in known if n not in base)
    coefficients = _law_coefficients(scene)
    state = expand(("position", "velocity", "spin"))
    coefficients += tuple(n for n in known if n not in coefficients and n not in state)
    return coefficients + state


def side_view_free(scene: Scene) -> tuple[str, ...]:
    """What a fit of a side view's pixel track estimates by default in ``scene``: the
    coefficients of the scene's law that act there (``e`` and ``mu_t`` under the factor
    law, ``e`` and ``mu`` under the friction law) and the release state in the view's plane
    (``SIDE_VIEW``)."""
    return _law_coefficients(scene) + SIDE_VIEW


def _law_coefficients(scene: Scene) -> tuple[str, ...]:
    return tuple(p.name for p in REGISTRY if p.needs_bounce and not p.opt_in and p.acts(scene))


def to_params(values: Mapping[str, Any], *, radius, mass=None, inertia=None, scene: Scene | None = None) -> Params:
    """The :class:`estim.Params` of ``values`` (``name -> value`` for every component whose
    entry has a field; NumPy, JAX or Python numbers) for a ball of ``radius``, ``mass``
    (which only a scene with air needs: ``None`` keeps the pytree of a plain simulation)
    and ``inertia`` (I / (m r^2); ``None``: a solid sphere's).

    With ``scene``, the entries that do not act there (:func:`acting`: the drag
    coefficient in a vacuum, ``mu_t`` under the friction law) are held at their defaults,
    as constants: they change nothing there, and a traced value would only add work to the
    compiled program."""
    fields: dict[str, Any] = {"radius": radius, "mass": mass}
    if inertia is not None:
        fields["inertia"] = inertia
    for p in REGISTRY:
        if p.field is None:
            continue
        idle = scene is not None and not p.acts(scene)
        fields[p.field] = _stack(list(p.default(None)) if idle else [values[c] for c in p.components])
    return Params(**fields)


def with_values(params: Params, values: Mapping[str, Any]) -> Params:
    """``params`` with the components ``values`` (``name -> value``) replaced, the others
    kept: for derivatives with respect to a few components of given parameters."""
    for name, v in values.items():
        p = component(name)
        if p.field is None:
            raise ValueError(f"{name} is not a field of Params")
        old = getattr(params, p.field)
        new = v if p.components == (name,) else old.at[..., p.components.index(name)].set(v)
        params = eqx.tree_at(lambda q, f=p.field: getattr(q, f), params, jnp.asarray(new, dtype=jnp.float64))
    return params


def values_for(ball: Ball, given: Mapping[str, Any]) -> dict[str, float]:
    """Every component: ``given`` where it names one, else the default for ``ball``.

    Raises:
        ValueError: a value that is not a finite number.
    """
    out = defaults(ball)
    for name, v in given.items():
        component(name)
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
                or not math.isfinite(float(v)):
            raise ValueError(f"{name} = {v!r} is not a finite number")
        out[name] = float(v)
    return out


def shown(values: Mapping[str, float], fitted: Iterable[str] = ()) -> list[str]:
    """The components a table or a caption shows: those shown ``"always"`` and the
    ``"fitted"`` ones among ``fitted``, in registry order, restricted to ``values``."""
    fitted = set(fitted)
    out = []
    for p in REGISTRY:
        for c, how in zip(p.components, p.show, strict=True):
            if c in values and (how == "always" or (how == "fitted" and c in fitted)):
                out.append(c)
    return out


def describe(values: Mapping[str, float], fitted: Iterable[str] = (), *, sep: str = "   ") -> str:
    """``"e = 0.580   mu_t = 0.950   vx0 = 0.500 m/s"``: the components :func:`shown`
    (a caption's line)."""
    parts = []
    for c in shown(values, fitted):
        unit = _ENTRY[c].unit
        parts.append(f"{c} = {float(values[c]):.3f}" + (f" {unit}" if unit else ""))
    return sep.join(parts)
