// The closed-form solver of estim as native CPU kernels, called from JAX through its
// foreign function interface (XLA FFI; estim.forward._native registers and calls them).
//
// What runs here is the *primal* of the gravity-only path: the plan of every ball (the
// discrete structure of its solution and its segments), its samples, its event list and
// its packed Trajectory rows. Derivatives never come here: JAX computes them by replaying
// the structure this kernel found with the differentiable closed forms of estim.forward._solver
// (estim.forward._native, the custom_jvp). Every function below is a line-by-line port of the
// JAX function of the same name, with the same formulas and the same tolerances; the
// docstrings there carry the maths (estim.forward._contact, estim.forward._curved,
// estim.forward._roll, estim.forward.laws, estim.forward._solver, estim.forward._trajectory) and
// tests/test_native.py checks that both give the same structure and the same numbers, to
// rounding, ball by ball. Both geometries run here: the seed's (a box is its faces) and
// exact edges and corners (the quartic contact search, exact normals, rolls over edges and
// corners, the spherical pendulum included).
//
// Why native: a JAX program of this event loop is a single XLA kernel of some 26,000 HLO
// lines that takes XLA 2.5 s to compile, and a call of it costs its buffers' allocations.
// Compiled here, once, at install, a call is the loop alone (docs/pages/speed.md).
//
// Semantics kept from JAX: jnp.minimum / jnp.maximum / jnp.min propagate NaN (jmin, jmax
// below), comparisons with NaN are false, and expressions are evaluated in the order the
// JAX code writes them (XLA does not reassociate floating point; where XLA fuses a multiply
// and an add under jit, or its sinh, cosh, asinh, sin, cos, atan2, asin and acos differ from
// the C library's by an ulp, the results differ by rounding: tests/test_native.py says where
// that grows).
//
// The contact law: the kernels implement the seed's factor law (estim.forward.laws.FactorLaw:
// reset, settle and its bounce series' closed forms, the section "The factor law" below)
// and no other; estim.forward._native.supports says so, and every other law runs on the JAX
// planner. The numbers shared with the JAX solver (tolerances, limits, the numbering of
// segment kinds, end reasons and event kinds, the face table's columns) are not written
// here: they come from estim/forward/_constants.py, through the header setup.py generates
// from it (_constants.h), and the module reports them back (constants()).

#include <Python.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <optional>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include "_constants.h"  // generated from estim/forward/_constants.py by setup.py
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

// Builds of a hot loop for several instruction sets, chosen at load time (GCC and Clang
// on x86-64 with glibc's ifunc; elsewhere the one baseline build).
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__)) && defined(__linux__)
#define ESTIM_TARGET_CLONES __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define ESTIM_TARGET_CLONES
#endif

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kPi = 3.141592653589793;  // (Python's math.pi, as jnp.pi)
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// Tolerances, limits, segment kinds (FLIGHT, TRAIN, SLIDE, UNUSED), end reasons (END,
// CONTACT, EXIT, BOUNCES, SETTLE) and event kinds (IMPACT, REST): _constants.h.

// Columns of a face-table row (estim.forward._contact.Faces.row).
constexpr int ROW = FACE_ROW, NORMAL = FACE_NORMAL, OFFSET = FACE_OFFSET, CENTRE = FACE_CENTRE, HALF = FACE_HALF,
              DIRECTION = FACE_DIRECTION, SOLID = FACE_SOLID;

inline double jmin(double a, double b) { return (a != a || b != b) ? kNaN : (a < b ? a : b); }
inline double jmax(double a, double b) { return (a != a || b != b) ? kNaN : (a > b ? a : b); }
inline double clip_index(double k, double hi) { return k < 0 ? 0 : (k > hi ? hi : k); }

struct V3 {
  double x[3];
  double operator[](int i) const { return x[i]; }
  double& operator[](int i) { return x[i]; }
};
inline V3 v3(double a, double b, double c) { return V3{{a, b, c}}; }
inline V3 load3(const double* p) { return V3{{p[0], p[1], p[2]}}; }
inline V3 operator+(V3 a, V3 b) { return v3(a[0] + b[0], a[1] + b[1], a[2] + b[2]); }
inline V3 operator-(V3 a, V3 b) { return v3(a[0] - b[0], a[1] - b[1], a[2] - b[2]); }
inline V3 operator*(double s, V3 a) { return v3(s * a[0], s * a[1], s * a[2]); }
inline V3 operator*(V3 a, double s) { return v3(a[0] * s, a[1] * s, a[2] * s); }
// estim._fold.inner: x0 y0 + x1 y1 + x2 y2, left to right
inline double inner(V3 a, V3 b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
inline bool all_finite(V3 a) { return std::isfinite(a[0]) && std::isfinite(a[1]) && std::isfinite(a[2]); }
const V3 kZero = v3(0.0, 0.0, 0.0);
const V3 kUp = v3(0.0, 0.0, 1.0);

// ---------------------------------------------------------------------------------------
// The scene for one ball radius (estim.forward._contact.Faces) and the solids (estim.forward._simulate).

struct Scene {
  int n_faces, n_solids, n_boxes, n_planes;
  const double* row;       // (faces, 14)
  const double* growth;    // (faces,)
  const double* rank;      // (faces,): 1 a flat face, 2 an edge, 3 a corner
  const double* box_lo;    // (solids, 3): solids as boxes, before growing by r
  const double* box_hi;
  const double* centre;    // (boxes, 3): the boxes themselves
  const double* half;
  const double* p_normal;  // (planes, 3)
  const double* p_offset;  // (planes,)
  double gravity;
  bool exact;  // exact geometry (edges and corners; estim.model._scene): else the seed's
};

// A broad phase for first_contact, exact: a face's contact point lies within
// ON_FACE_TOL of its solid's box grown by r along every axis, so the path cannot touch
// a solid's faces before it enters that box grown by BROAD_MARGIN more (a margin far
// above ON_FACE_TOL and the rounding of a contact time). For each axis, the earliest time
// the coordinate reaches the box's interval is a lower bound; the latest over the axes is
// the solid's bound.
constexpr double BROAD_MARGIN = 1e-6;

struct Faces {
  const Scene* s = nullptr;
  double radius = 0.0;
  int n_flat = 0;  // faces [0, n_flat) are flat, the rest edges and corners (exact geometry)
  std::vector<double> offset;  // plane offset for the ball's centre, per face
  std::vector<int32_t> order;  // rank * faces + index: ties go to lower rank, then index
  // The flat faces of each solid, [first[b], first[b + 1]) (estim.model._scene lists them solid
  // by solid); empty when a scene lists them otherwise, and then no broad phase is used.
  std::vector<int> first;
  std::vector<double> nx, ny, nz;  // the faces' normals, one array per axis
  std::vector<double> reach_lo[3], reach_hi[3];  // the solids' boxes grown for reach_bounds

  // The table for a ball of radius r, rebuilt only as far as the scene's buffers or the
  // radius differ from the last ball's (the balls of a call share a scene, and mostly
  // their radius).
  void reset(const Scene* scene, double r) {
    const std::array<const void*, 6> key{scene->row, scene->growth, scene->box_lo, scene->box_hi, scene->centre,
                                         scene->half};
    s = scene;
    if (key != built_from) {
      build(*scene);
      built_from = key;
      sized = false;
    }
    if (sized && radius == r) return;
    radius = r;
    const int F = scene->n_faces;
    offset.resize(F);
    for (int f = 0; f < F; ++f) offset[f] = scene->row[f * ROW + OFFSET] + radius * scene->growth[f];
    for (int i = 0; i < 3; ++i) {
      // (Padded to a multiple of 8 solids, so that reach_bounds runs whole vectors: the
      // padding's bounds are computed and never read.)
      reach_lo[i].assign((scene->n_solids + 7) / 8 * 8, 0.0);
      reach_hi[i].assign((scene->n_solids + 7) / 8 * 8, 0.0);
      for (int b = 0; b < scene->n_solids; ++b) {
        reach_lo[i][b] = lo(b, i) - BROAD_MARGIN;
        reach_hi[i][b] = hi(b, i) + BROAD_MARGIN;
      }
    }
    sized = true;
  }
  // Forgets the scene: a later call may bring another scene in the same buffers.
  void forget() { built_from = {}; }

 private:
  std::array<const void*, 6> built_from{};
  bool sized = false;

  void build(const Scene& scene) {
    const int F = scene.n_faces;
    order.resize(F);
    for (int f = 0; f < F; ++f) order[f] = static_cast<int32_t>(scene.rank[f]) * F + f;
    n_flat = 0;
    while (n_flat < F && scene.rank[n_flat] == 1) ++n_flat;
    first.assign(scene.n_solids + 1, n_flat);
    bool grouped = true;
    for (int f = 0, b = 0; f < n_flat && grouped; ++f) {  // b: the next solid to start
      const double solid = scene.row[f * ROW + SOLID];
      grouped = solid >= b - 1 && solid < scene.n_solids;
      for (; grouped && b <= solid; ++b) first[b] = f;
    }
    if (!grouped) first.clear();
    nx.resize(F);
    ny.resize(F);
    nz.resize(F);
    for (int f = 0; f < F; ++f) {
      nx[f] = scene.row[f * ROW + NORMAL];
      ny[f] = scene.row[f * ROW + NORMAL + 1];
      nz[f] = scene.row[f * ROW + NORMAL + 2];
    }
  }

 public:
  const double* row(int f) const { return s->row + f * ROW; }
  V3 normal(int f) const { return load3(row(f) + NORMAL); }
  double lo(int b, int i) const { return s->box_lo[b * 3 + i] - radius; }
  double hi(int b, int i) const { return s->box_hi[b * 3 + i] + radius; }
};

// ---------------------------------------------------------------------------------------
// estim.forward._contact

inline bool moves_into(double g1, double g2) {
  return (g1 < -SPEED_TOL) | ((std::fabs(g1) <= SPEED_TOL) & (g2 < -ACCEL_TOL));
}

// (Without branches, so that the compiler vectorises the face loop of ContactSearch:
// each operation as in estim.forward._contact.entering_time, the selects as jnp.where.)
inline __attribute__((always_inline)) double entering_time(double g0, double g1, double g2) {
  const bool touching = std::fabs(g0) <= POSITION_TOL;
  const bool pushed = moves_into(g1, g2);
  const bool along = touching & (std::fabs(g1) <= SPEED_TOL) & (std::fabs(g2) <= ACCEL_TOL);
  const double disc = g1 * g1 - 2.0 * g2 * g0;
  const bool positive = disc > 0;
  const bool has_root = positive | ((g2 < -ACCEL_TOL) & (disc >= 2.0 * g2 * POSITION_TOL));
  const double s = positive ? std::sqrt(positive ? disc : 1.0) : 0.0;
  const bool neg = g1 < 0;
  // neg: 2 g0 / (s - g1); else (-g1 - s) / (g2, or -1 where g2 = 0)
  const double tau = (neg ? 2.0 * g0 : -g1 - s) / (neg ? s - g1 : (g2 == 0 ? -1.0 : g2));
  const bool future = has_root & (tau > 0) & (neg | (g2 < 0));
  // A hop lower than rounding (g0 a hair inside, no real root): back after -2 g1 / g2.
  const bool hop = touching & !future & (g1 > SPEED_TOL) & (g2 < 0);
  const double back = -2.0 * g1 / (g2 < 0 ? g2 : -1.0);
  return (touching & pushed) ? 0.0 : ((future & !along) ? tau : (hop ? back : kInf));
}

// ballistic: p + v tau + a tau^2 / 2 (as ((p + v tau) + ((0.5 a) tau) tau)), v + a tau
inline V3 ballistic_p(V3 p, V3 v, V3 a, double tau) {
  V3 out;
  for (int i = 0; i < 3; ++i) out[i] = p[i] + v[i] * tau + 0.5 * a[i] * tau * tau;
  return out;
}
inline V3 ballistic_v(V3 v, V3 a, double tau) { return v + a * tau; }

bool on_face(V3 q, const double* centre, const double* half, double radius) {
  double excess = 0.0;
  for (int i = 0; i < 3; ++i) excess = excess + jmax(std::fabs(q[i] - centre[i]) - half[i], 0.0);
  return excess <= radius + ON_FACE_TOL;
}

// Lower bounds on when the path reaches each of n solids' boxes (grown): bound[b], the
// latest over the axes of the earliest time the coordinate reaches the box's interval.
// Along an axis without acceleration (x and y in flight) that time is a division; the
// loops over solids vectorise.
ESTIM_TARGET_CLONES
void reach_bounds(const Faces& fc, int n, V3 p, V3 v, V3 a, double* bound) {
  for (int b = 0; b < n; ++b) bound[b] = 0.0;
  for (int i = 0; i < 3; ++i) {
    const double *lo = fc.reach_lo[i].data(), *hi = fc.reach_hi[i].data();
    const double q = p[i], w = v[i], pull = a[i];
    if (pull != 0) {
      for (int b = 0; b < n; ++b) {
        const bool below = q < lo[b], above = q > hi[b];
        const double t = (below | above) ? entering_time(below ? lo[b] - q : q - hi[b], below ? -w : w, below ? -pull : pull)
                                         : (q >= lo[b] ? 0.0 : kInf);  // (inside; NaN: never)
        bound[b] = bound[b] > t ? bound[b] : t;
      }
      continue;
    }
    for (int b = 0; b < n; ++b) {
      const bool below = q < lo[b], above = q > hi[b];
      const double gap = below ? lo[b] - q : q - hi[b], toward = below ? w : -w;
      const double t = (below | above) ? (toward > 0 ? gap / (toward > 0 ? toward : 1.0) : kInf)
                                       : (q >= lo[b] ? 0.0 : kInf);  // (inside; NaN: never)
      bound[b] = bound[b] > t ? bound[b] : t;
    }
  }
}

// The entering time of each of n faces (normals nx, ny, nz; plane offsets), inf for the
// face `exclude`: the loop the contact search spends most of its time in. The compiler
// vectorises it, and builds it for AVX-512 and AVX2 as well as for the baseline x86-64
// (function multiversioning: the CPU picks at load time). Contraction to FMA is off
// (setup.py), so every version computes the same bits.
ESTIM_TARGET_CLONES
void face_times(const double* nx, const double* ny, const double* nz, const double* offset, int n, int exclude,
                V3 p, V3 v, V3 a, double* times) {
  const double p0 = p[0], p1 = p[1], p2 = p[2], v0 = v[0], v1 = v[1], v2 = v[2], a0 = a[0], a1 = a[1], a2 = a[2];
  for (int f = 0; f < n; ++f) {
    const double g0 = ((nx[f] * p0 + ny[f] * p1) + nz[f] * p2) - offset[f];
    const double g1 = (nx[f] * v0 + ny[f] * v1) + nz[f] * v2;
    const double g2 = (nx[f] * a0 + ny[f] * a1) + nz[f] * a2;
    // (Away from the plane and not approaching it: entering_time is inf.)
    const bool skip = ((g0 > POSITION_TOL) & (g1 >= 0) & (g2 >= 0)) | (f == exclude);
    const double t = entering_time(g0, g1, g2);
    times[f] = skip ? kInf : t;
  }
}

// ---------------------------------------------------------------------------------------
// estim.forward._curved and the edges and corners of estim.forward._contact (exact geometry)

// A piece's anchor (the edge's point or the vertex) and axis mask (estim.forward._contact._frame_of).
struct Piece {
  V3 anchor, mask;
};

Piece piece_of(const double* row) {
  Piece out;
  for (int i = 0; i < 3; ++i) {
    const double m = row[DIRECTION + i], h = row[HALF + i];
    out.anchor[i] = row[CENTRE + i] + m * (std::isfinite(h) ? h : 0.0);
    out.mask[i] = std::fabs(m);
  }
  return out;
}

inline V3 mul(V3 a, V3 b) { return v3(a[0] * b[0], a[1] * b[1], a[2] * b[2]); }
inline V3 cross(V3 a, V3 b) {
  return v3(a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]);
}

