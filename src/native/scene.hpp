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
  /// open-loop sequences (rollout's taus); saturated at the commands' bounds as torques.Saturation does.
  class Policies
  {
  public:
    int nv = 0, a_start = 0, a_stop = 0;  // the actuated dofs [a_start, a_stop)
    std::vector<Policy> rows;             // per run row (empty with taus)
    const double * taus = nullptr;        // (B, n_taus, nv), row-major (owned by Python for the run)
    int64_t n_taus = 0, taus_width = 0;
    bool saturate = false;
    Vec low, high;  // torques.command_bounds: the commands' bounds (± the effort limits without actuators)
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
    // Saturation.apply on one row: clip tau in place; counts the clipped dofs into dofs (nv), and whether any
    void clip(Vec & tau, int64_t * dofs, bool & clipped) const;
  };

  // ---- actuators (scenes/actuators.py) --------------------------------------------------------------------------
  enum class ActuatorKind : int
  {
    torque = 0,
    position = 1,
    velocity = 2,
  };

  struct ActuatorTerm  // one joint's actuator (Actuators.native_data(); inf: no such limit or curve)
  {
    int dof = 0, iq = 0;
    ActuatorKind kind = ActuatorKind::torque;
    double kp = 0.0, kv = 0.0, effort = 0.0, velocity_limit = 0.0, stall = 0.0, no_load = 0.0;
    bool limited = false;     // it has an actuator_limit ledger line
    double brake_gain = 0.0;  // its overspeed brake's gain k (0: none; it then has an actuator_overspeed line)
    // Set by SceneActuators::prepare() from the fields above:
    // Below this |speed| the brake's bounds provably leave the limits as they are and no torque lands on them (half
    // the speed where its band starts, if that band is at most 0.9 of the limit, else 0: always evaluated).
    double brake_from = 0.0;
    // Below this |speed| the interval is exactly ± the effort limit: the curve (with a margin), the velocity limit
    // and the brake (brake_from) cut nothing there (0: never taken as such).
    double plain_below = 0.0;
    bool servo = false, curve = false, speed_limited = false, braked = false;
  };

  // One row's velocity update while it takes the servos and brakes implicitly (Actuators.begin_implicit ..
  // end_implicit), per actuator: the law at the step's start, the speed there, the torque held, the clipped torque and
  // its side, which servos are free and which actuators brake, the armature before.
  struct ServoStep
  {
    std::vector<double> law, w, held, clipped, saved;
    std::vector<int> side;
    std::vector<char> free, braking;
    // revise()'s scratch, per actuator (sized by workspace(); no allocation or thread-local lookup per step)
    std::vector<double> law_next, low, high;
    std::vector<char> ok, within, brake, beyond;
    std::vector<int> side_next;
    double h = 0.0;
    int iterations = 0;
    bool active = false;
  };

  /// Actuators of one scene: the joint torques a command delivers at (q, v), their ledger powers, and the servos'
  /// implicit terms of semi-implicit Euler and the time-stepper (on a model copy's armature).
  class SceneActuators
  {
  public:
    int nv = 0;
    std::vector<ActuatorTerm> terms;
    int max_revisions = 0;  // actuators.MAX_REVISIONS
    bool servos = false;    // Actuators.implicit: a servo or an overspeed brake, taken inside semi-implicit steps
    int n_limited = 0, n_braked = 0;

    int n_flows() const
    {
      return static_cast<int>(terms.size()) + n_limited + n_braked;
    }
    // Each term's derived fields (brake_from, plain_below and the flags), servos, n_limited and n_braked from the
    // terms' data; throws if an actuator's dof or coordinate is out of range for a model of nv, nq
    void prepare(int nv_, int nq);
    // Actuators.evaluate for one actuator: its law's torque c and the torque after the limits and the brake
    void evaluate(const ActuatorTerm & a, const Vec & q, const Vec & v, const Vec & u, double & law,
                  double & tau) const;
    // Actuators._law for one actuator
    double law(const ActuatorTerm & a, const Vec & q, const Vec & v, const Vec & u) const;
    // Actuators._limits for one actuator at speed w (without its brake)
    void limits(const ActuatorTerm & a, double w, double & low, double & high) const;
    // Actuators._brakes for one actuator at speed w: the brake's upper and lower bounds
    void brakes(const ActuatorTerm & a, double w, double & upper, double & lower) const;
    // Actuators._interval for one actuator at speed w
    void interval(const ActuatorTerm & a, double w, double & low, double & high) const;
    // Actuators._select for one actuator: within, on its brake's bound (within ± the effort limit, or beyond it:
    // saturated), side, the interval
    void select(const ActuatorTerm & a, double law, double w, bool & within, bool & brake, bool & saturated, int & side,
                double & low, double & high) const;
    // Actuators.joint_torques into out (nv): u with the actuators' dofs replaced (the step's held torques if active)
    void joint_torques(const Vec & q, const Vec & v, const Vec & u, const ServoStep * step, double * out) const;
    // Actuators.powers into out (n_flows())
    void powers(const Vec & q, const Vec & v, const Vec & u, double * out) const;
    // joint_torques (no step held; torques may be null) and powers at the same (q, v, u) in one pass, each
    // actuator's law and limits computed once (an explicit method's stage needs both): the same numbers as the two
    // calls (powers is this without the torques)
    void torques_and_powers(const Vec & q, const Vec & v, const Vec & u, double * torques, double * flows) const;
    ServoStep workspace() const;
    // Actuators.begin_implicit / revise / end_implicit on `armature`, the model copy's that the step's ABA uses
    void begin(ServoStep & step, const Vec & q, const Vec & v, const Vec & u, double h, Vec & armature) const;
    bool revise(ServoStep & step, const Vec & v_next, Vec & armature) const;
    // After begin() (before any revision): u (nv) with the actuators' dofs replaced by their torques at the step's
    // start (joint_torques' at the state begin() was given, from the same law and interval)
    void clipped_torques(const ServoStep & step, const Vec & u, double * out) const;
    void end(ServoStep & step, Vec & armature) const;

  private:
    void hold(ServoStep & step, Vec & armature) const;  // Actuators._hold of the step's free, braking, clipped, side
  };
} // namespace multibody_sim

namespace nanobind
{
  class module_;
}

namespace multibody_sim
{
  // The Python classes _native.SceneForces, _native.Policies and _native.SceneActuators (scene.cpp), added by
  // module.cpp.
  void bind_scene(nanobind::module_ & m);
} // namespace multibody_sim
