// The native stepping kernel (see kernel.hpp): Core.advance over rows of one robot, with the Python kernel's
// arithmetic in its order. Each section names the Python function it renders.
#include "kernel.hpp"
#include "model.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <exception>
#include <functional>
#include <limits>
#include <mutex>
#include <thread>
#include <type_traits>

#include "pinocchio/algorithm/aba.hpp"
#include "pinocchio/algorithm/energy.hpp"
#include "pinocchio/algorithm/joint-configuration.hpp"

namespace multibody_sim
{
  namespace
  {
    using ConstRef = Eigen::Ref<const Vec>;
    constexpr double INF = std::numeric_limits<double>::infinity();

    // np.maximum: NaN wins.
    inline double nan_max(double a, double b)
    {
      if (std::isnan(a))
        return a;
      if (std::isnan(b))
        return b;
      return a > b ? a : b;
    }
  } // namespace

  // ---- one thread's rows and workspace ------------------------------------------------------------------------
  struct Thread
  {
    const Engine & e;
    pinocchio::Data data;
    int nq, nv, m, w;
    std::vector<int64_t> rows;  // the run rows this thread owns, ascending
    std::vector<char> alive;
    int64_t n_alive = 0;
    std::vector<Vec> q, v, flows, tau, qn, vn, fn, first;
    std::vector<char> has_first;
    std::vector<int64_t> pending;  // per row: the store cell whose energies wait for the next ABA at this state (-1)
    const Store * pending_store = nullptr;
    // workspace (no allocation in the step loop)
    RowMatrix K;  // stage derivatives (xi', v', ledger power), one row per stage
    Vec y, applied, acc, dv, xi, vs, qs, inc, chart_y, chart_t, q_last, v_last, size, diff, q_finite, yd, qd, vd;
    RowMatrix H, F;
    std::unique_ptr<SceneWork> sw;   // a scene's workspace (set_scene)
    std::unique_ptr<PolicyWork> pw;  // the native controllers' (set_policies)
    std::unique_ptr<ContactWork, void (*)(ContactWork *)> cw{nullptr, nullptr};  // a contact scene's (set_contact)
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
    Vec fx, pbuf, tau_control;
    bool dense_ready = false;
    bool no_armature;  // every armature exactly 0: kinetic_energy() needs no per-joint armature term
    int extra_evaluations = 0;
    CoreState st;
    AdvanceResult res;

    Thread(const Engine & engine, const std::vector<int64_t> & owned, const RowMatrix & Q0, const RowMatrix & V0)
    : e(engine)
    , data(engine.model_)
    , nq(engine.model_.nq)
    , nv(engine.model_.nv)
    , m(engine.n_ledger_)
    , w(2 * engine.model_.nv + engine.n_ledger_)
    , rows(owned)
    , no_armature((engine.model_.armature.array() == 0.0).all())
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
      fx = tau_control = vfree = Vec::Zero(nv);
      pbuf = Vec::Zero(std::max(m, 1));
    }

    // ---- the generalized forces ABA is given: Robot (tau - D v) or Scene._applied (tau + f(q, v, t) - D v) ------
    void applied_at(const Vec & qx, const Vec & vx, const Vec & tx, double ts)
    {
      if (e.scene_)
      {
        e.scene_->forces(*sw, e.model_, qx, vx, ts, fx);
        for (int i = 0; i < nv; ++i)
          applied[i] = tx[i] + fx[i];
        if (e.damped_)
          for (int i = 0; i < nv; ++i)
            applied[i] = applied[i] - e.damping_[i] * vx[i];
      }
      else if (e.damped_)
      {
        for (int i = 0; i < nv; ++i)
          applied[i] = tx[i] - e.damping_[i] * vx[i];
      }
      else
        applied = tx;
    }

    // ---- the dynamics of a stage: Robot.unchecked_forward_dynamics and Robot.ledger_power ----------------------
    void evaluate(const Vec & qx, const Vec & vx, const Vec & tx, int stage, double ts)
    {
      const pinocchio::Model & model = e.model_;
      applied_at(qx, vx, tx, ts);
      const Vec & a = pinocchio::aba(
        model, data, ConstRef(qx), ConstRef(vx), ConstRef(applied), pinocchio::Convention::WORLD);
      double * row = K.row(stage).data();
      for (int i = 0; i < nv; ++i)
        row[nv + i] = a[i];
      power(vx, tx, row + 2 * nv);
    }

