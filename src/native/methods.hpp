// The arithmetic of a step on one thread's rows, in the Python kernel's order (its specification): the forces ABA is
// given (Robot.unchecked_forward_dynamics, Scene._applied) and the ledger's powers, the chart map
// (ConfigurationSpace.chart_velocity, state.py), the stages and the step of ExplicitRungeKutta, AdaptiveRungeKutta
// (its error norm and dense output), SemiImplicitEuler and TimeStepping (explicit_rk.py, partitioned.py,
// timestepping.py), and a sample's state and energies (RowKernel._write). Each function names the Python code it
// renders. Rows holds one thread's rows (their states, the pending step's result) and the workspace the arithmetic
// reuses (no allocation per step); loop.hpp runs core.Core.advance over them. Included by engine.cpp only.
#pragma once

#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>
#include <vector>

#include "pinocchio/algorithm/aba.hpp"
#include "pinocchio/algorithm/energy.hpp"
#include "pinocchio/algorithm/joint-configuration.hpp"

#include "kernel.hpp"
#include "measure.hpp"  // the sensors' kinematics that wait for a step's first ABA (settle)

namespace multibody_sim
{
  // ---- one thread's rows and workspace ------------------------------------------------------------------------
  struct Rows
  {
    using ConstRef = Eigen::Ref<const Vec>;
    static constexpr double INF = std::numeric_limits<double>::infinity();

    // np.maximum: NaN wins.
    static double nan_max(double a, double b)
    {
      if (std::isnan(a))
        return a;
      if (std::isnan(b))
        return b;
      return a > b ? a : b;
    }

    const Engine & e;
    pinocchio::Data data;
    int nq, nv, m, w;
    std::vector<int64_t> rows;  // the run rows this thread owns, ascending
    std::vector<char> alive;
    int64_t n_alive = 0;
    std::vector<Vec> q, v, flows, tau, qn, vn, fn, first;
    std::vector<char> has_first;
    std::vector<int64_t> pending;  // per row: the store cell whose energies wait for the next ABA at this state (-1)
                                   // (and its delivered torques, with actuators: the next step's first evaluation)
    const Store * pending_store = nullptr;
    // workspace (no allocation in the step loop)
    RowMatrix K;  // stage derivatives (xi', v', ledger power), one row per stage
    Vec y, applied, acc, dv, xi, vs, qs, inc, chart_y, chart_t, q_last, v_last, size, diff, q_finite, yd, qd, vd;
    RowMatrix H, F;
    std::unique_ptr<SceneWork> sw;   // a scene's workspace (set_scene)
    std::unique_ptr<PolicyWork> pw;  // the native controllers' (set_policies)
    std::unique_ptr<ContactWork, void (*)(ContactWork *)> cw{nullptr, nullptr};  // a contact scene's (set_contact)
    std::unique_ptr<SensorWork> sensw;  // a scene's sensors' (set_sensors): their Data and the ticks kept
    std::vector<ContactRow> crow;  // per row: the contact solver state
    std::vector<int64_t> extra;    // per row: evaluations beyond st.evaluations (a contact step costs two)
    // Engine::save's copy of the rows' whole state (Stepper's undo point before each step)
    struct Saved
    {
      std::vector<Vec> q, v, flows, tau, first;
      std::vector<char> has_first, alive;
      int64_t n_alive = 0;
      std::vector<ContactRow> crow;
      std::vector<int64_t> extra;
    } saved;
    Vec vfree;
    Vec raised;  // a contact step's servos: what they added to each dof's armature (Actuators.raised_armature)
    std::vector<std::pair<int, double>> speed_work;  // the contact step's (ledger line, work) per velocity-limit row
    Vec fx, pbuf, tau_control;
    Vec tact;                      // the actuators' joint torques (actuated())
    pinocchio::Model servo_model;  // a scene with servos: the model whose armature a step raises (set_actuators)
    ServoStep servo;               // ... and that step's state
    bool dense_ready = false;
    bool no_armature;  // every armature exactly 0: kinetic_energy() needs no per-joint armature term
    bool velocity_kinds;  // every joint of a kind velocity_calc knows: kinetic_at_same_q needs no forwardKinematics
    int extra_evaluations = 0;
    // The physics of the row being stepped or sampled (select(j)): the engine's, or the row's own (set_rows).
    std::vector<const RowPhysics *> own;  // per row: its own physics, or empty (the engine's for every row)
    std::vector<char> own_plain;          // per row: its model's no_armature
    const pinocchio::Model * M = nullptr;
    const Vec * D = nullptr;
    const SceneForces * S = nullptr;
    const ContactScene * C = nullptr;
    const SceneActuators * A = nullptr;
    const Sensors * SS = nullptr;              // the sensors the row measures with (the engine's, or its own)
    pinocchio::Model * SM = nullptr;           // the servo model of the row (servo_model, or own_servo[j])
    std::vector<pinocchio::Model> own_servo;  // per row with its own physics and servos: its servo model
    bool plain = true;