// D and its derivatives along P(tau) = A + B tau + C tau^2 (estim.forward._curved._poly).
struct Quartic {
  V3 A, B, C;
  double r;
  struct Value {
    double value, slope, curvature;
  };
  void at(double t, V3* P, V3* dP) const {
    *P = (A + B * t) + (C * t) * t;
    *dP = B + (2.0 * C) * t;
  }
  Value D(double t) const {
    V3 P, dP;
    at(t, &P, &dP);
    return {inner(P, P) - r * r, 2.0 * inner(P, dP), 2.0 * (inner(dP, dP) + 2.0 * inner(P, C))};
  }
  Value dD(double t) const {  // halves of D', D'', D'''
    V3 P, dP;
    at(t, &P, &dP);
    return {inner(P, dP), inner(dP, dP) + 2.0 * inner(P, C), 6.0 * inner(dP, C)};
  }
};

// estim.forward._curved._bracketed_root
template <typename F>
double bracketed_root(const F& f, double lo, double hi) {
  double f_lo = f(lo).value;
  for (int i = 0; i < CURVED_BISECTIONS; ++i) {
    const double mid = 0.5 * (lo + hi);
    const double f_mid = f(mid).value;
    const bool right = (f_mid > 0) == (f_lo > 0);
    const double new_lo = right ? mid : lo, new_hi = right ? hi : mid;
    f_lo = right ? f_mid : f_lo;
    lo = new_lo;
    hi = new_hi;
  }
  const auto s = f(lo);
  double t = s.value * s.curvature > 0 ? lo : hi;
  for (int i = 0; i < CURVED_NEWTONS; ++i) {
    const auto x = f(t);
    const bool ok = x.slope != 0;
    t = jmin(jmax(t - (ok ? x.value / (ok ? x.slope : 1.0) : 0.0), lo), hi);
  }
  return t;
}

// estim.forward._curved._quadratic_roots: real roots of a2 t^2 + a1 t + a0, NaN where none.
void quadratic_roots(double a2, double a1, double a0, double* lo, double* hi) {
  const double disc = a1 * a1 - 4.0 * a2 * a0;
  const double s = std::sqrt(disc > 0 ? disc : 0.0);
  const double q = -0.5 * (a1 + (a1 >= 0 ? s : -s));
  const double safe_q = q != 0 ? q : 1.0;
  const double r1 = q / (a2 != 0 ? a2 : 1.0), r2 = q != 0 ? a0 / safe_q : 0.0;
  const bool real = (disc > 0) && (a2 != 0);
  *lo = real ? jmin(r1, r2) : kNaN;
  *hi = real ? jmax(r1, r2) : kNaN;
}

// estim.forward._curved._intervals: the interval ends start, the breaks inside (start,
// horizon) sorted (the others moved to the horizon), horizon; N breaks, N + 1 intervals.
template <int N>
void intervals(const double* breaks, double start, double horizon, double* lo, double* hi) {
  double pts[N];
  for (int i = 0; i < N; ++i) {
    const bool inside = std::isfinite(breaks[i]) && breaks[i] > start && breaks[i] < horizon;
    pts[i] = inside ? breaks[i] : horizon;
  }
  // estim.forward._curved._sorted: odd-even transposition, N rounds of minima and maxima
  // (NaN-propagating, as jnp.minimum and jnp.maximum: a NaN horizon stays NaN, never a
  // comparator that is not an order).
  for (int round = 0; round < N; ++round) {
    for (int i = round % 2; i + 1 < N; i += 2) {
      const double lo_i = jmin(pts[i], pts[i + 1]), hi_i = jmax(pts[i], pts[i + 1]);
      pts[i] = lo_i;
      pts[i + 1] = hi_i;
    }
  }
  lo[0] = start;
  for (int i = 0; i < N; ++i) lo[i + 1] = hi[i] = pts[i];
  hi[N] = horizon;
}

// estim.forward._curved.entering_times: every time in (start, horizon] at which D falls
// through zero, inf in unused slots (7 slots, in increasing order).
void entering_times(const Quartic& q, double start, double horizon, double* roots) {
  const V3 &A = q.A, &B = q.B, &C = q.C;
  const double r = q.r;
  const double c4 = inner(C, C);
  const bool quartic = c4 > 0;
  const double c4s = quartic ? c4 : 1.0;
  const double c3 = 2.0 * inner(B, C), c2 = inner(B, B) + 2.0 * inner(A, C);
  const double c1 = 2.0 * inner(A, B), c0 = inner(A, A) - r * r;
  for (int i = 0; i < 7; ++i) roots[i] = kInf;
  if (!quartic) {
    // C = 0: D enters once, at its smaller root 2 c0 / (-c1 + s).
    const double disc = c1 * c1 - 4.0 * c2 * c0;
    const double s = std::sqrt(disc > 0 ? disc : 0.0);
    const bool ok = (disc > 0) && (c0 > 0) && (c1 < 0);
    const double flat = ok ? 2.0 * c0 / (ok ? s - c1 : 1.0) : kInf;
    roots[0] = flat <= jmax(horizon, 0.0) ? flat : kInf;
    return;
  }
  const double cauchy = 1.0 + jmax(jmax(std::fabs(c3), std::fabs(c2)), jmax(std::fabs(c1), std::fabs(c0))) / c4s;
  const double T = jmax(jmin(horizon, cauchy), start);
  const auto d = [&q](double t) { return q.dD(t); };
  const auto D = [&q](double t) { return q.D(t); };
  // 1. Critical points of D.
  double sa, sb;
  quadratic_roots(6.0 * c4s, 6.0 * inner(B, C), inner(B, B) + 2.0 * inner(A, C), &sa, &sb);
  const double s0 = -inner(B, C) / (2.0 * c4s);
  const double breaks1[3] = {sa, s0, sb};
  double lo[7], hi[7];
  intervals<3>(breaks1, start, T, lo, hi);
  double breaks2[6];
  for (int i = 0; i < 4; ++i) {
    const bool change = (d(lo[i]).value > 0) != (d(hi[i]).value > 0);
    breaks2[i] = change ? bracketed_root(d, lo[i], hi[i]) : kNaN;
  }
  breaks2[4] = sa;
  breaks2[5] = sb;
  // 2. Entering roots of D between them.
  intervals<6>(breaks2, start, T, lo, hi);
  for (int i = 0; i < 7; ++i) {
    const bool enters = (D(lo[i]).value > 0) && (D(hi[i]).value <= 0) && (hi[i] > lo[i]);
    roots[i] = enters ? bracketed_root(D, lo[i], hi[i]) : kInf;
  }
}

// Whether the centre q lies in the Voronoi region of box piece `row` (estim.forward._contact.in_piece).
bool in_piece(V3 q, const double* row) {
  bool out = true;
  for (int i = 0; i < 3; ++i) {
    const double m = row[DIRECTION + i], c = row[CENTRE + i], h = row[HALF + i];
    const double d = q[i] - c;
    const bool beyond = m != 0 ? m * d - h >= -ON_FACE_TOL : true;
    const bool within = m == 0 ? std::fabs(d) - h <= ON_FACE_TOL : true;
    out = out && beyond && within;
  }
  return out;
}

// estim.forward._curved.distance_terms: A, B, C of P(tau) for a piece.
Quartic distance_terms(V3 p, V3 v, V3 a, const Piece& pc, double r) {
  return Quartic{mul(pc.mask, p - pc.anchor), mul(pc.mask, v), mul(0.5 * pc.mask, a), r};
}

// Earliest time the ball enters a curved piece within [start, horizon], inside its region;
// 0 if it touches the piece and moves into it; inf if never (estim.forward._contact._curved_time).
double curved_time(const Faces& fc, int face, V3 p, V3 v, V3 a, double start, double horizon) {
  const double* row = fc.row(face);
  const Quartic q = distance_terms(p, v, a, piece_of(row), fc.radius);
  // _touching_terms: G = |P| - r and its first two derivatives at 0
  const double rho = std::sqrt(inner(q.A, q.A));
  const double rho_s = rho > 0 ? rho : 1.0;
  const double g1 = inner(q.A, q.B) / rho_s;
  const double g2 = (inner(q.B, q.B) + 2.0 * inner(q.A, q.C)) / rho_s - g1 * g1 / rho_s;
  const double g0 = rho - q.r;
  const bool touching = std::fabs(g0) <= POSITION_TOL;
  if (touching && moves_into(g1, g2)) return 0.0;
  double roots[8];
  entering_times(q, start, horizon, roots + 1);
  const bool low = touching && (g1 > 0) && (g2 < 0) && (g1 * g1 <= -2.0 * g2 * HOP_HEIGHT);
  roots[0] = low ? -2.0 * g1 / (low ? g2 : -1.0) : kInf;
  double out = kInf;
  for (int i = 0; i < 8; ++i) {
    if (!std::isfinite(roots[i])) continue;
    if (in_piece(ballistic_p(p, v, a, roots[i]), row)) out = jmin(out, roots[i]);
  }
  return out;
}

// estim.forward._contact.parabola_box: the bounding box of the parabola over [0, h].
void parabola_box(V3 p, V3 v, V3 a, double h, V3* lo, V3* hi) {
  const V3 p1 = ballistic_p(p, v, a, h);
  for (int i = 0; i < 3; ++i) {
    const double apex = a[i] != 0 ? -v[i] / (a[i] != 0 ? a[i] : 1.0) : 0.0;
    const bool inside = (apex > 0) && (apex < h);
    const double t = inside ? apex : 0.0;
    const double q_apex = p[i] + v[i] * t + 0.5 * a[i] * t * t;
    (*lo)[i] = jmin(jmin(p[i], p1[i]), inside ? q_apex : p[i]);
    (*hi)[i] = jmax(jmax(p[i], p1[i]), inside ? q_apex : p[i]);
  }
}

// A piece's box of reach along axis i (estim.forward._contact._reach_box).
void reach_box(const Faces& fc, int face, int i, double* lo, double* hi) {
  const double* row = fc.row(face);
  const double m = row[DIRECTION + i], c = row[CENTRE + i], half = row[HALF + i], r = fc.radius;
  *lo = (m > 0 ? c + half : (m < 0 ? c - half - r : c - half)) - POSITION_TOL;
  *hi = (m > 0 ? c + half + r : (m < 0 ? c - half : c + half)) + POSITION_TOL;
}

// estim.forward._contact._axis_window along one axis: the hull (t0, t1) of the times in
// [0, horizon] the coordinate lies in [lo, hi].
void axis_window(double p, double v, double a, double lo, double hi, double horizon, double* t0, double* t1) {
  const double h = jmin(horizon, FAR_HORIZON);
  double cands[6] = {0.0, h, 0, 0, 0, 0};
  const double bounds[2] = {lo, hi};
  for (int k = 0; k < 2; ++k) {
    const double a2 = 0.5 * a, c0 = p - bounds[k];
    const double disc = v * v - 4.0 * a2 * c0;
    const double s = std::sqrt(disc >= 0 ? disc : 0.0);
    const double q = -0.5 * (v + (v >= 0 ? s : -s));
    const bool ok = disc >= 0;
    cands[2 + 2 * k] = (ok && a2 != 0) ? q / (a2 != 0 ? a2 : 1.0) : kNaN;
    cands[3 + 2 * k] = (ok && q != 0) ? c0 / (q != 0 ? q : 1.0) : kNaN;
  }
  const double margin = WINDOW_MARGIN * ((1.0 + std::fabs(lo)) + std::fabs(hi));
  *t0 = kInf;
  *t1 = -kInf;
  for (double c : cands) {
    const double t = std::isfinite(c) ? c : -1.0;
    const double x = p + v * t + 0.5 * a * t * t;
    const bool valid = (t >= 0) && (t <= h) && (x >= lo - margin) && (x <= hi + margin);
    *t0 = jmin(*t0, valid ? t : kInf);
    *t1 = jmax(*t1, valid ? t : -kInf);
  }
}

// estim.forward._contact._reach_window: the time window within [0, horizon] in which the
// parabola can be in the piece's box of reach, (t0, t1); empty if t0 > t1.
void reach_window(const Faces& fc, int face, V3 p, V3 v, V3 a, double horizon, double* t0, double* t1) {
  double lo[3], hi[3], w0[2], w1[2];
  for (int i = 0; i < 3; ++i) reach_box(fc, face, i, lo + i, hi + i);
  for (int i = 0; i < 2; ++i) axis_window(p[i], v[i], a[i], lo[i], hi[i], horizon, w0 + i, w1 + i);
  const double s0 = jmax(jmax(w0[0], w0[1]), 0.0), s1 = jmin(w1[0], w1[1]);
  const double z0 = p[2] + v[2] * s0 + 0.5 * a[2] * s0 * s0;
  const double z1 = p[2] + v[2] * s1 + 0.5 * a[2] * s1 * s1;
  const double apex = a[2] != 0 ? -v[2] / (a[2] != 0 ? a[2] : 1.0) : -1.0;
  const bool at_apex = (apex > s0) && (apex < s1);
  const double za = at_apex ? p[2] + v[2] * apex + 0.5 * a[2] * apex * apex : z0;
  const double z_lo = jmin(jmin(z0, z1), za), z_hi = jmax(jmax(z0, z1), za);
  const bool meets = (s0 <= s1) && (z_lo <= hi[2]) && (z_hi >= lo[2]);
  *t0 = meets ? s0 : kInf;
  *t1 = meets ? s1 : -kInf;
}

