// A scene's physics and the built-in controllers, rendered for the native kernel (methods.hpp and loop.hpp call them).
//
// The Python code is the specification: scenes/elements.py (ForceElements: springs plain and continuous, damping,
// regularized Coulomb friction, wrenches with their declared shapes; their ledger powers and the springs'
// energies), scenes/scene.py (how they join the dynamics) and controllers.py (PD, GravityCompensation, PDGravity)
// with driver.Saturation. Every coefficient arrives as named data from Python (ForceElements.native_data(), the
// controllers' native_data(), kernels/native.native_policies()); the arithmetic is theirs, in their order.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <vector>

#include <Eigen/Core>

#include "pinocchio/multibody.hpp"

namespace multibody_sim
{
  using Vec = Eigen::VectorXd;

  // ---- force elements (scenes/elements.py) -------------------------------------------------------------------
  struct SpringTerm  // out[dof] = (q[iq] - rest) * minus_k
  {
    int dof = 0, iq = 0;
    double rest = 0.0, minus_k = 0.0;
  };
  struct CircularTerm  // out[dof] = atan2(cr s - sr c, cr c + sr s) * minus_k, (c, s) = q[ic], q[ic + 1]
  {
    int dof = 0, ic = 0;
    double cos_rest = 1.0, sin_rest = 0.0, minus_k = 0.0;
  };
  struct CoefficientTerm  // damping: out[dof] -= v d; friction: out[dof] -= tanh(v / v_s) F_c
  {
    int dof = 0;
    double c = 0.0;
  };
  struct SpringEnergy  // ½ k x², x = q[iq] - rest (plain) or the wrapped angle (circular)
  {
    bool circular = false;
    int iq = 0;
    double rest = 0.0, cos_rest = 1.0, sin_rest = 0.0, k = 0.0;
  };

  // spec.ForceSpec.scale's shapes (a unit scale: the wrench is never multiplied)
  enum class Shape : int
  {
    unit = 0,
    step = 1,
    ramp = 2,
    sine = 3,
  };

  struct WrenchTerm
  {
    int push = -1;  // >= 0: a world force without torque, the point-mass model push_models[push] (elements._Push)
    int frame = 0;
    bool local = false;  // reference "local" (pinocchio LOCAL), else "world" (LOCAL_WORLD_ALIGNED)
    std::array<double, 6> w6 = {0, 0, 0, 0, 0, 0};
    Shape shape = Shape::unit;
    double start = 0.0, ramp_time = 1.0, frequency = 1.0, phase = 0.0;

    double scale(double t) const;  // ForceSpec.scale
  };

  class SceneForces;

  // A NumPy ufunc's float64 inner loop (PyUFuncGenericFunction): the scene's elementary functions are NumPy's
  // own, as the Python kernel calls them (NumPy's SIMD tanh and arctan2 differ from the C library's in the last
  // place on some CPUs, e.g. with AVX-512).
  struct NumpyLoop
  {
    using Function = void (*)(char **, const std::intptr_t *, const std::intptr_t *, void *);
    Function function = nullptr;  // null: the C library's function (agreement to round-off only)
    void * data = nullptr;
  };

  struct SceneWork  // one thread's workspace
  {
    pinocchio::Data data;                 // the scene model's (frame Jacobians)
    std::vector<pinocchio::Data> pushes;  // one per point-mass model
    pinocchio::Data::Matrix6x J;
    std::vector<Vec> unscaled;   // each wrench's Jᵀw at the latest forces() call (elements._wrench_forces)
    std::vector<double> scales;  // each wrench's scale then
    Vec zeros;
    std::vector<double> u, th;  // the friction terms' v / v_s and tanh of it

    SceneWork(const pinocchio::Model & model, const SceneForces & scene);
  };