    Rows(const Engine & engine, const std::vector<int64_t> & owned, const RowMatrix & Q0, const RowMatrix & V0)
    : e(engine)
    , data(engine.model_)
    , nq(engine.model_.nq)
    , nv(engine.model_.nv)
    , m(engine.n_ledger_)
    , w(2 * engine.model_.nv + engine.n_ledger_)
    , rows(owned)
    , no_armature((engine.model_.armature.array() == 0.0).all())
    , velocity_kinds(velocity_kinds_of(engine.model_, data))
    {
      const size_t n = rows.size();
      alive.assign(n, 1);
      n_alive = static_cast<int64_t>(n);
      for (size_t j = 0; j < n; ++j)
      {
        q.push_back(Q0.row(rows[j]).transpose());
        v.push_back(V0.row(rows[j]).transpose());
      }
      flows.assign(n, Vec::Zero(m));
      tau.assign(n, Vec::Zero(nv));
      qn.assign(n, Vec::Zero(nq));
      vn.assign(n, Vec::Zero(nv));
      fn.assign(n, Vec::Zero(m));
      first.assign(n, Vec::Zero(w));
      has_first.assign(n, 0);
      pending.assign(n, -1);
      crow.assign(n, ContactRow());
      extra.assign(n, 0);
      const int stages = std::max(engine.method_.stages, engine.method_.extended_stages);
      K = RowMatrix::Zero(std::max(stages, 1), w);
      y = Vec::Zero(w);
      inc = Vec::Zero(w);
      yd = Vec::Zero(w);
      applied = acc = dv = xi = vs = chart_y = chart_t = v_last = size = diff = vd = Vec::Zero(nv);
      qs = q_last = q_finite = qd = Vec::Zero(nq);
      size = Vec::Zero(2 * nv);
      H = RowMatrix::Zero(6, 6);
      F = RowMatrix::Zero(7, w);
      fx = tau_control = vfree = raised = Vec::Zero(nv);
      pbuf = Vec::Zero(std::max(m, 1));
      select(0);
    }

    // Row j's physics into M, D, S, C, A, SM, plain (before anything that computes with the row's model or elements).
    void select(size_t j)
    {
      if (own.empty())
      {
        M = &e.model_;
        D = &e.damping_;
        S = e.scene_.get();
        C = e.contact_.get();
        A = e.actuators_.get();
        SS = e.sensors_.get();
        SM = &servo_model;
        plain = no_armature;
        return;
      }
      const RowPhysics & r = *own[j];
      M = &r.model->model;
      D = &r.damping;
      S = r.scene.get();
      C = r.contact.get();
      A = r.actuators.get();
      SS = r.sensors ? r.sensors.get() : e.sensors_.get();
      SM = own_servo.empty() ? &servo_model : &own_servo[j];
      plain = own_plain[j];
    }

    // ---- the generalized forces ABA is given: Robot (tau - D v) or Scene._applied (tau + f(q, v, t) - D v, tau the
    // actuators' torques under the command where the scene has actuators) -----------------------------------------
    void applied_at(const Vec & qx, const Vec & vx, const Vec & command, double ts, bool actuated_ready = false)
    {
      const Vec & tx = A ? (actuated_ready ? tact : actuated(qx, vx, command)) : command;
      const Vec & damping = *D;
      if (S)
      {
        S->forces(*sw, *M, qx, vx, ts, fx);
        for (int i = 0; i < nv; ++i)
          applied[i] = tx[i] + fx[i];
        if (e.damped_)
          for (int i = 0; i < nv; ++i)
            applied[i] = applied[i] - damping[i] * vx[i];
      }
      else if (e.damped_)
      {
        for (int i = 0; i < nv; ++i)
          applied[i] = tx[i] - damping[i] * vx[i];
      }
      else
        applied = tx;
    }

    // Actuators.joint_torques at (qx, vx) under the command (the step's held torques while it takes servos inside)
    const Vec & actuated(const Vec & qx, const Vec & vx, const Vec & command)
    {
      A->joint_torques(qx, vx, command, &servo, tact.data());
      return tact;
    }

    // ---- the dynamics of a stage: Robot.unchecked_forward_dynamics and Robot.ledger_power ----------------------
    void evaluate(const Vec & qx, const Vec & vx, const Vec & tx, int stage, double ts)
    {
      const pinocchio::Model & model = *M;
      double * row = K.row(stage).data();
      // the actuators' torques and ledger powers at once (their law and limits evaluated once per stage)
      const bool fused = A && !servo.active;
      if (fused)
        A->torques_and_powers(qx, vx, tx, tact.data(), row + 2 * nv + e.n_robot_flows_);
      applied_at(qx, vx, tx, ts, fused);
      const Vec & a = pinocchio::aba(
        model, data, ConstRef(qx), ConstRef(vx), ConstRef(applied), pinocchio::Convention::WORLD);
      for (int i = 0; i < nv; ++i)
        row[nv + i] = a[i];
      power(qx, vx, tx, row + 2 * nv, fused);
    }

