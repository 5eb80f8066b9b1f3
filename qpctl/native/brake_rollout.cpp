// The brake rollout's loop in C++ on Pinocchio's own algorithms (issue 22, item 2): the oracle's brake
// (RNEA at q̈ = −κq̇, clipped to ±τ_max and the rate window) held over each step of the built-in
// simulator's RK4 on ABA, with the lazy clearance's bookkeeping (qpctl/safety/rollout.py). Every
// rigid-body quantity is pinocchio::rnea / pinocchio::aba of libpinocchio (the very code the Python
// bindings call); the arithmetic around them is written in the order of
// qpctl.simulation.simulator.rk4_step and qpctl.kernels.rollout, compiled without floating-point
// contraction, so the states equal the Python path's bit for bit (tests/test_native_rollout.py).
//
// Vector-space configurations only (nq == nv): the Python path serves robots with continuous or
// planar joints. The world clearance stays in Python: qpb_advance returns when the lazy bound no
// longer covers a step, the caller evaluates the clearance and calls again.
#include <pinocchio/multibody.hpp>
#include <pinocchio/algorithm/aba.hpp>
#include <pinocchio/algorithm/rnea.hpp>
#include <pinocchio/serialization.hpp>

#include <cmath>
#include <cstring>
#include <exception>
#include <string>