    void power(const Vec & vx, const Vec & tx, double * out) const  // ordered.ordered_dot
    {
      double s = tx[0] * vx[0];
      for (int i = 1; i < nv; ++i)
        s += tx[i] * vx[i];
      out[0] = s;
      if (e.damped_)
      {
        double d = vx[0] * (e.damping_[0] * vx[0]);
        for (int i = 1; i < nv; ++i)
          d += vx[i] * (e.damping_[i] * vx[i]);
        out[1] = d;
      }
      if (e.scene_)  // Scene.ledger_power: the elements' powers after the robot's
        e.scene_->powers(*sw, vx, out + e.n_robot_flows_);
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
        for (int col = 0; col < w; ++col)
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
      const Method & me = e.method_;
      const Vec &qj = q[j], &vj = v[j], &tj = tau[j];
      if (me.kind == Kind::timestepping)
        return attempt_contact(j, h, t);
      if (me.kind == Kind::semi_implicit_euler)
      {
        evaluate_acceleration(qj, vj, tj, t);
        settle(j);
        for (int i = 0; i < nv; ++i)
          vn[j][i] = vj[i] + h * acc[i];
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
      if (e.scene_ && !e.scene_->wrenches.empty())  // Scene.ledger_power at a new point: the wrenches' parts there
        e.scene_->forces(*sw, e.model_, qn[j], vn[j], t + h, fx);
      power(vn[j], tau[j], pbuf.data());
    }

    // ---- TimeStepping.attempt on row j (a contact scene): the pending state in qn, vn, fn -----------------------
    int attempt_contact(size_t j, double h, double t)
    {
      const Vec &qj = q[j], &vj = v[j], &tj = tau[j];
      evaluate_acceleration(qj, vj, tj, t);
      settle(j);
      for (int i = 0; i < nv; ++i)
        vfree[i] = vj[i] + h * acc[i];
      double work = 0.0, correction = 0.0, bounce = 0.0;
      const bool problem =
        e.contact_->step(*cw, e.model_, qj, vj, vfree, h, crow[j], vn[j], work, correction, bounce);
      move_along_new_velocity(j, h, t);
      const int smooth_n = m - 4;  // the contact's elements come last: contact, penetration_correction,
      double smooth = 0.0;         // restitution, timestep_error
      for (int i = 0; i < smooth_n; ++i)
      {
        fn[j][i] = h * pbuf[i];
        smooth += e.flow_work_[static_cast<size_t>(i)] ? fn[j][i] : -fn[j][i];
      }
      double kinetic, potential, kinetic_free, kinetic_next, kinetic_end, potential_end, unused;
      energies(qj, vj, kinetic, potential);
      energies(qj, vfree, kinetic_free, unused);
      if (problem)
        energies(qj, vn[j], kinetic_next, unused);
      else
        kinetic_next = kinetic_free;
      energies(qn[j], vn[j], kinetic_end, potential_end);
      fn[j][m - 4] = correction + bounce - work;
      fn[j][m - 3] = correction;
      fn[j][m - 2] = bounce;
      fn[j][m - 1] = (kinetic_free - kinetic) + (kinetic_end - kinetic_next) + (potential_end - potential) - smooth;
      if (problem)
        extra[j] += 1;
      return 1;
    }

    // Scene.unchecked_energies: (T, V) at (qx, vx)
    void energies(const Vec & qx, const Vec & vx, double & kinetic, double & potential)
    {
      pinocchio::forwardKinematics(e.model_, data, qx, vx);
      energies_from_data(qx, vx, nullptr, kinetic, potential);
    }

    void evaluate_acceleration(const Vec & qx, const Vec & vx, const Vec & tx, double t)
    {
      applied_at(qx, vx, tx, t);
      acc = pinocchio::aba(
        e.model_, data, ConstRef(qx), ConstRef(vx), ConstRef(applied), pinocchio::Convention::WORLD);
    }

    // ---- AdaptiveRungeKutta.attempt on row 0: the error norm; the pending state in qn, vn, fn -------------------
    double attempt_adaptive(double h, double t, int & evaluations)
    {
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
      pinocchio::forwardKinematics(e.model_, data, qx, vx);
      write_energies(store, at, qx, vx);
    }

    void write_state(const Store & store, int64_t at, const Vec & qx, const Vec & vx, const Vec & tx,
                     const double * fl) const
    {
      std::copy(qx.data(), qx.data() + nq, store.Q + at * nq);
      std::copy(vx.data(), vx.data() + nv, store.V + at * nv);
      std::copy(tx.data(), tx.data() + nv, store.TAU + at * nv);
      std::copy(fl, fl + m, store.FLOWS + at * m);
    }

    // pinocchio::computeKineticEnergy(model, data) at velocity vx: without armature, the same sum in the same order
    // without its per-joint visitor, which adds each joint's armature term: exactly 0 when the armature is and every
    // |v| < 1e150 (else v² may overflow and 0 · inf make it NaN: then Pinocchio's own call)
    double kinetic_energy(const Vec & vx)
    {
      const pinocchio::Model & model = e.model_;
      bool exact = no_armature;
      for (int r = 0; exact && r < nv; ++r)
        exact = std::abs(vx[r]) < 1e150;  // (false for NaN)
      if (!exact)
        return pinocchio::computeKineticEnergy(model, data);
      double sum = 0.0;
      for (pinocchio::JointIndex i = 1; i < static_cast<pinocchio::JointIndex>(model.njoints); ++i)
        sum += model.inertias[i].vtiv(data.v[i]);
      return sum * .5;
    }

    // pinocchio::computePotentialEnergy(model, data), written out as Pinocchio 4.1 has it
    double potential_energy() const
    {
      const pinocchio::Model & model = e.model_;
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
      if (e.scene_ && e.scene_->n_records())
        potential = potential + e.scene_->spring_energy(qx, record);
    }

    void stamp(const Store & store, int64_t i, int64_t b, double t) const
    {
      const int64_t at = store.at(i, b);
      store.T[at] = t;
      store.COUNTS[at * 3] = st.steps;
      store.COUNTS[at * 3 + 1] = st.rejected;
      store.COUNTS[at * 3 + 2] = st.evaluations + extra[static_cast<size_t>(b - rows.front())];
    }

    // core.RowKernel._write_contacts: a contact scene's active contacts of row j as sample i
    void note_contacts(int64_t i, size_t j)
    {
      if (e.contact_)
        res.records.push_back(ContactRecord{i, rows[j], crow[j].active});
    }

    // A sample's energies need forwardKinematics(q, v). On fixed steps the next step's first ABA runs at the
    // sampled state and computes the same joint placements (liMi, oMi: ABA's first pass does forwardKinematics'
    // arithmetic); only the velocity recursion is left, done here exactly as forwardKinematics does it. A sample
    // whose row takes no such step before advance() returns gets its energies by flush().
    void settle(size_t j)
    {
      if (pending[j] < 0)
        return;
      const pinocchio::Model & model = e.model_;
      for (pinocchio::JointIndex i = 1; i < static_cast<pinocchio::JointIndex>(model.njoints); ++i)
      {
        const pinocchio::JointIndex parent = model.parents[i];
        data.v[i] = data.joints[i].v();
        if (parent > 0)
          data.v[i] += data.liMi[i].actInv(data.v[parent]);
      }
      write_energies(*pending_store, pending[j], q[j], v[j]);
      pending[j] = -1;
    }

    void flush()
    {
      for (size_t j = 0; j < rows.size(); ++j)
        if (pending[j] >= 0)
        {
          pinocchio::forwardKinematics(e.model_, data, q[j], v[j]);
          write_energies(*pending_store, pending[j], q[j], v[j]);
          pending[j] = -1;
        }
    }

    // Core.record: every running row's current state as sample `count`
    void record(const Store & store)
    {
      const int64_t i = st.count;
      const bool defer = !e.control_.adaptive;
      for (size_t j = 0; j < rows.size(); ++j)
        if (alive[j])
        {
          stamp(store, i, rows[j], st.t);
          note_contacts(i, j);
          if (defer)
          {
            const int64_t at = store.at(i, rows[j]);
            write_state(store, at, q[j], v[j], tau[j], flows[j].data());
            pending[j] = at;
            pending_store = &store;
          }
          else
            write(store, i, rows[j], q[j], v[j], tau[j], flows[j].data());
        }
      advance_count();
      st.recorded = st.t;
    }

    void advance_count()
    {
      st.count += 1;
      if (static_cast<double>(st.count) >= st.soft_capacity)
        st.full = true;
    }

    // Core._record_stopping: the current state of rows js at index count, unless it is a sample already
    bool record_stopping(const Store & store, const std::vector<size_t> & js)
    {
      if (st.recorded == st.t)
        return false;
      for (size_t j : js)
      {
        stamp(store, st.count, rows[j], st.t);
        note_contacts(st.count, j);
        write(store, st.count, rows[j], q[j], v[j], tau[j], flows[j].data());
      }
      return true;
    }

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

    // ---- the step-size controllers (step_control.py) ---------------------------------------------------------
    double propose(double t_stop) const
    {
      const Control & c = e.control_;
      if (c.adaptive)
      {
        const double scale = std::max(c.first_step, std::abs(t_stop));
        if (st.step_time + st.step_h >= t_stop - c.landing * scale)
          return t_stop;
        return st.step_time + st.step_h;
      }
      const int64_t k_stop = std::max<int64_t>(
        st.step_k + 1, static_cast<int64_t>(std::ceil((t_stop - st.step_t0) / c.dt - c.sliver)));
      if (st.step_k + 1 < k_stop)
        return st.step_t0 + static_cast<double>(st.step_k + 1) * c.dt;
      return t_stop;
    }

    double step_size(double t_next) const
    {
      const Control & c = e.control_;
      if (c.adaptive)
        return t_next - st.step_time;
      const double grid = st.step_t0 + static_cast<double>(st.step_k + 1) * c.dt;
      return t_next == grid ? c.dt : t_next - st.step_time;
    }

    bool judge(double h, double error)  // PIController.next_step
    {
      const Control & c = e.control_;
      if (!std::isfinite(error))
      {
        st.rejected_last = true;
        st.step_h = h * c.factor_min;
        return false;
      }
      if (error <= 1.0)
      {
        error = std::max(error, 1e-10);
        double factor = c.safety * std::pow(error, -c.alpha) * std::pow(st.previous_error, c.beta);
        factor = std::min(st.rejected_last ? 1.0 : c.factor_max, std::max(c.factor_min, factor));
        st.previous_error = error;
        st.rejected_last = false;
        st.step_h = std::min(h * factor, c.max_step);
        return true;
      }
      const double factor = std::max(c.factor_min, c.safety * std::pow(error, -c.alpha));
      st.rejected_last = true;
      st.step_h = h * factor;
      return false;
    }

    void commit(double t_next)
    {
      const Control & c = e.control_;
      if (!c.adaptive)
      {
        if (t_next == st.step_t0 + static_cast<double>(st.step_k + 1) * c.dt)
          st.step_k += 1;
        else
        {
          st.step_t0 = t_next;
          st.step_k = 0;
        }
      }
      st.step_time = t_next;
    }

    // Sampler.due
    bool due(const Sampler & sampler, double t, double tolerance)
    {
      if (sampler.period > 0.0)
      {
        if (std::abs(t - static_cast<double>(st.next_output) * sampler.period) <= tolerance)
        {
          st.next_output += 1;
          return true;
        }
        return t == 0.0;
      }
      if (sampler.every == 0)
        return true;
      return st.steps % sampler.every == 0;
    }

    int64_t dense_count(const Sampler & sampler, double t_next, double tolerance) const
    {
      if (!(sampler.period > 0.0))
        return 0;
      int64_t n = 0;
      while (static_cast<double>(st.next_output + n) * sampler.period < t_next - tolerance)
        ++n;
      return n;
    }

    void stop_event(int code, size_t j, double time, bool added, int64_t counted_steps)
    {
      StopEvent ev;
      ev.code = code;
      ev.row = rows[j];
      ev.time = time;
      ev.step = st.steps + 1;
      ev.count = st.count;
      ev.added = added;
      ev.counts[0] = counted_steps;
      ev.counts[1] = st.rejected;
      ev.counts[2] = st.evaluations + extra[j];
      res.stops.push_back(ev);
    }

    void kill(size_t j)
    {
      if (alive[j])
      {
        alive[j] = 0;
        --n_alive;
      }
    }

    // ---- Core.advance over this thread's rows --------------------------------------------------------------
    // driver.Run._control at a control instant, natively: every running row's torque from the policies, counted
    // and saturated; a row whose output is not finite stops (STOP_CONTROL). Returns false when the store needs room.
    bool control(const Store & store)
    {
      const Policies & pol = *e.policies_;
      if (st.count + 1 > store.capacity)  // a failing row's last sample
      {
        res.status = NEED_ROOM;
        res.need = 1;
        return false;
      }
      for (size_t j = 0; j < rows.size(); ++j)
      {
        if (!alive[j])
          continue;
        const int64_t b = rows[j];
        e.calls_[b] += 1;
        if (!pol.torque(*pw, e.model_, b, st.instant, q[j], v[j], tau_control))
        {
          const std::vector<size_t> js{j};
          const bool added = record_stopping(store, js);
          stop_event(STOP_CONTROL, j, st.t, added, st.steps);
          kill(j);
          continue;
        }
        bool clipped = false;
        pol.clip(tau_control, e.saturated_dofs_ + b * nv, clipped);
        if (clipped)
          e.saturated_[b] += 1;
        tau[j] = tau_control;
        has_first[j] = 0;  // a torque given at a control instant is a jump
      }
      return true;
    }

    void run(double t_stop, int64_t limit, double tolerance, const Sampler & sampler, const Store & store)
    {
      loop(t_stop, limit, tolerance, sampler, store);
      flush();
    }

    void loop(double t_stop, int64_t limit, double tolerance, const Sampler & sampler, const Store & store)
    {
      res = AdvanceResult();
      const bool adaptive = e.control_.adaptive;
      const Policies * pol = e.policies_.get();
      const double t_end = t_stop;
      std::vector<size_t> bad;
      while (true)
      {
        const double t = st.t;
        if (t >= t_end)
        {
          res.status = REACHED;
          return;
        }
        // driver.Run._loop's control instants. Every step (adaptive, no control_dt): the driver controls between
        // its one-step advances, so a sample at t (taken at the end of the previous advance) carries the previous
        // torque, except at the run's start.
        const bool each = pol && pol->every_step;
        if (pol && t < pol->duration && n_alive && !(each && st.steps > 0))
        {
          if (pol->every_step ? t != st.last_control : t == pol->instant(st.instant))
          {
            if (!control(store))
              return;
            if (pol->every_step)
              st.last_control = t;
            else
              st.instant += 1;
          }
          if (!pol->every_step)  // the steps land on the next instant, as the driver's advance(target) does
          {
            t_stop = std::min(t_end, pol->instant(st.instant));
            if (adaptive)
              tolerance = e.control_.landing * std::max(e.control_.first_step, std::abs(t_stop));
          }
        }
        if (sampler.present && st.recorded != t && n_alive)
        {
          if (st.count + 1 > store.capacity)
          {
            res.status = NEED_ROOM;
            res.need = 1;
            return;
          }
          if (due(sampler, t, tolerance))
            record(store);
        }
        if (each && st.steps > 0 && t < pol->duration && n_alive && t != st.last_control)
        {
          if (!control(store))
            return;
          st.last_control = t;
        }
        if (!n_alive)
        {
          res.status = EMPTY;
          return;
        }
        if (res.taken == limit)
        {
          res.status = STEPPED;
          return;
        }
        if (st.full)
        {
          res.status = FULL;
          return;
        }
        const double t_next = propose(t_stop);
        const double h = step_size(t_next);
        const int64_t need = 1 + (adaptive ? dense_count(sampler, t_next, tolerance) : 0);
        if (st.count + need > store.capacity)
        {
          res.status = NEED_ROOM;
          res.need = need;
          return;
        }
        if (adaptive)
        {
          int evaluations = 0;
          const double error = attempt_adaptive(h, t, evaluations);
          st.evaluations += evaluations;
          if (!judge(h, error))
          {
            st.rejected += 1;
            first[0] = K.row(0).transpose();  // the retry state: the same start, the same torque
            has_first[0] = 1;
            if (st.step_h < tolerance)
            {
              collapse(store, t, tolerance, error);
              return;
            }
            continue;
          }
          if (st.step_h < tolerance)
          {
            collapse(store, t, tolerance, std::numeric_limits<double>::quiet_NaN());
            return;
          }
          if (sampler.period > 0.0)  // Core._dense_samples
          {
            int extra = 0;
            while (static_cast<double>(st.next_output) * sampler.period < t_next - tolerance)
            {
              const double t_out = static_cast<double>(st.next_output) * sampler.period;
              const int64_t i = st.count;
              stamp(store, i, rows[0], t_out);
              dense(h, t, (t_out - t) / h);
              for (int r = 0; r < m; ++r)
                y[r] = flows[0][r] + yd[2 * nv + r];
              write(store, i, rows[0], qd, vd, tau[0], y.data());
              extra = extra_evaluations;
              advance_count();
              st.next_output += 1;
            }
            st.evaluations += extra;
          }
        }
        else
        {
          int evaluations = 0;
          for (size_t j = 0; j < rows.size(); ++j)
            if (alive[j])
              evaluations = attempt_fixed(j, h, t);
          st.evaluations += evaluations;
        }
        bad.clear();
        for (size_t j = 0; j < rows.size(); ++j)
          if (alive[j] && !(qn[j].allFinite() && vn[j].allFinite()))
            bad.push_back(j);
        if (!bad.empty())  // their last sample is the state before this step; they leave once it is accepted
        {
          const bool added = record_stopping(store, bad);
          for (size_t j : bad)
          {
            stop_event(STOP_DIVERGED, j, t_next, added, st.steps);
            res.stops.back().dof = nonfinite_dof(j);
          }
        }
        for (size_t j = 0; j < rows.size(); ++j)  // RowKernel.accept
          if (alive[j])
          {
            q[j].swap(qn[j]);
            v[j].swap(vn[j]);
            for (int i = 0; i < m; ++i)
              flows[j][i] = flows[j][i] + fn[j][i];
            if (adaptive && e.method_.fsal)
            {
              first[j] = K.row(e.method_.stages - 1).transpose();
              has_first[j] = 1;
            }
          }
        st.t = t_next;
        commit(t_next);
        st.steps += 1;
        res.taken += 1;
        for (size_t j : bad)
          kill(j);
      }
    }

    void collapse(const Store & store, double t, double minimum, double error)
    {
      const std::vector<size_t> js{0};
      const bool added = record_stopping(store, js);
      stop_event(STOP_COLLAPSED, 0, t, added, st.steps);
      StopEvent & ev = res.stops.back();
      ev.h = st.step_h;
      ev.minimum = minimum;
      ev.error = error;
      kill(0);
      res.status = EMPTY;
    }
  };

