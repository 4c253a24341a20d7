// The closed-form solver of estim as native CPU kernels, called from JAX through its
// foreign function interface (XLA FFI; estim.forward._native registers and calls them).
//
// What runs here is the *primal* of the gravity-only path: the plan of every ball (the
// discrete structure of its solution and its segments), its samples, its event list and
// its packed Trajectory rows. Derivatives never come here: JAX computes them by replaying
// the structure this kernel found with the differentiable closed forms of estim.forward._solver
// (estim.forward._native, the custom_jvp). Every function below is a line-by-line port of the
// JAX function of the same name, with the same formulas and the same tolerances; the
// docstrings there carry the maths (estim.forward._contact, estim.forward.laws, estim.forward._solver,
// estim.forward._trajectory) and tests/test_native.py checks that both give the same structure
// and the same numbers, to rounding, ball by ball.
//
// Why native: a JAX program of this event loop is a single XLA kernel of some 26,000 HLO
// lines that takes XLA 2.5 s to compile, and a call of it costs its buffers' allocations.
// Compiled here, once, at install, a call is the loop alone (docs/pages/speed.md).
//
// Semantics kept from JAX: jnp.minimum / jnp.maximum / jnp.min propagate NaN (jmin, jmax
// below), comparisons with NaN are false, and expressions are evaluated in the order the
// JAX code writes them (XLA does not reassociate floating point).
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
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// Tolerances, limits, segment kinds (FLIGHT, TRAIN, SLIDE, UNUSED), end reasons (END,
// CONTACT, EXIT, BOUNCES, SETTLE) and event kinds (IMPACT, REST): _constants.h.

// Columns of a face-table row (estim.forward._contact.Faces.row), and the bordering faces
// of lower rank kept per face.
constexpr int ROW = FACE_ROW, NORMAL = FACE_NORMAL, OFFSET = FACE_OFFSET, CENTRE = FACE_CENTRE, HALF = FACE_HALF,
              DIRECTION = FACE_DIRECTION, SOLID = FACE_SOLID;