// The earliest contact with an edge or a corner within [0, horizon] (the earliest flat
// face's time), the curved part of estim.forward._contact.first_contact: the pieces whose box of
// reach the flight's bounding box meets, each within its window. time[f] for every piece.
void curved_times(const Faces& fc, V3 p, V3 v, V3 a, int exclude, bool sliding, double horizon, double* time) {
  const int F = fc.s->n_faces;
  const double* own = fc.row(exclude > 0 ? exclude : 0);
  V3 box_lo, box_hi;
  parabola_box(p, v, a, jmin(horizon, FAR_HORIZON), &box_lo, &box_hi);
  for (int f = fc.n_flat; f < F; ++f) {
    time[f] = kInf;
    const double* row = fc.row(f);
    bool reaches = true;
    for (int i = 0; i < 3 && reaches; ++i) {
      double lo, hi;
      reach_box(fc, f, i, &lo, &hi);
      reaches = (box_lo[i] <= hi) && (box_hi[i] >= lo);
    }
    const double borders = (row[DIRECTION] * own[DIRECTION] + row[DIRECTION + 1] * own[DIRECTION + 1]) +
                           row[DIRECTION + 2] * own[DIRECTION + 2];
    const bool excluded = sliding && exclude >= 0 && borders == 1 && row[SOLID] == own[SOLID];
    if (!reaches || f == exclude || excluded) continue;
    double t0, t1;
    reach_window(fc, f, p, v, a, horizon, &t0, &t1);
    if (!(t0 <= t1)) continue;
    time[f] = curved_time(fc, f, p, v, a, jmax(t0, 0.0), t1);
  }
}

// Unit outward normal of face `face` at the centre q (estim.forward._contact.contact_normal).
V3 contact_normal(const Faces& fc, int face, V3 q) {
  if (fc.s->rank[face] < 2) return fc.normal(face);
  const Piece pc = piece_of(fc.row(face));
  const V3 P = mul(pc.mask, q - pc.anchor);
  const double n = std::sqrt(inner(P, P)), d = n > 0 ? n : 1.0;
  return v3(P[0] / d, P[1] / d, P[2] / d);
}

// Squared speed of v across curved piece `face` at normal n (estim.forward._contact.across_speed2).
double across_speed2(const Faces& fc, int face, V3 v, V3 n) {
  const double* row = fc.row(face);
  const V3 along = v3(1.0 - std::fabs(row[DIRECTION]), 1.0 - std::fabs(row[DIRECTION + 1]),
                      1.0 - std::fabs(row[DIRECTION + 2]));
  const V3 tangential = v - inner(v, n) * n;
  const bool edge = (along[0] + along[1]) + along[2] == 1;
  const double a = inner(along, v);
  return inner(tangential, tangential) - (edge ? a * a : 0.0);
}

// The horizontal line a ball pressed onto curved piece `face` rolls about
// (estim.forward._contact.roll_axis): pivot, axis, and whether that is its motion.
struct RollAxis {
  V3 pivot, axis;
  bool exact;
};

RollAxis roll_axis(const Faces& fc, int face, V3 p, V3 v) {
  const double* row = fc.row(face);
  const Piece pc = piece_of(row);
  const bool edge = (pc.mask[0] + pc.mask[1]) + pc.mask[2] == 2;
  const V3 flat = v3(1.0, 1.0, 0.0);
  const V3 m = mul(load3(row + DIRECTION), flat);
  const V3 d = mul(p - pc.anchor, flat), w = mul(v, flat);
  const double d_len = std::sqrt(inner(d, d)), w_len = std::sqrt(inner(w, w));
  V3 h;
  if (d_len > 0) {
    for (int i = 0; i < 3; ++i) h[i] = d[i] / (d_len > 0 ? d_len : 1.0);
  } else {
    for (int i = 0; i < 3; ++i) h[i] = w[i] / (w_len > 0 ? w_len : 1.0);
  }
  if (edge) {
    const double norm = std::sqrt(jmax(inner(m, m), 1.0));
    for (int i = 0; i < 3; ++i) h[i] = m[i] / norm;
  }
  if (!(inner(h, h) > 0)) h = v3(1.0, 0.0, 0.0);
  const bool planar = std::fabs(d[0] * w[1] - d[1] * w[0]) <= AXIS_TOL * d_len * w_len;
  return RollAxis{pc.anchor, cross(h, kUp), edge ? (pc.mask[2] == 1 && inner(m, m) == 1) : planar};
}

// Time at which a ball rolling about edge `face` reaches an end of the edge; inf on a
// corner (estim.forward._contact.roll_exit_time).
double roll_exit_time(const Faces& fc, int face, V3 pivot, V3 axis, V3 p, V3 v) {
  const double* row = fc.row(face);
  const double half = (row[HALF] * std::fabs(axis[0]) + row[HALF + 1] * std::fabs(axis[1])) +
                      row[HALF + 2] * std::fabs(axis[2]);
  const double along = inner(p - pivot, axis), u = inner(v, axis);
  const bool moves = std::fabs(u) > SPEED_TOL;
  const double end = u > 0 ? half : -half;
  const double tau = (end - along) / (moves ? u : 1.0);
  const Piece pc = piece_of(row);
  const bool edge = ((1.0 - pc.mask[0]) + (1.0 - pc.mask[1])) + (1.0 - pc.mask[2]) == 1;
  return (edge && moves) ? jmax(tau, 0.0) : kInf;
}

// The piece of the same box a ball rolling on `face` moves onto when it leaves that piece's
// region across `axis` with velocity v (estim.forward._contact.next_piece): -1 if none.
int next_piece(const Faces& fc, int face, int axis, V3 v) {
  const double* row = fc.row(face);
  double target[3];
  bool nonzero = false;
  for (int i = 0; i < 3; ++i) {
    const double m = row[DIRECTION + i];
    const double sign = v[axis] > 0 ? 1.0 : (v[axis] < 0 ? -1.0 : 0.0);  // (jnp.sign of v . e)
    target[i] = i == axis ? (m == 0 ? sign : 0.0) : m;
    nonzero = nonzero || target[i] != 0;
  }
  if (!nonzero) return -1;
  for (int f = 0; f < fc.s->n_faces; ++f) {
    const double* r = fc.row(f);
    if (r[DIRECTION] == target[0] && r[DIRECTION + 1] == target[1] && r[DIRECTION + 2] == target[2] &&
        r[SOLID] == row[SOLID])
      return f;
  }
  return -1;
}

// ---------------------------------------------------------------------------------------
// A ball rolling over an edge or a corner (estim.forward._roll; its docstring has the maths).

// estim.forward._roll.carlson_rf
inline double carlson_rf(double x, double y, double z) {
  for (int i = 0; i < RF_STEPS; ++i) {
    const double sx = std::sqrt(x), sy = std::sqrt(y), sz = std::sqrt(z);
    const double lam = sx * (sy + sz) + sy * sz;
    x = 0.25 * (x + lam);
    y = 0.25 * (y + lam);
    z = 0.25 * (z + lam);
  }
  const double mean = (x + y + z) / 3.0;
  const double dx = 1.0 - x / mean, dy = 1.0 - y / mean;
  const double dz = -(dx + dy);
  const double e2 = dx * dy - dz * dz;
  const double e3 = dx * dy * dz;
  return (1.0 + e2 * (e2 / 24.0 - 0.1 - 3.0 * e3 / 44.0) + e3 / 14.0) / std::sqrt(mean);
}

// estim.forward._roll.Pendulum (jnp.where: only the selected side is computed).
struct Pendulum {
  double k = 0.0, sqrt_k = 0.0;
  bool rests = false, positive = false;
  double beta = 0.0, b = 0.0, sigma = 1.0, w0 = 0.0, t0 = 0.0, w_end = 0.0;
  bool reaches_top = false;
  double duration = 0.0;

  Pendulum() = default;
  Pendulum(double s0, double omega0, double k_) : k(k_), sqrt_k(std::sqrt(k_)) {
    double B = omega0 * omega0 - 4.0 * k * s0 * s0;
    rests = (B == 0.0) && (s0 == 0.0);
    B = B == 0.0 ? RIDGE_B * k : B;
    positive = B > 0;
    beta = std::sqrt(std::fabs(B));
    b = beta / (2.0 * sqrt_k);
    sigma = omega0 < 0 ? -1.0 : 1.0;
    const double sinh0 = (positive ? 2.0 * sqrt_k * sigma * s0 : omega0) / beta;
    w0 = std::asinh(sinh0);
    t0 = time(w0);
    const double s_star = std::sqrt(jmax((k - B) / (6.0 * k), 0.0));
    const bool inwards = positive && (sigma < 0);
    const double ratio = s_star / b;
    const double w_star = positive ? std::asinh(ratio) : std::acosh(jmax(ratio, 1.0));
    w_end = jmax(inwards ? 0.0 : w_star, w0);
    reaches_top = inwards;
    duration = rests ? kInf : time(w_end) - t0;
  }

  // Pendulum.half_sine
  double half_sine(double w) const { return positive ? sigma * b * std::sinh(w) : b * std::cosh(w); }

  // Pendulum.rate
  double rate(double w) const { return positive ? sigma * beta * std::cosh(w) : beta * std::sinh(w); }

  // Pendulum._time
  double time(double w) const {
    const double s = half_sine(w);
    const double ch = std::cosh(w);
    const double c2 = ch * ch;
    const double one_b2 = 1.0 - b * b;
    const double y = positive ? c2 : jmax(one_b2, 0.0);
    const double z = positive ? 1.0 : one_b2 * c2;
    return std::sinh(w) * carlson_rf(1.0 - s * s, y, z) / sqrt_k;
  }

  // Pendulum.angle_at (the last, differentiable Newton step of JAX is one more step here)
  double angle_at(double tau) const {
    const double target = t0 + tau;
    const double lo = w0, hi = w_end;
    double w = w0 + sqrt_k * tau;
    for (int i = 0; i <= ROLL_NEWTONS; ++i) {
      const double s = half_sine(w);
      const double f = time(w) - target, slope = sqrt_k * std::sqrt(1.0 - s * s);
      const double next = w - f * slope;
      w = i < ROLL_NEWTONS ? jmin(jmax(next, lo), hi) : next;  // (the last: unclipped)
    }
    return w;
  }
};

// estim.forward._roll.Roll
struct Roll {
  V3 pivot, axis, out;
  double along, u, r;
  Pendulum motion;

  Roll(V3 pivot_, V3 axis_, V3 p0, V3 v0, double g) : pivot(pivot_), axis(axis_) {
    const V3 d = p0 - pivot;
    along = inner(d, axis);
    u = inner(v0, axis);
    const V3 arm = d - along * axis;
    r = std::sqrt(inner(arm, arm));
    out = cross(kUp, axis);
    const double theta = std::atan2(inner(arm, out), arm[2]);
    const double omega = inner(v0, std::cos(theta) * out - std::sin(theta) * kUp) / r;
    motion = Pendulum(std::sin(0.5 * theta), omega, g / r);
  }

  // Roll.duration
  double duration() const { return motion.duration; }

  // Roll.reaches_top
  bool reaches_top() const { return motion.reaches_top; }

  // Roll.state
  void state(double tau, V3* p, V3* v) const {
    const double end = std::isfinite(motion.duration) ? motion.duration : tau;
    const double w = motion.angle_at(motion.rests ? 0.0 : jmin(jmax(tau, 0.0), end));
    const double s = motion.rests ? 0.0 : motion.half_sine(w);
    const double rate = motion.rests ? 0.0 : motion.rate(w);
    const double cos_t = 1.0 - 2.0 * s * s;
    const double sin_t = 2.0 * s * std::sqrt(jmax(1.0 - s * s, 0.0));
    const V3 base = pivot + (along + u * tau) * axis;
    *p = base + r * (sin_t * out + cos_t * kUp);
    *v = u * axis + r * rate * (cos_t * out - sin_t * kUp);
  }
};

// estim.forward._roll.carlson_rc
inline double carlson_rc(double x, double y) {
  for (int i = 0; i < RF_STEPS; ++i) {
    const double lam = 2.0 * std::sqrt(x) * std::sqrt(y) + y;
    x = 0.25 * (x + lam);
    y = 0.25 * (y + lam);
  }
  const double mean = (x + 2.0 * y) / 3.0;
  const double s = (y - mean) / mean;
  return (1.0 + s * s * (0.3 + s * (1.0 / 7.0 + s * (0.375 + s * 9.0 / 22.0)))) / std::sqrt(mean);
}

// estim.forward._roll.carlson_rj
inline double carlson_rj(double x, double y, double z, double p) {
  double total = 0.0, scale = 1.0;
  for (int i = 0; i < RF_STEPS; ++i) {
    const double sx = std::sqrt(x), sy = std::sqrt(y), sz = std::sqrt(z);
    const double lam = sx * (sy + sz) + sy * sz;
    const double root = p * (sx + sy + sz) + sx * sy * sz;
    const double alpha = root * root;
    const double beta = p * ((p + lam) * (p + lam));
    total = total + scale * carlson_rc(alpha, beta);
    x = 0.25 * (x + lam);
    y = 0.25 * (y + lam);
    z = 0.25 * (z + lam);
    p = 0.25 * (p + lam);
    scale = 0.25 * scale;
  }
  const double mean = 0.2 * (x + y + z + 2.0 * p);
  const double dx = 1.0 - x / mean, dy = 1.0 - y / mean, dz = 1.0 - z / mean, dp = 1.0 - p / mean;
  const double ea = dx * (dy + dz) + dy * dz;
  const double eb = dx * dy * dz;
  const double ec = dp * dp;
  const double ed = ea - 3.0 * ec;
  const double ee = eb + 2.0 * dp * (ea - ec);
  const double series = (1.0 + ed * (-3.0 / 14.0 + 0.75 * 3.0 / 22.0 * ed - 1.5 * 3.0 / 26.0 * ee)
                         + eb * (1.0 / 6.0 + dp * (-6.0 / 22.0 + dp * 3.0 / 26.0))
                         + dp * ea * (1.0 / 3.0 - dp * 3.0 / 22.0) - dp * ec / 3.0);
  return 3.0 * total + scale * series / (mean * std::sqrt(mean));
}

