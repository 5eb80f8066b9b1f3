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
  explicit Brake(const pinocchio::Model& m)
      : model(m), data(m), qdd(m.nv), tau(m.nv), raw(m.nv), qs(m.nq), dq(m.nv), dv(m.nv), ahead(m.nq),
        vahead(m.nv), aahead(m.nv), kq(m.nv, 4), ka(m.nv, 4) {}
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
  IO_SETTLE, IO_SETTLE_BELOW, IO_DECAY, IO_BETA, IO_GAMMA, IO_CREEP, IO_PENDING, IO_SIZE
};
// qpb_advance's answers.
enum { NEED_CLEARANCE = 0, AT_REST_END = 1, FAILED = 2, HORIZON = 3, SETTLED = 4 };

int qpb_io_size() { return IO_SIZE; }

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
// lowers io[SETTLE_BELOW] and calls again, which takes the pending step.
int qpb_advance(void* h, double* q, double* v, double* prev, const double* tau_max, const double* window,
                const double* q_min, const double* q_max, const double* rho, const double* target, double* io) {
  Brake& b = *static_cast<Brake*>(h);
  const int n = b.model.nv;
  const long steps = static_cast<long>(io[IO_STEPS]);
  const double dt = io[IO_DT], level = io[IO_LEVEL], stop_below = io[IO_STOP_BELOW], gain = io[IO_GAIN];
  const double move = io[IO_OBSTACLE_SPEED] * dt;
  const bool lazy = io[IO_LAZY] != 0.0;
  double still = io[IO_STILL], last = io[IO_LAST], drift = io[IO_DRIFT], worst = io[IO_WORST];
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
        if (lazy && last - drift > level) {
          worst = std::min(worst, last - drift);
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

}  // extern "C"