constexpr int LOWER = FACE_LOWER;

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
  const int32_t* rank;     // (faces,)
  const int32_t* lower;    // (faces, 6)
  const double* box_lo;    // (solids, 3): solids as boxes, before growing by r
  const double* box_hi;
  const double* centre;    // (boxes, 3): the boxes themselves
  const double* half;
  const double* p_normal;  // (planes, 3)
  const double* p_offset;  // (planes,)
  double gravity;
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
  std::vector<double> offset;  // plane offset for the ball's centre, per face
  std::vector<int32_t> order;  // rank * faces + index: ties go to lower rank, then index
  // The faces of each solid, [first[b], first[b + 1]) (estim.model._scene lists them solid by
  // solid); empty when a scene lists them otherwise, and then no broad phase is used.
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
    for (int f = 0; f < F; ++f) order[f] = scene.rank[f] * F + f;
    first.assign(scene.n_solids + 1, F);
    bool grouped = true;
    for (int f = 0, b = 0; f < F && grouped; ++f) {  // b: the next solid to start
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
  std::vector<Candidate> found, alive;
  std::vector<double> bound;  // per solid
  std::vector<double> time;   // per face

  std::pair<double, int> operator()(const Faces& fc, V3 p, V3 v, V3 a, int exclude) {
    const int F = fc.s->n_faces;
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
      best = resolve(fc, p, v, a);
    }
    return best;
  }

  // The earliest candidate, ties to the lowest order, dropping up to three that are
  // blocked (the ball touches a lower-rank face bordering it without entering it).
  std::pair<double, int> resolve(const Faces& fc, V3 p, V3 v, V3 a) {
    std::vector<Candidate>* list = &found;  // (copied to `alive` only to drop one)
    for (int rounds = 0;; ++rounds) {
      const std::vector<Candidate>& c = *list;
      double t_min = kInf;
      for (const Candidate& x : c) t_min = jmin(t_min, x.tau);
      if (!std::isfinite(t_min)) return {t_min, -1};
      size_t pick = 0;
      int32_t best = std::numeric_limits<int32_t>::max();
      for (size_t j = 0; j < c.size(); ++j)
        if (c[j].tau <= t_min + TIE_TIME && c[j].order < best) best = c[j].order, pick = j;
      const int face = c[pick].face;
      if (rounds == 3 || !blocked(fc, p, v, a, face, t_min)) return {t_min, face};
      if (list == &found) alive = found, list = &alive;
      alive.erase(alive.begin() + pick);
    }
  }

  static bool blocked(const Faces& fc, V3 p, V3 v, V3 a, int face, double t) {
    const V3 qf = ballistic_p(p, v, a, t), wf = ballistic_v(v, a, t);
    for (int k = 0; k < LOWER; ++k) {
      const int j = fc.s->lower[face * LOWER + k];
      if (j < 0) continue;
      const V3 nj = fc.normal(j);
      const double gj0 = inner(nj, qf) - fc.offset[j], gj1 = inner(nj, wf), gj2 = inner(nj, a);
      const bool touches = std::fabs(gj0) <= POSITION_TOL;
      // A ball at the apex of a graze leaves the face by no more than gj1^2 / (2 |gj2|)
      // before falling into it: within POSITION_TOL that is entering it.
      const bool grazes = (gj2 < -ACCEL_TOL) && (gj1 * gj1 <= -2.0 * gj2 * POSITION_TOL);
      const bool enters = moves_into(gj1, gj2) || grazes;
      if (touches && !enters) return true;
    }
    return false;
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

bool series_clear(const Faces& fc, int face, V3 p, V3 v, double duration, double gravity) {
  const double d = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) * duration + 0.5 * gravity * (duration * duration);
  const double solid = fc.row(face)[SOLID];
  for (int b = 0; b < fc.s->n_solids; ++b) {
    bool meets = static_cast<double>(b) != solid;
    for (int i = 0; i < 3 && meets; ++i) meets = (p[i] - d < fc.hi(b, i)) && (p[i] + d > fc.lo(b, i));
    if (meets) return false;
  }
  return true;
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
  V3 p1, v1, v1_post, normal;
};
constexpr int SEGMENT_NUMBERS = 23;

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
void decide_end(const Faces& fc, const Ball& b, const Step& st, double t_end, ContactSearch& search,
                int32_t* reason, int32_t* face) {
  const V3 a = v3(0.0, 0.0, -1.0) * fc.s->gravity;
  if (st.kind == TRAIN) {
    const Series s = series(st.v, fc.normal(support_face(st.support)), a);
    const double duration = s.period * geometric_sum(b.rates.by_e, st.n);  // series_end(s, st.n).t
    *reason = st.t + duration >= t_end ? END : (std::isfinite(st.n) ? BOUNCES : SETTLE);
    *face = -1;
    return;
  }
  const bool sliding = st.kind == SLIDE;
  V3 v0 = st.v, acc = a;
  if (sliding) slide_frame(fc, st.support, st.v, a, &v0, &acc);
  const auto [tau_c, f] = search(fc, st.p, v0, acc, st.support);
  const double tau_x = sliding ? slide_exit_time(fc, support_face(st.support), st.p, v0, acc) : kInf;
  const double tau_b = jmin(tau_c, tau_x);
  *reason = st.t + tau_b >= t_end ? END : (tau_c <= tau_x ? CONTACT : EXIT);
  *face = *reason == CONTACT ? f : -1;
}

// Carry the state through one segment with structure d.
Segment advance(const Faces& fc, const Ball& b, const Step& st, const Decision& d, double t_end) {
  const V3 a = v3(0.0, 0.0, -1.0) * fc.s->gravity;
  Segment seg;
  seg.t0 = st.t;
  seg.p0 = st.p;
  seg.v0 = st.v;
  seg.acc = a;
  seg.normal = kZero;
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
  if (d.kind == SLIDE) slide_frame(fc, d.support, st.v, a, &seg.v0, &seg.acc);
  const int face = d.face > 0 ? d.face : 0;
  double tau_b;
  if (d.reason == CONTACT) tau_b = face_entering_time(fc, face, st.p, seg.v0, seg.acc);
  else if (d.reason == EXIT) tau_b = slide_exit_time(fc, support_face(d.support), st.p, seg.v0, seg.acc);
  else tau_b = t_end - st.t;
  if (!std::isfinite(tau_b)) tau_b = 0.0;
  seg.p1 = ballistic_p(st.p, seg.v0, seg.acc, tau_b);
  seg.v1 = ballistic_v(seg.v0, seg.acc, tau_b);
  seg.v1_post = d.reason == CONTACT ? contact_velocity(seg.v1, fc.normal(face), a, b.rates) : seg.v1;
  seg.t1 = st.t + tau_b;
  return seg;
}

