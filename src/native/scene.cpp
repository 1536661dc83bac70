// A scene's force elements and the built-in controllers for the native kernel (see scene.hpp): each function
// names the Python code it renders, whose arithmetic it repeats in the same order.
#include "scene.hpp"
#include "model.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "pinocchio/algorithm/frames.hpp"
#include "pinocchio/algorithm/jacobian.hpp"
#include "pinocchio/algorithm/joint-configuration.hpp"
#include "pinocchio/algorithm/rnea.hpp"

namespace multibody_sim
{
  using Matrix6x = pinocchio::Data::Matrix6x;

  SceneWork::SceneWork(const pinocchio::Model & model, const SceneForces & scene)
  : data(model)
  , J(Matrix6x::Zero(6, model.nv))
  , unscaled(scene.wrenches.size(), Vec::Zero(model.nv))
  , scales(scene.wrenches.size(), 1.0)
  , zeros(Vec::Zero(model.nv))
  , u(std::max(scene.rough.size(), scene.ledger_rough.size()))
  , th(u.size())
  {
    for (const pinocchio::Model & push : scene.push_models)
      pushes.emplace_back(push);
  }

  std::unique_ptr<SceneWork> SceneForces::workspace(const pinocchio::Model & model) const
  {
    return std::unique_ptr<SceneWork>(new SceneWork(model, *this));
  }

  double WrenchTerm::scale(double t) const  // spec.ForceSpec.scale
  {
    if (shape == Shape::unit)
      return 1.0;
    if (t < start)
      return 0.0;
    if (shape == Shape::step)
      return 1.0;
    if (shape == Shape::ramp)
    {
      const double x = (t - start) / ramp_time;
      return 1.0 < x ? 1.0 : x;  // Python's min(x, 1.0)
    }
    return std::sin(2.0 * M_PI * frequency * (t - start) + phase);
  }

  void SceneForces::tanh(const double * x, double * out, std::intptr_t n) const
  {
    if (!tanh_loop.function)
    {
      for (std::intptr_t i = 0; i < n; ++i)
        out[i] = std::tanh(x[i]);
      return;
    }
    char * args[2] = {const_cast<char *>(reinterpret_cast<const char *>(x)), reinterpret_cast<char *>(out)};
    const std::intptr_t steps[2] = {sizeof(double), sizeof(double)};
    tanh_loop.function(args, &n, steps, tanh_loop.data);
  }

  double SceneForces::atan2(double y, double x) const
  {
    if (!atan2_loop.function)
      return std::atan2(y, x);
    double out = 0.0;
    char * args[3] = {reinterpret_cast<char *>(&y), reinterpret_cast<char *>(&x), reinterpret_cast<char *>(&out)};
    const std::intptr_t n = 1, steps[3] = {sizeof(double), sizeof(double), sizeof(double)};
    atan2_loop.function(args, &n, steps, atan2_loop.data);
    return out;
  }

  namespace
  {
    // np.arctan2(cr s - sr c, cr c + sr s): the angle of (c, s) from the rest angle, wrapped to (-π, π]
    inline double wrapped(const SceneForces & scene, const Vec & q, int ic, double cos_rest, double sin_rest)
    {
      const double c = q[ic], s = q[ic + 1];
      return scene.atan2(cos_rest * s - sin_rest * c, cos_rest * c + sin_rest * s);
    }
  } // namespace

  // ForceElements.evaluate (_joint_forces, then each wrench's part added in order)
  void SceneForces::forces(
    SceneWork & work, const pinocchio::Model & model, const Vec & q, const Vec & v, double t, Vec & out) const
  {
    if (zero_all)
      out.setZero();
    for (const SpringTerm & s : springs)
      out[s.dof] = (q[s.iq] - s.rest) * s.minus_k;
    for (const CircularTerm & s : circular)
      out[s.dof] = wrapped(*this, q, s.ic, s.cos_rest, s.sin_rest) * s.minus_k;
    for (const CoefficientTerm & d : damped)
      out[d.dof] = out[d.dof] - v[d.dof] * d.c;
    if (!rough.empty())
    {
      const size_t n = rough.size();
      for (size_t i = 0; i < n; ++i)
        work.u[i] = v[rough[i].dof] * inv_vs;
      tanh(work.u.data(), work.th.data(), static_cast<std::intptr_t>(n));
      for (size_t i = 0; i < n; ++i)
        out[rough[i].dof] = out[rough[i].dof] - work.th[i] * rough[i].c;
    }
    if (wrenches.empty())
      return;
    // elements._Push.forces: -rnea(q, 0, 0) of the point-mass model under the gravity f
    for (size_t k = 0; k < wrenches.size(); ++k)
    {
      const WrenchTerm & w = wrenches[k];
      if (w.push < 0)
        continue;
      const Vec & tau = pinocchio::rnea(
        push_models[w.push], work.pushes[w.push], q, work.zeros, work.zeros);
      Vec & f = work.unscaled[k];
      for (int i = 0; i < nv; ++i)
        f[i] = -tau[i];
    }
    // the others: wᵀ J with J the frame Jacobian (one frame: its support only; more: one kinematics pass)
    if (others.size() == 1)
    {
      const WrenchTerm & w = wrenches[others[0]];
      work.J.setZero();
      pinocchio::computeFrameJacobian(
        model, work.data, q, w.frame, w.local ? pinocchio::LOCAL : pinocchio::LOCAL_WORLD_ALIGNED, work.J);
    }
    else if (!others.empty())
      pinocchio::computeJointJacobians(model, work.data, q);
    for (int k : others)
    {
      const WrenchTerm & w = wrenches[k];
      if (others.size() > 1)
      {
        work.J.setZero();
        pinocchio::getFrameJacobian(
          model, work.data, w.frame, w.local ? pinocchio::LOCAL : pinocchio::LOCAL_WORLD_ALIGNED, work.J);
      }
      Vec & f = work.unscaled[k];
      for (int c = 0; c < nv; ++c)  // ordered.ordered_sum(w6, J)
      {
        double s = w.w6[0] * work.J(0, c);
        for (int r = 1; r < 6; ++r)
          s += w.w6[r] * work.J(r, c);
        f[c] = s;
      }
    }
    for (size_t k = 0; k < wrenches.size(); ++k)
    {
      const double scale = wrenches[k].scale(t);
      work.scales[k] = scale;
      const Vec & f = work.unscaled[k];
      if (scale == 1.0)
        for (int i = 0; i < nv; ++i)
          out[i] = out[i] + f[i];
      else
        for (int i = 0; i < nv; ++i)
          out[i] = out[i] + f[i] * scale;
    }
  }