    // Scene.ledger_power: the robot's (the ideal torque sources' power, joint damping), the actuators' (unless
    // `actuators_done`: evaluate() wrote them), the elements'
    void power(const Vec & qx, const Vec & vx, const Vec & tx, double * out, bool actuators_done = false) const
    {  // ordered.ordered_dot
      const bool actuated = A != nullptr;  // then its dofs' commands are no torques: 0 here
      double s = (actuated && e.actuated_dof_[0] ? 0.0 : tx[0]) * vx[0];
      for (int i = 1; i < nv; ++i)
        s += (actuated && e.actuated_dof_[i] ? 0.0 : tx[i]) * vx[i];
      out[0] = s;
      if (e.damped_)
      {
        const Vec & damping = *D;
        double d = vx[0] * (damping[0] * vx[0]);
        for (int i = 1; i < nv; ++i)
          d += vx[i] * (damping[i] * vx[i]);
        out[1] = d;
      }
      if (actuated && !actuators_done)
        A->powers(qx, vx, tx, out + e.n_robot_flows_);
      if (S)  // the elements' powers after the robot's and the actuators'
        S->powers(*sw, vx, out + e.n_robot_flows_ + e.n_actuator_flows_);
    }

    // ---- ConfigurationSpace.chart_velocity: Σ c_n Hⁿ v by Horner's rule on each curved block -------------------
    void chart_velocity(const Vec & xis, const Vec & vx, double * out)
    {
      for (int i = 0; i < nv; ++i)
        out[i] = vx[i];
      const int terms = e.method_.chart_terms;
      if (terms == 0)
        return;
      const std::vector<double> & c = e.half_series_;
      for (const ChartBlock & block : e.blocks_)
      {
        const int d = block.d, s0 = block.start;
        for (int r = 0; r < d; ++r)
          for (int col = 0; col < d; ++col)
            H(r, col) = xis[s0 + block.index[r * d + col]] * block.half_sign[r * d + col];
        for (int r = 0; r < d; ++r)
          chart_y[r] = vx[s0 + r] * c[terms];
        for (int k = terms - 1; k >= 0; --k)
        {
          for (int r = 0; r < d; ++r)  // ordered.ordered_matvec
          {
            double s = H(r, 0) * chart_y[0];
            for (int col = 1; col < d; ++col)
              s += H(r, col) * chart_y[col];
            chart_t[r] = s;
          }
          for (int r = 0; r < d; ++r)
          {
            if (k < 2)
              chart_t[r] += vx[s0 + r];
            else if (c[k] != 0.0)
              chart_t[r] += vx[s0 + r] * c[k];
            chart_y[r] = chart_t[r];
          }
        }
        for (int r = 0; r < d; ++r)
          out[s0 + r] = chart_y[r];
      }
    }

    // ---- explicit_rk._fill_stages: stages start..stop-1 from the rows before them ------------------------------
    void fill_stages(int start, int stop, const double * a, const double * c, int lda, const Vec & q0,
                     const Vec & v0, const Vec & tx, double h, double t)
    {
      const bool flat = e.blocks_.empty();
      for (int i = start; i < stop; ++i)
      {
        const double * ai = a + i * lda;
        for (int col = 0; col < 2 * nv; ++col)  // (the stage's state; its ledger columns are only combined at the end)
        {
          double s = ai[0] * K(0, col);
          for (int j = 1; j < i; ++j)
            s += ai[j] * K(j, col);
          y[col] = s * h;
        }
        for (int r = 0; r < nv; ++r)
        {
          xi[r] = y[r];
          vs[r] = v0[r] + y[nv + r];
        }
        e.integrate_(e.model_, q0, xi, qs);
        double * row = K.row(i).data();
        if (flat)
          for (int r = 0; r < nv; ++r)
            row[r] = vs[r];
        else
          chart_velocity(xi, vs, row);
        evaluate(qs, vs, tx, i, t + c[i] * h);
      }
    }

    // (weights @ K[:count]) * h into out (width w)
    void combine(const double * weights, int count, double h, Vec & out) const
    {
      for (int col = 0; col < w; ++col)
      {
        double s = weights[0] * K(0, col);
        for (int j = 1; j < count; ++j)
          s += weights[j] * K(j, col);
        out[col] = s * h;
      }
    }