// Kind, support and bounce count of the segment that follows seg.
void next_structure(const Faces& fc, const Ball& b, const Segment& seg, const Decision& d, Step* next) {
  const double e = b.e, g = fc.s->gravity;
  const V3 a = v3(0.0, 0.0, -1.0) * g;
  const int face = d.face > 0 ? d.face : 0;
  const V3 n_face = fc.normal(face);
  const V3 post = seg.v1_post;
  const bool settled = (std::fabs(inner(post, n_face)) <= REST_SPEED) && (inner(n_face, a) < 0);
  const bool up = n_face[2] > 1.0 - AXIS_TOL;
  const bool inclined = (inner(n_face, a) < 0) && !up && (e < 1);  // FactorLaw.accumulates
  const V3 if_support = fc.normal(support_face(d.support));
  const bool stays = (d.kind == SLIDE) && (std::fabs(inner(n_face, if_support)) < AXIS_TOL);
  // (Only a contact after which the ball neither stays on its face nor settles can start
  // a train: only then is its bounce count needed.)
  const bool may_train = d.reason == CONTACT && !stays && !settled;
  double n_train = 0.0;
  if (may_train && inclined) {
    // on_bevel: a whole Zeno series, if it lands on the face and meets nothing else
    const Series s = series(post, n_face, a);
    const Start whole = series_end(s, kInf, b.rates);
    const V3 x_inf = whole.x, x_one = series_end(s, 1.0, b.rates).x;
    const double* row = fc.row(face);
    const bool lands = on_face(seg.p1 + x_inf, row + CENTRE, row + HALF, fc.radius) &&
                       on_face(seg.p1 + x_one, row + CENTRE, row + HALF, fc.radius);
    const bool clear = series_clear(fc, face, seg.p1, post, whole.t, g);
    n_train = (lands && clear) ? kInf : 0.0;
  } else if (may_train && up) {
    // on_upward: how many bounces provably land on the face
    const double w = post[2];
    const V3 u = v3(post[0], post[1], 0.0);
    const double t_flight = 2.0 * w / g;
    const double reach = train_reach(fc, face, seg.p1, u, w * w / (2.0 * g));
    const double speed = std::sqrt(u[0] * u[0] + u[1] * u[1]);
    const double y = speed > 0 ? reach / (speed > 0 ? speed * t_flight : 1.0) : kInf;
    n_train = reach < 0 ? 0.0 : geometric_count(b.rates.by_emu, y);  // FactorLaw.landings_within
  }
  const int32_t after_kind = (stays || settled) ? SLIDE : (((up || inclined) && n_train >= 1) ? TRAIN : FLIGHT);
  const int32_t after_support = stays ? d.support : face;
  int32_t kind, support;
  switch (d.reason) {
    case CONTACT: kind = after_kind; support = after_support; break;
    case SETTLE: kind = SLIDE; support = d.support; break;
    case END: kind = UNUSED; support = -1; break;
    case EXIT: kind = FLIGHT; support = d.support; break;
    default: kind = FLIGHT; support = -1; break;
  }
  if (!(kind == TRAIN || kind == SLIDE || d.reason == EXIT)) support = -1;
  next->t = seg.t1;
  next->p = seg.p1;
  next->v = seg.v1_post;
  next->kind = kind;
  next->support = support;
  next->n = kind == TRAIN ? n_train : 0.0;
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
  bool done = false;
  while (k < S && !done) {
    Decision d{st.kind, st.support, st.n, END, -1};
    decide_end(fc, b, st, t_end, search, &d.reason, &d.face);
    const Segment seg = advance(fc, b, st, d, t_end);
    out->decisions[k] = d;
    out->segments[k] = seg;
    next_structure(fc, b, seg, d, &st);
    ++k;
    done = d.reason == END;
  }
  out->n_segments = k;
  out->complete = done;
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
    f.acc = f.normal = kZero;
  }
}

// ---------------------------------------------------------------------------------------
// estim.forward._balls: a ball inside a solid (deeper than INSIDE_DEPTH), and the planned path's check