  // ForceElements.powers (_joint_powers, then each wrench's work (Jᵀw)·v, ordered)
  void SceneForces::powers(SceneWork & work, const Vec & v, double * out) const
  {
    int i = 0;
    for (const CoefficientTerm & d : ledger_damped)
    {
      const double x = v[d.dof];
      out[i++] = x * x * d.c;
    }
    if (!ledger_rough.empty())
    {
      const size_t n = ledger_rough.size();
      for (size_t r = 0; r < n; ++r)
        work.u[r] = v[ledger_rough[r].dof] * inv_vs;
      tanh(work.u.data(), work.th.data(), static_cast<std::intptr_t>(n));
      for (size_t r = 0; r < n; ++r)
        out[i++] = v[ledger_rough[r].dof] * work.th[r] * ledger_rough[r].c;
    }
    for (size_t k = 0; k < wrenches.size(); ++k)
    {
      const Vec & f = work.unscaled[k];
      double s = f[0] * v[0];
      for (int c = 1; c < nv; ++c)
        s += f[c] * v[c];
      out[i++] = work.scales[k] == 1.0 ? s : s * work.scales[k];
    }
  }

  // ForceElements.potential_energies (and their ordered sum, as Scene.unchecked_energies adds it)
  double SceneForces::spring_energy(const Vec & q, double * record) const
  {
    double total = 0.0;
    for (size_t i = 0; i < energies.size(); ++i)
    {
      const SpringEnergy & s = energies[i];
      const double x = s.circular ? wrapped(*this, q, s.iq, s.cos_rest, s.sin_rest) : q[s.iq] - s.rest;
      const double e = 0.5 * s.k * x * x;
      if (record)
        record[i] = e;
      total = i ? total + e : e;
    }
    return total;
  }

  // ---- controllers ------------------------------------------------------------------------------------------
  std::unique_ptr<PolicyWork> Policies::workspace(const pinocchio::Model & model) const
  {
    return std::unique_ptr<PolicyWork>(new PolicyWork(model));
  }

  double Policies::instant(int64_t j) const  // driver.RunSettings.control_instant
  {
    if (adaptive)
    {
      const double t = static_cast<double>(j) * period;
      return duration < t ? duration : t;  // Python's min(duration, t)
    }
    const int64_t k = j * every;
    return k < n_steps ? static_cast<double>(k) * dt : duration;
  }

  bool Policies::torque(
    PolicyWork & work, const pinocchio::Model & model, int64_t row, int64_t j, const Vec & q, const Vec & v,
    Vec & tau) const
  {
    if (taus)  // Torques.compute: taus[rows, min(instant, n - 1)]
    {
      const double * x = taus + (row * n_taus + std::min<int64_t>(j, n_taus - 1)) * nv;
      for (int i = 0; i < nv; ++i)
        tau[i] = x[i];
      return true;
    }
    const Policy & p = rows[static_cast<size_t>(row)];
    if (p.kind != PolicyKind::gravity)  // PD.__call__
    {
      pinocchio::difference(model, q, p.q_ref, work.error);
      tau.setZero();
      for (int i = a_start; i < a_stop; ++i)
        tau[i] = p.kp[i - a_start] * work.error[i] + p.kd[i - a_start] * (p.v_ref[i] - v[i]);
    }
    if (p.kind != PolicyKind::pd)  // GravityCompensation.__call__ (PDGravity: pd + gravity)
    {
      const Vec & g = pinocchio::computeGeneralizedGravity(model, work.data, q);
      if (p.kind == PolicyKind::gravity)
        for (int i = 0; i < nv; ++i)
          tau[i] = (i < a_start || i >= a_stop) ? 0.0 : g[i];
      else
        for (int i = 0; i < nv; ++i)
          tau[i] = tau[i] + ((i < a_start || i >= a_stop) ? 0.0 : g[i]);
    }
    return tau.allFinite();
  }

  namespace
  {
    // np.maximum and np.minimum of two numbers: NaN if either is; of equal numbers (0 and -0) the second
    inline double np_maximum(double a, double b)
    {
      return (a > b || a != a) ? a : b;
    }
    inline double np_minimum(double a, double b)
    {
      return (a < b || a != a) ? a : b;
    }
  } // namespace