  /// ForceElements of one scene: f(q, v, t), the elements' ledger powers, the springs' energies.
  class SceneForces
  {
  public:
    int nv = 0;
    bool zero_all = true;  // out starts at zero (else every dof is assigned by a spring term: the whole span)
    double inv_vs = 1.0;  // 1 / friction_velocity
    std::vector<SpringTerm> springs;
    std::vector<CircularTerm> circular;
    std::vector<CoefficientTerm> damped, rough;         // force terms
    std::vector<CoefficientTerm> ledger_damped, ledger_rough;  // ledger terms (nonzero coefficients only)
    std::vector<WrenchTerm> wrenches;
    std::vector<int> others;  // the wrenches that take a frame Jacobian, in order
    std::vector<pinocchio::Model> push_models;
    std::vector<SpringEnergy> energies;
    NumpyLoop tanh_loop, atan2_loop;  // np.tanh, np.arctan2

    int n_flows() const
    {
      return static_cast<int>(ledger_damped.size() + ledger_rough.size() + wrenches.size());
    }
    int n_records() const
    {
      return static_cast<int>(energies.size());
    }

    std::unique_ptr<SceneWork> workspace(const pinocchio::Model & model) const;
    // ForceElements.evaluate: the elements' generalized force at (q, v, t) into out (nv); the wrenches' parts
    // are kept in `work` for powers().
    void forces(SceneWork & work, const pinocchio::Model & model, const Vec & q, const Vec & v, double t,
                Vec & out) const;
    // ForceElements.powers: the elements' ledger powers at v, with the wrench parts of the latest forces() call.
    void powers(SceneWork & work, const Vec & v, double * out) const;
    void tanh(const double * x, double * out, std::intptr_t n) const;  // np.tanh of n numbers
    double atan2(double y, double x) const;                              // np.arctan2
    // The springs' energies into `record` (n_records(), may be null); returns their ordered sum (0 with none).
    double spring_energy(const Vec & q, double * record) const;
  };

  // ---- built-in controllers (controllers.py) and open-loop torques, at control instants -----------------------
  enum class PolicyKind : int
  {
    pd = 0,
    gravity = 1,
    pd_gravity = 2,
  };

  struct Policy  // one row's controller
  {
    PolicyKind kind = PolicyKind::pd;
    Vec q_ref, v_ref, kp, kd;  // kp, kd: (actuated); q_ref (nq), v_ref (nv)
  };

  struct PolicyWork
  {
    pinocchio::Data data;
    Vec error;

    explicit PolicyWork(const pinocchio::Model & model)
    : data(model)
    , error(Vec::Zero(model.nv))
    {
    }
  };

  /// Where the torques come from at the control instants of a run, natively: one built-in controller per row, or
  /// open-loop sequences (rollout's taus); saturated at the effort limits as driver.Saturation does.
  class Policies
  {
  public:
    int nv = 0, a_start = 0, a_stop = 0;  // the actuated dofs [a_start, a_stop)
    std::vector<Policy> rows;             // per run row (empty with taus)
    const double * taus = nullptr;        // (B, n_taus, nv), row-major (owned by Python for the run)
    int64_t n_taus = 0, taus_width = 0;
    bool saturate = false;
    Vec effort;
    // control instants: fixed steps: k·dt for k = j·every < n_steps, else the duration; adaptive: min(duration, j·period)
    bool adaptive = false, every_step = false;  // every_step: adaptive without control_dt (at every step's start)
    double dt = 0.0, duration = 0.0, period = 0.0;
    int64_t every = 1, n_steps = 0;

    double instant(int64_t j) const;  // RunSettings.control_instant
    std::unique_ptr<PolicyWork> workspace(const pinocchio::Model & model) const;
    // Row `row`'s torque at (q, v), control instant j, into tau (saturated); false when it is not finite (Python
    // then takes that instant: its checks say why).
    bool torque(PolicyWork & work, const pinocchio::Model & model, int64_t row, int64_t j, const Vec & q,
                const Vec & v, Vec & tau) const;
    // Saturation.apply on one row: clip tau in place; counts the clipped dofs into dofs (nv) and returns whether any
    void clip(Vec & tau, int64_t * dofs, bool & clipped) const;
  };
} // namespace multibody_sim

namespace nanobind
{
  class module_;
}

namespace multibody_sim
{
  // The Python classes _native.SceneForces and _native.Policies (scene.cpp), added by module.cpp.
  void bind_scene(nanobind::module_ & m);
} // namespace multibody_sim
