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

  void Policies::clip(Vec & tau, int64_t * dofs, bool & clipped) const  // driver.Saturation.apply
  {
    clipped = false;
    if (!saturate)
      return;
    for (int i = 0; i < nv; ++i)
      if (std::abs(tau[i]) > effort[i])
      {
        clipped = true;
        dofs[i] += 1;
      }
    if (clipped)
      for (int i = 0; i < nv; ++i)  // np.clip(tau, -effort, effort)
        tau[i] = std::min(std::max(tau[i], -effort[i]), effort[i]);
  }
} // namespace multibody_sim

// ---- Python bindings: _native.SceneForces, _native.Policies (native_core.py is their only user) ---------------
#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/tuple.h>
#include <nanobind/stl/vector.h>

#define NO_IMPORT_ARRAY
#define NO_IMPORT_UFUNC
#define NPY_NO_DEPRECATED_API NPY_1_7_API_VERSION
#include <numpy/ndarraytypes.h>
#include <numpy/ufuncobject.h>

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
  nb::class_<SceneForces>(m, "SceneForces", "A scene's force elements (scenes/elements.py), for the native kernel.")
    .def(
      "__init__",
      [](
        SceneForces * self, const NativeModel & model, bool zero_all, double inv_vs,
        std::vector<std::tuple<int, int, double, double>> springs,
        std::vector<std::tuple<int, int, double, double, double>> circular,
        std::vector<std::tuple<int, double>> damped, std::vector<std::tuple<int, double>> rough,
        std::vector<std::tuple<int, double>> ledger_damped, std::vector<std::tuple<int, double>> ledger_rough,
        std::vector<std::tuple<int, int, bool, std::vector<double>, int, std::vector<double>>> wrenches,
        std::vector<const NativeModel *> push_models,
        std::vector<std::tuple<bool, int, double, double, double, double>> energies) {
        new (self) SceneForces();
        self->tanh_loop = numpy_loop("tanh");
        self->atan2_loop = numpy_loop("arctan2");
        const pinocchio::Model & robot = model.model;
        const int nv = robot.nv, nq = robot.nq;
        self->nv = nv;
        self->zero_all = zero_all;
        self->inv_vs = inv_vs;
        const auto check = [](bool ok, const char * what) {
          if (!ok)
            throw std::invalid_argument(std::string("scene elements: ") + what + " out of range");
        };
        for (auto & [dof, iq, rest, minus_k] : springs)
        {
          check(0 <= dof && dof < nv && 0 <= iq && iq < nq, "a spring's dof or coordinate");
          self->springs.push_back({dof, iq, rest, minus_k});
        }
        for (auto & [dof, ic, cos_rest, sin_rest, minus_k] : circular)
        {
          check(0 <= dof && dof < nv && 0 <= ic && ic + 1 < nq, "a continuous spring's dof or coordinate");
          self->circular.push_back({dof, ic, cos_rest, sin_rest, minus_k});
        }
        const auto terms = [&](std::vector<std::tuple<int, double>> & from, std::vector<CoefficientTerm> & to) {
          for (auto & [dof, c] : from)
          {
            check(0 <= dof && dof < nv, "a damping or friction dof");
            to.push_back({dof, c});
          }
        };
        terms(damped, self->damped);
        terms(rough, self->rough);
        terms(ledger_damped, self->ledger_damped);
        terms(ledger_rough, self->ledger_rough);
        for (const NativeModel * push : push_models)
        {
          check(push && push->model.nq == nq && push->model.nv == nv, "a point-mass model");
          self->push_models.push_back(push->model);
        }
        for (auto & [push, frame, local, w6, shape, shape_params] : wrenches)
        {
          WrenchTerm w;
          w.push = push;
          w.frame = frame;
          w.local = local;
          check(w6.size() == 6 && shape_params.size() == 4 && 0 <= shape && shape <= 3, "a wrench's data");
          check(push < static_cast<int>(self->push_models.size()), "a wrench's point-mass model");
          check(0 <= frame && frame < static_cast<int>(robot.nframes), "a wrench's frame");
          for (int i = 0; i < 6; ++i)
            w.w6[i] = w6[static_cast<size_t>(i)];
          w.shape = static_cast<Shape>(shape);
          w.start = shape_params[0];
          w.ramp_time = shape_params[1];
          w.frequency = shape_params[2];
          w.phase = shape_params[3];
          if (push < 0)
            self->others.push_back(static_cast<int>(self->wrenches.size()));
          self->wrenches.push_back(w);
        }
        for (auto & [circ, iq, rest, cos_rest, sin_rest, k] : energies)
        {
          check(0 <= iq && iq + (circ ? 1 : 0) < nq, "a spring's coordinate");
          SpringEnergy e;
          e.circular = circ;
          e.iq = iq;
          e.rest = rest;
          e.cos_rest = cos_rest;
          e.sin_rest = sin_rest;
          e.k = k;
          self->energies.push_back(e);
        }
      },
      nb::arg("model"), nb::arg("zero_all"), nb::arg("inv_vs"), nb::arg("springs"), nb::arg("circular"),
      nb::arg("damped"), nb::arg("rough"), nb::arg("ledger_damped"), nb::arg("ledger_rough"), nb::arg("wrenches"),
      nb::arg("push_models"), nb::arg("energies"))
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
        return std::make_tuple(out, flows, record, total);
      },
      nb::arg("model"), nb::arg("q"), nb::arg("v"), nb::arg("t"),
      "(force (nv,), ledger powers, spring energies, their sum) at (q, v, t): the kernel's arithmetic, for tests.");

  nb::class_<Policies>(m, "Policies", "Built-in controllers or open-loop torques at control instants (native).")
    .def(
      "__init__",
      [](
        Policies * self, int nv, int a_start, int a_stop,
        std::vector<std::tuple<int, Vec, Vec, Vec, Vec>> rows, nb::ndarray<double, nb::c_contig, nb::device::cpu> taus,
        Vec effort, bool saturate, bool adaptive, bool every_step, double dt, double duration, double period,
        int64_t every, int64_t n_steps) {
        new (self) Policies();
        self->nv = nv;
        self->a_start = a_start;
        self->a_stop = a_stop;
        if (!(0 <= a_start && a_start <= a_stop && a_stop <= nv) || effort.size() != nv)
          throw std::invalid_argument("policies: actuated range or effort out of range");
        const int n = a_stop - a_start;
        for (auto & [kind, q_ref, v_ref, kp, kd] : rows)
        {
          if (kind < 0 || kind > 2 || v_ref.size() != nv || kp.size() != n || kd.size() != n)
            throw std::invalid_argument("policies: a controller's data disagree with the model's sizes");
          Policy p;
          p.kind = static_cast<PolicyKind>(kind);
          p.q_ref = q_ref;
          p.v_ref = v_ref;
          p.kp = kp;
          p.kd = kd;
          self->rows.push_back(p);
        }
        if (taus.ndim() == 3 && taus.shape(0) > 0)
        {
          if (static_cast<int>(taus.shape(2)) != nv || taus.shape(1) == 0)
            throw std::invalid_argument("policies: taus must have shape (B, n_control, nv)");
          self->taus = taus.data();
          self->n_taus = static_cast<int64_t>(taus.shape(1));
        }
        self->effort = effort;
        self->saturate = saturate;
        self->adaptive = adaptive;
        self->every_step = every_step;
        self->dt = dt;
        self->duration = duration;
        self->period = period;
        self->every = every;
        self->n_steps = n_steps;
      },
      nb::arg("nv"), nb::arg("a_start"), nb::arg("a_stop"), nb::arg("rows"), nb::arg("taus"), nb::arg("effort"),
      nb::arg("saturate"), nb::arg("adaptive"), nb::arg("every_step"), nb::arg("dt"), nb::arg("duration"), nb::arg("period"),
      nb::arg("every"), nb::arg("n_steps"),
      "taus (B, n_control, nv) must stay alive as long as the kernel runs (native_core keeps it).");
}