// estim.forward._roll._third_kind
inline double third_kind(double n, double sin_psi, double cos_psi, double delta2) {
  const double s2 = sin_psi * sin_psi;
  const double c2 = cos_psi * cos_psi;
  return sin_psi * carlson_rf(c2, delta2, 1.0) + n / 3.0 * s2 * sin_psi * carlson_rj(c2, delta2, 1.0, 1.0 - n * s2);
}

// estim.forward._roll.Spherical (signs: the corner's direction, or null: no region exit).
struct Spherical {
  V3 vertex;
  double g, r, L, z1, z2, z3, K, m, n1, n2, psi0, t0, phi_psi0, phi0, psi_end, duration;
  int exit_axis = -1;

  Spherical(V3 vertex_, V3 p0, V3 v0, double g_, const double* signs) : vertex(vertex_), g(g_) {
    const V3 d = p0 - vertex;
    const double r2 = inner(d, d);
    r = std::sqrt(r2);
    const double z0 = d[2], dz0 = v0[2];
    const double energy = 0.5 * inner(v0, v0) + g * z0;
    L = d[0] * v0[1] - d[1] * v0[0];
    const double a = -energy / g, b = -r2, c = (2.0 * energy * r2 - L * L) / (2.0 * g);
    const double q = (a * a - 3.0 * b) / 9.0;
    const double rr = (2.0 * a * a * a - 9.0 * a * b + 27.0 * c) / 54.0;
    const double sq = std::sqrt(jmax(q, 0.0));
    const double cube = sq * q;
    const double theta = std::acos(jmin(jmax(rr / (cube > 0 ? cube : 1.0), -1.0), 1.0));
    double roots[3];
    const int ks[3] = {0, 2, 1};
    for (int j = 0; j < 3; ++j) {
      double z = -2.0 * sq * std::cos((theta + 2.0 * kPi * ks[j]) / 3.0) - a / 3.0;
      for (int i = 0; i < 2; ++i) {
        const double f = ((z + a) * z + b) * z + c;
        const double df = (3.0 * z + 2.0 * a) * z + b;
        z = z - (df != 0 ? f / df : 0.0);
      }
      roots[j] = z;
    }
    z1 = roots[0];
    z2 = roots[1];
    z3 = roots[2];
    const double span = z2 - z1;
    K = 2.0 * r / std::sqrt(2.0 * g * (z3 - z2));
    m = -span / (z3 - z2);
    n1 = -span / (r - z2);
    n2 = span / (r + z2);
    const double sin0 = -r * dz0 / std::sqrt(2.0 * g * (z0 - z1) * (z3 - z0) * span);
    const double cos0 = std::sqrt(jmax((z0 - z1) / span, 0.0));
    psi0 = std::atan2(sin0, cos0);
    t0 = time(psi0);
    phi_psi0 = azimuth(psi0);
    phi0 = std::atan2(d[1], d[0]);
    const double s_star2 = jmin(jmax((z2 - 2.0 * energy / (3.0 * g)) / span, 0.0), 1.0);
    const bool pressed = 3.0 * g * z0 >= 2.0 * energy;
    const double psi_star = pressed ? jmax(std::asin(std::sqrt(s_star2)), psi0) : psi0;
    psi_end = psi_star;
    if (signs != nullptr) {
      const double x0 = signs[0] * d[0], y0 = signs[1] * d[1];
      const double turn = signs[0] * signs[1] * L;
      const double beta0 = std::atan2(y0, x0);
      const double room = turn > 0 ? 0.5 * kPi - beta0 : beta0;
      bool crosses;
      const double psi_exit = crossing(room, psi0, psi_star, &crosses);
      exit_axis = crosses ? (turn > 0 ? 0 : 1) : -1;
      psi_end = crosses ? psi_exit : psi_star;
    }
    duration = time(psi_end) - t0;
  }

  // Spherical._time
  double time(double psi) const {
    const double s = std::sin(psi), c = std::cos(psi);
    return K * s * carlson_rf(c * c, 1.0 - m * s * s, 1.0);
  }

  // Spherical._azimuth
  double azimuth(double psi) const {
    const double s = std::sin(psi), c = std::cos(psi);
    const double delta2 = 1.0 - m * s * s;
    return L * K / (2.0 * r) * (third_kind(n1, s, c, delta2) / (r - z2) + third_kind(n2, s, c, delta2) / (r + z2));
  }

  // Spherical._height
  double height(double psi) const {
    const double s = std::sin(psi);
    return z2 - (z2 - z1) * s * s;
  }

  // Spherical._crossing (the differentiable step of JAX is one more step here)
  double crossing(double room, double lo, double hi, bool* crosses) const {
    auto turned = [&](double psi) { return std::fabs(azimuth(psi) - phi_psi0); };
    auto rate = [&](double psi) {
      const double z = height(psi);
      const double s = std::sin(psi);
      return std::fabs(L) / (r * r - z * z) * K / std::sqrt(1.0 - m * s * s);
    };
    *crosses = turned(hi) >= room;
    double a = lo, b = hi, x = 0.5 * (lo + hi);
    for (int i = 0; i < SPHERE_STEPS; ++i) {
      const double f = turned(x) - room;
      const double a1 = f < 0 ? x : a, b1 = f < 0 ? b : x;
      const double newton = x - f / rate(x);
      a = a1;
      b = b1;
      x = (newton > a && newton < b) ? newton : 0.5 * (a + b);
    }
    x = *crosses ? x : b;
    return x - (turned(x) - room) / rate(x);
  }

  // Spherical.state
  void state(double tau, V3* p, V3* v) const {
    tau = jmin(jmax(tau, 0.0), duration);
    const double target = t0 + tau;
    double psi = psi0 + tau / K;
    for (int i = 0; i <= ROLL_NEWTONS; ++i) {
      const double s = std::sin(psi);
      const double f = time(psi) - target, slope = std::sqrt(1.0 - m * s * s) / K;
      const double next = psi - f * slope;
      psi = i < ROLL_NEWTONS ? jmin(jmax(next, psi0), psi_end) : next;  // (the last: unclipped)
    }
    const double s = std::sin(psi), c = std::cos(psi);
    const double z = height(psi);
    const double dz = -(z2 - z1) * 2.0 * s * c * std::sqrt(1.0 - m * s * s) / K;
    const double rho2 = r * r - z * z;
    const double rho = std::sqrt(rho2);
    const double phi = phi0 + azimuth(psi) - phi_psi0;
    const double dphi = L / rho2;
    const double drho = -z * dz / rho;
    const double cp = std::cos(phi), sp = std::sin(phi);
    *p = vertex + v3(rho * cp, rho * sp, z);
    *v = v3(drho * cp - rho * dphi * sp, drho * sp + rho * dphi * cp, dz);
  }
};

// estim.forward._solver.RollOver (only the selected motion is computed).
struct RollOver {
  V3 pivot, axis;
  bool spherical = false;
  int exit_axis = -1;
  double ends = 0.0;
  std::optional<Roll> plane;
  std::optional<Spherical> sphere;

  RollOver(const Faces& fc, int face, V3 p, V3 v) {
    const RollAxis ax = roll_axis(fc, face, p, v);
    const bool corner = fc.s->rank[face] == 3;
    spherical = corner && !ax.exact;
    pivot = ax.pivot;
    axis = spherical ? kZero : ax.axis;
    const double g = fc.s->gravity;
    if (spherical) {
      sphere.emplace(pivot, p, v, g, fc.row(face) + DIRECTION);
      exit_axis = sphere->exit_axis;
      ends = sphere->duration;
    } else {
      plane.emplace(pivot, ax.axis, p, v, g);
      ends = jmin(plane->duration(), roll_exit_time(fc, face, pivot, ax.axis, p, v));
    }
  }

  void state(double tau, V3* p, V3* v) const {
    if (spherical) sphere->state(tau, p, v);
    else plane->state(tau, p, v);
  }

  // RollOver.follows
  static bool follows(const Faces& fc, int face, V3 p, V3 v) {
    return roll_axis(fc, face, p, v).exact || fc.s->rank[face] == 3;
  }
};

struct Candidate {
  double tau;
  int32_t order;
  int face;
};

// Earliest face the ball enters, and when; (inf, -1) if none (estim.forward._contact.first_contact).
// The faces of a solid are tested only while the solid's reach bound could still beat the
// earliest contact found so far (to within the TIE_TIME that ties faces): the result is
// that of testing every face, the blocked faces and the ties included.
struct ContactSearch {
  std::vector<Candidate> found;
  std::vector<double> bound;  // per solid
  std::vector<double> time;   // per face

  // `sliding`: the ball slides on `exclude`, and meets none of its edges and corners.
  std::pair<double, int> operator()(const Faces& fc, V3 p, V3 v, V3 a, int exclude, bool sliding) {
    const int F = fc.n_flat;
    found.clear();
    const bool broad = !fc.first.empty();
    const int groups = broad ? fc.s->n_solids : 1;
    // Solids in the order of their bounds, ties to the lower index.
    const int padded = static_cast<int>(fc.reach_lo[0].size());  // (solids, padded)
    bound.resize(std::max(padded, 1));
    if (broad) reach_bounds(fc, padded, p, v, a, bound.data());
    else bound[0] = 0.0;
    time.resize(F);
    std::pair<double, int> best{kInf, -1};
    for (int taken = 0; taken < groups; ++taken) {
      int b = 0;
      for (int c = 1; c < groups; ++c) b = bound[c] < bound[b] ? c : b;
      // (A bound is NaN never: NaN positions enter nothing.)
      if (!(bound[b] < kInf) || bound[b] > best.first + TIE_TIME) break;  // (and so are the solids after it)
      bound[b] = kInf;  // (taken)
      const int lo = broad ? fc.first[b] : 0, hi = broad ? fc.first[b + 1] : F;
      // Every face's entering time first (face_times), then the few faces with a time, on
      // the solid's box.
      double* times = time.data();
      face_times(fc.nx.data() + lo, fc.ny.data() + lo, fc.nz.data() + lo, fc.offset.data() + lo, hi - lo,
                 exclude - lo, p, v, a, times + lo);
      for (int f = lo; f < hi; ++f) {
        const double t = times[f];
        if (!std::isfinite(t)) continue;
        const double* r = fc.row(f);
        if (on_face(ballistic_p(p, v, a, t), r + CENTRE, r + HALF, fc.radius))
          found.push_back(Candidate{t, fc.order[f], f});
      }
      best = resolve();
    }
    if (fc.n_flat == fc.s->n_faces) return best;
    // Edges and corners reached before the earliest flat face; ties to the lowest rank,
    // then index, over the faces and the pieces (no blocking: estim.forward._contact.first_contact).
    time.resize(fc.s->n_faces);
    curved_times(fc, p, v, a, exclude, sliding, best.first, time.data());
    double t_min = best.first;
    for (int f = fc.n_flat; f < fc.s->n_faces; ++f) t_min = jmin(t_min, time[f]);
    if (!std::isfinite(t_min)) return {t_min, -1};
    int32_t pick = std::numeric_limits<int32_t>::max();
    for (const Candidate& x : found)
      if (x.tau <= t_min + TIE_TIME) pick = std::min(pick, x.order);
    for (int f = fc.n_flat; f < fc.s->n_faces; ++f)
      if (time[f] <= t_min + TIE_TIME) pick = std::min(pick, fc.order[f]);
    return {t_min, pick % fc.s->n_faces};
  }

  // The earliest candidate, ties to the lowest order.
  std::pair<double, int> resolve() const {
    double t_min = kInf;
    for (const Candidate& x : found) t_min = jmin(t_min, x.tau);
    if (!std::isfinite(t_min)) return {t_min, -1};
    size_t pick = 0;
    int32_t best = std::numeric_limits<int32_t>::max();
    for (size_t j = 0; j < found.size(); ++j)
      if (found[j].tau <= t_min + TIE_TIME && found[j].order < best) best = found[j].order, pick = j;
    return {t_min, found[pick].face};
  }
};

double face_entering_time(const Faces& fc, int face, V3 p, V3 v, V3 a) {
  const V3 n = fc.normal(face);
  return entering_time(inner(n, p) - fc.offset[face], inner(n, v), inner(n, a));
}

double slide_exit_time(const Faces& fc, int face, V3 p, V3 v, V3 a) {
  const double* r = fc.row(face);
  double out = kInf;
  for (int i = 0; i < 3; ++i) {
    const double m = r[DIRECTION + i], c = r[CENTRE + i], h = r[HALF + i];
    const double q = p[i] - c;
    const bool finite = std::isfinite(h);
    const double sign_lo = m < 0 ? -1.0 : 1.0, bound_lo = m < 0 ? -h : h;
    const double sign_hi = m > 0 ? 1.0 : -1.0, bound_hi = m > 0 ? -h : h;
    const double t_lo = entering_time(sign_lo * q + (finite ? bound_lo : 1.0), sign_lo * v[i], sign_lo * a[i]);
    const double t_hi = entering_time(sign_hi * q + (finite ? bound_hi : 1.0), sign_hi * v[i], sign_hi * a[i]);
    out = jmin(out, (finite && m <= 0) ? t_lo : kInf);
    out = jmin(out, (finite && m >= 0) ? t_hi : kInf);
  }
  return out;
}

double train_reach(const Faces& fc, int face, V3 p, V3 u, double height) {
  const double* r = fc.row(face);
  const double solid = r[SOLID];
  const double zeta = p[2];
  const double speed = std::sqrt(u[0] * u[0] + u[1] * u[1]);
  const bool moving = speed > 0;
  double d[2], dd[2];
  bool dz[2];
  for (int i = 0; i < 2; ++i) {
    d[i] = moving ? u[i] / (moving ? speed : 1.0) : 0.0;
    dz[i] = std::fabs(d[i]) > AXIS_TOL;
    dd[i] = dz[i] ? d[i] : 1.0;
  }
  double obstacle = kInf;
  for (int b = 0; b < fc.s->n_solids; ++b) {
    const bool overlap = (fc.lo(b, 2) < zeta + height - POSITION_TOL) && (fc.hi(b, 2) > zeta + POSITION_TOL);
    if (!overlap || static_cast<double>(b) == solid) continue;  // (not hit: obstacle is left as it is)
    double enter = -kInf, leave = kInf;
    for (int i = 0; i < 2; ++i) {
      const double lo = fc.lo(b, i), hi = fc.hi(b, i);
      const double t1 = (lo - p[i]) / dd[i], t2 = (hi - p[i]) / dd[i];
      const bool inside = (p[i] > lo + POSITION_TOL) && (p[i] < hi - POSITION_TOL);
      const double s_in = dz[i] ? jmin(t1, t2) : (inside ? -kInf : kInf);
      const double s_out = dz[i] ? jmax(t1, t2) : (inside ? kInf : -kInf);
      enter = i == 0 ? s_in : jmax(enter, s_in);
      leave = i == 0 ? s_out : jmin(leave, s_out);
    }
    enter = jmax(enter, 0.0);
    const bool hit = overlap && (enter < leave - POSITION_TOL) && (static_cast<double>(b) != solid);
    obstacle = jmin(obstacle, hit ? enter : kInf);
  }
  double exit_face = kInf;
  if (moving) {
    for (int i = 0; i < 2; ++i) {
      const double c = r[CENTRE + i], h = r[HALF + i];
      const double edge = d[i] > 0 ? c + h : c - h;
      exit_face = jmin(exit_face, (dz[i] && std::isfinite(h)) ? (edge - p[i]) / dd[i] : kInf);
    }
  }
  const double reach = jmin(obstacle, exit_face);
  return obstacle <= POSITION_TOL ? -1.0 : jmax(reach, 0.0);
}