namespace {

struct Brake {
  pinocchio::Model model;
  pinocchio::Data data;
  Eigen::VectorXd qdd, tau, raw, qs, dq, dv, ahead, vahead, aahead;
  Eigen::MatrixXd kq, ka;  // (n, 4): the stages' velocities and accelerations, one column each
  // a settled retreat's walk (qpb_walk_plan, qpb_walk_clear): its acceleration, its previous configuration
  Eigen::VectorXd wqdd, wprev;
  explicit Brake(const pinocchio::Model& m)
      : model(m), data(m), qdd(m.nv), tau(m.nv), raw(m.nv), qs(m.nq), dq(m.nv), dv(m.nv), ahead(m.nq),
        vahead(m.nv), aahead(m.nv), kq(m.nv, 4), ka(m.nv, 4), wqdd(m.nv), wprev(m.nv) {}
};

using Map = Eigen::Map<Eigen::VectorXd>;
using CMap = Eigen::Map<const Eigen::VectorXd>;
// The argument type of libpinocchio's explicit instantiations of aba and rnea: passing it makes the
// calls those instantiations (extern templates), not new ones compiled here.
using CRef = Eigen::Ref<const Eigen::VectorXd>;

// The brake's torque into b.tau (qpctl.safety.rollout.BrakeRollout.torque, kernels.rollout.clip_brake);
// while a retreat steers (qpctl.safety.retreat), RNEA at its q̈* = ω²(q* − q) − 2ωq̇ (w2 = ω², w1 = 2ω).
void brake_torque(Brake& b, const double* q, const double* v, const double* prev, double gain,
                  const double* tau_max, const double* window, bool steering, const double* target, double w2,
                  double w1) {
  const int n = b.model.nv;
  if (steering)
    for (int i = 0; i < n; ++i) b.qdd[i] = (target[i] - q[i]) * w2 - w1 * v[i];
  else
    for (int i = 0; i < n; ++i) b.qdd[i] = v[i] * -gain;
  b.tau = pinocchio::rnea(b.model, b.data, CRef(CMap(q, b.model.nq)), CRef(CMap(v, n)), CRef(b.qdd));
  b.raw = b.tau;
  const bool rate = std::isfinite(prev[0]);
  for (int i = 0; i < n; ++i) {
    double x = std::min(std::max(b.tau[i], -tau_max[i]), tau_max[i]);
    if (rate) x = std::min(std::max(x, prev[i] - window[i]), prev[i] + window[i]);
    b.tau[i] = x;
  }
}

// One RK4 step of the held b.tau over dt, (q, v) in place (kernels.rollout.stage_into / finish);
// returns Σᵢ ρᵢ|Δqᵢ|.
double rk4_step(Brake& b, double* q, double* v, double dt, const double* rho) {
  const int n = b.model.nv;
  b.ka.col(0) = pinocchio::aba(b.model, b.data, CRef(CMap(q, n)), CRef(CMap(v, n)), CRef(b.tau));
  const double hs[3] = {0.5 * dt, 0.5 * dt, dt};
  for (int i = 0; i < 3; ++i) {
    const double h = hs[i];
    if (i == 0)
      for (int j = 0; j < n; ++j) b.kq(j, 0) = v[j];
    for (int j = 0; j < n; ++j) b.kq(j, i + 1) = v[j] + h * b.ka(j, i);
    for (int j = 0; j < n; ++j) b.qs[j] = q[j] + h * b.kq(j, i);
    b.ka.col(i + 1) = pinocchio::aba(b.model, b.data, CRef(b.qs), CRef(b.kq.col(i + 1)), CRef(b.tau));
  }
  const double c = dt / 6;
  double travel = 0.0;
  for (int j = 0; j < n; ++j) {
    b.dq[j] = c * (((b.kq(j, 0) + 2.0 * b.kq(j, 1)) + 2.0 * b.kq(j, 2)) + b.kq(j, 3));
    b.dv[j] = c * (((b.ka(j, 0) + 2.0 * b.ka(j, 1)) + 2.0 * b.ka(j, 2)) + b.ka(j, 3));
  }
  for (int j = 0; j < n; ++j) q[j] += b.dq[j];
  for (int j = 0; j < n; ++j) v[j] += b.dv[j];
  for (int j = 0; j < n; ++j) travel += rho[j] * std::abs(b.dq[j]);
  return travel;
}

// The brake settled into its decay (qpctl.safety.rollout, "Settled"; kernels.rollout.settled), its
// torque b.tau unclipped (the caller tests it: unclipped()): along q̇e^{−κt} the torque's change over
// the next step, d = |RNEA(q + Δt·q̇, e·q̇, −κe·q̇) − τ| (e = e^{−κΔt}), stays within beta of the rate window and
// |τ| + d/(κΔt) — the torque's whole change if its rate decays with the speed — within beta of τ_max.
bool settled(Brake& b, const double* q, const double* v, double gain, double dt, double decay, double beta,
             const double* tau_max, const double* window) {
  const int n = b.model.nv;
  for (int i = 0; i < n; ++i) {
    b.ahead[i] = q[i] + dt * v[i];
    b.vahead[i] = v[i] * decay;
    b.aahead[i] = b.vahead[i] * -gain;
  }
  const Eigen::VectorXd& next = pinocchio::rnea(b.model, b.data, CRef(b.ahead), CRef(b.vahead), CRef(b.aahead));
  for (int i = 0; i < n; ++i) {
    const double d = std::abs(next[i] - b.tau[i]);
    if (!(d <= beta * window[i]) || !(std::abs(b.tau[i]) + d / (gain * dt) <= beta * tau_max[i])) return false;
  }
  return true;
}

// True if neither limit clipped the brake's torque (b.tau is b.raw).
bool unclipped(const Brake& b) {
  for (int i = 0; i < b.model.nv; ++i)
    if (b.tau[i] != b.raw[i]) return false;
  return true;
}

// A settled retreat's steering in closed form (qpctl/safety/walk.py): with e₀ = q₀ − q* and
// c = q̇₀ + ω·e₀, the unclipped steering q̈ = ω²(q* − q) − 2ωq̇ gives q = q* + (e₀ + c·s)e^{−ωs} and
// q̇ = (q̇₀ − ω·c·s)e^{−ωs}, s after the walk's start (kernels.walk.steer_state, the same operations).
void steer_state(const double* q0, const double* v0, const double* target, double w, double s, int n, double* q,
                 double* v) {
  const double x = std::exp(-w * s);
  for (int i = 0; i < n; ++i) {
    const double e0 = q0[i] - target[i];
    const double c = v0[i] + w * e0;
    q[i] = target[i] + (e0 + c * s) * x;
    v[i] = (v0[i] - w * c * s) * x;
  }
}

enum { MOVING = 0, AT_REST = 1, OUTSIDE = 2 };

int state_code(const double* q, const double* v, int n, const double* q_min, const double* q_max,
               double rest_speed) {
  for (int i = 0; i < n; ++i)
    if (!std::isfinite(q[i]) || q[i] < q_min[i] || q[i] > q_max[i]) return OUTSIDE;
  bool rest = true;
  for (int i = 0; i < n; ++i) {
    if (!std::isfinite(v[i])) return OUTSIDE;
    if (std::abs(v[i]) > rest_speed) rest = false;
  }
  return rest ? AT_REST : MOVING;
}

thread_local std::string last_error;

}  // namespace