  // ---- a pool of threads that each run their own rows' loop, joined once per advance() --------------------------
  struct Engine::Pool
  {
    std::vector<std::thread> workers;
    std::mutex mutex;
    std::condition_variable start, done;
    std::function<void(size_t)> job;
    uint64_t generation = 0;
    size_t pending = 0;
    bool quit = false;
    std::exception_ptr error;  // the first exception a worker raised in this run

    explicit Pool(size_t n)
    {
      for (size_t i = 1; i < n; ++i)
        workers.emplace_back([this, i] { loop(i); });
    }

    ~Pool()
    {
      {
        std::lock_guard<std::mutex> lock(mutex);
        quit = true;
      }
      start.notify_all();
      for (std::thread & t : workers)
        t.join();
    }

    void loop(size_t i)
    {
      uint64_t seen = 0;
      while (true)
      {
        std::function<void(size_t)> task;
        {
          std::unique_lock<std::mutex> lock(mutex);
          start.wait(lock, [&] { return quit || generation != seen; });
          if (quit)
            return;
          seen = generation;
          task = job;
        }
        std::exception_ptr failure;
        try
        {
          task(i);
        }
        catch (...)  // an exception must not end a worker thread (std::terminate): the caller rethrows it
        {
          failure = std::current_exception();
        }
        {
          std::lock_guard<std::mutex> lock(mutex);
          if (failure && !error)
            error = failure;
          if (--pending == 0)
            done.notify_one();
        }
      }
    }

