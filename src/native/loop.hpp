// core.Core.advance over one thread's rows: the step-size controllers (step_control.py), the samples (Core.record,
// Sampler.due, Core._dense_samples), the rows that stop (Core._note_stops: StopEvents), the built-in controllers at
// the control instants (driver.Run._control, natively) and the loop itself, each decision in the Python core's
// order. The arithmetic of each step is methods.hpp's. Included by engine.cpp only.
#pragma once

#include <algorithm>
#include <cmath>
#include <limits>
#include <new>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "measure.hpp"
#include "methods.hpp"

namespace multibody_sim
{
  struct Thread : Rows
  {
    using Rows::Rows;

    CoreState st;       // the core's state while this thread's rows advance (Engine::advance copies it in and out)
    AdvanceResult res;  // what this call did: status, stops, contact records

    // ---- samples: Core.record, Core._count, Core._record_stopping ------------------------------------------------
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
          select(j);  // the row's actuators give its delivered torques
          if (defer)
          {
            const int64_t at = store.at(i, rows[j]);
            write_state(store, at, q[j], v[j], tau[j], flows[j].data(), true);
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
        select(j);
        stamp(store, st.count, rows[j], st.t);
        note_contacts(st.count, j);
        write(store, st.count, rows[j], q[j], v[j], tau[j], flows[j].data());
      }
      return true;
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

    // How Python names a C++ library's exception (nanobind's translation), as TimeStepping.attempt words it.
    static std::string library_message(const std::exception & error)
    {
      const char * name = "RuntimeError";
      if (dynamic_cast<const std::invalid_argument *>(&error) || dynamic_cast<const std::domain_error *>(&error)
          || dynamic_cast<const std::length_error *>(&error) || dynamic_cast<const std::range_error *>(&error))
        name = "ValueError";
      else if (dynamic_cast<const std::out_of_range *>(&error))
        name = "IndexError";
      else if (dynamic_cast<const std::overflow_error *>(&error))
        name = "OverflowError";
      else if (dynamic_cast<const std::bad_alloc *>(&error))
        name = "MemoryError";
      return std::string(name) + " raised in the contact step: " + error.what();
    }

    std::vector<std::pair<size_t, std::string>> failures;  // this step's rows whose step threw
    std::vector<size_t> failed_rows;

    // Core._fail_rows: each failed row stops at the step's start, its state there its last sample; false when no
    // row is left running (Core.advance then returns EMPTY)
    bool fail_rows(const Store & store, double t)
    {
      failed_rows.clear();
      for (const auto & f : failures)
        failed_rows.push_back(f.first);
      const bool added = record_stopping(store, failed_rows);
      for (const auto & [j, message] : failures)
      {
        stop_event(STOP_FAILED, j, t, added, st.steps);
        res.stops.back().message = message;
        kill(j);
      }
      return n_alive > 0;
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
          failures.clear();
          for (size_t j = 0; j < rows.size(); ++j)
            if (alive[j])
            {
              try  // a library's exception fails this row's step, as in the Python kernel (TimeStepping.attempt)
              {
                evaluations = attempt_fixed(j, h, t);
              }
              catch (const std::exception & error)
              {
                failures.emplace_back(j, library_message(error));
                evaluations = 1;
              }
            }
          st.evaluations += evaluations;
          if (!failures.empty() && !fail_rows(store, t))
          {
            res.status = EMPTY;
            return;
          }
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
        if (e.sensors_)
          sense(h, t_next);
      }
    }

    // sensors.Ticks.after_step: the running rows whose tick ends this step of h (at t) measure their state now with
    // the step's acceleration (v+ - v) / h (vn holds v since the accept's swap), its contacts, and the torque delivered
    // under its command (Actuators.joint_torques at the tick's state; the command itself without actuators).
    void sense(double h, double t)
    {
      SensorWork & w = *sensw;
      for (size_t j = 0; j < rows.size(); ++j)
      {
        if (!alive[j] || (e.sensor_done_[static_cast<size_t>(rows[j])] + st.steps) % e.sensor_every_ != 0)
          continue;
        select(j);  // the row's model, actuators, contact and sensors
        const Sensors & sensors = *SS;
        w.a = (v[j] - vn[j]) / h;
        const Vec * delivered = &tau[j];  // the joint_torque sensors': the torque the actuators deliver at the tick
        if (A && e.sensor_torques_)
        {
          A->joint_torques(q[j], v[j], tau[j], nullptr, w.tau.data());
          delivered = &w.tau;
        }
        const size_t at = w.values.size();
        w.values.resize(at + static_cast<size_t>(sensors.width));
        const bool defer = w.deferrable && !e.control_.adaptive;
        measure_sensors(sensors, *M, w, q[j], v[j], w.a, *delivered, C ? &crow[j].active : nullptr, h,
                        w.values.data() + at, defer ? SensorPart::now : SensorPart::all);
        if (defer)
          w.defer(j, rows.size(), at, w.a);
        w.times.push_back(t);
        w.rows.push_back(rows[j]);
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
} // namespace multibody_sim