// A ratio q of geometric sums, with log(q) and expm1(log(q)) computed on first use and
// kept: a ball's closed forms sum the same few ratios again and again, and many balls
// never sum some of them.
struct Ratio {
  double q = 0.5;

  Ratio() = default;
  explicit Ratio(double q_) : q(q_) {}
  double lq() const { return ready(), lq_; }
  double em1() const { return ready(), em1_; }

 private:
  mutable double lq_ = 0.0, em1_ = 0.0;
  mutable bool ready_ = false;
  void ready() const {
    if (ready_) return;
    lq_ = std::log((q == 1.0 || q == 0.0) ? 0.5 : q);
    em1_ = std::expm1(lq_);
    ready_ = true;
  }
};

double geometric_sum(const Ratio& r, double n) {
  const double q = r.q;
  const bool one = q == 1.0, zero = q == 0.0, finite = std::isfinite(n);
  if (one) return finite ? n + 0.5 * n * (n - 1.0) * (q - 1.0) : kInf;
  if (zero) return n >= 1 ? 1.0 + q * jmin(n - 1.0, 1.0) : 0.0;
  if (!finite) return -1.0 / r.em1();
  return std::expm1(jmin(n * r.lq(), 0.0)) / r.em1();
}

double geometric_count(const Ratio& r, double y) {
  const double q = r.q;
  // (r.lq() is log(q) for 0 < q < 1 and log(0.5) otherwise, as in estim.forward._contact)
  const double arg = 1.0 - y * (1.0 - q);
  const double n_gen = arg > 0 ? std::floor(std::log(arg) / r.lq()) : kInf;
  double n = q >= 1.0 ? std::floor(y) : (q <= 0.0 ? (y >= 1 ? kInf : 0.0) : n_gen);
  if (y < 0) n = -1.0;
  const bool finite = std::isfinite(n) && n >= 0;
  const double nf = finite ? n : 0.0;
  const bool up = finite && geometric_sum(r, nf + 1) <= y;
  const bool down = finite && nf > 0 && geometric_sum(r, nf) > y;
  if (up) n = nf + 1;
  if (down) n = nf - 1;
  return y < 0 ? -1.0 : jmax(n, 0.0);
}

double safe_power(double x, double n) {
  const bool finite = std::isfinite(n), whole = finite && n >= 1;
  if (!whole) return finite ? 1.0 : (x == 1.0 ? 1.0 : 0.0);
  const double rest = x > 0 ? std::pow(x, n - 1.0) : (n == 1.0 ? 1.0 : 0.0);
  return x * rest;
}

// ---------------------------------------------------------------------------------------
// The factor law (estim.forward.laws.FactorLaw): its reset, its settle and the closed forms
// of its bounce series (estim.forward.laws.AbstractSummableLaw: state_at, series_end).

// estim.forward.laws.series
struct Series {
  V3 normal;
  double a_n;
  V3 a_t;
  double w;
  V3 u;
  double period;
};

Series series(V3 v, V3 normal, V3 a) {
  const double a_n = inner(a, normal), w = inner(v, normal);
  return Series{normal, a_n, a - a_n * normal, w, v - w * normal, 2.0 * w / -a_n};
}

// A ball's coefficients e and mu_t (estim.forward.laws.FactorCoefficients) with the ratios
// its bounce series sum: e, e mu_t and e^2, and for the divided differences K and L e2 mu_t
// and e2^2, e2 being e moved by SERIES_GAP off mu_t where they nearly agree
// (estim.forward.laws._factor._differences).
struct Rates {
  double e, mu, e2, gap;
  Ratio by_e, by_emu, by_ee, by_e2mu, by_e2e2;

  Rates() = default;
  Rates(double e_, double mu_) : e(e_), mu(mu_) {
    const bool close = std::fabs(mu - e) < SERIES_GAP;
    e2 = close ? (e >= SERIES_GAP ? e - SERIES_GAP : e + SERIES_GAP) : e;
    gap = mu - e2;
    by_e = Ratio(e);
    by_emu = Ratio(e * mu);
    by_ee = Ratio(e * e);
    by_e2mu = Ratio(e2 * mu);
    by_e2e2 = Ratio(e2 * e2);
  }
};

struct Start {
  double t;
  V3 x, v;
};

// Time offset, displacement and velocity at the start of flight j (after bounce j).
Start flight_start(const Series& s, double j, const Rates& c) {
  const double mu = c.mu;
  const double t = s.period * geometric_sum(c.by_e, j);
  const double jj = std::isfinite(t) ? j : 0.0;
  const double p_mu = safe_power(mu, j), p_e = safe_power(c.e, j);
  const double g_emu = geometric_sum(c.by_emu, jj), g_ee = geometric_sum(c.by_ee, jj);
  // (e2 is e unless e and mu nearly agree: then the same powers and sums, not again.)
  const bool moved = c.e2 != c.e;
  const double k = (p_mu - (moved ? safe_power(c.e2, j) : p_e)) / c.gap;
  const double l = ((moved ? geometric_sum(c.by_e2mu, jj) : g_emu) - (moved ? geometric_sum(c.by_e2e2, jj) : g_ee)) / c.gap;
  const double period2 = s.period * s.period;
  Start out;
  out.t = t;
  for (int i = 0; i < 3; ++i) {
    out.x[i] = s.period * (s.u[i] * g_emu + s.a_t[i] * s.period * mu * l) + 0.5 * s.a_t[i] * period2 * g_ee;
    const double u_j = p_mu * s.u[i] + s.a_t[i] * s.period * mu * k;
    out.v[i] = u_j + (s.w * p_e) * s.normal[i];
  }
  return out;
}

// Displacement and velocity tau after the series began (at most n_max bounces).
void state_at(const Series& s, double tau, const Rates& c, double n_max, V3* dx, V3* v) {
  double j = geometric_count(c.by_e, tau / s.period);
  j = jmin(jmin(j, n_max), MAX_COUNT);
  const Start st = flight_start(s, j, c);
  const double tau_j = tau - st.t;
  const V3 a_full = s.a_t + s.a_n * s.normal;
  for (int i = 0; i < 3; ++i) {
    (*dx)[i] = st.x[i] + st.v[i] * tau_j + 0.5 * a_full[i] * (tau_j * tau_j);
    (*v)[i] = st.v[i] + a_full[i] * tau_j;
  }
}

Start series_end(const Series& s, double n, const Rates& c) {
  Start st = flight_start(s, n, c);
  if (!std::isfinite(n)) st.v = st.v - inner(st.v, s.normal) * s.normal;
  return st;
}

// FactorLaw.reset: v+ = mu_t (v - (v . n) n) - e (v . n) n
V3 reset(V3 v, V3 n, const Rates& c) {
  const double vn = inner(v, n);
  return c.mu * (v - vn * n) - c.e * vn * n;
}

// AbstractContactLaw.contact_velocity with FactorLaw.rebound (e (-v . n)) and
// FactorLaw.settle (the tangential velocity stays only if mu_t = 1).
V3 contact_velocity(V3 v, V3 n, V3 a, const Rates& c) {
  const double vn = inner(v, n);
  const V3 tangential = v - vn * n;
  const bool impact = -vn > REST_SPEED;
  const bool settles = (c.e * -vn <= REST_SPEED) && (inner(n, a) < 0);
  if (!impact) return tangential;
  if (settles) return tangential * (c.mu == 1.0 ? 1.0 : 0.0);
  return reset(v, n, c);
}

// ---------------------------------------------------------------------------------------
// estim.forward._solver

struct Decision {
  int32_t kind, support;
  double n;
  int32_t reason, face;
};

struct Segment {
  double t0;
  V3 p0, v0, acc;
  double t1;
  V3 p1, v1, v1_post, normal, pivot;  // normal: a TRAIN's face, a ROLL's axis; pivot: a ROLL's
};
constexpr int SEGMENT_NUMBERS = 26;

// A roll's state tau into segment s (estim.forward._trajectory.roll_states): about its axis,
// or, for a roll over a corner off its plane (no axis), the spherical pendulum.
void roll_state(const Segment& s, double g, double tau, V3* p, V3* v) {
  if (s.normal[0] == 0 && s.normal[1] == 0 && s.normal[2] == 0) Spherical(s.pivot, s.p0, s.v0, g, nullptr).state(tau, p, v);
  else Roll(s.pivot, s.normal, s.p0, s.v0, g).state(tau, p, v);
}

void write_segment(const Segment& s, double* o) {
  o[0] = s.t0;
  for (int i = 0; i < 3; ++i) {
    o[1 + i] = s.p0[i];
    o[4 + i] = s.v0[i];
    o[7 + i] = s.acc[i];
    o[11 + i] = s.p1[i];
    o[14 + i] = s.v1[i];
    o[17 + i] = s.v1_post[i];
    o[20 + i] = s.normal[i];
    o[23 + i] = s.pivot[i];
  }
  o[10] = s.t1;
}

struct Ball {
  double e, mu_t, radius;  // radius: the contact radius
  V3 position, velocity;
  Rates rates;
};

// The radius every contact reads, estim.Params.contact_radius: radius - compression; NaN
// where the radius itself is not > 0, so that the radius check fails where the JAX path's
// does (estim.forward._simulate).
inline double contact_radius(double radius, double compression) {
  return radius > 0 ? radius - compression : std::numeric_limits<double>::quiet_NaN();
}

struct Step {  // the state a segment starts from, and its structure so far
  double t;
  V3 p, v;
  int32_t kind, support;
  double n;
};

inline int support_face(int32_t support) { return support > 0 ? support : 0; }

void slide_frame(const Faces& fc, int32_t support, V3 v, V3 a, V3* sv, V3* sa) {
  const V3 n = fc.normal(support_face(support));
  *sv = v - inner(v, n) * n;
  *sa = a - inner(a, n) * n;
}

// How the segment starting at st ends: (reason, face).
// tau: the time to the contact the search found (read by advance on an edge or a corner).
void decide_end(const Faces& fc, const Ball& b, const Step& st, double t_end, ContactSearch& search,
                int32_t* reason, int32_t* face, double* tau) {
  const V3 a = v3(0.0, 0.0, -1.0) * fc.s->gravity;
  if (st.kind == TRAIN) {
    const Series s = series(st.v, fc.normal(support_face(st.support)), a);
    const double duration = s.period * geometric_sum(b.rates.by_e, st.n);  // series_end(s, st.n).t
    *reason = st.t + duration >= t_end ? END : (std::isfinite(st.n) ? BOUNCES : SETTLE);
    *face = -1;
    *tau = kInf;
    return;
  }
  if (st.kind == ROLL) {
    const int sup = support_face(st.support);
    const double ends = RollOver(fc, sup, st.p, st.v).ends;
    *reason = st.t + ends >= t_end ? END : EXIT;
    *face = -1;
    *tau = kInf;
    return;
  }
  const bool sliding = st.kind == SLIDE;
  V3 v0 = st.v, acc = a;
  if (sliding) slide_frame(fc, st.support, st.v, a, &v0, &acc);
  const auto [tau_c, f] = search(fc, st.p, v0, acc, st.support, sliding);
  const double tau_x = sliding ? slide_exit_time(fc, support_face(st.support), st.p, v0, acc) : kInf;
  const double tau_b = jmin(tau_c, tau_x);
  *reason = st.t + tau_b >= t_end ? END : (tau_c <= tau_x ? CONTACT : EXIT);
  *face = *reason == CONTACT ? f : -1;
  *tau = tau_c;
}

// Carry the state through one segment with structure d. found: the contact time the
// search found (on an edge or a corner it is the contact's time: not searched again).
Segment advance(const Faces& fc, const Ball& b, const Step& st, const Decision& d, double t_end, double found) {
  const V3 a = v3(0.0, 0.0, -1.0) * fc.s->gravity;
  Segment seg;
  seg.t0 = st.t;
  seg.p0 = st.p;
  seg.v0 = st.v;
  seg.acc = a;
  seg.normal = seg.pivot = kZero;
  if (d.kind == UNUSED) {
    seg.t1 = st.t;
    seg.p1 = st.p;
    seg.v1 = seg.v1_post = st.v;
    return seg;
  }
  if (d.kind == TRAIN) {
    const V3 n_sup = fc.normal(support_face(d.support));
    const Series s = series(st.v, n_sup, a);
    double tau;
    if (d.reason == END) {
      tau = t_end - st.t;
      V3 travel, vel;
      state_at(s, tau, b.rates, d.n, &travel, &vel);
      seg.p1 = st.p + travel;
      seg.v1 = vel;
    } else {
      const Start full = series_end(s, d.n, b.rates);
      tau = std::isfinite(full.t) ? full.t : 0.0;
      seg.p1 = st.p + full.x;
      seg.v1 = full.v;
    }
    seg.t1 = st.t + tau;
    seg.v1_post = seg.v1;
    seg.normal = n_sup;
    return seg;
  }
  if (d.kind == ROLL) {
    const int sup = support_face(d.support);
    const RollOver motion(fc, sup, st.p, st.v);
    const double ends = motion.ends;
    const double tau_r = d.reason == END ? t_end - st.t : (std::isfinite(ends) ? ends : 0.0);
    motion.state(tau_r, &seg.p1, &seg.v1);
    seg.v1_post = seg.v1;
    seg.t1 = st.t + tau_r;
    seg.normal = motion.axis;
    seg.pivot = motion.pivot;
    return seg;
  }
  if (d.kind == SLIDE) slide_frame(fc, d.support, st.v, a, &seg.v0, &seg.acc);
  const int face = d.face > 0 ? d.face : 0;
  const bool curved = fc.s->rank[face] >= 2;
  double tau_b;
  if (d.reason == CONTACT && curved) tau_b = std::isfinite(found) && found > 0 ? found : 0.0;
  else if (d.reason == CONTACT) tau_b = face_entering_time(fc, face, st.p, seg.v0, seg.acc);
  else if (d.reason == EXIT) tau_b = slide_exit_time(fc, support_face(d.support), st.p, seg.v0, seg.acc);
  else tau_b = t_end - st.t;
  if (!std::isfinite(tau_b)) tau_b = 0.0;
  seg.p1 = ballistic_p(st.p, seg.v0, seg.acc, tau_b);
  seg.v1 = ballistic_v(seg.v0, seg.acc, tau_b);
  seg.v1_post = d.reason == CONTACT ? contact_velocity(seg.v1, contact_normal(fc, face, seg.p1), a, b.rates) : seg.v1;
  seg.t1 = st.t + tau_b;
  return seg;
}