    void run(const std::function<void(size_t)> & f)
    {
      {
        std::lock_guard<std::mutex> lock(mutex);
        job = f;
        pending = workers.size();
        ++generation;
      }
      start.notify_all();
      std::exception_ptr failure;
      try
      {
        f(0);
      }
      catch (...)
      {
        failure = std::current_exception();
      }
      std::unique_lock<std::mutex> lock(mutex);
      done.wait(lock, [&] { return pending == 0; });
      if (!failure)
        failure = error;
      error = nullptr;
      if (failure)
        std::rethrow_exception(failure);
    }
  };

  // ---- Engine -----------------------------------------------------------------------------------------------------
  namespace
  {
    // Whether a joint's Lie group (pinocchio::LieGroupMap) is the vector space R^nq, where integrate is q + v.
    struct IsVectorSpace : boost::static_visitor<bool>
    {
      template<typename JointModel>
      bool operator()(const JointModel &) const
      {
        using Group = typename pinocchio::LieGroupMap::template operation<JointModel>::type;
        using Flat = pinocchio::VectorSpaceOperationTpl<JointModel::NQ, double, 0>;
        return std::is_same<Group, Flat>::value && JointModel::NQ == JointModel::NV;
      }
    };
  } // namespace

  Integrate::Integrate(const pinocchio::Model & model)
  {
    for (pinocchio::JointIndex i = 1; i < static_cast<pinocchio::JointIndex>(model.njoints); ++i)
    {
      const auto & joint = model.joints[i];
      if (!boost::apply_visitor(IsVectorSpace(), joint.toVariant()))
      {
        others.push_back(i);
        continue;
      }
      const int q = joint.idx_q(), v = joint.idx_v(), n = joint.nq();
      if (!spans.empty() && spans.back().q + spans.back().n == q && spans.back().v + spans.back().n == v)
        spans.back().n += n;
      else
        spans.push_back(Span{q, v, n});
    }
  }

  void Integrate::operator()(const pinocchio::Model & model, const Vec & q, const Vec & v, Vec & out) const
  {
    for (const Span & s : spans)
      for (int i = 0; i < s.n; ++i)
        out[s.q + i] = q[s.q + i] + v[s.v + i];
    if (others.empty())
      return;
    using Step = pinocchio::IntegrateStep<pinocchio::LieGroupMap, Vec, Vec, Vec>;
    Step::ArgsType args(q, v, out);
    for (pinocchio::JointIndex i : others)
      Step::run(model.joints[i], args);
  }

  Engine::Engine(
    const pinocchio::Model & model,
    const Method & method,
    const std::vector<ChartBlock> & blocks,
    const std::vector<double> & half_series,
    const Vec & damping,
    int n_ledger,
    const Control & control,
    const RowMatrix & Q0,
    const RowMatrix & V0,
    int num_threads)
  : model_(model)
  , integrate_(model_)
  , method_(method)
  , blocks_(blocks)
  , half_series_(half_series)
  , damping_(damping)
  , damped_(damping.size() && (damping.array() != 0.0).any())
  , n_ledger_(n_ledger)
  , control_(control)
  , n_robot_flows_(damped_ ? 2 : 1)
  {
    neutral_ = pinocchio::neutral(model_);
    const int64_t B = Q0.rows();
    const int64_t n = std::max<int64_t>(1, std::min<int64_t>(num_threads, B));
    for (int64_t i = 0; i < n; ++i)  // rows split across threads once per run
    {
      std::vector<int64_t> owned;
      for (int64_t b = i * B / n; b < (i + 1) * B / n; ++b)
        owned.push_back(b);
      threads_.emplace_back(new Thread(*this, owned, Q0, V0));
    }
    if (n > 1)
      pool_.reset(new Pool(static_cast<size_t>(n)));
  }

  Engine::~Engine() = default;

  void Engine::set_scene(std::shared_ptr<const SceneForces> scene)
  {
    const int contact_flows = method_.kind == Kind::timestepping ? 4 : 0;  // the time-stepper's, last
    if (scene && (scene->nv != model_.nv || n_robot_flows_ + scene->n_flows() + contact_flows != n_ledger_))
      throw std::invalid_argument("the scene's elements disagree with the model's sizes or the ledger");
    scene_ = scene;
    for (auto & th : threads_)
      th->sw = scene ? scene->workspace(model_) : nullptr;
  }