  void Policies::clip(Vec & tau, int64_t * dofs, bool & clipped) const  // torques.Saturation.apply
  {
    clipped = false;
    if (!saturate)
      return;
    for (int i = 0; i < nv; ++i)
      if (low[i] > tau[i] || high[i] < tau[i])
      {
        clipped = true;
        dofs[i] += 1;
      }
    if (clipped)
      for (int i = 0; i < nv; ++i)  // np.minimum(np.maximum(tau, low), high)
        tau[i] = np_minimum(np_maximum(tau[i], low[i]), high[i]);
  }

  // ---- actuators: scenes/actuators.py's Actuators, one actuator at a time in its arithmetic ----------------------
  void SceneActuators::evaluate(const ActuatorTerm & a, const Vec & q, const Vec & v, const Vec & u, double & law,
                                double & tau) const
  {
    law = this->law(a, q, v, u);
    double low, high;
    interval(a, v[a.dof], low, high);
    tau = np_minimum(np_maximum(law, low), high);
  }

  double SceneActuators::law(const ActuatorTerm & a, const Vec & q, const Vec & v, const Vec & u) const
  {
    const double w = v[a.dof];
    switch (a.kind)
    {
      case ActuatorKind::position:
        return a.kp * (u[a.dof] - q[a.iq]) - a.kv * w;
      case ActuatorKind::velocity:
        return a.kv * (u[a.dof] - w);
      default:
        return u[a.dof];
    }
  }

  void SceneActuators::prepare(int nv_, int nq)
  {
    nv = nv_;
    servos = false;
    n_limited = n_braked = 0;
    constexpr double inf = std::numeric_limits<double>::infinity();
    for (ActuatorTerm & a : terms)
    {
      if (!(0 <= a.dof && a.dof < nv && 0 <= a.iq && a.iq < nq))
        throw std::invalid_argument("SceneActuators: an actuator's dof or coordinate out of range");
      a.servo = a.kind != ActuatorKind::torque;
      a.curve = std::isfinite(a.stall);
      a.speed_limited = std::isfinite(a.velocity_limit);
      a.braked = a.brake_gain > 0.0;
      // With |w| < (1 - band) v_max / 2 the brake's upper bound k (v_max - w) >= effort (1 + band) / (2 band),
      // above the limits' high (at most the effort limit) with a margin round-off cannot cross while the band
      // is at most 0.9; the lower bound likewise: Actuators._interval's clamps change nothing there, and _select
      // finds no torque on a brake's bound.
      const double start = a.braked ? a.velocity_limit - a.effort / a.brake_gain : 0.0;
      a.brake_from = start >= 0.1 * a.velocity_limit ? 0.5 * start : 0.0;
      // The curve stall (1 - s / no_load) stays above the effort limit, by at least half their difference (with
      // stall >= 1.001 effort: far beyond round-off), for s below half its knee no_load (1 - effort / stall); the
      // drive limit is then the effort limit itself (np.minimum of it and a larger number).
      double plain = inf;
      if (a.curve)
        plain = a.stall >= 1.001 * a.effort ? 0.5 * (a.no_load * (1.0 - a.effort / a.stall)) : 0.0;
      if (a.speed_limited)
        plain = std::min(plain, a.velocity_limit);  // below it: speed >= velocity_limit is false
      if (a.braked)
        plain = std::min(plain, a.brake_from);
      a.plain_below = plain >= 0.0 ? plain : 0.0;  // (NaN: 0)
      servos = servos || a.servo || a.braked;
      n_limited += a.limited ? 1 : 0;
      n_braked += a.braked ? 1 : 0;
    }
  }

  void SceneActuators::limits(const ActuatorTerm & a, double w, double & low, double & high) const
  {
    if (std::abs(w) < a.plain_below)  // (NaN: no) the curve and the velocity limit cut nothing here (prepare())
    {
      low = -a.effort;
      high = a.effort;
      return;
    }
    double drive = a.effort;
    const double speed = std::abs(w);
    if (a.curve)
      drive = np_minimum(drive, a.stall * np_maximum(0.0, 1.0 - speed / a.no_load));
    if (a.speed_limited && speed >= a.velocity_limit)
      drive = 0.0;
    low = w > 0.0 ? -a.effort : -drive;
    high = w < 0.0 ? a.effort : drive;
  }

  void SceneActuators::brakes(const ActuatorTerm & a, double w, double & upper, double & lower) const
  {
    const double limit = a.braked ? a.velocity_limit : 0.0;
    upper = a.brake_gain * (limit - w);
    lower = -(a.brake_gain * (limit + w));
  }

  namespace
  {
    // Actuators._interval's second half: the limits (low, high) within the brake's bounds (upper, lower)
    void within_brake(const ActuatorTerm & a, double upper, double lower, double & low, double & high)
    {
      high = np_maximum(-a.effort, np_minimum(high, upper));
      low = np_minimum(a.effort, np_maximum(low, lower));
    }
  } // namespace

  void SceneActuators::interval(const ActuatorTerm & a, double w, double & low, double & high) const
  {
    limits(a, w, low, high);
    if (a.braked && !(std::abs(w) < a.brake_from))
    {
      double upper, lower;
      brakes(a, w, upper, lower);
      within_brake(a, upper, lower, low, high);
    }
  }