// Kind, support and bounce count of the segment that follows seg; false where the ball
// cannot go on (a roll over an edge that is not horizontal: not followed, as in
// estim.forward._solver._next_structure).
bool next_structure(const Faces& fc, const Ball& b, const Segment& seg, const Decision& d, Step* next) {
  const double g = fc.s->gravity;
  const V3 a = v3(0.0, 0.0, -1.0) * g;
  const int face = d.face > 0 ? d.face : 0;
  const V3 n_face = contact_normal(fc, face, seg.p1);
  const V3 post = seg.v1_post;
  // On an edge or a corner (exact geometry) a ball without normal speed rolls over it where
  // gravity presses it on more than its motion across the curve pulls it off.
  const bool curved = fc.s->rank[face] >= 2 && d.reason == CONTACT;
  const bool touches = std::fabs(inner(post, n_face)) <= REST_SPEED;
  const bool settled = touches && (inner(n_face, a) < 0) && !curved;
  const bool rolls = curved && touches && (inner(n_face, a) + across_speed2(fc, face, post, n_face) / fc.radius < 0);
  const bool grazed = curved && touches;
  const bool up = n_face[2] > 1.0 - AXIS_TOL && !curved;
  const V3 if_support = fc.normal(support_face(d.support));
  const bool stays = (d.kind == SLIDE) && (std::fabs(inner(n_face, if_support)) < AXIS_TOL) && !curved;
  // (Only a contact after which the ball neither stays on its face nor settles can start
  // a train: only then is its bounce count needed.)
  const bool may_train = d.reason == CONTACT && !stays && !settled;
  double n_train = 0.0;
  if (may_train && up) {
    // on_upward: how many bounces provably land on the face
    const double w = post[2];
    const V3 u = v3(post[0], post[1], 0.0);
    const double t_flight = 2.0 * w / g;
    const double reach = train_reach(fc, face, seg.p1, u, w * w / (2.0 * g));
    const double speed = std::sqrt(u[0] * u[0] + u[1] * u[1]);
    const double y = speed > 0 ? reach / (speed > 0 ? speed * t_flight : 1.0) : kInf;
    n_train = reach < 0 ? 0.0 : geometric_count(b.rates.by_emu, y);  // FactorLaw.landings_within
  }
  int32_t after_kind = (stays || settled) ? SLIDE : ((up && n_train >= 1) ? TRAIN : FLIGHT);
  after_kind = rolls ? ROLL : after_kind;
  const int32_t after_support = stays ? d.support : face;
  int32_t kind, support;
  switch (d.reason) {
    case CONTACT: kind = after_kind; support = after_support; break;
    case SETTLE: kind = SLIDE; support = d.support; break;
    case END: kind = UNUSED; support = -1; break;
    case EXIT: kind = FLIGHT; support = d.support; break;
    default: kind = FLIGHT; support = -1; break;
  }
  const bool keeps = kind == TRAIN || kind == SLIDE || kind == ROLL || d.reason == EXIT ||
                     (d.reason == CONTACT && grazed);
  if (!keeps) support = -1;
  bool goes_on = true;
  if (rolls || d.kind == ROLL) {
    // A ball that starts to roll rolls about a horizontal line where that is its motion;
    // one whose roll reaches the end of its edge goes on over the corner there.
    bool onto = false;
    int onward = -1;
    if (d.kind == ROLL && d.reason == EXIT) {
      // Off an edge's end onto the corner there; off a corner's region onto the edge it
      // crossed into; only if pressed onto it, as at a contact.
      const int sup = support_face(d.support);
      const RollOver motion(fc, sup, seg.p0, seg.v0);
      const bool at_end = motion.spherical
                              ? motion.exit_axis >= 0
                              : roll_exit_time(fc, sup, motion.pivot, motion.axis, seg.p1, seg.v1) <= TIE_TIME;
      const double* row = fc.row(sup);
      int free = 0;  // (an edge's axis: the first of least |m|)
      for (int i = 1; i < 3; ++i) free = std::fabs(row[DIRECTION + i]) < std::fabs(row[DIRECTION + free]) ? i : free;
      if (motion.spherical) free = motion.exit_axis > 0 ? motion.exit_axis : 0;
      onward = next_piece(fc, sup, free, seg.v1);
      bool pressed = false;
      if (onward >= 0) {
        const V3 n_on = contact_normal(fc, onward, seg.p1);
        pressed = inner(n_on, a) + across_speed2(fc, onward, seg.v1, n_on) / fc.radius < 0;
      }
      onto = at_end && onward >= 0 && pressed;
    }
    const bool followed = RollOver::follows(fc, onto ? onward : face, seg.p1, onto ? seg.v1 : post);
    if (onto) {
      kind = ROLL;
      support = onward;
    }
    goes_on = !(rolls || onto) || followed;
  }
  next->t = seg.t1;
  next->p = seg.p1;
  next->v = seg.v1_post;
  next->kind = kind;
  next->support = support;
  next->n = kind == TRAIN ? n_train : 0.0;
  return goes_on;
}

struct Plan {
  std::vector<Decision> decisions;
  std::vector<Segment> segments;
  int n_segments = 0;
  bool complete = false;
};

// The discrete structure of one ball's solution and its segments (estim.forward._solver.plan).
// Only the slots used are written: pad() fills the rest where they are read.
void plan(const Faces& fc, const Ball& b, double t_end, int S, Plan* out, ContactSearch& search) {
  out->decisions.resize(S);
  out->segments.resize(S);
  Step st{0.0, b.position, b.velocity, FLIGHT, -1, 0.0};
  int k = 0;
  int done = 0;  // 1: at t_end; -1: cannot go on
  while (k < S && done == 0) {
    Decision d{st.kind, st.support, st.n, END, -1};
    double found;
    decide_end(fc, b, st, t_end, search, &d.reason, &d.face, &found);
    const Segment seg = advance(fc, b, st, d, t_end, found);
    out->decisions[k] = d;
    out->segments[k] = seg;
    const bool goes_on = next_structure(fc, b, seg, d, &st);
    ++k;
    done = goes_on ? (d.reason == END ? 1 : 0) : -1;
  }
  out->n_segments = k;
  out->complete = done == 1;
}

// The unused slots of a plan as estim.forward._solver.plan leaves them: unused decisions, and
// segments that hold the final state.
void pad(Plan* pl) {
  const int S = static_cast<int>(pl->segments.size());
  const Segment last = pl->segments[std::max(pl->n_segments - 1, 0)];
  for (int i = pl->n_segments; i < S; ++i) {
    pl->decisions[i] = Decision{UNUSED, -1, 0.0, END, -1};
    Segment& f = pl->segments[i];
    f.t0 = f.t1 = last.t1;
    f.p0 = f.p1 = last.p1;
    f.v0 = f.v1 = f.v1_post = last.v1_post;
    f.acc = f.normal = f.pivot = kZero;
  }
}

// ---------------------------------------------------------------------------------------
// estim.forward._balls: a ball inside a solid (deeper than INSIDE_DEPTH), and the planned path's check

bool inside_solid(const Faces& fc, V3 p, double r, bool path) {
  const Scene& sc = *fc.s;
  const double limit = r - INSIDE_DEPTH;
  // Exact geometry: closer than r to the box. The seed's: a box is entered beyond one of
  // its faces only, not beyond two or three at once; along a path, only where the centre
  // is inside the box itself (a ball passes corners).
  for (int b = 0; b < sc.n_boxes; ++b) {
    double depth = 0.0, gap_max = -kInf, squares = 0.0;
    int beyond = 0;
    for (int i = 0; i < 3; ++i) {
      const double gap = std::fabs(p[i] - sc.centre[b * 3 + i]) - sc.half[b * 3 + i];
      const double excess = jmax(gap, 0.0);
      gap_max = jmax(gap_max, gap);
      beyond += excess > 0.0;
      depth = depth + excess;
      squares = squares + excess * excess;
    }
    if (sc.exact ? std::sqrt(squares) < limit : (path ? gap_max < -INSIDE_DEPTH : (beyond <= 1 && depth < limit)))
      return true;
  }
  for (int k = 0; k < sc.n_planes; ++k) {
    const double height = p[0] * sc.p_normal[k * 3] + p[1] * sc.p_normal[k * 3 + 1] + p[2] * sc.p_normal[k * 3 + 2];
    if (height < sc.p_offset[k] + r - INSIDE_DEPTH) return true;
  }
  return false;
}

// (Each point once: a segment starts where the one before it ends, and a bounce series'
// middle is taken at its start.)
bool stays_outside(const Faces& fc, double r, const Plan& pl) {
  if (pl.n_segments > 0 && inside_solid(fc, pl.segments[0].p0, r, true)) return false;
  for (int k = 0; k < pl.n_segments; ++k) {
    const Segment& s = pl.segments[k];
    const double half = 0.5 * (s.t1 - s.t0);
    V3 middle = ballistic_p(s.p0, s.v0, s.acc, half), v;
    if (pl.decisions[k].kind == ROLL) roll_state(s, fc.s->gravity, half, &middle, &v);
    const bool middle_inside = pl.decisions[k].kind != TRAIN && inside_solid(fc, middle, r, true);
    if (middle_inside || inside_solid(fc, s.p1, r, true)) return false;
  }
  return true;
}

// ---------------------------------------------------------------------------------------
// estim.forward._trajectory

// Position and velocity at time t (estim.forward._trajectory.sample).
void sample(const Plan& pl, const Rates& c, double g, double t, V3* p, V3* v) {
  // (Unused slots start at inf in estim.forward._trajectory.sample: they never count.)
  int count = 0;
  for (int k = 0; k < pl.n_segments; ++k) count += pl.segments[k].t0 <= t;
  const int k = count > 0 ? count - 1 : 0;
  const Segment& s = pl.segments[k];
  const double tau = t - s.t0;
  if (pl.decisions[k].kind == ROLL) {
    roll_state(s, g, tau, p, v);
  } else if (pl.decisions[k].kind == TRAIN) {
    const V3 a = v3(0.0, 0.0, -1.0) * g;
    const bool is_train = inner(s.v0, s.normal) > 0;
    const V3 normal = is_train ? s.normal : kUp;
    const Series sr = series(is_train ? s.v0 : normal, normal, a);
    V3 dp;
    state_at(sr, tau, c, pl.decisions[k].n, &dp, v);
    *p = s.p0 + dp;
  } else {
    for (int i = 0; i < 3; ++i) (*p)[i] = s.p0[i] + s.v0[i] * tau + 0.5 * s.acc[i] * (tau * tau);
    *v = ballistic_v(s.v0, s.acc, tau);
  }
}

struct Event {
  double t;
  V3 position, pre, post;
  int32_t face, kind;
};

// The bounces of a train that are listed, and the event slots a segment takes (capped).
void listed(const Segment& seg, const Decision& d, const Rates& c, double g, int max_events, double* bounces,
            double* capped) {
  const double e = c.e;
  const bool is_train = d.kind == TRAIN;
  const bool contact = (d.reason == CONTACT) && (d.kind != UNUSED);
  if (!is_train) {  // (the bounce count of a train is all the rest is for)
    *bounces = 0.0;
    *capped = jmin(contact ? 1.0 : 0.0, max_events + 1.0);
    return;
  }
  const double a_n = (is_train ? seg.normal[2] : 1.0) * -g;
  const double w = is_train ? inner(seg.v0, seg.normal) : 1.0;
  const double t_flight = 2.0 * w / -a_n;
  const double before_end = geometric_count(c.by_e, (seg.t1 - seg.t0) / t_flight);
  double b = d.reason == BOUNCES ? d.n : jmin(before_end, d.n);
  const bool proper = e > 0 && e < 1;
  const double le = std::log(proper ? e : 0.5);
  const double ratio = std::log(LISTED_FLIGHT / t_flight);
  double listable = t_flight >= LISTED_FLIGHT ? std::floor(ratio / le) + 1.0 : 0.0;
  listable = proper ? listable : (e == 0 ? 0.0 : kInf);
  if (!std::isfinite(d.n)) b = jmin(b, listable);
  const double settles = (is_train && d.reason == SETTLE) ? 1.0 : 0.0;
  const double total = contact ? 1.0 : (is_train ? b : 0.0) + settles;
  *bounces = b;
  *capped = jmin(total, max_events + 1.0);
}

// Where the last listed bounce of a train began its next flight (train_bounce): bounce j
// ends flight j - 1, which the bounce before it began.
struct LastBounce {
  int segment = -1;
  double j = 0.0;
  Start at;
};

// Bounce j (from 1) of the train segment k, s (estim.forward._trajectory._bounce /
// estim.forward.laws.AbstractSummableLaw.bounce).
void train_bounce(const Segment& s, int k, double j, const Rates& c, double g, Event* ev, LastBounce* last) {
  const bool is_train = inner(s.v0, s.normal) > 0;
  const V3 normal = is_train ? s.normal : kUp;
  const Series sr = series(is_train ? s.v0 : normal, normal, v3(0.0, 0.0, -1.0) * g);
  const Start at = flight_start(sr, j, c);
  const bool known = last->segment == k && last->j == j - 1.0;
  const Start before = known ? last->at : flight_start(sr, j - 1.0, c);
  *last = LastBounce{k, j, at};
  const double tau = at.t - before.t;
  const V3 a_full = sr.a_t + sr.a_n * sr.normal;
  ev->t = s.t0 + at.t;
  ev->position = s.p0 + at.x;
  ev->pre = before.v + a_full * tau;
  ev->post = at.v;
}

// One ball's event list, and the buffers list_events fills it from.
struct EventList {
  std::vector<Event> events;
  std::vector<double> bounces, ends, capped;  // per segment
};