    // ---- ExplicitRungeKutta.attempt / SemiImplicitEuler.attempt on row j: the pending state in qn, vn, fn -------
    int attempt_fixed(size_t j, double h, double t)
    {
      select(j);
      const Method & me = e.method_;
      const Vec &qj = q[j], &vj = v[j], &tj = tau[j];
      if (me.kind == Kind::timestepping)
        return attempt_contact(j, h, t);
      if (me.kind == Kind::semi_implicit_euler)
      {
        extra[j] += velocity_update(j, h, t, vn[j]);
        end_servos();
        move_along_new_velocity(j, h, t);
        for (int i = 0; i < m; ++i)
          fn[j][i] = h * pbuf[i];
        return 1;
      }
      const int s = me.stages;
      for (int r = 0; r < nv; ++r)
        K(0, r) = vj[r];
      evaluate(qj, vj, tj, 0, t);
      settle(j);
      fill_stages(1, s, me.a.data(), me.c.data(), s, qj, vj, tj, h, t);
      combine(me.b.data(), s, h, inc);
      for (int r = 0; r < nv; ++r)
      {
        xi[r] = inc[r];
        vn[j][r] = vj[r] + inc[nv + r];
      }
      e.integrate_(e.model_, qj, xi, qn[j]);
      for (int i = 0; i < m; ++i)
        fn[j][i] = inc[2 * nv + i];
      return s;
    }

    // SemiImplicitEuler and TimeStepping after v' = vn[j]: q' = q ⊕ h v' into qn[j], and the ledger's power at
    // (q', v') at t + h into pbuf (the wrenches' parts taken there)
    void move_along_new_velocity(size_t j, double h, double t)
    {
      for (int i = 0; i < nv; ++i)
        dv[i] = h * vn[j][i];
      e.integrate_(e.model_, q[j], dv, qn[j]);
      if (S && !S->wrenches.empty())  // Scene.ledger_power at a new point: the wrenches' parts there
        S->forces(*sw, *M, qn[j], vn[j], t + h, fx);
      power(qn[j], vn[j], tau[j], pbuf.data());
    }

    // SemiImplicitEuler's and TimeStepping's velocity update v + h a(q, v, tau) of row j into out, a scene's servos
    // taken inside the step (integrators.base.velocity_update: Actuators.begin_implicit and revise on the servo
    // model's armature; end_servos() ends it, after the contact problem); returns the revisions (each an evaluation)
    int velocity_update(size_t j, double h, double t, Vec & out)
    {
      const Vec &qj = q[j], &vj = v[j], &tj = tau[j];
      const bool servos = A && A->servos;
      if (servos)
        A->begin(servo, qj, vj, tj, h, SM->armature);
      const pinocchio::Model & model = servos ? *SM : *M;
      evaluate_acceleration(model, qj, vj, tj, t);
      settle(j);
      for (int i = 0; i < nv; ++i)
        out[i] = vj[i] + h * acc[i];
      int revisions = 0;
      while (servos && A->revise(servo, out, SM->armature))
      {
        evaluate_acceleration(model, qj, vj, tj, t);
        for (int i = 0; i < nv; ++i)
          out[i] = vj[i] + h * acc[i];
        revisions += 1;
      }
      return revisions;
    }

    void end_servos()
    {
      if (servo.active)
        A->end(servo, SM->armature);
    }

    // ---- TimeStepping.attempt on row j (a contact scene): the pending state in qn, vn, fn -----------------------
    int attempt_contact(size_t j, double h, double t)
    {
      const Vec &qj = q[j], &vj = v[j];
      extra[j] += velocity_update(j, h, t, vfree);
      const bool servos = servo.active;  // the contact problem's M then has the servos' armature too
      double work = 0.0, correction = 0.0, bounce = 0.0;
      bool problem = false;
      try  // a library's exception (coal, Boost, Eigen) leaves the servo model as it was, then fails the row
      {
        problem = C->step(*cw, servos ? *SM : *M, data, qj, vj, vfree, h, crow[j], vn[j], work, correction, bounce,
                          speed_work);
      }
      catch (...)
      {
        end_servos();
        throw;
      }
      if (servos)  // Actuators.raised_armature: what the servos added to the armature the problem's M has
        for (int i = 0; i < nv; ++i)
          raised[i] = SM->armature[i] - M->armature[i];
      end_servos();
      move_along_new_velocity(j, h, t);
      const int smooth_n = m - 4;  // the contact's elements come last: contact, penetration_correction,
      double smooth = 0.0;         // restitution, timestep_error
      for (int i = 0; i < smooth_n; ++i)
      {
        fn[j][i] = h * pbuf[i];
        smooth += e.flow_work_[static_cast<size_t>(i)] ? fn[j][i] : -fn[j][i];
      }
      double held = 0.0;  // the velocity-limit rows' work, out of the contact's into their actuators' lines
      for (const auto & [line, sw] : speed_work)
      {
        fn[j][line] -= sw;
        held += sw;
      }
      // V at qj (and T there, without a contact step's M) from the joint placements the velocity update's ABA left
      // in data (the contact step and the ledger's powers above only read them): forwardKinematics(qj, ·)'s
      // arithmetic, its joint calc not redone
      double kinetic, potential, kinetic_free, kinetic_next, kinetic_end, potential_end;
      if (problem)  // T at qj from the contact step's M there (less the servos' raised armature)
      {
        const Vec * less = servos ? &raised : nullptr;
        kinetic = C->kinetic_energy(*cw, vj, less);
        kinetic_free = C->kinetic_energy(*cw, vfree, less);
        kinetic_next = C->kinetic_energy(*cw, vn[j], less);
      }
      else
      {
        kinetic = kinetic_at_same_q(qj, vj);
        kinetic_free = kinetic_at_same_q(qj, vfree);
        kinetic_next = kinetic_free;  // (no problem: v⁺ = v_free)
      }
      potential = potential_energy();
      if (S && S->n_records())
        potential = potential + S->spring_energy(qj, nullptr);
      energies(qn[j], vn[j], kinetic_end, potential_end);
      fn[j][m - 4] = correction + bounce - (work - held);
      fn[j][m - 3] = correction;
      fn[j][m - 2] = bounce;
      fn[j][m - 1] = (kinetic_free - kinetic) + (kinetic_end - kinetic_next) + (potential_end - potential) - smooth;
      if (servos && problem)  // the contact's work is T's change under the raised armature: the rest is the step's
        fn[j][m - 1] += (kinetic_next - kinetic_free) - work;
      if (problem)
        extra[j] += 1;
      return 1;
    }

