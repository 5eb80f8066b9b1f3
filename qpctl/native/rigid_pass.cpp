// The tick's rigid-body pass in C++ (issue 23, the thin shell): pinocchio::crba in the world convention
// and pinocchio::nonLinearEffects of libpinocchio — the very calls qpctl.tick.rigid_pass makes through
// the Python bindings, here without the interpreter between them. The compiled tick calls qpr_pass
// through its address (qpctl.kernels.pin_native); the workspace's numpy views read this handle's Data
// (qpr_addresses), laid out as pin.Data is (qpctl.tick.bind_native checks it against the bindings'
// numbers, bit for bit).
//
// The model is the controller's, copied at construction (Model.saveToString); its gravity is read
// from the caller's model on every pass, so a gravity changed afterwards counts from the next tick.
#include <pinocchio/multibody.hpp>
#include <pinocchio/algorithm/crba.hpp>
#include <pinocchio/algorithm/rnea.hpp>
#include <pinocchio/serialization.hpp>

#include <cstdint>
#include <exception>
#include <string>

namespace {

thread_local std::string last_error;

struct Rigid {
  pinocchio::Model model;
  pinocchio::Data data;
  explicit Rigid(const pinocchio::Model& m) : model(m), data(m) {}
};

using CMap = Eigen::Map<const Eigen::VectorXd>;
// The argument type of libpinocchio's explicit instantiations (extern templates): the calls below
// are those instantiations, the bindings' own.
using CRef = Eigen::Ref<const Eigen::VectorXd>;

}  // namespace

extern "C" {

const char* qpr_error() { return last_error.c_str(); }

void* qpr_new(const char* text, long len) {
  try {
    pinocchio::Model m;
    m.loadFromString(std::string(text, static_cast<size_t>(len)));
    return new Rigid(m);
  } catch (const std::exception& e) {
    last_error = e.what();
    return nullptr;
  }
}

void qpr_free(void* h) { delete static_cast<Rigid*>(h); }

// The addresses of the handle's Data arrays the tick reads, into out[0..5): oMi[0]'s rotation
// (njoints placements of 12 doubles each), a_gf[0] (njoints motions of 6), J (6 × nv, column-major),
// M (nv × nv, column-major), nle (nv); out[5] = the stride in bytes between two placements.
void qpr_addresses(void* h, std::uintptr_t* out) {
  Rigid& r = *static_cast<Rigid*>(h);
  out[0] = reinterpret_cast<std::uintptr_t>(r.data.oMi[0].rotation().data());
  out[1] = reinterpret_cast<std::uintptr_t>(r.data.a_gf[0].toVector().data());
  out[2] = reinterpret_cast<std::uintptr_t>(r.data.J.data());
  out[3] = reinterpret_cast<std::uintptr_t>(r.data.M.data());
  out[4] = reinterpret_cast<std::uintptr_t>(r.data.nle.data());
  out[5] = r.model.njoints > 1 ? reinterpret_cast<std::uintptr_t>(r.data.oMi[1].rotation().data()) - out[0] : 0;
}

// crba (world convention) and nonLinearEffects at (q, v) with the gravity g (3 doubles, the caller's
// model's): 0, or 1 when Pinocchio threw (qpr_error says what). Pointers as integers: the compiled
// tick passes its arrays' addresses.
int qpr_pass(std::uintptr_t h, std::uintptr_t q, std::uintptr_t v, std::uintptr_t g) {
  Rigid& r = *reinterpret_cast<Rigid*>(h);
  try {
    const double* gp = reinterpret_cast<const double*>(g);
    r.model.gravity.linear() << gp[0], gp[1], gp[2];
    const CMap qm(reinterpret_cast<const double*>(q), r.model.nq);
    const CMap vm(reinterpret_cast<const double*>(v), r.model.nv);
    pinocchio::crba(r.model, r.data, CRef(qm), pinocchio::Convention::WORLD);
    pinocchio::nonLinearEffects(r.model, r.data, CRef(qm), CRef(vm));
    return 0;
  } catch (const std::exception& e) {
    last_error = e.what();
    return 1;
  }
}

}  // extern "C"