  void Engine::set_policies(
    std::shared_ptr<const Policies> policies, int64_t * calls, int64_t * saturated, int64_t * saturated_dofs)
  {
    if (policies && policies->nv != model_.nv)
      throw std::invalid_argument("the controllers disagree with the model's sizes");
    policies_ = policies;
    calls_ = calls;
    saturated_ = saturated;
    saturated_dofs_ = saturated_dofs;
    for (auto & th : threads_)
      th->pw = policies ? policies->workspace(model_) : nullptr;
  }

  AdvanceResult Engine::advance(
    double t_stop, int64_t limit, double tolerance, const Sampler & sampler, const Store & store, CoreState & state)
  {
    for (auto & th : threads_)
      th->st = state;
    if (pool_)
      pool_->run([&](size_t i) { threads_[i]->run(t_stop, limit, tolerance, sampler, store); });
    else
      threads_[0]->run(t_stop, limit, tolerance, sampler, store);
    // Every thread with rows left took the same decisions; else the one that went furthest stands for the run.
    Thread * lead = nullptr;
    for (auto & th : threads_)
      if (th->n_alive && (!lead || !lead->n_alive || th->st.steps > lead->st.steps))
        lead = th.get();
    if (!lead)
      for (auto & th : threads_)
        if (!lead || th->st.steps > lead->st.steps || th->st.count > lead->st.count)
          lead = th.get();
    AdvanceResult out;
    out.status = lead->n_alive ? lead->res.status : EMPTY;
    out.taken = lead->res.taken;
    out.need = lead->res.need;
    state = lead->st;
    for (auto & th : threads_)
    {
      out.stops.insert(out.stops.end(), th->res.stops.begin(), th->res.stops.end());
      for (ContactRecord & r : th->res.records)
        out.records.push_back(std::move(r));
      th->res.records.clear();
    }
    std::stable_sort(out.stops.begin(), out.stops.end(), [](const StopEvent & a, const StopEvent & b) {
      return a.step != b.step ? a.step < b.step : a.row < b.row;
    });
    for (auto & th : threads_)  // every thread continues from the run's time (rows that all stopped included)
      th->st = state;
    return out;
  }

  std::vector<ContactRecord> Engine::write_rows(int64_t i, const std::vector<int64_t> & rows, const Store & store)
  {
    std::vector<ContactRecord> records;
    for (int64_t b : rows)
      for (auto & th : threads_)
        for (size_t j = 0; j < th->rows.size(); ++j)
          if (th->rows[j] == b)
          {
            th->write(store, i, b, th->q[j], th->v[j], th->tau[j], th->flows[j].data());
            if (contact_)
              records.push_back(ContactRecord{i, b, th->crow[j].active});
          }
    return records;
  }

  void Engine::set_contact(std::shared_ptr<const ContactScene> contact, const std::vector<bool> & flow_work)
  {
    if (contact && (contact->nv != model_.nv || n_ledger_ < 4 || static_cast<int>(flow_work.size()) != n_ledger_ - 4))
      throw std::invalid_argument("the contact scene disagrees with the model's sizes or the ledger");
    if (contact && method_.kind != Kind::timestepping)
      throw std::invalid_argument("a contact scene steps with the timestepping kind only");
    contact_ = contact;
    flow_work_ = flow_work;
    for (auto & th : threads_)
    {
      if (contact)
        th->cw = contact->workspace(model_);
      else
        th->cw.reset();
    }
  }

  std::pair<Thread *, size_t> Engine::locate(int64_t row) const
  {
    for (auto & th : threads_)
      for (size_t j = 0; j < th->rows.size(); ++j)
        if (th->rows[j] == row)
          return {th.get(), j};
    throw std::invalid_argument("no such row");
  }

  ContactRow Engine::contact_row(int64_t row) const
  {
    const auto [th, j] = locate(row);
    return th->crow[j];
  }

  std::vector<int64_t> Engine::extra_evaluations(const std::vector<int64_t> & rows) const
  {
    std::vector<int64_t> out;
    for (int64_t b : rows)
    {
      int64_t x = 0;
      for (auto & th : threads_)
        for (size_t j = 0; j < th->rows.size(); ++j)
          if (th->rows[j] == b)
            x = th->extra[j];
      out.push_back(x);
    }
    return out;
  }

  void Engine::set_torques(const RowMatrix & TAU, bool jump)
  {
    if (TAU.rows() != running() || TAU.cols() != model_.nv)
      throw std::invalid_argument("torques must have shape (running rows, nv)");
    int64_t r = 0;
    for (auto & th : threads_)
      for (size_t j = 0; j < th->rows.size(); ++j)
        if (th->alive[j])
        {
          th->tau[j] = TAU.row(r++).transpose();
          if (jump)
            th->has_first[j] = 0;
        }
  }

  void Engine::keep(const std::vector<bool> & keep)
  {
    if (static_cast<int64_t>(keep.size()) != running())
      throw std::invalid_argument("keep needs one flag per running row");
    size_t r = 0;
    for (auto & th : threads_)
      for (size_t j = 0; j < th->rows.size(); ++j)
        if (th->alive[j])
          if (!keep[r++])
            th->kill(j);
  }

  std::vector<int64_t> Engine::running_rows() const
  {
    std::vector<int64_t> out;
    for (auto & th : threads_)
      for (size_t j = 0; j < th->rows.size(); ++j)
        if (th->alive[j])
          out.push_back(th->rows[j]);
    return out;
  }

  RowMatrix Engine::running_q() const
  {
    RowMatrix out(running(), model_.nq);
    int64_t r = 0;
    for (auto & th : threads_)
      for (size_t j = 0; j < th->rows.size(); ++j)
        if (th->alive[j])
          out.row(r++) = th->q[j].transpose();
    return out;
  }

  RowMatrix Engine::running_v() const
  {
    RowMatrix out(running(), model_.nv);
    int64_t r = 0;
    for (auto & th : threads_)
      for (size_t j = 0; j < th->rows.size(); ++j)
        if (th->alive[j])
          out.row(r++) = th->v[j].transpose();
    return out;
  }

  Vec Engine::flows_of(int64_t row) const
  {
    for (auto & th : threads_)
      for (size_t j = 0; j < th->rows.size(); ++j)
        if (th->rows[j] == row)
          return th->flows[j];
    return Vec();
  }

  void Engine::set_state(int64_t row, const Vec & q, const Vec & v, const Vec & flows)
  {
    if (q.size() != model_.nq || v.size() != model_.nv || flows.size() != n_ledger_)
      throw std::invalid_argument("a row's state has the wrong sizes");
    for (auto & th : threads_)
      for (size_t j = 0; j < th->rows.size(); ++j)
        if (th->rows[j] == row)
        {
          th->q[j] = q;
          th->v[j] = v;
          th->flows[j] = flows;
          th->has_first[j] = 0;
          th->crow[j] = ContactRow();  // RowKernel.set_row: the solver state restarts (TimeStepping.init)
        }
  }