    // Scene.unchecked_energies: (T, V) at (qx, vx)
    void energies(const Vec & qx, const Vec & vx, double & kinetic, double & potential)
    {
      pinocchio::forwardKinematics(*M, data, qx, vx);
      energies_from_data(qx, vx, nullptr, kinetic, potential);
    }

    // T at (qx, vx) where data holds the joint placements at qx (an ABA's or forwardKinematics' there):
    // forwardKinematics(qx, vx)'s velocities from them, its arithmetic (each joint's velocity-only calc is its
    // calc(q, v)'s velocity part for the joint kinds below; any other kind has forwardKinematics run in full)
    double kinetic_at_same_q(const Vec & qx, const Vec & vx)
    {
      const pinocchio::Model & model = *M;
      const auto njoints = static_cast<pinocchio::JointIndex>(model.njoints);
      if (!velocity_kinds)
      {
        pinocchio::forwardKinematics(model, data, qx, vx);
        return kinetic_energy(vx);
      }
      for (pinocchio::JointIndex i = 1; i < njoints; ++i)
        velocity_calc(model.joints[i], data.joints[i], vx, true);
      velocities_from_placements();
      return kinetic_energy(vx);
    }

    // forwardKinematics' velocity recursion, its arithmetic, on the joint placements (liMi) and joint velocities
    // (each joint's calc) data holds: every joint's data.v
    void velocities_from_placements()
    {
      const pinocchio::Model & model = e.model_;  // (the rows' models share its tree)
      for (pinocchio::JointIndex i = 1; i < static_cast<pinocchio::JointIndex>(model.njoints); ++i)
      {
        const pinocchio::JointIndex parent = model.parents[i];
        data.v[i] = data.joints[i].v();
        if (parent > 0)
          data.v[i] += data.liMi[i].actInv(data.v[parent]);
      }
    }

    // Whether every joint of the model is of a kind velocity_calc knows (fixed by the model's tree: rows share it;
    // only the kinds are looked at, `data` is not written)
    static bool velocity_kinds_of(const pinocchio::Model & model, pinocchio::Data & data)
    {
      const Vec zero = Vec::Zero(model.nv);
      for (pinocchio::JointIndex i = 1; i < static_cast<pinocchio::JointIndex>(model.njoints); ++i)
        if (!velocity_calc(model.joints[i], data.joints[i], zero, false))
          return false;
      return true;
    }

    // whether the joint is of a kind above (and, if run, its velocity-only calc at vx)
    static bool velocity_calc(const pinocchio::JointModel & joint, pinocchio::JointData & jd, const Vec & vx, bool run)
    {
      using namespace pinocchio;
      return velocity_calc_as<JointModelRX, JointModelRY, JointModelRZ, JointModelFreeFlyer, JointModelRevoluteUnaligned,
                              JointModelRUBX, JointModelRUBY, JointModelRUBZ, JointModelRevoluteUnboundedUnaligned,
                              JointModelPX, JointModelPY, JointModelPZ, JointModelPrismaticUnaligned,
                              JointModelSpherical, JointModelTranslation>(joint, jd, vx, run);
    }

    template<typename... Kinds>
    static bool velocity_calc_as(const pinocchio::JointModel & joint, pinocchio::JointData & jd, const Vec & vx, bool run)
    {
      return (velocity_calc_one<Kinds>(joint, jd, vx, run) || ...);
    }

    template<typename Kind>
    static bool velocity_calc_one(const pinocchio::JointModel & joint, pinocchio::JointData & jd, const Vec & vx, bool run)
    {
      const Kind * kind = boost::get<Kind>(&joint.toVariant());
      if (kind && run)
        kind->calc(boost::get<typename Kind::JointDataDerived>(jd.toVariant()), pinocchio::Blank(), vx);
      return kind != nullptr;
    }

