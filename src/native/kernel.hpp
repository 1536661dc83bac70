// The native stepping kernel: the Python core's loop (core.Core.advance) over rows of one robot, in C++.
//
// The Python kernel is the specification (src/multibody_sim/core.py, kernels/row.py, integrators/explicit_rk.py,
// integrators/partitioned.py, state.py, step_control.py); the C++ renders the same arithmetic in the same order.
// This header holds the kernel's data (what a method is, the chart map, the step-size controller, the loop's state,
// the sample store, a row's stop: each arrives from or goes back to Python as a named struct, module.cpp) and the
// engine's interface. The rest, one concept per file: methods.hpp (the arithmetic of a step), loop.hpp (the loop
// over one thread's rows), engine.cpp (the engine: rows over threads), module.cpp (the bindings). Everything a
// method is (its tableau, its error weights, its dense output) arrives as data: no coefficient is written here.
#pragma once

#include <array>
#include <cstdint>
#include <limits>
#include <memory>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

#include <Eigen/Core>

#include "pinocchio/multibody.hpp"

#include "contact.hpp"  // a contact scene's geometry, constraints and cone solve (contact.cpp)
#include "model.hpp"    // NativeModel: a model handed over from Python
#include "scene.hpp"    // a scene's force elements and the built-in controllers (scene.cpp)
#include "sensors.hpp"  // a scene's sensors (measured at ticks: measure.hpp)

namespace multibody_sim
{
  using Vec = Eigen::VectorXd;
  using RowMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

  // What a method is (the Python integrator's native_data(): its kind and its own arrays).
  enum class Kind : int
  {
    explicit_rk = 0,  // ExplicitRungeKutta: a tableau, fixed steps
    embedded = 1,     // EmbeddedRungeKutta: error weights e = b - b_hat, dense weights
    dop853 = 2,       // DormandPrince853: combined error estimate, three extra stages for dense output
    semi_implicit_euler = 3,
    timestepping = 4,  // TimeStepping on a contact scene (contact.hpp): semi-implicit Euler with impulses
  };

  struct Method  // _native.Method
  {
    Kind kind = Kind::explicit_rk;
    int stages = 0;
    std::vector<double> a, b, c;  // a: stages x stages, row-major
    int chart_terms = 0;
    bool fsal = false;
    std::vector<double> e;      // embedded: b - b_hat
    std::vector<double> dense;  // embedded: the quartic term's weights (empty: cubic Hermite)
    std::vector<double> e5, e3;  // dop853's error weights
    int extended_stages = 0;     // dop853: the stages with the dense output's extra ones
    std::vector<double> a_extended, c_extended, dense_weights;  // dense_weights: 4 x extended_stages
  };

  // One curved block of the chart map (state.ConfigurationSpace.native_data()): H = xi[start + index] * half_sign.
  struct ChartBlock  // _native.ChartBlock
  {
    int start = 0, d = 0;  // d: the block's size
    std::vector<int> index;
    std::vector<double> half_sign;
  };

  struct Chart  // _native.Chart: the curved blocks and the series' coefficients in H = A / 2 (state._HALF_SERIES)
  {
    std::vector<ChartBlock> blocks;
    std::vector<double> half_series;
  };

  // The step-size controllers' constants (step_control.ConstantStep / PIController.native_data()).
  struct ConstantStepData  // _native.ConstantStep
  {
    double dt = 0.0, sliver = 0.0, landing = 0.0;
  };

  struct PIControllerData  // _native.PIController
  {
    double alpha = 0.0, beta = 0.0, safety = 0.0, factor_min = 0.0, factor_max = 0.0;
    double max_step = 0.0, first_step = 0.0, landing = 0.0;
  };

  // The controller the engine runs: either one's constants, and the run's tolerances (adaptive methods).
  struct Control
  {
    bool adaptive = false;
    double dt = 0.0, sliver = 0.0;
    double alpha = 0.0, beta = 0.0, safety = 0.0, factor_min = 0.0, factor_max = 0.0;
    double max_step = 0.0, first_step = 0.0;
    double rtol = 0.0, atol = 0.0;
    double landing = 0.0;  // step_control.LANDING_FRACTION
  };