  namespace
  {
    // Whether an actuator's brake's bound on `side` (upper, lower: brakes()) lies beyond its effort limit
    bool beyond_effort(const ActuatorTerm & a, double upper, double lower, int side)
    {
      return side > 0 ? !(upper > -a.effort) : !(lower < a.effort);
    }
  } // namespace

  // Actuators._select for one actuator: its limits and its brake's bounds evaluated once; brake: clipped at its
  // brake's bound within ± the effort limit, saturated: clipped at its brake's bound beyond it
  void SceneActuators::select(const ActuatorTerm & a, double law, double w, bool & within, bool & brake,
                              bool & saturated, int & side, double & low, double & high) const
  {
    limits(a, w, low, high);
    const double limit_low = low, limit_high = high;
    double upper = 0.0, lower = 0.0;
    // below plain_below the brake's bounds cut nothing and hold no torque (prepare()): not evaluated
    const bool braked = a.braked && !(std::abs(w) < a.plain_below);
    if (braked)
    {
      brakes(a, w, upper, lower);
      if (!(std::abs(w) < a.brake_from))  // as interval()
        within_brake(a, upper, lower, low, high);
    }
    within = law >= low && law <= high;
    side = law > high ? 1 : -1;
    brake = saturated = false;
    if (braked && !within && (side > 0 ? upper < limit_high : lower > limit_low))
    {
      saturated = beyond_effort(a, upper, lower, side);
      brake = !saturated;
    }
  }

  void SceneActuators::joint_torques(const Vec & q, const Vec & v, const Vec & u, const ServoStep * step,
                                     double * out) const
  {
    for (int i = 0; i < nv; ++i)
      out[i] = u[i];
    const ActuatorTerm * a = terms.data();
    const size_t n = terms.size();
    if (step && step->active)
    {
      const double * held = step->held.data();
      for (size_t k = 0; k < n; ++k)
        out[a[k].dof] = held[k];
      return;
    }
    double law, tau;
    for (size_t k = 0; k < n; ++k)
    {
      evaluate(a[k], q, v, u, law, tau);
      out[a[k].dof] = tau;
    }
  }

  void SceneActuators::powers(const Vec & q, const Vec & v, const Vec & u, double * out) const
  {
    torques_and_powers(q, v, u, nullptr, out);
  }

  void SceneActuators::torques_and_powers(const Vec & q, const Vec & v, const Vec & u, double * torques,
                                         double * flows) const
  {
    if (torques)
      for (int i = 0; i < nv; ++i)
        torques[i] = u[i];
    const size_t n = terms.size();
    size_t m = n, b = n + static_cast<size_t>(n_limited);
    double low, high;
    for (size_t k = 0; k < n; ++k)
    {
      const ActuatorTerm & a = terms[k];
      const double c = law(a, q, v, u);
      const double w = v[a.dof];
      flows[k] = c * w;
      if (std::abs(w) < a.plain_below)  // (rk4's four stages: the interval ± the effort limit, the brake idle)
      {
        const double limited = np_minimum(np_maximum(c, -a.effort), a.effort);
        if (a.limited)
          flows[m++] = (c - limited) * w;
        if (a.braked)  // the brake's torque is the limited one itself: (limited - tau) w as below
          flows[b++] = (limited - limited) * w;
        if (torques)
          torques[a.dof] = limited;
        continue;
      }
      limits(a, w, low, high);
      const double limited = np_minimum(np_maximum(c, low), high);  // evaluate's torque without a brake
      if (a.limited)
        flows[m++] = (c - limited) * w;
      double tau = limited;
      if (a.braked)  // evaluate's interval: the limits within the brake's bounds from brake_from on
      {
        if (!(std::abs(w) < a.brake_from))  // (below it the clamps leave the limits: tau is `limited`)
        {
          double upper, lower;
          brakes(a, w, upper, lower);
          within_brake(a, upper, lower, low, high);
          tau = np_minimum(np_maximum(c, low), high);
        }
        flows[b++] = (limited - tau) * w;
      }
      if (torques)
        torques[a.dof] = tau;
    }
  }

  ServoStep SceneActuators::workspace() const
  {
    const size_t n = terms.size();
    ServoStep step;
    step.law.assign(n, 0.0);
    step.w.assign(n, 0.0);
    step.held.assign(n, 0.0);
    step.clipped.assign(n, 0.0);
    step.saved.assign(n, 0.0);
    step.side.assign(n, 1);
    step.free.assign(n, 0);
    step.braking.assign(n, 0);
    for (auto * x : {&step.law_next, &step.low, &step.high})
      x->assign(n, 0.0);
    for (auto * x : {&step.ok, &step.within, &step.brake, &step.beyond})
      x->assign(n, 0);
    step.side_next.assign(n, 1);
    return step;
  }