    void evaluate_acceleration(const pinocchio::Model & model, const Vec & qx, const Vec & vx, const Vec & tx, double t)
    {
      applied_at(qx, vx, tx, t);
      acc = pinocchio::aba(model, data, ConstRef(qx), ConstRef(vx), ConstRef(applied), pinocchio::Convention::WORLD);
    }

    // ---- AdaptiveRungeKutta.attempt on row 0: the error norm; the pending state in qn, vn, fn -------------------
    double attempt_adaptive(double h, double t, int & evaluations)
    {
      select(0);
      const Method & me = e.method_;
      const Control & ctl = e.control_;
      const size_t j = 0;
      const Vec &qj = q[j], &vj = v[j], &tj = tau[j];
      const int s = me.stages;
      for (int r = 0; r < nv; ++r)
        K(0, r) = vj[r];
      if (has_first[j])
        for (int col = nv; col < w; ++col)
          K(0, col) = first[j][col];
      else
        evaluate(qj, vj, tj, 0, t);
      fill_stages(1, s, me.a.data(), me.c.data(), s, qj, vj, tj, h, t);
      combine(me.b.data(), s, h, inc);
      if (me.fsal)
      {
        qn[j] = qs;
        vn[j] = vs;
      }
      else
      {
        for (int r = 0; r < nv; ++r)
        {
          xi[r] = inc[r];
          vn[j][r] = vj[r] + inc[nv + r];
        }
        e.integrate_(e.model_, qj, xi, qn[j]);
      }
      for (int i = 0; i < m; ++i)
        fn[j][i] = inc[2 * nv + i];
      // explicit_rk._error_scale
      pinocchio::difference(e.model_, e.neutral_, qj, diff);
      for (int r = 0; r < nv; ++r)
        size[r] = std::abs(diff[r]);
      pinocchio::difference(e.model_, e.neutral_, qn[j], diff);
      for (int r = 0; r < nv; ++r)
        size[r] = nan_max(size[r], std::abs(diff[r]));
      for (int r = 0; r < nv; ++r)
        size[nv + r] = nan_max(std::abs(vj[r]), std::abs(vn[j][r]));
      for (int r = 0; r < 2 * nv; ++r)
        size[r] = ctl.atol + ctl.rtol * size[r];
      double norm;
      if (me.kind == Kind::dop853)
      {
        double e5 = 0.0, e3 = 0.0;
        for (int col = 0; col < 2 * nv; ++col)
        {
          double s5 = me.e5[0] * K(0, col), s3 = me.e3[0] * K(0, col);
          for (int i = 1; i < s; ++i)
          {
            s5 += me.e5[i] * K(i, col);
            s3 += me.e3[i] * K(i, col);
          }
          const double x5 = s5 / size[col], x3 = s3 / size[col];
          e5 = col ? e5 + x5 * x5 : x5 * x5;
          e3 = col ? e3 + x3 * x3 : x3 * x3;
        }
        norm = (e5 == 0.0 && e3 == 0.0) ? 0.0 : h * e5 / std::sqrt((e5 + 0.01 * e3) * (2 * nv));
      }
      else
      {
        double sum = 0.0;  // ordered.ordered_dot of the scaled errors
        for (int col = 0; col < 2 * nv; ++col)
        {
          double x = me.e[0] * K(0, col);
          for (int i = 1; i < s; ++i)
            x += me.e[i] * K(i, col);
          x = x * h / size[col];
          sum = col ? sum + x * x : x * x;
        }
        norm = std::sqrt(sum / (2 * nv));
      }
      const double qq = qn[j].dot(qn[j]) + vn[j].dot(vn[j]);
      if (!std::isfinite(norm) || !std::isfinite(qq))
        norm = INF;
      evaluations = s - (has_first[j] ? 1 : 0);
      dense_ready = false;
      extra_evaluations = 0;
      return norm;
    }