  // What the Python side owns and the native loop advances (_native.LoopState, in and out of every advance()): the
  // core's counts (core.Core), the store's count (recording.SampleStore), the sampler's next output (core.Sampler)
  // and the step-size controller's state (ConstantStep: step_t0, step_k, step_time; PIController: step_time,
  // step_h, previous_error, rejected_last).
  struct LoopState
  {
    int64_t steps = 0, rejected = 0, evaluations = 0;
    double recorded = 0.0;  // the time of the latest sample
    int64_t count = 0;      // store.count
    bool full = false;      // store.full
    double soft_capacity = 0.0;
    int64_t next_output = 1;  // Sampler.next_output
    double step_t0 = 0.0;
    int64_t step_k = 0;
    double step_time = 0.0, step_h = 0.0, previous_error = 1.0;
    bool rejected_last = false;
  };

  // ... with what the engine keeps itself: each thread's copy while it runs.
  struct CoreState : LoopState
  {
    double t = 0.0;       // the kernel's time [s] (kernel.t)
    int64_t instant = 0;  // native control: the next control instant's number (driver.Run._loop's `instant`)
    double last_control = std::numeric_limits<double>::quiet_NaN();  // ... every step: the latest (`passed`)
  };

  // The sample store's arrays (recording.SampleStore.batch_major), batch-major: X[b, i, :] is row b's sample i at
  // cell at(i, b).
  struct Store
  {
    int64_t at(int64_t i, int64_t b) const
    {
      return b * capacity + i;
    }

    double * T = nullptr;
    double * Q = nullptr;
    double * V = nullptr;
    double * TAU = nullptr;
    double * ENERGY = nullptr;
    double * FLOWS = nullptr;
    int64_t * COUNTS = nullptr;
    double * EXTRA = nullptr;  // (capacity, B, extra_width): the system's records (a scene's spring energies)
    int64_t capacity = 0, B = 0, extra_width = 0;
  };

  // A row that stopped inside the loop (core.RowStop's evidence; Python writes the message): _native.StopEvent.
  struct StopEvent
  {
    int code = 0;  // a StopCode
    int64_t row = 0;
    double time = 0.0;
    int64_t step = 0;  // the step that failed (steps + 1 then)
    int64_t dof = 0;   // diverged: the first non-finite velocity coordinate
    int64_t count = 0;  // store.count when it stopped
    bool added = false;  // a last sample was written for it at index count
    int64_t counts[3] = {0, 0, 0};  // its frozen (steps, rejected, evaluations)
    double h = 0.0, minimum = 0.0, error = 0.0;  // collapsed: the step, the minimum, the error norm (NaN: none)
    std::string message;  // failed: the library's exception, as the Python kernel words it
  };

  enum Status : int
  {
    REACHED = 0,
    STEPPED = 1,
    FULL = 2,
    EMPTY = 3,
    NEED_ROOM = 4,
  };
  enum StopCode : int
  {
    STOP_DIVERGED = 1,
    STOP_COLLAPSED = 2,
    STOP_CONTROL = 3,  // a native controller's output is not finite (Python says why)
    STOP_FAILED = 4,   // a library's exception inside the row's step (its message)
  };

  struct Sampler  // core.Sampler.native_data(): _native.Sampler
  {
    bool present = false;
    int64_t every = 0;  // 0: none
    double period = 0.0;  // 0: none
  };

  // A sample's active contacts (core.RowKernel._write_contacts): store.write_contacts(i, b, rows).
  struct ContactRecord
  {
    int64_t i = 0, b = 0;
    std::vector<std::array<double, 11>> rows;
  };

  struct AdvanceResult
  {
    int status = REACHED;
    int64_t taken = 0;  // accepted steps in this call
    int64_t need = 0;   // NEED_ROOM: samples the store must have room for beyond count
    std::vector<StopEvent> stops;
    std::vector<ContactRecord> records;  // the contacts of the samples written (contact scenes)
  };

