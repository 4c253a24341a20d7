"""The numbers the JAX solver and the native kernels share, defined once, here.

Tolerances, limits, the numbering of segment kinds, end reasons and event kinds, and the
columns of the face table: everything ``estim/forward/_kernels.cc`` would otherwise copy by
hand. This file is plain Python with no imports, so that ``setup.py`` can read it at build
time (``runpy``) and write ``estim/forward/_constants.h``, the header the kernels are
compiled with: a change here reaches C++ at the next build. The compiled kernels report
the values they were built with (``_kernels.constants()``), and ``estim.forward._native``
runs them only where these agree with this file (a stale build falls back to the JAX
planner); ``tests/test_laws.py`` checks both, and that the C++ source writes none of
these numbers as a literal.

Only names in upper case with an ``int`` or ``float`` value are exported to C++: a float as
``constexpr double`` (written in hexadecimal, exactly), an int as ``constexpr int32_t``.
"""

# --- Tolerances (estim.forward._contact) --------------------------------------------------
# Positions are metres of order 1-10, so rounding is ~1e-15 m; a face counts as touched
# within POSITION_TOL and a normal speed below SPEED_TOL counts as zero.
POSITION_TOL = 1e-12
SPEED_TOL = 1e-12
# Likewise a normal acceleration below ACCEL_TOL (m/s^2) counts as zero. Accelerations are
# of order g ~ 10, so rounding leaves ~1e-15 in one that is zero exactly (a ball sliding
# along two inclined planes got G2 = -1.2e-15 for one, "entered" it at tau = 0, and so on,
# switching faces forever at one instant).
ACCEL_TOL = 1e-12
# A hop off an edge or a corner lower than HOP_HEIGHT (m) lands where the quadratic model of
# its distance says, not where the quartic does (estim.forward._contact._curved_time).
HOP_HEIGHT = 1e-9
# A point on a face's plane lies on the face if it is inside the grown box to ON_FACE_TOL.
ON_FACE_TOL = 1e-9
# A bounce whose post-impact normal speed is below REST_SPEED ends the bounce series: the
# remaining flights would last less than 2 REST_SPEED / g ~ 2e-10 s in all.
REST_SPEED = 1e-9
# Contacts less than TIE_TIME (s) apart are simultaneous: the tie goes to the face of lower
# rank (a face before an edge before a corner), then of lower index.
TIE_TIME = 1e-12
# A component (or a cosine) of unit vectors within AXIS_TOL of 0 or 1 is taken as exactly
# so: a face whose normal has n_z > 1 - AXIS_TOL points up, two faces whose normals have
# |n . m| < AXIS_TOL are perpendicular, and a direction of travel's component below
# AXIS_TOL is zero (over the metres a bounce series travels it moves the ball less than
# ON_FACE_TOL: ``estim.forward._contact.train_reach``).
AXIS_TOL = 1e-12
# A ball starts inside a solid when its centre is deeper than INSIDE_DEPTH (m) in the
# solid grown by its radius (estim.forward._balls.inside).
INSIDE_DEPTH = 1e-9

# --- Edges and corners (estim.forward._curved, estim.forward._roll) --------------------------
# A contact time on an edge or a corner: CURVED_BISECTIONS bisections shrink its bracket by
# 2^-24 (6e-9 s on a 0.1 s window), then Newton's method converges quadratically from there
# in CURVED_NEWTONS steps (to 1e-16 s).
CURVED_BISECTIONS = 24
CURVED_NEWTONS = 6
# A flight's time window near a piece is searched to at most FAR_HORIZON (s) ahead (an
# infinite horizon: a million seconds), and its crossings of the piece's box of reach are
# kept within WINDOW_MARGIN times (1 + the box's coordinates) of its bounds (they are on the
# bounds up to rounding).
FAR_HORIZON = 1e6
WINDOW_MARGIN = 1e-9
# Duplication steps of Carlson's R_F: each divides the spread of its arguments by 4, and
# after the first the spread is below 1, so 12 leave a series error below 1e-30 (Carlson 1995).
RF_STEPS = 12
# Newton steps for the hyperbolic angle of a time inside a roll: dt/dw is within a factor
# sqrt 2 of constant, and the first step starts within a factor 2.
ROLL_NEWTONS = 10
# Bracketed Newton steps for where a roll over a corner leaves the corner's region
# (estim.forward._roll.Spherical): each at least halves the bracket where Newton's step
# leaves it.
SPHERE_STEPS = 40
# A roll whose energy parameter B is exactly 0 (moving off the ridge, by rounding) is taken
# as B = RIDGE_B k, a hair above 0 (its time depends on B like B log B).
RIDGE_B = 1e-300