  void SceneActuators::begin(ServoStep & step, const Vec & q, const Vec & v, const Vec & u, double h,
                             Vec & armature) const
  {
    step.h = h;
    step.iterations = 0;
    bool within, brake, saturated;
    double low, high;
    // the step's arrays through local pointers: stores to the char arrays may alias anything, and would make the
    // compiler reload each vector's data pointer at every actuator
    const size_t n = terms.size();
    const ActuatorTerm * terms_ = terms.data();
    double *law_ = step.law.data(), *w_ = step.w.data(), *saved = step.saved.data(), *clipped = step.clipped.data();
    int * side = step.side.data();
    char *free_ = step.free.data(), *braking = step.braking.data();
    double * arm = armature.data();
    for (size_t k = 0; k < n; ++k)
    {
      const ActuatorTerm & a = terms_[k];
      const double c = law(a, q, v, u), w = v[a.dof];
      law_[k] = c;
      w_[k] = w;
      saved[k] = arm[a.dof];
      select(a, c, w, within, brake, saturated, side[k], low, high);
      free_[k] = a.servo && within;
      braking[k] = brake || saturated;  // on its line even beyond the effort limit: it may reach its band
      clipped[k] = np_minimum(np_maximum(c, low), high);
    }
    step.active = true;
    hold(step, armature);
  }

  void SceneActuators::hold(ServoStep & step, Vec & armature) const
  {
    const double h = step.h;
    const size_t n = terms.size();
    const ActuatorTerm * terms_ = terms.data();  // (local pointers, as in begin())
    const double *law = step.law.data(), *w = step.w.data(), *saved = step.saved.data();
    const double * clipped = step.clipped.data();
    const int * side = step.side.data();
    const char *free_ = step.free.data(), *braking = step.braking.data();
    double *held = step.held.data(), *arm = armature.data();
    for (size_t k = 0; k < n; ++k)
    {
      const ActuatorTerm & a = terms_[k];
      if (free_[k])
      {
        const double hkp = h * a.kp;
        arm[a.dof] = saved[k] + (h * a.kv + h * hkp);
        held[k] = law[k] - hkp * w[k];
      }
      else if (braking[k])
      {
        double upper, lower;
        brakes(a, w[k], upper, lower);
        arm[a.dof] = saved[k] + h * a.brake_gain;
        held[k] = side[k] > 0 ? upper : lower;
      }
      else
      {
        arm[a.dof] = saved[k] + 0.0;  // (as np.where's 0: -0 becomes +0)
        held[k] = clipped[k];
      }
    }
  }

  bool SceneActuators::revise(ServoStep & step, const Vec & v_next, Vec & armature) const
  {
    const size_t n = terms.size();
    const double h = step.h;
    bool consistent = true;
    std::vector<double> &law_next = step.law_next, &low = step.low, &high = step.high;
    std::vector<char> &ok = step.ok, &within = step.within, &brake = step.brake, &beyond = step.beyond;
    std::vector<int> & side = step.side_next;
    {
      const ActuatorTerm * terms_ = terms.data();  // (local pointers, as in begin())
      const double *law = step.law.data(), *w_ = step.w.data(), *vn = v_next.data();
      const int * side_ = step.side.data();
      const char *free_ = step.free.data(), *braking = step.braking.data();
      double *law_next_ = law_next.data(), *low_ = low.data(), *high_ = high.data();
      char *ok_ = ok.data(), *within_ = within.data(), *brake_ = brake.data(), *beyond_ = beyond.data();
      int * side_next = side.data();
      for (size_t k = 0; k < n; ++k)
      {
        const ActuatorTerm & a = terms_[k];
        const double w = w_[k], wn = vn[a.dof];
        // A torque actuator held at its clipped torque stays consistent unless its torque lands on a brake's
        // bound, which select() finds nowhere below brake_from (prepare()): its law and interval are not needed
        if (!a.servo && !braking[k] && (!a.braked || std::abs(wn) < a.brake_from))
        {
          ok_[k] = 1;
          continue;
        }
        const double c = law[k] - (h * a.kp) * w - (h * a.kp + a.kv) * (wn - w);  // the law at the step's end
        law_next_[k] = c;
        bool in, on_brake, beyond_effort;
        double lo, hi;
        int s;
        select(a, c, wn, in, on_brake, beyond_effort, s, lo, hi);
        low_[k] = lo;
        high_[k] = hi;
        side_next[k] = s;
        within_[k] = in;
        brake_[k] = on_brake;
        const bool past = side_[k] > 0 ? c >= hi : c <= lo;
        beyond_[k] = past;
        const bool fine = free_[k] ? in : braking[k] ? on_brake && s == side_[k] : !on_brake && (!a.servo || past);
        ok_[k] = fine;
        consistent = consistent && fine;
      }
    }
    if (consistent || step.iterations >= max_revisions)
      return false;
    step.iterations += 1;
    for (size_t k = 0; k < n; ++k)
    {
      if (ok[k])
        continue;
      const ActuatorTerm & a = terms[k];
      const bool servo = a.servo;
      // a brake beyond the effort limit at the start that did not land on its line: held at the effort limit
      bool stays = false;
      if (step.braking[k])
      {
        double upper, lower;
        brakes(a, step.w[k], upper, lower);
        stays = beyond_effort(a, upper, lower, step.side[k]);
      }
      const bool freed = servo && !step.free[k] && !step.braking[k] && !beyond[k];
      step.free[k] = !stays && (freed || (servo && within[k]));
      step.braking[k] = !stays && brake[k] && !freed;
      if (!stays)
        step.side[k] = side[k];
      if (!step.free[k] && !step.braking[k])  // clipped at the step's end: held at its interval's bound there
        step.clipped[k] = np_minimum(np_maximum(law_next[k], low[k]), high[k]);
      if (stays)
        step.clipped[k] = -step.side[k] * a.effort;
    }
    hold(step, armature);
    return true;
  }