    // ---- dense output at t + θh of the pending step of row 0 (EmbeddedRungeKutta / DormandPrince853) -----------
    void dense(double h, double t, double theta)
    {
      const Method & me = e.method_;
      const size_t j = 0;
      const Vec &qj = q[j], &vj = v[j];
      const int s = me.stages;
      if (me.kind == Kind::dop853)
      {
        if (!dense_ready)
        {
          fill_stages(s, me.extended_stages, me.a_extended.data(), me.c_extended.data(), me.extended_stages, qj, vj,
                      tau[j], h, t);
          extra_evaluations = me.extended_stages - s;
          combine(me.b.data(), s, h, yd);  // delta
          for (int col = 0; col < w; ++col)
          {
            const double delta = yd[col];
            F(0, col) = delta;
            F(1, col) = h * K(0, col) - delta;
            F(2, col) = 2.0 * delta - h * (K(s - 1, col) + K(0, col));
          }
          for (int r = 0; r < 4; ++r)
          {
            const double * d = me.dense_weights.data() + r * me.extended_stages;
            for (int col = 0; col < w; ++col)
            {
              double x = d[0] * K(0, col);
              for (int i = 1; i < me.extended_stages; ++i)
                x += d[i] * K(i, col);
              F(3 + r, col) = h * x;
            }
          }
          dense_ready = true;
        }
        for (int col = 0; col < w; ++col)
        {
          double x = 0.0;
          for (int i = 0; i < 7; ++i)
          {
            x += F(6 - i, col);
            x *= (i % 2 == 0) ? theta : 1.0 - theta;
          }
          yd[col] = x;
        }
      }
      else
      {
        const bool quartic = !me.dense.empty();
        for (int col = 0; col < w; ++col)
        {
          double r1 = me.b[0] * K(0, col);
          for (int i = 1; i < s; ++i)
            r1 += me.b[i] * K(i, col);
          const double r2 = K(0, col) - r1;
          double r3 = 2.0 * r1 - K(0, col) - K(s - 1, col);
          if (quartic)
          {
            double dk = me.dense[0] * K(0, col);
            for (int i = 1; i < s; ++i)
              dk += me.dense[i] * K(i, col);
            r3 = r3 + (1.0 - theta) * dk;
          }
          yd[col] = h * theta * (r1 + (1.0 - theta) * (r2 + theta * r3));
        }
      }
      for (int r = 0; r < nv; ++r)
      {
        xi[r] = yd[r];
        vd[r] = vj[r] + yd[nv + r];
      }
      e.integrate_(e.model_, qj, xi, qd);
    }

    // ---- samples: RowKernel._write -------------------------------------------------------------------------------
    void write(const Store & store, int64_t i, int64_t b, const Vec & qx, const Vec & vx, const Vec & tx,
               const double * fl)
    {
      const int64_t at = store.at(i, b);
      write_state(store, at, qx, vx, tx, fl);
      pinocchio::forwardKinematics(*M, data, qx, vx);
      write_energies(store, at, qx, vx);
    }

    // deferred: the delivered torques are left to settle() or flush() (a pending sample of this state)
    void write_state(const Store & store, int64_t at, const Vec & qx, const Vec & vx, const Vec & tx,
                     const double * fl, bool deferred = false) const
    {
      std::copy(qx.data(), qx.data() + nq, store.Q + at * nq);
      std::copy(vx.data(), vx.data() + nv, store.V + at * nv);
      std::copy(tx.data(), tx.data() + nv, store.TAU + at * nv);
      std::copy(fl, fl + m, store.FLOWS + at * m);
      if (A && !deferred)  // Scene.unchecked_record: the torques delivered, after the springs' energies
        A->joint_torques(qx, vx, tx, nullptr, delivered_cell(store, at));
    }

    double * delivered_cell(const Store & store, int64_t at) const
    {
      return store.EXTRA + at * store.extra_width + (e.scene_ ? e.scene_->n_records() : 0);
    }

    // pinocchio::computeKineticEnergy(model, data) at velocity vx: the same sum in the same order without its
    // per-joint visitor. Per joint it adds vtiv, then its armature term Σ armature · v² (joint_v is vx's segment):
    // for a 1-dof joint armature · (v · v), written out; for a joint of more dofs (a free flyer) exactly +0 when its
    // armature is 0 and every |v| < 1e150 (else v² may overflow and 0 · inf make it NaN), and adding +0 changes no
    // sum here (it starts at +0). Otherwise (armature on a multi-dof joint, huge or NaN speeds) Pinocchio's own call.
    double kinetic_energy(const Vec & vx)
    {
      const pinocchio::Model & model = *M;
      bool exact = true;
      for (int r = 0; exact && r < nv; ++r)
        exact = std::abs(vx[r]) < 1e150;  // (false for NaN)
      if (!exact)
        return pinocchio::computeKineticEnergy(model, data);
      double sum = 0.0;
      for (pinocchio::JointIndex i = 1; i < static_cast<pinocchio::JointIndex>(model.njoints); ++i)
      {
        sum += model.inertias[i].vtiv(data.v[i]);
        if (plain)
          continue;
        const int dofs = model.nvs[i], at = model.idx_vs[i];
        if (dofs == 1)
          sum += model.armature[at] * (vx[at] * vx[at]);
        else
          for (int k = 0; k < dofs; ++k)
            if (model.armature[at + k] != 0.0)
              return pinocchio::computeKineticEnergy(model, data);
      }
      return sum * .5;
    }

    // pinocchio::computePotentialEnergy(model, data), written out as Pinocchio 4.1 has it
    double potential_energy() const
    {
      const pinocchio::Model & model = *M;
      const Eigen::Vector3d & g = model.gravity.linear();
      Eigen::Vector3d com_global;
      double energy = 0.0;
      for (pinocchio::JointIndex i = 1; i < static_cast<pinocchio::JointIndex>(model.njoints); ++i)
      {
        com_global.noalias() = data.oMi[i].translation() + data.oMi[i].rotation() * model.inertias[i].lever();
        energy -= model.inertias[i].mass() * com_global.dot(g);
      }
      return energy;
    }