  // One row's own physics (a randomised scene's row, Scene.with_parameters): its model (masses, inertias, armature),
  // joint damping, force elements (friction coefficients), contact scene (coefficients, exact friction forces),
  // actuators (gains, limits, curves) and sensors (a force-torque sensor's cut masses), with the engine's structure
  // (the same joints, elements, shapes, pairs, actuator kinds and sensors; other values).
  // The built-in controllers keep the engine's model: a controller was made for the scene as declared.
  struct RowPhysics  // _native.RowPhysics
  {
    std::shared_ptr<NativeModel> model;
    Vec damping;
    std::shared_ptr<SceneForces> scene;     // null when the engine has none
    std::shared_ptr<ContactScene> contact;  // null when the engine has none
    std::shared_ptr<SceneActuators> actuators;  // null when the engine has none
    std::shared_ptr<Sensors> sensors;  // null: the engine's (set_sensors)
  };

  struct Rows;    // one thread's rows, their states and workspace (methods.hpp)
  struct Thread;  // ... and the loop over them (loop.hpp)

  // pinocchio::integrate(model, q, v, out) without its per-joint visitor where the joint's Lie group is a vector
  // space (revolute, prismatic, ...: out = q + v, the same additions): runs of such joints are one loop each, and
  // the other joints (free-flyer, spherical, planar, unbounded revolute, composite, mimic) take Pinocchio's own
  // per-joint step. Bit for bit pinocchio::integrate's result.
  struct Integrate
  {
    struct Span
    {
      int q = 0, v = 0, n = 0;  // out[q + i] = q[q + i] + v[v + i] for i < n
    };
    std::vector<Span> spans;
    std::vector<pinocchio::JointIndex> others;

    explicit Integrate(const pinocchio::Model & model);
    void operator()(const pinocchio::Model & model, const Vec & q, const Vec & v, Vec & out) const;
  };

  // The kernel of one run: the model, the rows' states, the method and the controller's constants.
  class Engine
  {
  public:
    Engine(
      const pinocchio::Model & model,
      const Method & method,
      const std::vector<ChartBlock> & blocks,
      const std::vector<double> & half_series,
      const Vec & damping,
      bool damped,
      int n_ledger,
      const Control & control,
      const RowMatrix & Q0,
      const RowMatrix & V0,
      int num_threads);
    ~Engine();

    // Core.advance towards t_stop, at most `limit` accepted steps (< 0: no limit), with the landing `tolerance`.
    AdvanceResult advance(
      double t_stop, int64_t limit, double tolerance, const Sampler & sampler, const Store & store, CoreState & state);

    // Write the current state of run rows `rows` as sample i (Q, V, TAU, FLOWS, ENERGY; the caller writes T, COUNTS).
    std::vector<ContactRecord> write_rows(int64_t i, const std::vector<int64_t> & rows, const Store & store);

    void set_torques(const RowMatrix & TAU, bool jump);  // the running rows' torques, in order
    void keep(const std::vector<bool> & keep);          // the running rows to keep, in order
    std::vector<int64_t> running_rows() const;
    RowMatrix running_q() const;
    RowMatrix running_v() const;
    Vec flows_of(int64_t row) const;
    void set_state(int64_t row, const Vec & q, const Vec & v, const Vec & flows);  // by hand: a jump
    // Row `row`'s whole state (q, v, flows, tau, the solver state's first stage row, whether it holds one).
    std::tuple<Vec, Vec, Vec, Vec, Vec, bool> snapshot_row(int64_t row) const;
    // Every row's whole state (as snapshot_row, with the contact solver's state and the rows running), kept inside
    // the engine (one copy: the next save() overwrites it), and back: Stepper's undo point before each step.
    void save();
    void restore_saved();
    int64_t running() const;

    // A scene's actuators join the dynamics, ledger and records (before set_scene and the first advance()).
    void set_actuators(std::shared_ptr<const SceneActuators> actuators);
    // A scene's force elements join the dynamics, ledger and energies (before the first advance()).
    void set_scene(std::shared_ptr<const SceneForces> scene);
    // Torques come from `policies` at its control instants, inside advance() (no return to Python per instant);
    // counted per run row into calls (B,), saturated (B,) and saturated_dofs (B, nv) (driver.Run's arrays).
    void set_policies(
      std::shared_ptr<const Policies> policies, int64_t * calls, int64_t * saturated, int64_t * saturated_dofs);