  void SceneActuators::clipped_torques(const ServoStep & step, const Vec & u, double * out) const
  {
    for (int i = 0; i < nv; ++i)
      out[i] = u[i];
    const ActuatorTerm * a = terms.data();
    const double * clipped = step.clipped.data();
    for (size_t k = 0; k < terms.size(); ++k)
      out[a[k].dof] = clipped[k];
  }

  void SceneActuators::end(ServoStep & step, Vec & armature) const
  {
    if (!step.active)
      return;
    for (size_t k = 0; k < terms.size(); ++k)
      armature[terms[k].dof] = step.saved[k];
    step.active = false;
  }
} // namespace multibody_sim

// ---- Python bindings: _native.SceneForces, _native.Policies and their terms (kernels/native.py is their user) ----
#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/array.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/vector.h>

#define NO_IMPORT_ARRAY
#define NO_IMPORT_UFUNC
#define NPY_NO_DEPRECATED_API NPY_1_7_API_VERSION
#include <numpy/ndarraytypes.h>
#include <numpy/ufuncobject.h>

#include "model.hpp"
#include "structs.hpp"

namespace nb = nanobind;

namespace
{
  // numpy.<name>'s inner loop over float64 arguments only (its public PyUFuncObject fields); none: the C library's
  multibody_sim::NumpyLoop numpy_loop(const char * name)
  {
    multibody_sim::NumpyLoop loop;
    nb::object ufunc = nb::module_::import_("numpy").attr(name);
    if (std::string(Py_TYPE(ufunc.ptr())->tp_name) != "numpy.ufunc")
      return loop;
    const PyUFuncObject * u = reinterpret_cast<const PyUFuncObject *>(ufunc.ptr());
    for (int i = 0; i < u->ntypes; ++i)
    {
      bool doubles = true;
      for (int k = 0; k < u->nargs; ++k)
        doubles = doubles && u->types[i * u->nargs + k] == NPY_DOUBLE;
      if (doubles)
      {
        loop.function = reinterpret_cast<multibody_sim::NumpyLoop::Function>(u->functions[i]);
        loop.data = u->data[i];
        return loop;
      }
    }
    return loop;
  }
} // namespace