  std::tuple<Vec, Vec, Vec, Vec, Vec, bool> Engine::snapshot_row(int64_t row) const
  {
    for (auto & th : threads_)
      for (size_t j = 0; j < th->rows.size(); ++j)
        if (th->rows[j] == row)
          return {th->q[j], th->v[j], th->flows[j], th->tau[j], th->first[j], th->has_first[j] != 0};
    throw std::invalid_argument("no such row");
  }

  void Engine::save()
  {
    for (auto & th : threads_)
    {
      Thread::Saved & s = th->saved;
      s.q = th->q;  // (same-sized vectors: copied into the storage of the last save)
      s.v = th->v;
      s.flows = th->flows;
      s.tau = th->tau;
      s.first = th->first;
      s.has_first = th->has_first;
      s.alive = th->alive;
      s.n_alive = th->n_alive;
      s.crow = th->crow;
      s.extra = th->extra;
    }
    saved_ = true;
  }

  void Engine::restore_saved()
  {
    if (!saved_)
      throw std::logic_error("restore_saved() before save()");
    for (auto & th : threads_)
    {
      const Thread::Saved & s = th->saved;
      th->q = s.q;
      th->v = s.v;
      th->flows = s.flows;
      th->tau = s.tau;
      th->first = s.first;
      th->has_first = s.has_first;
      th->alive = s.alive;
      th->n_alive = s.n_alive;
      th->crow = s.crow;
      th->extra = s.extra;
    }
  }

  int64_t Engine::running() const
  {
    int64_t n = 0;
    for (auto & th : threads_)
      n += th->n_alive;
    return n;
  }

} // namespace multibody_sim

// ---- Python bindings: _native.Kernel and the named structs it takes (kernels/native.py is their only user) -------
#include <nanobind/eigen/dense.h>
#include <nanobind/ndarray.h>
#include <nanobind/nanobind.h>
#include <nanobind/stl/shared_ptr.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/tuple.h>
#include <nanobind/stl/variant.h>
#include <nanobind/stl/vector.h>

#include "structs.hpp"

namespace nb = nanobind;

namespace
{
  using Doubles = nb::ndarray<double, nb::c_contig, nb::device::cpu>;
  using Ints = nb::ndarray<int64_t, nb::c_contig, nb::device::cpu>;

  // recording.SampleStore's batch-major arrays (STORE_ARRAYS), shape (B, capacity, ...) each: _native.Store. The
  // struct holds references to them while the engine writes into them.
  struct StoreArrays
  {
    Doubles T, Q, V, TAU, ENERGY, FLOWS;
    Ints COUNTS;
    Doubles EXTRA;
  };

  void check_store(const StoreArrays & a)
  {
    const auto cells = [&](const Doubles & X) {
      return X.ndim() == 3 && X.shape(0) == a.T.shape(0) && X.shape(1) == a.T.shape(1);
    };
    const size_t n = a.T.ndim() == 2 ? a.T.shape(0) * a.T.shape(1) : 0;
    if (a.T.ndim() != 2 || a.COUNTS.size() != 3 * n || a.ENERGY.size() != 2 * n || !cells(a.Q) || !cells(a.V)
        || !cells(a.TAU) || !cells(a.ENERGY) || !cells(a.FLOWS) || !cells(a.EXTRA))
      throw std::invalid_argument("Store: the sample store's arrays disagree in shape");
  }

  multibody_sim::Store store_of(const StoreArrays & a)
  {
    multibody_sim::Store s;
    s.T = a.T.data();
    s.Q = a.Q.data();
    s.V = a.V.data();
    s.TAU = a.TAU.data();
    s.ENERGY = a.ENERGY.data();
    s.FLOWS = a.FLOWS.data();
    s.COUNTS = a.COUNTS.data();
    s.EXTRA = a.EXTRA.data();
    s.extra_width = static_cast<int64_t>(a.EXTRA.shape(2));
    s.B = static_cast<int64_t>(a.T.shape(0));  // batch-major: (B, capacity, ...)
    s.capacity = static_cast<int64_t>(a.T.shape(1));
    return s;
  }

  // recording.SampleStore.write_contacts for the samples the engine wrote, on the store's `contacts` dict itself
  // (row b -> {sample index: rows (k, 11)}): dict operations run no Python code, so a signal handler (Ctrl-C)
  // never sees the samples counted without their contacts.
  void write_contacts(nb::dict contacts, std::vector<multibody_sim::ContactRecord> & records)
  {
    for (multibody_sim::ContactRecord & r : records)
    {
      nb::int_ b(r.b), i(r.i);
      if (!contacts.contains(b))
        contacts[b] = nb::dict();
      nb::dict held = nb::borrow<nb::dict>(contacts[b]);
      if (r.rows.empty())
      {
        if (held.contains(i))
          nb::del(held[i]);
        continue;
      }
      const size_t k = r.rows.size();
      double * buffer = new double[k * 11];
      for (size_t c = 0; c < k; ++c)
        std::copy(r.rows[c].begin(), r.rows[c].end(), buffer + 11 * c);
      nb::capsule owner(buffer, [](void * p) noexcept { delete[] static_cast<double *>(p); });
      held[i] = nb::cast(nb::ndarray<nb::numpy, double, nb::ndim<2>>(buffer, {k, 11}, owner));
    }
    records.clear();
  }

  // A contact run's evaluations beyond the core's count, per running position of the Python core (`rows`, the rows
  // stopped in this call included: NativeCore._take_pending compacts both) into `extra`.
  void write_extra_evaluations(const multibody_sim::Engine & engine, const Ints & rows, Ints & extra)
  {
    if (!engine.has_contact())
      return;
    std::vector<int64_t> wanted(rows.data(), rows.data() + rows.size());
    const std::vector<int64_t> counts = engine.extra_evaluations(wanted);
    for (size_t p = 0; p < counts.size() && p < extra.size(); ++p)
      extra.data()[p] = counts[p];
  }

  // What advance() did: why it returned (core.py's REACHED, STEPPED, FULL, EMPTY, or "need_room"), the steps it
  // took, and the samples the store must have room for beyond its count (need_room): _native.Advance.
  struct Advance
  {
    std::string status;
    int64_t taken = 0, need = 0;
  };

  const char * status_name(int status)
  {
    switch (status)
    {
    case multibody_sim::REACHED:
      return "reached";
    case multibody_sim::STEPPED:
      return "stepped";
    case multibody_sim::FULL:
      return "full";
    case multibody_sim::EMPTY:
      return "empty";
    default:
      return "need_room";
    }
  }

  const char * stop_name(int code)
  {
    return code == multibody_sim::STOP_DIVERGED ? "diverged" : code == multibody_sim::STOP_COLLAPSED ? "collapsed" : "control";
  }

  // Method's shapes, by field.
  void check_method(multibody_sim::Method & me)
  {
    const auto need = [](bool ok, const std::string & what) {
      if (!ok)
        throw std::invalid_argument("Method." + what);
    };
    const size_t s = static_cast<size_t>(me.stages);
    need(me.stages >= 1, "stages must be >= 1");
    need(me.a.size() == s * s, "a must hold stages x stages entries");
    need(me.b.size() == s && me.c.size() == s, "b and c must hold `stages` entries each");
    need(me.chart_terms >= 0, "chart_terms must be >= 0");
    if (me.kind == multibody_sim::Kind::embedded)
      need(me.e.size() == s && (me.dense.empty() || me.dense.size() == s), "e (and dense) must hold `stages` entries");
    if (me.kind == multibody_sim::Kind::dop853)
    {
      const size_t x = static_cast<size_t>(me.extended_stages);
      need(me.e5.size() == s && me.e3.size() == s, "e5 and e3 must hold `stages` entries each");
      need(x >= s && me.a_extended.size() == x * x && me.c_extended.size() == x && me.dense_weights.size() == 4 * x,
           "a_extended, c_extended, dense_weights must be extended_stages x extended_stages, extended_stages, 4 x "
           "extended_stages");
    }
  }
} // namespace