    // A contact scene's geometry and constraints (the timestepping kind); flow_work: per ledger entry before the
    // contact's four, whether it is a "work" element (else a dissipation), as the time-stepper books them.
    void set_contact(std::shared_ptr<const ContactScene> contact, const std::vector<bool> & flow_work);
    bool has_contact() const
    {
      return static_cast<bool>(contact_);
    }
    ContactRow contact_row(int64_t row) const;  // a row's solver state (its counts)
    // Whether a row's step may cost more than the run's evaluations (a contact problem, a servo's revisions).
    bool uneven_evaluations() const
    {
      return contact_ || (actuators_ && actuators_->servos);
    }
    // A scene's sensors tick at the end of every `every`-th step of a run row, counted from the row's start (`done`:
    // the steps each run row took before this engine, shape (B,)); each tick's measurement is kept until
    // take_ticks() (sensors.Ticks.source).
    void set_sensors(std::shared_ptr<const Sensors> sensors, int64_t every, const std::vector<int64_t> & done);
    // The ticks since the last take_ticks: how many.
    int64_t tick_count() const;
    // Those ticks: times (n,) and run rows (n,), each row's in time order, their measurements copied row-major into
    // `out`, shape (room >= n, width: the sensors'), a buffer the caller reuses (no fresh memory written per call).
    std::tuple<Vec, Eigen::Matrix<int64_t, Eigen::Dynamic, 1>> take_ticks(double * out, int64_t room, int64_t width);
    // Each run row's own physics (after set_actuators, set_scene and set_contact, before the first advance()): rows
    // step on their own model, damping, elements, contact coefficients and actuators, and measure with their own
    // sensors (set_sensors may come before or after). Throws invalid_argument naming what disagrees with the
    // engine's structure.
    void set_rows(const std::vector<RowPhysics> & rows);
    // Throws invalid_argument when a row's own sensors are not `sensors`' (same kinds, places and cuts' joints).
    static void check_row_sensors(const Sensors * sensors, const std::vector<RowPhysics> & rows);
    // Evaluations each run row made beyond the run's count (contact steps cost two), for rows `rows`.
    std::vector<int64_t> extra_evaluations(const std::vector<int64_t> & rows) const;

    const pinocchio::Model & model() const
    {
      return model_;
    }

    double t = 0.0;  // the running rows' time [s] (kernel.t)
    int64_t instant = 0;  // native control (CoreState.instant, last_control)
    double last_control = std::numeric_limits<double>::quiet_NaN();

  private:
    friend struct Rows;  // methods.hpp
    friend struct Thread;  // loop.hpp
    // The thread that runs run row `row` and the row's place in it; throws invalid_argument if none runs it.
    std::pair<Thread *, size_t> locate(int64_t row) const;
    pinocchio::Model model_;
    Integrate integrate_;
    Method method_;
    std::vector<ChartBlock> blocks_;
    std::vector<double> half_series_;
    Vec damping_;
    bool damped_;
    int n_ledger_;
    Control control_;
    Vec neutral_;
    std::shared_ptr<const SceneForces> scene_;
    std::shared_ptr<const SceneActuators> actuators_;
    std::vector<char> actuated_dof_;  // per dof: whether an actuator drives it
    int n_actuator_flows_ = 0;        // the actuators' ledger entries, after the robot's
    std::shared_ptr<const Policies> policies_;
    std::shared_ptr<const ContactScene> contact_;
    std::shared_ptr<const Sensors> sensors_;
    int64_t sensor_every_ = 1;
    bool sensor_torques_ = false;  // whether a joint_torque sensor reads (the actuators' delivered torque then)
    std::vector<int64_t> sensor_done_;
    std::vector<bool> flow_work_;
    std::vector<RowPhysics> rows_;  // per run row (set_rows), or empty: the engine's physics for every row
    int64_t *calls_ = nullptr, *saturated_ = nullptr, *saturated_dofs_ = nullptr;
    int n_robot_flows_ = 1;  // the robot's ledger entries before the scene's (joint torques, joint damping)
    std::vector<std::unique_ptr<Thread>> threads_;
    bool saved_ = false;
    struct Pool;
    std::unique_ptr<Pool> pool_;
  };

} // namespace multibody_sim

namespace nanobind
{
  class module_;
}

namespace multibody_sim
{
  // The kernel's Python bindings (class _native.Kernel over a _native.Model, and the named structs it takes),
  // defined in module.cpp.
  void bind_kernel(nanobind::module_ & m);
} // namespace multibody_sim