# --- Bounce series (estim.forward.laws) -----------------------------------------------------
# Where mu_t and e agree to within SERIES_GAP the factor law's divided differences are
# evaluated with e moved by SERIES_GAP (estim.forward.laws.FactorLaw).
SERIES_GAP = 1e-6
# Bounce counts are whole floats; beyond 2^52 float64 cannot count them. (An e = 1 series
# with a 0.2 us period reaches 10^7 bounces in 2 s: a cap of 10^6 made such a ball fall
# through its face after 10^6 bounces.)
MAX_COUNT = 4503599627370496.0  # 2.0**52
# Bounces of a Zeno series whose flight is shorter than LISTED_FLIGHT (s) are summed, not
# listed as events.
LISTED_FLIGHT = 1e-6

# --- How a ball moves in a closed-form segment (Decision.kind), and in an ODE step's mode ---
# FLIGHT: a parabola (or an integrated flight); TRAIN: a whole bounce series on one face,
# summed in closed form; SLIDE: moving along (or resting on) a face; UNUSED: a padding slot;
# ROLL: rolling over an edge or a corner (estim.forward._roll; exact geometry only). The
# ODE path's mode (Step.mode) is FLIGHT, SLIDE or ROLL: the same notion.
FLIGHT = 0
TRAIN = 1
SLIDE = 2
UNUSED = 3
ROLL = 4

# --- Why a closed-form segment ends (Decision.reason) ----------------------------------------
END = 0  # at t_end
CONTACT = 1  # at a contact with a face
EXIT = 2  # sliding off a face's edge, or leaving an edge or a corner the ball rolls over
BOUNCES = 3  # a bounce series ends after its last bounce that provably lands on its face
SETTLE = 4  # a bounce series accumulates (Zeno): the ball comes to rest or slides

# --- What an ODE step is (estim.forward._ode, Step.kind) -------------------------------------
# Not the kinds above: an integrator step is not a segment (one flight takes many steps),
# and its kind says how the step ends (at its length, at t_end, at a contact, at a slide's
# exit), or that it is a bounce series summed in closed form (the ODE's counterpart of a
# TRAIN) or a padding slot. Their values are those the ODE path has always written (a
# Trajectory's solution.steps.kind).
STEP_PLAIN = 0
STEP_LAST = 1
STEP_CONTACT = 2
STEP_EXIT = 3
STEP_ZENO = 4
STEP_UNUSED = 5
STEP_DETACH = 6  # a roll over an edge or a corner ends where the surface stops pushing

# --- Event kinds (estim.forward._trajectory, Events.kind) ------------------------------------
IMPACT = 0
REST = 1

# --- Columns of a face-table row (estim.forward._contact.Faces.row) ---------------------------
# unit normal (3), plane offset H (1), centre (3) and half sizes (3) of the owning box,
# face direction m (3), index of the owning solid (1).
FACE_NORMAL = 0
FACE_OFFSET = 3
FACE_CENTRE = 4
FACE_HALF = 7
FACE_DIRECTION = 10
FACE_SOLID = 13
FACE_ROW = 14


def exported() -> dict[str, int | float]:
    """The constants the kernels are built with: every upper-case int or float above."""
    return {k: v for k, v in globals().items()
            if k.isupper() and isinstance(v, (int, float)) and not isinstance(v, bool)}