// The event list of one ball (estim.forward._trajectory.list_events_used); returns the count of
// events that happened (listed or not).
double list_events(const Plan& pl, const Rates& c, double g, int max_events, EventList* out) {
  // (Only the used segments: an unused one takes no slot, so every slot below falls in
  // a used segment.)
  const int S = pl.n_segments;
  std::vector<double>&bounces = out->bounces, &ends = out->ends, &capped = out->capped;
  bounces.resize(S);
  ends.resize(S);
  capped.resize(S);
  double total = 0.0;
  for (int k = 0; k < S; ++k) {
    listed(pl.segments[k], pl.decisions[k], c, g, max_events, &bounces[k], &capped[k]);
    total = total + capped[k];
    ends[k] = total;
  }
  std::vector<Event>* events = &out->events;
  events->clear();
  int count = 0;  // segments that end at or before the slot (ends never decrease)
  LastBounce last;
  for (int slot = 0; slot < max_events && slot < total; ++slot) {
    const double i = slot;
    while (count < S && ends[count] <= i) ++count;
    const int k = static_cast<int>(clip_index(count, S - 1));
    const double local = i - (ends[k] - capped[k]) + 1.0;
    const Segment& s = pl.segments[k];
    const Decision& d = pl.decisions[k];
    const bool train_slot = d.kind == TRAIN;
    const bool settle_slot = train_slot && d.reason == SETTLE && local > bounces[k];
    Event ev;
    if (!train_slot || settle_slot) {
      ev.t = s.t1;
      ev.position = s.p1;
      ev.pre = s.v1;
      ev.post = s.v1_post;
    } else {
      train_bounce(s, k, local, c, g, &ev, &last);
    }
    ev.face = train_slot ? d.support : d.face;
    const V3 jump = ev.pre - ev.post;
    const double size = std::sqrt(jump[0] * jump[0] + jump[1] * jump[1] + jump[2] * jump[2]);
    ev.kind = (settle_slot || size <= REST_SPEED) ? REST : IMPACT;
    events->push_back(ev);
  }
  return total;
}

// What one thread reuses from ball to ball, and from call to call (its buffers only:
// workspace() forgets the scene, whose buffers XLA may reuse for another scene).
struct Workspace {
  Faces faces;
  ContactSearch search;
  Plan plan;
  EventList events;
};

Workspace& workspace() {
  static thread_local Workspace ws;
  ws.faces.forget();
  return ws;
}

// ---------------------------------------------------------------------------------------
// The FFI handlers.
//
// Inputs come with the shapes estim.forward._native gives them (a batch of N balls sharing one
// scene, t_end and ts) plus any leading axes that jax.vmap added: with
// vmap_method="expand_dims" every input gets the same leading axes, of length 1 where it
// is not batched. The handlers loop over the broadcast leading axes ("outer" items), each
// a whole call of its own.

// Where each part of a Trajectory's rows lives: the start column of each field in the
// numbers (float) or the integers row, -1 where not kept. The order is that of
// estim.forward._native.FIELDS.
enum Field {
  FINAL_T, FINAL_POSITION, FINAL_VELOCITY, COMPLETE,
  POSITION, VELOCITY,
  EVENT_T, EVENT_POSITION, EVENT_PRE, EVENT_POST, EVENT_FACE, EVENT_KIND, EVENT_COUNT, EVENT_TRUNCATED,
  SEG_T0, SEG_P0, SEG_V0, SEG_ACC, SEG_T1, SEG_P1, SEG_V1, SEG_V1_POST, SEG_NORMAL, SEG_PIVOT,
  DEC_KIND, DEC_SUPPORT, DEC_N, DEC_REASON, DEC_FACE,
  SOL_E, SOL_MU_T,
  N_FIELDS
};

// The leading (vmap) axes of a call, and where outer item o of each input starts.
struct Outer {
  std::vector<int64_t> dims;
  int64_t count = 1;

  explicit Outer(ffi::Span<const int64_t> result_dims, int natural) {
    for (size_t d = 0; d + natural < result_dims.size(); ++d) {
      dims.push_back(result_dims[d]);
      count *= result_dims[d];
    }
  }
  // Whether a buffer has the leading axes and `natural` axes of its own.
  bool fits(ffi::Span<const int64_t> buf, int natural) const {
    if (buf.size() != dims.size() + natural) return false;
    for (size_t d = 0; d < dims.size(); ++d)
      if (buf[d] != 1 && buf[d] != dims[d]) return false;
    return true;
  }
  // Element offset of outer item o in a buffer with these leading axes (1: broadcast).
  int64_t offset(ffi::Span<const int64_t> buf, int64_t o) const {
    int64_t inner = 1;
    for (size_t d = dims.size(); d < buf.size(); ++d) inner *= buf[d];
    int64_t off = 0, stride = 1;
    for (size_t d = dims.size(); d-- > 0;) {
      const int64_t i = o % dims[d];
      o /= dims[d];
      if (buf[d] != 1) off += i * stride;
      stride *= buf[d];
    }
    return off * inner;
  }
};

template <ffi::DataType T>
const ffi::NativeType<T>* at(const Outer& outer, const ffi::Buffer<T>& b, int64_t o) {
  return b.typed_data() + outer.offset(b.dimensions(), o);
}

// The scene as one buffer (estim.forward._native._scene_operands): its arrays flattened one
// after the other, and the counts of its faces, solids, boxes and planes (`counts`), which
// say where each array starts, and whether its geometry is exact. (One operand instead of
// eleven: each operand, a constant of the program in a jitted call, costs the call a
// little; the faces' ranks, small integers, travel as numbers: an integer operand of all
// ones, as the seed's geometry has, is a broadcast that XLA computes at every call.)
struct SceneBuffers {
  ffi::Buffer<ffi::F64> numbers;
  ffi::Span<const int64_t> counts;  // faces, solids, boxes, planes, exact geometry (0, 1)

  int64_t faces() const { return counts[0]; }
  int64_t solids() const { return counts[1]; }
  int64_t boxes() const { return counts[2]; }
  int64_t planes() const { return counts[3]; }
  // row, growth, rank, box_lo, box_hi, centre, half, plane normals, plane offsets, gravity
  int64_t n_numbers() const { return faces() * (ROW + 2) + solids() * 6 + boxes() * 6 + planes() * 4 + 1; }

  bool fit(const Outer& outer) const {
    if (counts.size() != 5) return false;
    for (int64_t c : counts)
      if (c < 0) return false;
    const auto nd = numbers.dimensions();
    return outer.fits(nd, 1) && nd[nd.size() - 1] == n_numbers();
  }
  Scene scene(const Outer& outer, int64_t o) const {
    Scene s;
    s.n_faces = static_cast<int>(faces());
    s.n_solids = static_cast<int>(solids());
    s.n_boxes = static_cast<int>(boxes());
    s.n_planes = static_cast<int>(planes());
    const double* x = at(outer, numbers, o);
    const auto next = [&x](int64_t size) {
      const double* start = x;
      x += size;
      return start;
    };
    s.row = next(faces() * ROW);
    s.growth = next(faces());
    s.rank = next(faces());
    s.box_lo = next(solids() * 3);
    s.box_hi = next(solids() * 3);
    s.centre = next(boxes() * 3);
    s.half = next(boxes() * 3);
    s.p_normal = next(planes() * 3);
    s.p_offset = next(planes());
    s.gravity = *next(1);
    s.exact = counts[4] != 0;
    return s;
  }
};

// Item i of a buffer that holds one item per ball (N of them) or one for all (a value the
// parameters do not batch, passed once instead of N times); items of `natural` axes
// (1: a number, 2: a 3-vector).
template <typename B>
int64_t items(const B& b, int natural) {
  return b.dimensions()[b.dimensions().size() - natural];
}
const double* item(const Outer& outer, const ffi::Buffer<ffi::F64>& b, int natural, int64_t o, int64_t i, int64_t N) {
  return at(outer, b, o) + (items(b, natural) == N ? i : 0) * (natural == 2 ? 3 : 1);
}
bool one_or_each(const Outer& outer, const ffi::Buffer<ffi::F64>& b, int natural, int64_t N) {
  return outer.fits(b.dimensions(), natural) && (items(b, natural) == N || items(b, natural) == 1);
}

// The balls' parameters, each one per ball or one for all.
struct BallBuffers {
  ffi::Buffer<ffi::F64> e, mu_t, radius, position, velocity, compression;
  int64_t N;

  bool fit(const Outer& outer) const {
    return one_or_each(outer, e, 1, N) && one_or_each(outer, mu_t, 1, N) && one_or_each(outer, radius, 1, N) &&
           one_or_each(outer, position, 2, N) && one_or_each(outer, velocity, 2, N) &&
           one_or_each(outer, compression, 1, N);
  }
  Ball ball(const Outer& outer, int64_t o, int64_t i) const {
    const double e_i = *item(outer, e, 1, o, i, N), mu_i = *item(outer, mu_t, 1, o, i, N);
    const double r = contact_radius(*item(outer, radius, 1, o, i, N), *item(outer, compression, 1, o, i, N));
    return Ball{e_i, mu_i, r, load3(item(outer, position, 2, o, i, N)), load3(item(outer, velocity, 2, o, i, N)),
                Rates(e_i, mu_i)};
  }
};

// The balls as rows of parameters (estim.forward._record's packing of estim.Params), with the
// columns where e, mu_t, radius, position, velocity and compression start.
struct BallRows {
  ffi::Buffer<ffi::F64> rows;
  ffi::Span<const int64_t> columns;

  bool fit(const Outer& outer) const {
    const auto d = rows.dimensions();
    if (!outer.fits(d, 2) || columns.size() != 6) return false;
    const int64_t width = d[d.size() - 1];
    for (size_t k = 0; k < 6; ++k) {  // position, velocity: three columns; the others one
      const bool vector = k == 3 || k == 4;
      if (columns[k] < 0 || columns[k] + (vector ? 3 : 1) > width) return false;
    }
    return true;
  }
  Ball ball(const Outer& outer, int64_t o, int64_t i) const {
    const auto d = rows.dimensions();
    const double* r = at(outer, rows, o) + d[d.size() - 1] * i;
    const double e = r[columns[0]], mu = r[columns[1]];
    return Ball{e, mu, contact_radius(r[columns[2]], r[columns[5]]), load3(r + columns[3]), load3(r + columns[4]),
                Rates(e, mu)};
  }
};

// Runs fn(first, last) over [0, n) on XLA's intra-op thread pool and the calling thread,
// in blocks of `grain` that each takes as it comes free (balls differ in cost), and waits.
template <typename Fn>
void parallel_for(ffi::ThreadPool& pool, int64_t n, int64_t grain, Fn fn) {
  const int64_t blocks = (n + grain - 1) / grain;
  const int64_t helpers = std::min<int64_t>(std::max<int64_t>(1, pool.num_threads()), blocks) - 1;
  if (helpers <= 0) {
    fn(0, n);
    return;
  }
  std::atomic<int64_t> next(0), left(helpers);
  const auto work = [&] {
    for (int64_t first; (first = next.fetch_add(grain, std::memory_order_relaxed)) < n;)
      fn(first, std::min(first + grain, n));
  };
  for (int64_t h = 0; h < helpers; ++h) {
    pool.Schedule([&] {
      work();
      left.fetch_sub(1, std::memory_order_release);
    });
  }
  work();
  while (left.load(std::memory_order_acquire) > 0) std::this_thread::yield();
}

const ffi::Error kShapes = ffi::Error::InvalidArgument("estim: the native solver got inputs of unexpected shapes");

// Plan every ball: decisions, segments, segment count and completion (estim.forward._solver.Plan).
ffi::Error PlanImpl(ffi::ThreadPool pool, ffi::Buffer<ffi::F64> scene_numbers,
                    ffi::Buffer<ffi::F64> balls, ffi::Buffer<ffi::F64> t_end, ffi::ResultBuffer<ffi::S32> kind, ffi::ResultBuffer<ffi::S32> support, ffi::ResultBuffer<ffi::F64> n,
                    ffi::ResultBuffer<ffi::S32> reason, ffi::ResultBuffer<ffi::S32> face,
                    ffi::ResultBuffer<ffi::F64> segments, ffi::ResultBuffer<ffi::S32> n_segments,
                    ffi::ResultBuffer<ffi::PRED> complete, ffi::Span<const int64_t> counts,
                    ffi::Span<const int64_t> columns) {
  const SceneBuffers sb{scene_numbers, counts};
  const BallRows bb{balls, columns};
  const Outer outer(kind->dimensions(), 2);  // kind: (..., N, S)
  if (!sb.fit(outer) || !bb.fit(outer) || !outer.fits(t_end.dimensions(), 0)) return kShapes;
  const auto own = kind->dimensions();
  const int64_t N = own[own.size() - 2], S = own[own.size() - 1];
  parallel_for(pool, outer.count * N, 64, [&](int64_t first, int64_t last) {
    Workspace& ws = workspace();
    Plan& pl = ws.plan;
    for (int64_t w = first; w < last; ++w) {
      const int64_t o = w / N, i = w % N;
      const Scene sc = sb.scene(outer, o);
      const Ball b = bb.ball(outer, o, i);
      ws.faces.reset(&sc, b.radius);
      plan(ws.faces, b, at(outer, t_end, o)[0], static_cast<int>(S), &pl, ws.search);
      pad(&pl);
      for (int64_t k = 0; k < S; ++k) {
        const Decision& d = pl.decisions[k];
        const int64_t slot = w * S + k;
        kind->typed_data()[slot] = d.kind;
        support->typed_data()[slot] = d.support;
        n->typed_data()[slot] = d.n;
        reason->typed_data()[slot] = d.reason;
        face->typed_data()[slot] = d.face;
        write_segment(pl.segments[k], segments->typed_data() + slot * SEGMENT_NUMBERS);
      }
      n_segments->typed_data()[w] = pl.n_segments;
      complete->typed_data()[w] = pl.complete;
    }
  });
  return ffi::Error::Success();
}

// The inputs of one ball against the checks of estim.forward._simulate._INPUT_CHECKS: 0 if all
// pass, else 1 + the index of the first that fails. (The last of them, UNREAD_BY_KERNELS_CHECKS,
// are of parameters the kernels never read: the friction law's and the air's.)
int input_code(const Faces& fc, const Ball& b, bool has_mass, double mass, double drag, V3 spin, double t_end,
               const double* ts, int64_t T) {
  const bool bad[] = {
      !(b.e >= 0 && b.e <= 1),
      !(b.mu_t >= 0 && b.mu_t <= 1),
      !(b.radius > 0),
      !all_finite(b.position),
      !all_finite(b.velocity),
      has_mass && !(mass > 0),
      !(drag >= 0),
      !all_finite(spin),
  };
  for (int k = 0; k < 8; ++k)
    if (bad[k]) return k + 1;
  if (!(std::isfinite(t_end) && t_end > 0)) return 9;
  for (int64_t j = 0; j < T; ++j)
    if (!(std::isfinite(ts[j]) && ts[j] >= 0 && ts[j] <= t_end)) return 10;
  if (inside_solid(fc, b.position, b.radius, false)) return 11;
  return 0;
}