bool inside_solid(const Faces& fc, V3 p, double r, bool path) {
  const Scene& sc = *fc.s;
  const double limit = r - INSIDE_DEPTH;
  // The seed's geometry (the only one the kernels run, estim.forward._native.supports): a
  // box is entered beyond one of its faces only, not beyond two or three at once; along a
  // path, only where the centre is inside the box itself (a ball passes corners).
  for (int b = 0; b < sc.n_boxes; ++b) {
    double depth = 0.0, gap_max = -kInf;
    int beyond = 0;
    for (int i = 0; i < 3; ++i) {
      const double gap = std::fabs(p[i] - sc.centre[b * 3 + i]) - sc.half[b * 3 + i];
      const double excess = jmax(gap, 0.0);
      gap_max = jmax(gap_max, gap);
      beyond += excess > 0.0;
      depth = depth + excess;
    }
    if (path ? gap_max < -INSIDE_DEPTH : (beyond <= 1 && depth < limit)) return true;
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
    const bool middle_inside =
        pl.decisions[k].kind != TRAIN && inside_solid(fc, ballistic_p(s.p0, s.v0, s.acc, 0.5 * (s.t1 - s.t0)), r, true);
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
  if (pl.decisions[k].kind == TRAIN) {
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

// The scene as two buffers (estim.forward._native._scene_operands): its numbers and its integers,
// each its arrays flattened one after the other, and the counts of its faces, solids,
// boxes and planes (`counts`), which say where each array starts. (Two operands instead
// of eleven: each operand, a constant of the program in a jitted call, costs the call a
// little.)
struct SceneBuffers {
  ffi::Buffer<ffi::F64> numbers;
  ffi::Buffer<ffi::S32> integers;
  ffi::Span<const int64_t> counts;  // faces, solids, boxes, planes

  int64_t faces() const { return counts[0]; }
  int64_t solids() const { return counts[1]; }
  int64_t boxes() const { return counts[2]; }
  int64_t planes() const { return counts[3]; }
  // row, growth, box_lo, box_hi, centre, half, plane normals, plane offsets, gravity
  int64_t n_numbers() const { return faces() * (ROW + 1) + solids() * 6 + boxes() * 6 + planes() * 4 + 1; }
  int64_t n_integers() const { return faces() * (1 + LOWER); }  // rank, lower

  bool fit(const Outer& outer) const {
    if (counts.size() != 4) return false;
    for (int64_t c : counts)
      if (c < 0) return false;
    const auto nd = numbers.dimensions(), id = integers.dimensions();
    return outer.fits(nd, 1) && outer.fits(id, 1) && nd[nd.size() - 1] == n_numbers() &&
           id[id.size() - 1] == n_integers();
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
    s.box_lo = next(solids() * 3);
    s.box_hi = next(solids() * 3);
    s.centre = next(boxes() * 3);
    s.half = next(boxes() * 3);
    s.p_normal = next(planes() * 3);
    s.p_offset = next(planes());
    s.gravity = *next(1);
    const int32_t* k = at(outer, integers, o);
    s.rank = k;
    s.lower = k + faces();
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
ffi::Error PlanImpl(ffi::ThreadPool pool, ffi::Buffer<ffi::F64> scene_numbers, ffi::Buffer<ffi::S32> scene_integers,
                    ffi::Buffer<ffi::F64> balls, ffi::Buffer<ffi::F64> t_end, ffi::ResultBuffer<ffi::S32> kind, ffi::ResultBuffer<ffi::S32> support, ffi::ResultBuffer<ffi::F64> n,
                    ffi::ResultBuffer<ffi::S32> reason, ffi::ResultBuffer<ffi::S32> face,
                    ffi::ResultBuffer<ffi::F64> segments, ffi::ResultBuffer<ffi::S32> n_segments,
                    ffi::ResultBuffer<ffi::PRED> complete, ffi::Span<const int64_t> counts,
                    ffi::Span<const int64_t> columns) {
  const SceneBuffers sb{scene_numbers, scene_integers, counts};
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
    for (Field f : {SEG_ACC, SEG_NORMAL}) fill(f, 3 * n, 3 * S, 0.0);
    fill(SEG_PIVOT, 0, 3 * S, 0.0);  // (no rolls: the seed's geometry has no edges)
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
                          ffi::Buffer<ffi::S32> scene_integers, ffi::Buffer<ffi::F64> e, ffi::Buffer<ffi::F64> mu_t,
                          ffi::Buffer<ffi::F64> radius, ffi::Buffer<ffi::F64> position,
                          ffi::Buffer<ffi::F64> velocity, ffi::Buffer<ffi::F64> compression,
                          ffi::Buffer<ffi::F64> mass, ffi::Buffer<ffi::F64> drag,
                          ffi::Buffer<ffi::F64> spin, ffi::Buffer<ffi::F64> t_end, ffi::Buffer<ffi::F64> ts,
                          ffi::ResultBuffer<ffi::F64> record, ffi::ResultBuffer<ffi::S32> flags, int64_t max_segments,
                          int64_t max_events, bool checks, ffi::Span<const int64_t> fields, std::string_view messages,
                          ffi::Span<const int64_t> counts) {
  const SceneBuffers sb{scene_numbers, scene_integers, counts};
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
      .Arg<ffi::Buffer<ffi::F64>>()   // the scene's numbers
      .Arg<ffi::Buffer<ffi::S32>>();  // the scene's integers
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