void multibody_sim::bind_kernel(nb::module_ & m)  // called by module.cpp
{
  using namespace multibody_sim;
  Struct<Method>(m, "Method", "A stepping method as the engine renders it (Integrator.native_data()).")
    .choice("kind", &Method::kind,
            {{"explicit_rk", Kind::explicit_rk}, {"embedded", Kind::embedded}, {"dop853", Kind::dop853},
             {"semi_implicit_euler", Kind::semi_implicit_euler}, {"timestepping", Kind::timestepping}})
    .field("stages", &Method::stages, "int")
    .field("a", &Method::a, "list[float]")
    .field("b", &Method::b, "list[float]")
    .field("c", &Method::c, "list[float]")
    .field("chart_terms", &Method::chart_terms, "int")
    .optional("fsal", &Method::fsal, "bool")
    .optional("e", &Method::e, "list[float]")
    .optional("dense", &Method::dense, "list[float]")
    .optional("e5", &Method::e5, "list[float]")
    .optional("e3", &Method::e3, "list[float]")
    .optional("extended_stages", &Method::extended_stages, "int")
    .optional("a_extended", &Method::a_extended, "list[float]")
    .optional("c_extended", &Method::c_extended, "list[float]")
    .optional("dense_weights", &Method::dense_weights, "list[float]")
    .finish(check_method);
  Struct<ChartBlock>(m, "ChartBlock", "One curved block of the chart map (ConfigurationSpace.native_data()).")
    .field("start", &ChartBlock::start, "int")
    .field("size", &ChartBlock::d, "int")
    .field("index", &ChartBlock::index, "list[int]")
    .field("half_sign", &ChartBlock::half_sign, "list[float]")
    .finish([](ChartBlock & b) {
      const size_t n = static_cast<size_t>(b.d) * static_cast<size_t>(b.d);
      if (b.d < 1 || b.d > 6 || b.index.size() != n || b.half_sign.size() != n)
        throw std::invalid_argument("ChartBlock: index and half_sign must be size x size with 1 <= size <= 6");
    });
  Struct<Chart>(m, "Chart", "The configuration space's chart map (ConfigurationSpace.native_data()).")
    .field("blocks", &Chart::blocks, "list[ChartBlock]")
    .field("half_series", &Chart::half_series, "list[float]")
    .finish();
  Struct<ConstantStepData>(m, "ConstantStep", "Constant steps' constants (step_control.ConstantStep.native_data()).")
    .field("dt", &ConstantStepData::dt, "float")
    .field("sliver", &ConstantStepData::sliver, "float")
    .field("landing", &ConstantStepData::landing, "float")
    .finish();
  Struct<PIControllerData>(m, "PIController", "The PI controller's constants (PIController.native_data()).")
    .field("alpha", &PIControllerData::alpha, "float")
    .field("beta", &PIControllerData::beta, "float")
    .field("safety", &PIControllerData::safety, "float")
    .field("factor_min", &PIControllerData::factor_min, "float")
    .field("factor_max", &PIControllerData::factor_max, "float")
    .field("max_step", &PIControllerData::max_step, "float")
    .field("first_step", &PIControllerData::first_step, "float")
    .field("landing", &PIControllerData::landing, "float")
    .finish();
  Struct<Sampler>(m, "Sampler", "When the loop records samples (core.Sampler.native_data(); 0: none).")
    .field("every", &Sampler::every, "int")
    .field("period", &Sampler::period, "float")
    .finish([](Sampler & s) { s.present = true; });
  Struct<LoopState>(
    m, "LoopState",
    "What the Python side owns and the engine advances, in and out of advance(): the core's counts, the store's "
    "count, the sampler's next output, the step-size controller's state.")
    .field("steps", &LoopState::steps, "int")
    .field("rejected", &LoopState::rejected, "int")
    .field("evaluations", &LoopState::evaluations, "int")
    .field("recorded", &LoopState::recorded, "float")
    .field("count", &LoopState::count, "int")
    .field("full", &LoopState::full, "bool")
    .field("soft_capacity", &LoopState::soft_capacity, "float")
    .field("next_output", &LoopState::next_output, "int")
    .field("step_t0", &LoopState::step_t0, "float")
    .field("step_k", &LoopState::step_k, "int")
    .field("step_time", &LoopState::step_time, "float")
    .field("step_h", &LoopState::step_h, "float")
    .field("previous_error", &LoopState::previous_error, "float")
    .field("rejected_last", &LoopState::rejected_last, "bool")
    .finish();
  Struct<StoreArrays>(m, "Store", "The sample store's batch-major arrays (recording.STORE_ARRAYS).")
    .field("T", &StoreArrays::T, "a C-contiguous float64 array")
    .field("Q", &StoreArrays::Q, "a C-contiguous float64 array")
    .field("V", &StoreArrays::V, "a C-contiguous float64 array")
    .field("TAU", &StoreArrays::TAU, "a C-contiguous float64 array")
    .field("ENERGY", &StoreArrays::ENERGY, "a C-contiguous float64 array")
    .field("FLOWS", &StoreArrays::FLOWS, "a C-contiguous float64 array")
    .field("COUNTS", &StoreArrays::COUNTS, "a C-contiguous int64 array")
    .field("EXTRA", &StoreArrays::EXTRA, "a C-contiguous float64 array")
    .finish(check_store);

  nb::class_<StopEvent>(m, "StopEvent", "A row the engine stopped (core.RowStop's evidence).")
    .def_prop_ro("kind", [](const StopEvent & e) { return std::string(stop_name(e.code)); },
                 "\"diverged\", \"collapsed\" (an adaptive step) or \"control\" (a native controller's output)")
    .def_ro("row", &StopEvent::row)
    .def_ro("time", &StopEvent::time)
    .def_ro("step", &StopEvent::step, "the step that failed: the core's steps + 1 then")
    .def_ro("dof", &StopEvent::dof, "diverged: the first non-finite velocity coordinate")
    .def_ro("count", &StopEvent::count, "store.count when it stopped")
    .def_ro("added", &StopEvent::added, "whether a last sample was written for it at index count")
    .def_prop_ro("steps", [](const StopEvent & e) { return e.counts[0]; }, "its frozen step count")
    .def_prop_ro("rejected", [](const StopEvent & e) { return e.counts[1]; })
    .def_prop_ro("evaluations", [](const StopEvent & e) { return e.counts[2]; })
    .def_ro("h", &StopEvent::h, "collapsed: the step [s]")
    .def_ro("minimum", &StopEvent::minimum, "collapsed: the smallest step allowed [s]")
    .def_ro("error", &StopEvent::error, "collapsed: the error norm (NaN: not judged)");
  nb::class_<Advance>(m, "Advance", "What Kernel.advance() did.")
    .def_ro("status", &Advance::status)
    .def_ro("taken", &Advance::taken)
    .def_ro("need", &Advance::need);

  nb::class_<Engine>(m, "Kernel", "The native stepping kernel of one run (multibody_sim.kernels.native drives it).")
    .def(
      "__init__",
      [](Engine * self, const NativeModel & model, const Method & method, const Chart & chart,
         const std::variant<ConstantStepData, PIControllerData> & control, const Eigen::VectorXd & damping,
         int n_ledger, double rtol, double atol, const RowMatrix & Q0, const RowMatrix & V0, int num_threads) {
        Control c;
        if (const auto * fixed = std::get_if<ConstantStepData>(&control))
        {
          c.dt = fixed->dt;
          c.sliver = fixed->sliver;
          c.landing = fixed->landing;
        }
        else
        {
          const PIControllerData & pi = std::get<PIControllerData>(control);
          c.adaptive = true;
          c.alpha = pi.alpha;
          c.beta = pi.beta;
          c.safety = pi.safety;
          c.factor_min = pi.factor_min;
          c.factor_max = pi.factor_max;
          c.max_step = pi.max_step;
          c.first_step = pi.first_step;
          c.landing = pi.landing;
          c.rtol = rtol;
          c.atol = atol;
        }
        const pinocchio::Model & robot = model.model;
        if (Q0.cols() != robot.nq || V0.cols() != robot.nv || Q0.rows() != V0.rows() || damping.size() != robot.nv)
          throw std::invalid_argument("initial states or damping disagree with the model's sizes");
        new (self)
          Engine(robot, method, chart.blocks, chart.half_series, damping, n_ledger, c, Q0, V0, num_threads);
      },
      nb::arg("model"), nb::kw_only(), nb::arg("method"), nb::arg("chart"), nb::arg("control"), nb::arg("damping"),
      nb::arg("n_ledger"), nb::arg("rtol"), nb::arg("atol"), nb::arg("Q0"), nb::arg("V0"), nb::arg("num_threads"),
      "The engine of one run: the robot, its method, chart map and step-size controller (named structs), the "
      "damping (nv,), the ledger's size, the tolerances (adaptive methods), the rows' initial states (B, nq), "
      "(B, nv) and the threads the rows are split over.")
    .def(
      "advance",
      [](Engine & self, double t_stop, int64_t limit, double tolerance, LoopState & state, const StoreArrays & store,
         const Sampler * sampler, nb::list stops, nb::dict contacts, Ints rows, Ints extra_evaluations) {
        CoreState s;
        static_cast<LoopState &>(s) = state;
        s.t = self.t;
        s.instant = self.instant;
        s.last_control = self.last_control;
        const Sampler sampling = sampler ? *sampler : Sampler();
        const Store arrays = store_of(store);
        AdvanceResult result;
        {
          nb::gil_scoped_release release;
          result = self.advance(t_stop, limit, tolerance, sampling, arrays, s);
        }
        // The state comes back in `state` and the stops in `stops` before this call returns: no Python code runs
        // in between, so a signal handler (Ctrl-C) that runs when it returns never sees the work half recorded.
        self.t = s.t;
        self.instant = s.instant;
        self.last_control = s.last_control;
        state = s;
        for (const StopEvent & ev : result.stops)
          stops.append(nb::cast(ev));
        write_contacts(contacts, result.records);
        write_extra_evaluations(self, rows, extra_evaluations);
        return Advance{status_name(result.status), result.taken, result.need};
      },
      nb::arg("t_stop"), nb::arg("limit"), nb::arg("tolerance"), nb::kw_only(), nb::arg("state"), nb::arg("store"),
      nb::arg("sampler").none(), nb::arg("stops"), nb::arg("contacts"), nb::arg("rows"),
      nb::arg("extra_evaluations"),
      "Core.advance towards t_stop, at most `limit` accepted steps, with the landing `tolerance`: advances `state` "
      "(a LoopState) in place, appends the rows that stop to `stops` (StopEvent), their contacts to `contacts` "
      "(the store's dict) and the evaluations beyond the core's count of the running `rows` to "
      "`extra_evaluations`.")
    .def(
      "write_rows",
      [](Engine & self, int64_t i, std::vector<int64_t> rows, const StoreArrays & store, nb::dict contacts) {
        const Store arrays = store_of(store);
        if (i < 0 || i >= arrays.capacity)
          throw std::invalid_argument("sample index out of the store");
        for (int64_t b : rows)
          if (b < 0 || b >= arrays.B)
            throw std::invalid_argument("row out of the store");
        std::vector<ContactRecord> records = self.write_rows(i, rows, arrays);
        write_contacts(contacts, records);
      },
      nb::arg("i"), nb::arg("rows"), nb::kw_only(), nb::arg("store"), nb::arg("contacts"),
      "Write run rows `rows` as sample i of the store, their contacts into `contacts` (the store's dict).")
    .def(
      "set_contact",
      [](Engine & self, std::shared_ptr<ContactScene> contact, std::vector<bool> flow_work) {
        self.set_contact(contact, flow_work);
      },
      nb::arg("contact"), nb::arg("flow_work"),
      "A contact scene's geometry and constraints (_native.ContactScene) for the timestepping kind; flow_work: "
      "per ledger entry before the contact's four, whether it is work (else dissipated).")
    .def_prop_ro("has_contact", &Engine::has_contact)
    .def("contact_row", &Engine::contact_row)
    .def(
      "set_scene", [](Engine & self, std::shared_ptr<SceneForces> scene) { self.set_scene(scene); },
      nb::arg("scene"), "A scene's force elements (_native.SceneForces) join the dynamics (scene.cpp).")
    .def(
      "set_policies",
      [](Engine & self, std::shared_ptr<Policies> policies, Ints calls, Ints saturated, Ints saturated_dofs) {
        const size_t B = static_cast<size_t>(self.running());
        if (calls.size() != B || saturated.size() != B || saturated_dofs.size() != B * self.model().nv)
          throw std::invalid_argument("set_policies: the count arrays must have shapes (B,), (B,), (B, nv)");
        self.set_policies(policies, calls.data(), saturated.data(), saturated_dofs.data());
      },
      nb::arg("policies"), nb::arg("calls"), nb::arg("saturated"), nb::arg("saturated_dofs"),
      "Torques from native controllers at the control instants (scene.cpp); the count arrays stay alive for the "
      "run (kernels/native.py keeps them).")
    .def("set_torques", &Engine::set_torques)
    .def("keep", &Engine::keep)
    .def("running_rows", &Engine::running_rows)
    .def("running_q", &Engine::running_q)
    .def("running_v", &Engine::running_v)
    .def("flows_of", &Engine::flows_of)
    .def("set_state", &Engine::set_state)
    .def(
      "row_state",
      [](const Engine & self, int64_t row) {
        const auto [q, v, flows, tau, first, has_first] = self.snapshot_row(row);
        return std::make_tuple(q, v);
      },
      nb::arg("row"), "Run row `row`'s current (q, v).")
    .def("save", &Engine::save, "Keep every row's whole state (one copy, overwritten by the next save()).")
    .def("restore_saved", &Engine::restore_saved, "Return every row to the state of the last save().")
    .def_prop_ro("running", &Engine::running)
    .def_rw("t", &Engine::t);
}