// One ball's Trajectory rows (estim.forward._simulate: plan, samples, events, final state, dense
// solution, packed as estim.forward._record lays them out); returns its check code.
int trajectory_rows(const Scene& sc, const Ball& b, double te, const double* ts, int64_t T, int S, int E,
                    ffi::Span<const int64_t> fields, double* num, int32_t* ints, Workspace& ws) {
  Plan& pl = ws.plan;
  const double g = sc.gravity;
  auto put = [&](Field f, int64_t k, double x) { num[fields[f] + k] = x; };
  auto put3 = [&](Field f, int64_t k, V3 x) {
    for (int c = 0; c < 3; ++c) num[fields[f] + 3 * k + c] = x[c];
  };
  auto put_int = [&](Field f, int64_t k, int32_t x) { ints[fields[f] + k] = x; };
  ws.faces.reset(&sc, b.radius);
  plan(ws.faces, b, te, S, &pl, ws.search);
  const bool complete = pl.complete && stays_outside(ws.faces, b.radius, pl);
  const Segment& last_seg = pl.segments[std::max(pl.n_segments - 1, 0)];
  put(FINAL_T, 0, te);
  put3(FINAL_POSITION, 0, last_seg.p1);
  put3(FINAL_VELOCITY, 0, last_seg.v1_post);
  put_int(COMPLETE, 0, complete);
  if (fields[POSITION] >= 0) {
    for (int64_t j = 0; j < T; ++j) {
      V3 p, v;
      sample(pl, b.rates, g, ts[j], &p, &v);
      put3(POSITION, j, p);
      put3(VELOCITY, j, v);
    }
  }
  // (Slots past the last used one are written field by field, as runs of one value.)
  auto fill = [&](Field f, int64_t from, int64_t to, double x) { std::fill(num + fields[f] + from, num + fields[f] + to, x); };
  auto fill3 = [&](Field f, int64_t from, int64_t to, V3 x) {
    for (int64_t k = from; k < to; ++k) put3(f, k, x);
  };
  auto fill_int = [&](Field f, int64_t from, int64_t to, int32_t x) {
    std::fill(ints + fields[f] + from, ints + fields[f] + to, x);
  };
  if (fields[EVENT_T] >= 0) {
    const double total = list_events(pl, b.rates, g, E, &ws.events);
    const std::vector<Event>& events = ws.events.events;
    const int n = static_cast<int>(std::min<size_t>(events.size(), E));
    for (int j = 0; j < n; ++j) {
      const Event& ev = events[j];
      put(EVENT_T, j, ev.t);
      put3(EVENT_POSITION, j, ev.position);
      put3(EVENT_PRE, j, ev.pre);
      put3(EVENT_POST, j, ev.post);
      put_int(EVENT_FACE, j, ev.face);
      put_int(EVENT_KIND, j, ev.kind);
    }
    // Unused slots: t = inf, zero vectors, face and kind -1 (estim.forward._trajectory).
    fill(EVENT_T, n, E, kInf);
    for (Field f : {EVENT_POSITION, EVENT_PRE, EVENT_POST}) fill(f, 3 * n, 3 * E, 0.0);
    fill_int(EVENT_FACE, n, E, -1);
    fill_int(EVENT_KIND, n, E, -1);
    put_int(EVENT_COUNT, 0, static_cast<int32_t>(jmin(total, E)));
    put_int(EVENT_TRUNCATED, 0, total > E);
  }
  if (fields[SEG_T0] >= 0) {
    const int n = pl.n_segments;
    for (int k = 0; k < n; ++k) {
      const Segment& s = pl.segments[k];
      const Decision& d = pl.decisions[k];
      put(SEG_T0, k, s.t0);
      put3(SEG_P0, k, s.p0);
      put3(SEG_V0, k, s.v0);
      put3(SEG_ACC, k, s.acc);
      put(SEG_T1, k, s.t1);
      put3(SEG_P1, k, s.p1);
      put3(SEG_V1, k, s.v1);
      put3(SEG_V1_POST, k, s.v1_post);
      put3(SEG_NORMAL, k, s.normal);
      put3(SEG_PIVOT, k, s.pivot);
      put_int(DEC_KIND, k, d.kind);
      put_int(DEC_SUPPORT, k, d.support);
      put(DEC_N, k, d.n);
      put_int(DEC_REASON, k, d.reason);
      put_int(DEC_FACE, k, d.face);
    }
    // Unused slots as pad() leaves them: the final state, held.
    const Segment& last = pl.segments[std::max(n - 1, 0)];
    for (Field f : {SEG_T0, SEG_T1}) fill(f, n, S, last.t1);
    for (Field f : {SEG_P0, SEG_P1}) fill3(f, n, S, last.p1);
    for (Field f : {SEG_V0, SEG_V1, SEG_V1_POST}) fill3(f, n, S, last.v1_post);
    for (Field f : {SEG_ACC, SEG_NORMAL, SEG_PIVOT}) fill(f, 3 * n, 3 * S, 0.0);
    fill_int(DEC_KIND, n, S, UNUSED);
    fill_int(DEC_SUPPORT, n, S, -1);
    fill(DEC_N, n, S, 0.0);
    fill_int(DEC_REASON, n, S, END);
    fill_int(DEC_FACE, n, S, -1);
    put(SOL_E, 0, b.e);
    put(SOL_MU_T, 0, b.mu_t);
  }
  return complete ? 0 : 12;
}

// Every ball's Trajectory rows, with the argument checks when asked: then the first
// failing check over the balls (the smallest code, as estim.forward._simulate orders them) is
// returned as an error carrying its message (`messages`: one per line, in code order).
ffi::Error TrajectoryImpl(ffi::ThreadPool pool, ffi::Buffer<ffi::F64> scene_numbers,
                          ffi::Buffer<ffi::F64> e, ffi::Buffer<ffi::F64> mu_t,
                          ffi::Buffer<ffi::F64> radius, ffi::Buffer<ffi::F64> position,
                          ffi::Buffer<ffi::F64> velocity, ffi::Buffer<ffi::F64> compression,
                          ffi::Buffer<ffi::F64> mass, ffi::Buffer<ffi::F64> drag,
                          ffi::Buffer<ffi::F64> spin, ffi::Buffer<ffi::F64> t_end, ffi::Buffer<ffi::F64> ts,
                          ffi::ResultBuffer<ffi::F64> record, ffi::ResultBuffer<ffi::S32> flags, int64_t max_segments,
                          int64_t max_events, bool checks, ffi::Span<const int64_t> fields, std::string_view messages,
                          ffi::Span<const int64_t> counts) {
  const SceneBuffers sb{scene_numbers, counts};
  const Outer outer(record->dimensions(), 2);  // record: (..., N, numbers)
  const auto own = record->dimensions();
  const int64_t N = own[own.size() - 2], n_numbers = own[own.size() - 1];
  const BallBuffers bb{e, mu_t, radius, position, velocity, compression, N};
  // mass, drag and spin (read by the checks only) come one per ball or one for all; no
  // mass at all where the parameters have none.
  const bool mass_shaped = outer.fits(mass.dimensions(), 1), has_mass = mass_shaped && items(mass, 1) > 0;
  if (!sb.fit(outer) || !bb.fit(outer) || !mass_shaped || (has_mass && !one_or_each(outer, mass, 1, N)) ||
      !one_or_each(outer, drag, 1, N) || !one_or_each(outer, spin, 2, N) || !outer.fits(t_end.dimensions(), 0) ||
      !outer.fits(ts.dimensions(), 1) || fields.size() != N_FIELDS)
    return kShapes;
  const int64_t n_integers = flags->dimensions()[flags->dimensions().size() - 1];
  const int64_t T = ts.dimensions()[ts.dimensions().size() - 1];
  std::vector<int> codes(checks ? outer.count * N : 0, 0);

  parallel_for(pool, outer.count * N, 64, [&](int64_t first, int64_t last) {
    Workspace& ws = workspace();
    for (int64_t w = first; w < last; ++w) {
      const int64_t o = w / N, i = w % N;
      const Scene sc = sb.scene(outer, o);
      const Ball b = bb.ball(outer, o, i);
      const double te = at(outer, t_end, o)[0];
      const double* times = at(outer, ts, o);
      const int complete_code = trajectory_rows(sc, b, te, times, T, static_cast<int>(max_segments),
                                                static_cast<int>(max_events), fields, record->typed_data() + w * n_numbers,
                                                flags->typed_data() + w * n_integers, ws);
      if (checks) {
        const double m = has_mass ? *item(outer, mass, 1, o, i, N) : 1.0;
        const double cd = *item(outer, drag, 1, o, i, N);
        const V3 spin_i = load3(item(outer, spin, 2, o, i, N));
        const int code = input_code(ws.faces, b, has_mass, m, cd, spin_i, te, times, T);  // (faces: this ball's)
        codes[w] = code > 0 ? code : complete_code;
      }
    }
  });

  int first = 0;
  for (int c : codes)
    if (c > 0 && (first == 0 || c < first)) first = c;
  if (first > 0) {
    std::string_view rest = messages;
    for (int k = 1; k < first && rest.find('\n') != std::string_view::npos; ++k) rest = rest.substr(rest.find('\n') + 1);
    return ffi::Error::InvalidArgument(std::string(rest.substr(0, rest.find('\n'))));
  }
  return ffi::Error::Success();
}

}  // namespace

// Both handlers' first arguments: XLA's thread pool, then the scene (estim.forward._native.
// _scene_operands; its `counts` attribute comes last).
static auto scene_binding() {
  return ffi::Ffi::Bind()
      .Ctx<ffi::ThreadPool>()
      .Arg<ffi::Buffer<ffi::F64>>();  // the scene
}

XLA_FFI_DEFINE_HANDLER_SYMBOL(EstimPlan, PlanImpl,
                              scene_binding()
                                  .Arg<ffi::Buffer<ffi::F64>>()  // balls: rows of parameters
                                  .Arg<ffi::Buffer<ffi::F64>>()  // t_end
                                  .Ret<ffi::Buffer<ffi::S32>>()  // kind
                                  .Ret<ffi::Buffer<ffi::S32>>()  // support
                                  .Ret<ffi::Buffer<ffi::F64>>()  // n
                                  .Ret<ffi::Buffer<ffi::S32>>()  // reason
                                  .Ret<ffi::Buffer<ffi::S32>>()  // face
                                  .Ret<ffi::Buffer<ffi::F64>>()  // segments
                                  .Ret<ffi::Buffer<ffi::S32>>()  // n_segments
                                  .Ret<ffi::Buffer<ffi::PRED>>()  // complete
                                  .Attr<ffi::Span<const int64_t>>("counts")    // the scene's faces, solids, boxes, planes
                                  .Attr<ffi::Span<const int64_t>>("columns"));  // of e, mu_t, radius, position, velocity, compression

XLA_FFI_DEFINE_HANDLER_SYMBOL(EstimTrajectory, TrajectoryImpl,
                              scene_binding()
                                  .Arg<ffi::Buffer<ffi::F64>>()  // e
                                  .Arg<ffi::Buffer<ffi::F64>>()  // mu_t
                                  .Arg<ffi::Buffer<ffi::F64>>()  // radius
                                  .Arg<ffi::Buffer<ffi::F64>>()  // position
                                  .Arg<ffi::Buffer<ffi::F64>>()  // velocity
                                  .Arg<ffi::Buffer<ffi::F64>>()  // compression
                                  .Arg<ffi::Buffer<ffi::F64>>()  // mass (or empty)
                                  .Arg<ffi::Buffer<ffi::F64>>()  // drag coefficient
                                  .Arg<ffi::Buffer<ffi::F64>>()  // spin
                                  .Arg<ffi::Buffer<ffi::F64>>()  // t_end
                                  .Arg<ffi::Buffer<ffi::F64>>()  // ts
                                  .Ret<ffi::Buffer<ffi::F64>>()  // record
                                  .Ret<ffi::Buffer<ffi::S32>>()  // flags
                                  .Attr<int64_t>("max_segments")
                                  .Attr<int64_t>("max_events")
                                  .Attr<bool>("checks")
                                  .Attr<ffi::Span<const int64_t>>("fields")
                                  .Attr<std::string_view>("messages")
                                  .Attr<ffi::Span<const int64_t>>("counts"));  // the scene's faces, solids, boxes, planes

// A Python module whose `handlers()` gives the two handlers as capsules, for
// jax.ffi.register_ffi_target.
static PyObject* handlers(PyObject*, PyObject*) {
  return Py_BuildValue("{s:N,s:N}", "estim_plan", PyCapsule_New(reinterpret_cast<void*>(EstimPlan), nullptr, nullptr),
                       "estim_trajectory",
                       PyCapsule_New(reinterpret_cast<void*>(EstimTrajectory), nullptr, nullptr));
}

// `constants()`: the numbers this module was compiled with (_constants.h), name -> value,
// for estim.forward._native to check against estim/forward/_constants.py.
static PyObject* constants(PyObject*, PyObject*) {
  PyObject* out = PyDict_New();
  if (out == nullptr) return nullptr;
  for (const EstimConstant& c : kConstants) {
    PyObject* value = PyFloat_FromDouble(c.value);
    if (value == nullptr || PyDict_SetItemString(out, c.name, value) < 0) {
      Py_XDECREF(value);
      Py_DECREF(out);
      return nullptr;
    }
    Py_DECREF(value);
  }
  return out;
}

static PyMethodDef kMethods[] = {
    {"handlers", handlers, METH_NOARGS, "The XLA FFI handlers of estim's closed-form solver, as capsules."},
    {"constants", constants, METH_NOARGS, "The shared constants the kernels were compiled with (name -> value)."},
    {nullptr, nullptr, 0, nullptr}};

static PyModuleDef kModule = {PyModuleDef_HEAD_INIT, "_kernels",
                              "estim's closed-form solver as native CPU kernels (XLA FFI handlers).", -1, kMethods};

PyMODINIT_FUNC PyInit__kernels(void) { return PyModule_Create(&kModule); }