extern "C" {

// The io block of qpb_advance (doubles): the rollout's state and its parameters.
enum {
  IO_K, IO_STEPS, IO_STILL, IO_LAST, IO_DRIFT, IO_WORST, IO_LEVEL, IO_STOP_BELOW, IO_GAIN, IO_DT,
  IO_OBSTACLE_SPEED, IO_REST_SPEED, IO_REST_TIME, IO_EVALUATED, IO_LAZY, IO_T0, IO_UNTIL, IO_W2, IO_W1,
  IO_SETTLE, IO_SETTLE_BELOW, IO_DECAY, IO_BETA, IO_GAMMA, IO_CREEP, IO_PENDING, IO_WALK_AFTER, IO_STRAY, IO_SIZE
};
// qpb_advance's answers.
enum { NEED_CLEARANCE = 0, AT_REST_END = 1, FAILED = 2, HORIZON = 3, SETTLED = 4, WALK = 5 };

// The walk's io block (qpb_walk_plan, qpb_walk_clear; qpctl/safety/walk.py's W_* order) and qpb_walk_clear's answers.
enum {
  W_K, W_T0, W_DT, W_UNTIL, W_OMEGA, W_GAIN, W_BETA, W_EVERY, W_STRAY, W_STEPS, W_NSW, W_DEV, W_RETRY, W_J,
  W_LAST, W_DRIFT, W_WORST, W_EVALUATED, W_LEVEL, W_LAZY, W_MOVE, W_PROG, W_SWITCH_STRAY, W_SIZE
};
enum { WALKED = 1, REFUSED = 2 };

int qpb_io_size() { return IO_SIZE; }

int qpb_walk_size() { return W_SIZE; }

const char* qpb_error() { return last_error.c_str(); }

void* qpb_new(const char* text, long len) {
  try {
    pinocchio::Model m;
    m.loadFromString(std::string(text, static_cast<size_t>(len)));
    if (m.nq != m.nv) {
      last_error = "the native rollout needs a vector-space configuration (nq == nv)";
      return nullptr;
    }
    return new Brake(m);
  } catch (const std::exception& e) {
    last_error = e.what();
    return nullptr;
  }
}

void qpb_free(void* h) { delete static_cast<Brake*>(h); }

int qpb_nv(void* h) { return static_cast<Brake*>(h)->model.nv; }

// Pinocchio's ABA and RNEA through the handle's model (the tests hold them to the bindings').
void qpb_aba(void* h, const double* q, const double* v, const double* tau, double* out) {
  Brake& b = *static_cast<Brake*>(h);
  const int n = b.model.nv;
  Map(out, n) = pinocchio::aba(b.model, b.data, CRef(CMap(q, n)), CRef(CMap(v, n)), CRef(CMap(tau, n)));
}

void qpb_rnea(void* h, const double* q, const double* v, const double* a, double* out) {
  Brake& b = *static_cast<Brake*>(h);
  const int n = b.model.nv;
  Map(out, n) = pinocchio::rnea(b.model, b.data, CRef(CMap(q, n)), CRef(CMap(v, n)), CRef(CMap(a, n)));
}

// One RK4 step of the held torque ``tau`` over dt from (q, v), in place (BrakeRollout.successor: the
// step the simulator takes with a proposal); returns Σᵢ ρᵢ|Δqᵢ|.
double qpb_step(void* h, double* q, double* v, const double* tau, double dt, const double* rho) {
  Brake& b = *static_cast<Brake*>(h);
  for (int i = 0; i < b.model.nv; ++i) b.tau[i] = tau[i];
  return rk4_step(b, q, v, dt, rho);
}

// The rollout's loop (qpctl.safety.rollout.BrakeRollout.run) from step io[K] on, (q, v, prev) in
// place, until it needs the clearance at the current step (NEED_CLEARANCE: the caller evaluates it
// at q, sets io[LAST], io[DRIFT] = 0, io[WORST] = min(io[WORST], clearance), io[EVALUATED] = 1, and
// calls again), ends at rest (AT_REST_END), fails (FAILED: below stop_below, past a joint limit, or
// not finite) or runs out of steps (HORIZON). io[K] is the step reached. Step k is at the time
// io[T0] + k·dt; before io[UNTIL] the retreat toward ``target`` steers (io[UNTIL] = −inf: the brake).
// With io[SETTLE] ≠ 0, a step whose brake has settled (settled()) with its creep, io[GAMMA]·Σᵢρᵢ|q̇ᵢ|/κ,
// below io[SETTLE_BELOW] returns SETTLED before the step is taken (io[CREEP]: that creep; io[PENDING] = 1:
// the step's checks done and its torque in the handle); the caller tests the rest and, if it refuses,
// lowers io[SETTLE_BELOW] and calls again, which takes the pending step. With io[SETTLE] ≠ 0, a retreat's
// steering step from io[WALK_AFTER] on whose torque was not clipped returns WALK the same way (pending):
// the caller tries the walk (qpb_walk_plan, qpb_walk_clear) and, if it is refused, sets io[WALK_AFTER]
// to the step it may be tried again from and calls again.
int qpb_advance(void* h, double* q, double* v, double* prev, const double* tau_max, const double* window,
                const double* q_min, const double* q_max, const double* rho, const double* target, double* io) {
  Brake& b = *static_cast<Brake*>(h);
  const int n = b.model.nv;
  const long steps = static_cast<long>(io[IO_STEPS]);
  const double dt = io[IO_DT], level = io[IO_LEVEL], stop_below = io[IO_STOP_BELOW], gain = io[IO_GAIN];
  const double move = io[IO_OBSTACLE_SPEED] * dt;
  const bool lazy = io[IO_LAZY] != 0.0;
  double still = io[IO_STILL], last = io[IO_LAST], drift = io[IO_DRIFT], worst = io[IO_WORST];
  const double stray = io[IO_STRAY];  // after a walk: its allowance, off every clearance (0 otherwise)
  bool evaluated = io[IO_EVALUATED] != 0.0;
  long k = static_cast<long>(io[IO_K]);
  int answer = HORIZON;
  const bool settle = io[IO_SETTLE] != 0.0;
  bool pending = io[IO_PENDING] != 0.0;
  io[IO_PENDING] = 0.0;
  for (; k < steps; ++k) {
    if (pending) {
      pending = false;  // this step's checks and torque were done before SETTLED returned
    } else {
      if (!evaluated) {
        if (lazy && last - drift - stray > level) {
          worst = std::min(worst, last - drift - stray);
        } else {
          answer = NEED_CLEARANCE;
          break;
        }
      }
      evaluated = false;
      const int code = state_code(q, v, n, q_min, q_max, io[IO_REST_SPEED]);
      if (worst < stop_below || code == OUTSIDE) {
        answer = FAILED;
        break;
      }
      const bool steering = io[IO_T0] + static_cast<double>(k) * dt < io[IO_UNTIL];
      still = code == AT_REST && !steering ? still + dt : 0.0;  // a retreat's rest is its brake's
      if (still >= io[IO_REST_TIME]) {
        answer = AT_REST_END;
        break;
      }
      brake_torque(b, q, v, prev, gain, tau_max, window, steering, target, io[IO_W2], io[IO_W1]);
      if (settle && steering && static_cast<double>(k) >= io[IO_WALK_AFTER] && unclipped(b)) {
        io[IO_PENDING] = 1.0;  // a settled retreat's walk may end the rollout here (qpb_walk_plan)
        answer = WALK;
        break;
      }
      if (settle && !steering && unclipped(b)) {
        double creep = 0.0;
        for (int i = 0; i < n; ++i) creep += rho[i] * std::abs(v[i]);
        creep = creep * io[IO_GAMMA] / gain;
        if (creep < io[IO_SETTLE_BELOW] &&
            settled(b, q, v, gain, dt, io[IO_DECAY], io[IO_BETA], tau_max, window)) {
          io[IO_CREEP] = creep;
          io[IO_PENDING] = 1.0;
          answer = SETTLED;
          break;
        }
      }
    }
    for (int i = 0; i < n; ++i) prev[i] = b.tau[i];
    const double travel = rk4_step(b, q, v, dt, rho);
    if (lazy) drift += travel + move;
  }
  io[IO_K] = static_cast<double>(k);
  io[IO_STILL] = still;
  io[IO_LAST] = last;
  io[IO_DRIFT] = drift;
  io[IO_WORST] = worst;
  io[IO_EVALUATED] = evaluated ? 1.0 : 0.0;
  return answer;
}

// A settled retreat's walk, its plan (qpctl/safety/walk.py, "The walk"): from the pending steering step
// wio[K] at (q0, v0) — its torque, unclipped, the handle's b.tau —, the steering in closed form
// (steer_state) is sampled at steps 1, every, 2·every, … and the last steering step nsw − 1 (nsw: the
// first step where t ≥ until, within the horizon wio[STEPS]): each sample's torque
// RNEA(q, q̇, ω²(q* − q) − 2ωq̇) within beta of τ_max and its change from the sample before within beta of
// the rate window times the steps between. Returns 1 (wio[NSW]; the last sample's torque into tau_out; T and
// wio[PROG] zeroed for qpb_walk_clear) or 0 (refused; wio[RETRY]: the step from which a walk may be tried
// again — the failed sample's, at least every steps on —, inf: not in this rollout).
int qpb_walk_plan(void* h, const double* q0, const double* v0, const double* target, const double* tau_max,
                  const double* window, double* T, double* wq, double* wv, double* tau_out, double* wio) {
  Brake& b = *static_cast<Brake*>(h);
  const int n = b.model.nv;
  const long k = static_cast<long>(wio[W_K]), steps = static_cast<long>(wio[W_STEPS]);
  const long every = static_cast<long>(wio[W_EVERY]);
  const double t0 = wio[W_T0], dt = wio[W_DT], until = wio[W_UNTIL], w = wio[W_OMEGA];
  const double beta = wio[W_BETA], w2 = w * w, w1 = 2.0 * w;
  long nsw = 1;
  while (t0 + static_cast<double>(k + nsw) * dt < until) ++nsw;
  wio[W_NSW] = static_cast<double>(nsw);
  if (k + nsw >= steps) {
    wio[W_RETRY] = INFINITY;
    return 0;
  }
  Map before(tau_out, n);
  before = b.tau;
  long jprev = 0;
  for (long j = 1; j < nsw;) {
    steer_state(q0, v0, target, w, static_cast<double>(j) * dt, n, wq, wv);
    for (int i = 0; i < n; ++i) b.wqdd[i] = (target[i] - wq[i]) * w2 - w1 * wv[i];
    const Eigen::VectorXd& tau = pinocchio::rnea(b.model, b.data, CRef(CMap(wq, n)), CRef(CMap(wv, n)), CRef(b.wqdd));
    const double span = beta * static_cast<double>(j - jprev);
    for (int i = 0; i < n; ++i) {
      if (!(std::abs(tau[i]) <= beta * tau_max[i]) || !(std::abs(tau[i] - before[i]) <= span * window[i])) {
        wio[W_RETRY] = static_cast<double>(k + std::max(j, every));
        return 0;
      }
    }
    before = tau;
    jprev = j;
    if (j == nsw - 1) break;
    j = std::min(j < every ? every : j + every, nsw - 1);
  }
  for (int i = 0; i < n; ++i) {
    T[i] = 0.0;
    b.wprev[i] = q0[i];
  }
  wio[W_PROG] = 0.0;
  return 1;
}

// The walk's clearance (qpctl/safety/walk.py, "The walk"), from step wio[J] + 1 of a planned walk (wio[J]
// = 0 at the start, the exact loop's lazy bound in wio[LAST], wio[DRIFT], wio[WORST]): at each step j the
// closed-form state into (wq, wv), each joint's travel so far into T, Σᵢρᵢ|Δqᵢ| into wio[PROG] and the lazy
// bound as the rollout keeps it; at j < nsw, that bound lowered by the stray δ = stray·wio[PROG]:
// NEED_CLEARANCE where it no longer covers the level (the caller evaluates the clearance at wq at
// t0 + (k + j)·dt, sets wio[LAST], wio[DRIFT] = 0, wio[EVALUATED] = 1 and calls again), REFUSED where the
// clearance less δ is not above wio[LEVEL] or a joint is within stray·ΣᵢTᵢ of a limit (wio[RETRY]: the step
// halfway there, at least every steps on); at j = nsw, WALKED
// (wq, wv: the switch's state, its step's travel in wio[DRIFT]; Tᵢ += |q̇ᵢ|/κ and wio[DEV] =
// wio[SWITCH_STRAY]·ΣᵢρᵢTᵢ: the stray the rollout goes on with; wio[WORST]: the least clearance less the strays).
int qpb_walk_clear(void* h, const double* q0, const double* v0, const double* target, const double* q_min,
                   const double* q_max, const double* rho, double* T, double* wq, double* wv, double* wio) {
  Brake& b = *static_cast<Brake*>(h);
  const int n = b.model.nv;
  const long nsw = static_cast<long>(wio[W_NSW]);
  const double dt = wio[W_DT], w = wio[W_OMEGA], level = wio[W_LEVEL], move = wio[W_MOVE];
  const double stray = wio[W_STRAY];
  const bool lazy = wio[W_LAZY] != 0.0;
  double last = wio[W_LAST], drift = wio[W_DRIFT], worst = wio[W_WORST], prog = wio[W_PROG];
  bool evaluated = wio[W_EVALUATED] != 0.0;
  long j = static_cast<long>(wio[W_J]) + (evaluated ? 0 : 1);
  int answer = REFUSED;
  for (; j <= nsw; ++j) {
    double bound = last;
    if (!evaluated) {
      steer_state(q0, v0, target, w, static_cast<double>(j) * dt, n, wq, wv);
      double travel = 0.0;
      for (int i = 0; i < n; ++i) {
        const double d = std::abs(wq[i] - b.wprev[i]);
        T[i] += d;
        travel += rho[i] * d;
        b.wprev[i] = wq[i];
      }
      prog += travel;
      drift += travel + move;
      if (j == nsw) {
        double dev = 0.0;
        for (int i = 0; i < n; ++i) {
          T[i] += std::abs(wv[i]) / wio[W_GAIN];
          dev += rho[i] * T[i];
        }
        wio[W_DEV] = wio[W_SWITCH_STRAY] * dev;
        answer = WALKED;
        break;
      }
      if (!(lazy && last - drift - stray * prog > level)) {
        answer = NEED_CLEARANCE;
        break;
      }
      bound = last - drift;
    }
    evaluated = false;
    const double dev = stray * prog;
    if (!(bound - dev > level)) {
      answer = REFUSED;
      break;
    }
    worst = std::min(worst, bound - dev);
    double turn = 0.0;  // every joint's travel so far [rad]: the dynamics couple the joints' strays
    for (int i = 0; i < n; ++i) turn += T[i];
    const double d = stray * turn;
    bool inside = true;
    for (int i = 0; i < n; ++i) inside = inside && wq[i] - d >= q_min[i] && wq[i] + d <= q_max[i];
    if (!inside) {
      answer = REFUSED;
      break;
    }
  }
  wio[W_J] = static_cast<double>(j);
  wio[W_LAST] = last;
  wio[W_DRIFT] = drift;
  wio[W_WORST] = worst;
  wio[W_PROG] = prog;
  wio[W_EVALUATED] = evaluated ? 1.0 : 0.0;
  // a refused walk may be tried again halfway to where it was refused (the stray grows from a walk's start)
  if (answer == REFUSED) wio[W_RETRY] = wio[W_K] + std::max(std::floor(0.5 * static_cast<double>(j)), wio[W_EVERY]);
  return answer;
}

}  // extern "C"