    // Robot.unchecked_energies from data's kinematics at qx (oMi and v, as forwardKinematics(q, v) leaves them)
    void write_energies(const Store & store, int64_t at, const Vec & qx, const Vec & vx)
    {
      energies_from_data(qx, vx, store.EXTRA + at * store.extra_width, store.ENERGY[at * 2], store.ENERGY[at * 2 + 1]);
    }

    // (T, V) at (qx, vx) from data's kinematics there; a scene's springs add theirs (Scene.unchecked_energies) and,
    // given a sample's record, write their potentials into it (unchecked_record)
    void energies_from_data(const Vec & qx, const Vec & vx, double * record, double & kinetic, double & potential)
    {
      kinetic = kinetic_energy(vx);
      potential = potential_energy();
      if (S && S->n_records())
        potential = potential + S->spring_energy(qx, record);
    }

    // A sample's energies need forwardKinematics(q, v). On fixed steps the next step's first ABA runs at the
    // sampled state and computes the same joint placements (liMi, oMi: ABA's first pass does forwardKinematics'
    // arithmetic); only the velocity recursion is left, done here exactly as forwardKinematics does it. A sample
    // whose row takes no such step before advance() returns gets its energies by flush().
    // A waiting sensor tick at this state (SensorWork::defer) is measured here too, with the same velocities (the
    // sample's when it has one: the same arithmetic, so they are not computed twice).
    void settle(size_t j)
    {
      const bool sample = pending[j] >= 0;
      if (sample)
      {
        velocities_from_placements();
        write_energies(*pending_store, pending[j], q[j], v[j]);
        if (A)  // the delivered torques at the sample: this step's first evaluation computed them there
          delivered_at_start(j, delivered_cell(*pending_store, pending[j]));
        pending[j] = -1;
      }
      if (sensw && sensw->waits(j))
      {
        SensorWork & sw_ = *sensw;
        sensing::kinematics_after_aba(*M, data, sw_, v[j], sw_.pending_a[j], sample);
        measure_kinematic(j, &data);
      }
    }

    // Actuators.joint_torques at row j's state under its command, as the step from it has evaluated them there (at
    // its first evaluation, before any revision): the fused stage's or the actuated() torques (tact), or while a
    // step takes servos inside, the torques its begin() clipped (Actuators.evaluate's, from the same law and interval)
    void delivered_at_start(size_t j, double * out) const
    {
      if (servo.active)
        A->clipped_torques(servo, tau[j], out);
      else
        std::copy(tact.data(), tact.data() + nv, out);
    }

    // Row j's waiting tick: its imu and frame_pose sensors from the kinematics in `kinematics` (the step's Data, or
    // by default sensw->data)
    void measure_kinematic(size_t j, pinocchio::Data * kinematics = nullptr)
    {
      SensorWork & w = *sensw;
      const Vec & a = w.pending_a[j];
      measure_sensors(*SS, *M, w, q[j], v[j], a, a, nullptr, 1.0,
                      w.values.data() + w.pending[j], SensorPart::kinematic, kinematics);
      w.pending[j] = -1;
    }

    void flush()
    {
      if (sensw)
        for (size_t j = 0; j < rows.size(); ++j)
          if (sensw->waits(j))
          {
            select(j);
            sensing::kinematics(*M, *sensw, q[j], v[j], sensw->pending_a[j]);
            measure_kinematic(j);
          }
      for (size_t j = 0; j < rows.size(); ++j)
        if (pending[j] >= 0)
        {
          select(j);
          pinocchio::forwardKinematics(*M, data, q[j], v[j]);
          write_energies(*pending_store, pending[j], q[j], v[j]);
          if (A)
            A->joint_torques(q[j], v[j], tau[j], nullptr, delivered_cell(*pending_store, pending[j]));
          pending[j] = -1;
        }
    }

    // ---- a row that leaves: what made it diverge, and its removal from the running rows ----------------------
    // RowKernel.nonfinite_dof: the first non-finite velocity coordinate of row j's pending state (else of q's)
    int64_t nonfinite_dof(size_t j)
    {
      for (int i = 0; i < nv; ++i)
        if (!std::isfinite(vn[j][i]))
          return i;
      for (int i = 0; i < nq; ++i)
        q_finite[i] = std::isfinite(qn[j][i]) ? qn[j][i] : 0.0;
      pinocchio::difference(e.model_, q[j], q_finite, diff);
      for (int i = 0; i < nv; ++i)
        if (!std::isfinite(diff[i]))
          return i;
      return 0;
    }

    void kill(size_t j)
    {
      if (alive[j])
      {
        alive[j] = 0;
        --n_alive;
      }
    }
  };
} // namespace multibody_sim