void multibody_sim::bind_scene(nb::module_ & m)  // called by module.cpp
{
  using namespace multibody_sim;
  // ---- a scene's force elements: ForceElements.native_data()
  Struct<SpringTerm>(m, "SpringTerm", "out[dof] = (q[iq] - rest) * minus_k")
    .field("dof", &SpringTerm::dof, "int")
    .field("iq", &SpringTerm::iq, "int")
    .field("rest", &SpringTerm::rest, "float")
    .field("minus_k", &SpringTerm::minus_k, "float")
    .finish();
  Struct<CircularTerm>(m, "CircularTerm", "out[dof] = wrapped angle from the rest angle * minus_k (continuous joint)")
    .field("dof", &CircularTerm::dof, "int")
    .field("ic", &CircularTerm::ic, "int")
    .field("cos_rest", &CircularTerm::cos_rest, "float")
    .field("sin_rest", &CircularTerm::sin_rest, "float")
    .field("minus_k", &CircularTerm::minus_k, "float")
    .finish();
  Struct<CoefficientTerm>(m, "CoefficientTerm", "A damping (c = d) or friction (c = F_c) coefficient on dof.")
    .field("dof", &CoefficientTerm::dof, "int")
    .field("c", &CoefficientTerm::c, "float")
    .finish();
  Struct<WrenchTerm>(m, "WrenchTerm", "A wrench on a frame, with its declared shape in time (spec.ForceSpec.scale).")
    .field("push", &WrenchTerm::push, "int")
    .field("frame", &WrenchTerm::frame, "int")
    .field("local", &WrenchTerm::local, "bool")
    .field("w6", &WrenchTerm::w6, "6 floats")
    .choice("shape", &WrenchTerm::shape,
            {{"constant", Shape::unit}, {"step", Shape::step}, {"ramp", Shape::ramp}, {"sine", Shape::sine}})
    .field("start", &WrenchTerm::start, "float")
    .field("ramp_time", &WrenchTerm::ramp_time, "float")
    .field("frequency", &WrenchTerm::frequency, "float")
    .field("phase", &WrenchTerm::phase, "float")
    .finish();
  Struct<SpringEnergy>(m, "SpringEnergy", "A spring's stored energy ½ k x² (x: q[iq] - rest, or the wrapped angle).")
    .field("circular", &SpringEnergy::circular, "bool")
    .field("iq", &SpringEnergy::iq, "int")
    .field("rest", &SpringEnergy::rest, "float")
    .field("cos_rest", &SpringEnergy::cos_rest, "float")
    .field("sin_rest", &SpringEnergy::sin_rest, "float")
    .field("k", &SpringEnergy::k, "float")
    .finish();

  auto forces = std::make_shared<Fields<SceneForces>>("SceneForces");
  forces->member("zero_all", &SceneForces::zero_all, "bool")
    .member("inv_vs", &SceneForces::inv_vs, "float")
    .member("springs", &SceneForces::springs, "list[SpringTerm]")
    .member("circular", &SceneForces::circular, "list[CircularTerm]")
    .member("damped", &SceneForces::damped, "list[CoefficientTerm]")
    .member("rough", &SceneForces::rough, "list[CoefficientTerm]")
    .member("ledger_damped", &SceneForces::ledger_damped, "list[CoefficientTerm]")
    .member("ledger_rough", &SceneForces::ledger_rough, "list[CoefficientTerm]")
    .member("wrenches", &SceneForces::wrenches, "list[WrenchTerm]")
    .custom("push_models",
            [](SceneForces & self, nb::handle value) {
              std::vector<const NativeModel *> models;
              Fields<SceneForces>::cast_into(models, value, "SceneForces.push_models", "list[Model]");
              for (const NativeModel * push : models)
              {
                if (!push)
                  throw nb::type_error("SceneForces.push_models: expected list[Model], got None");
                self.push_models.push_back(push->model);
              }
            })
    .member("energies", &SceneForces::energies, "list[SpringEnergy]");
  nb::class_<SceneForces>(m, "SceneForces", "A scene's force elements (scenes/elements.py), for the native kernel.")
    .def(
      "__init__",
      [forces](SceneForces * self, const NativeModel & model, nb::kwargs kwargs) {
        SceneForces s = forces->parse(kwargs);
        const pinocchio::Model & robot = model.model;
        const int nv = robot.nv, nq = robot.nq;
        const auto check = [](bool ok, const char * what) {
          if (!ok)
            throw std::invalid_argument(std::string("SceneForces: ") + what + " out of range");
        };
        s.nv = nv;
        s.tanh_loop = numpy_loop("tanh");
        s.atan2_loop = numpy_loop("arctan2");
        for (const SpringTerm & t : s.springs)
          check(0 <= t.dof && t.dof < nv && 0 <= t.iq && t.iq < nq, "a spring's dof or coordinate");
        for (const CircularTerm & t : s.circular)
          check(0 <= t.dof && t.dof < nv && 0 <= t.ic && t.ic + 1 < nq, "a continuous spring's dof or coordinate");
        for (const auto * terms : {&s.damped, &s.rough, &s.ledger_damped, &s.ledger_rough})
          for (const CoefficientTerm & t : *terms)
            check(0 <= t.dof && t.dof < nv, "a damping or friction dof");
        for (const pinocchio::Model & push : s.push_models)
          check(push.nq == nq && push.nv == nv, "a point-mass model");
        s.others.clear();
        for (size_t k = 0; k < s.wrenches.size(); ++k)
        {
          const WrenchTerm & w = s.wrenches[k];
          check(w.push < static_cast<int>(s.push_models.size()), "a wrench's point-mass model");
          check(0 <= w.frame && w.frame < static_cast<int>(robot.nframes), "a wrench's frame");
          if (w.push < 0)
            s.others.push_back(static_cast<int>(k));
        }
        for (const SpringEnergy & e : s.energies)
          check(0 <= e.iq && e.iq + (e.circular ? 1 : 0) < nq, "a spring's coordinate");
        new (self) SceneForces(std::move(s));
      },
      nb::arg("model"), nb::arg("kwargs"),
      "From the scene's model and the elements' named data (ForceElements.native_data()).")
    .def_ro("springs", &SceneForces::springs)
    .def_ro("wrenches", &SceneForces::wrenches)
    .def_prop_ro("n_flows", &SceneForces::n_flows)
    .def_prop_ro("n_records", &SceneForces::n_records)
    .def_prop_ro(
      "numpy_functions",
      [](const SceneForces & self) { return self.tanh_loop.function != nullptr && self.atan2_loop.function != nullptr; },
      "Whether tanh and arctan2 are NumPy's own loops (else the C library's: agreement to round-off only).")
    .def(
      "evaluate",
      [](const SceneForces & self, NativeModel & model, const Vec & q, const Vec & v, double t) {
        if (q.size() != model.model.nq || v.size() != model.model.nv || model.model.nv != self.nv)
          throw std::invalid_argument("evaluate: q, v must have nq, nv entries of the scene's model");
        std::unique_ptr<SceneWork> work = self.workspace(model.model);
        Vec out = Vec::Zero(self.nv);
        self.forces(*work, model.model, q, v, t, out);
        Vec flows = Vec::Zero(self.n_flows());
        self.powers(*work, v, flows.data());
        Vec record = Vec::Zero(self.n_records());
        const double total = self.spring_energy(q, record.data());
        return nb::make_tuple(out, flows, record, total);
      },
      nb::arg("model"), nb::arg("q"), nb::arg("v"), nb::arg("t"),
      "(force (nv,), ledger powers, spring energies, their sum) at (q, v, t): the kernel's arithmetic, for tests.")
    .attr("fields") = forces->names();

  // ---- the torques at control instants: kernels/native.native_policies() and the controllers' native_data()
  Struct<Policy>(m, "Policy", "One row's built-in controller (PD, GravityCompensation, PDGravity .native_data()).")
    .choice("kind", &Policy::kind,
            {{"pd", PolicyKind::pd}, {"gravity", PolicyKind::gravity}, {"pd_gravity", PolicyKind::pd_gravity}})
    .field("q_ref", &Policy::q_ref, "an array of nq floats")
    .field("v_ref", &Policy::v_ref, "an array of nv floats")
    .field("kp", &Policy::kp, "an array of floats, one per actuated dof")
    .field("kd", &Policy::kd, "an array of floats, one per actuated dof")
    .finish();
  auto policies = std::make_shared<Fields<Policies>>("Policies");
  policies->member("nv", &Policies::nv, "int")
    .member("a_start", &Policies::a_start, "int")
    .member("a_stop", &Policies::a_stop, "int")
    .member("rows", &Policies::rows, "list[Policy]")
    .custom("taus",
            [](Policies & self, nb::handle value) {
              using Taus = nb::ndarray<double, nb::c_contig, nb::device::cpu>;
              Taus taus;
              Fields<Policies>::cast_into(taus, value, "Policies.taus", "a C-contiguous float64 array");
              if (taus.ndim() == 3 && taus.shape(0) > 0)
              {
                if (taus.shape(1) == 0)
                  throw std::invalid_argument("Policies.taus must have shape (B, n_control, nv)");
                self.taus = taus.data();  // kept alive by the caller for the run (kernels/native.py)
                self.n_taus = static_cast<int64_t>(taus.shape(1));
                self.taus_width = static_cast<int64_t>(taus.shape(2));
              }
            })
    .member("low", &Policies::low, "an array of nv floats")
    .member("high", &Policies::high, "an array of nv floats")
    .member("saturate", &Policies::saturate, "bool")
    .member("adaptive", &Policies::adaptive, "bool")
    .member("every_step", &Policies::every_step, "bool")
    .member("dt", &Policies::dt, "float")
    .member("duration", &Policies::duration, "float")
    .member("period", &Policies::period, "float")
    .member("every", &Policies::every, "int")
    .member("n_steps", &Policies::n_steps, "int");
  nb::class_<Policies>(m, "Policies", "Built-in controllers or open-loop torques at control instants (native).")
    .def(
      "__init__",
      [policies](Policies * self, nb::kwargs kwargs) {
        Policies p = policies->parse(kwargs);
        const int nv = p.nv, n = p.a_stop - p.a_start;
        if (!(0 <= p.a_start && p.a_start <= p.a_stop && p.a_stop <= nv) || p.low.size() != nv || p.high.size() != nv)
          throw std::invalid_argument("Policies: actuated range or command bounds out of range");
        if (p.taus && p.taus_width != nv)
          throw std::invalid_argument("Policies.taus must have shape (B, n_control, nv)");
        for (const Policy & row : p.rows)
          if (row.v_ref.size() != nv || row.kp.size() != n || row.kd.size() != n)
            throw std::invalid_argument("Policies: a controller's data disagree with the model's sizes");
        new (self) Policies(std::move(p));
      },
      nb::arg("kwargs"),
      "taus (B, n_control, nv) must stay alive as long as the kernel runs (kernels/native.py keeps it).")
    .attr("fields") = policies->names();

  // ---- a scene's actuators: Actuators.native_data()
  Struct<ActuatorTerm>(m, "ActuatorTerm", "One joint's actuator (scenes/actuators.Actuator); inf: no such limit.")
    .field("dof", &ActuatorTerm::dof, "int")
    .field("iq", &ActuatorTerm::iq, "int")
    .choice("kind", &ActuatorTerm::kind,
            {{"torque", ActuatorKind::torque}, {"position", ActuatorKind::position}, {"velocity", ActuatorKind::velocity}})
    .field("kp", &ActuatorTerm::kp, "float")
    .field("kv", &ActuatorTerm::kv, "float")
    .field("effort", &ActuatorTerm::effort, "float")
    .field("velocity_limit", &ActuatorTerm::velocity_limit, "float")
    .field("stall", &ActuatorTerm::stall, "float")
    .field("no_load", &ActuatorTerm::no_load, "float")
    .field("limited", &ActuatorTerm::limited, "bool")
    .field("brake_gain", &ActuatorTerm::brake_gain, "float")
    .finish();
  auto actuators = std::make_shared<Fields<SceneActuators>>("SceneActuators");
  actuators->member("terms", &SceneActuators::terms, "list[ActuatorTerm]")
    .member("max_revisions", &SceneActuators::max_revisions, "int");
  nb::class_<SceneActuators>(m, "SceneActuators", "A scene's actuators (scenes/actuators.py), for the native kernel.")
    .def(
      "__init__",
      [actuators](SceneActuators * self, const NativeModel & model, nb::kwargs kwargs) {
        SceneActuators s = actuators->parse(kwargs);
        s.prepare(model.model.nv, model.model.nq);
        new (self) SceneActuators(std::move(s));
      },
      nb::arg("model"), nb::arg("kwargs"), "From the scene's model and the actuators' named data.")
    .def_prop_ro("n_flows", &SceneActuators::n_flows)
    .def(
      "evaluate",
      [](const SceneActuators & self, const Vec & q, const Vec & v, const Vec & u) {
        if (v.size() != self.nv || u.size() != self.nv)
          throw std::invalid_argument("evaluate: v and u must have nv entries");
        Vec torques = Vec::Zero(self.nv);
        self.joint_torques(q, v, u, nullptr, torques.data());
        Vec flows = Vec::Zero(self.n_flows());
        self.powers(q, v, u, flows.data());
        return nb::make_tuple(torques, flows);
      },
      nb::arg("q"), nb::arg("v"), nb::arg("u"),
      "(joint torques (nv,), ledger powers) at (q, v) under u: the kernel's arithmetic, for tests.")
    .attr("fields") = actuators->names();
}
