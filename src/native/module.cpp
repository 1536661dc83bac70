// multibody_sim._native: the compiled side of multibody-sim (see multibody_sim/native.py, which loads it).
//
// Here: the model hand-over (Pinocchio's binary serialization, bytes -> NativeModel), the build's version, and the
// floor measurement (an RK4 loop of Pinocchio calls, scripts/bench_native_floor.py). The stepping kernel binds
// itself through bind_kernel (src/native/kernel.cpp, when present).
#include <cstdint>
#include <sstream>
#include <stdexcept>
#include <string>

#include <boost/archive/binary_iarchive.hpp>
#include <boost/iostreams/device/array.hpp>
#include <boost/iostreams/stream_buffer.hpp>

#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>
#include <nanobind/stl/string.h>

#include <pinocchio/algorithm/aba.hpp>
#include <pinocchio/algorithm/joint-configuration.hpp>
#include <pinocchio/config.hpp>
#include <pinocchio/serialization.hpp>

#include "model.hpp"

namespace nb = nanobind;

namespace multibody_sim
{
#ifdef MULTIBODY_SIM_WITH_KERNEL
  void bind_kernel(nb::module_ & m); // src/native/kernel.cpp
  void bind_scene(nb::module_ & m);  // src/native/scene.cpp
  void bind_contact(nb::module_ & m);  // src/native/contact.cpp
#endif

  namespace
  {
    pinocchio::Model model_from_archive(const char * bytes, std::size_t size)
    {
      pinocchio::Model model;
      try
      {
        boost::iostreams::stream_buffer<boost::iostreams::basic_array_source<char>> stream(bytes, size);
        boost::archive::binary_iarchive archive(stream);
        archive >> model;
      }
      catch (const std::exception & e)
      {
        throw std::invalid_argument(
          std::string("model bytes are not a Pinocchio binary archive of a Model (from model.saveToBinary(")
          + "pin.serialization.StreamBuffer())): " + e.what());
      }
      return model;
    }
  } // namespace

  NativeModel::NativeModel(const char * bytes, std::size_t size)
  : model(model_from_archive(bytes, size))
  , data(model)
  {
  }

  namespace
  {
    using Vector = Eigen::VectorXd;
    using ConstRef = Eigen::Ref<const Vector>;

    void check_size(const char * name, const ConstRef & x, Eigen::Index expected)
    {
      if (x.size() != expected)
      {
        std::ostringstream message;
        message << name << " must have " << expected << " entries, got " << x.size();
        throw std::invalid_argument(message.str());
      }
    }

    /// n RK4 steps of size dt from (q, v) under constant tau: 4 aba (WORLD) + 4 integrate per step, no
    /// allocation in the loop. The floor of an RK4 step in C++ (docs/native_floor.md), and written in the order
    /// tests/test_native.py repeats with Pinocchio's Python calls to compare bit for bit.
    nb::tuple rk4_floor(
      NativeModel & self, const ConstRef & q0, const ConstRef & v0, const ConstRef & tau, double dt, std::int64_t n)
    {
      const pinocchio::Model & model = self.model;
      pinocchio::Data & data = self.data;
      check_size("q0", q0, model.nq);
      check_size("v0", v0, model.nv);
      check_size("tau", tau, model.nv);
      if (n < 0)
        throw std::invalid_argument("n must be >= 0, got " + std::to_string(n));
      Vector q(q0), v(v0), qi(model.nq), vi(model.nv), dq(model.nv), a1(model.nv), a2(model.nv), a3(model.nv),
        a4(model.nv), v2(model.nv), v3(model.nv), v4(model.nv);
      const double h = 0.5 * dt, w = dt / 6.0;
      const auto aba = [&](const Vector & qs, const Vector & vs) -> const Vector & {
        return pinocchio::aba(
          model, data, ConstRef(qs), ConstRef(vs), ConstRef(tau), pinocchio::Convention::WORLD);
      };
      {
        nb::gil_scoped_release release;
        for (std::int64_t i = 0; i < n; ++i)
        {
          a1 = aba(q, v);
          dq = h * v;
          pinocchio::integrate(model, q, dq, qi);
          v2 = v + h * a1;
          a2 = aba(qi, v2);
          dq = h * v2;
          pinocchio::integrate(model, q, dq, qi);
          v3 = v + h * a2;
          a3 = aba(qi, v3);
          dq = dt * v3;
          pinocchio::integrate(model, q, dq, qi);
          v4 = v + dt * a3;
          a4 = aba(qi, v4);
          dq = w * (v + 2.0 * v2 + 2.0 * v3 + v4);
          pinocchio::integrate(model, q, dq, qi);
          q.swap(qi);
          v += w * (a1 + 2.0 * a2 + 2.0 * a3 + a4);
        }
      }
      return nb::make_tuple(q, v);
    }
  } // namespace
} // namespace multibody_sim

NB_MODULE(_native, m)
{
  using multibody_sim::NativeModel;
  m.doc() = "The compiled side of multibody-sim (load it through multibody_sim.native).";
  // The Pinocchio whose headers and libpinocchio_default.so the extension was built against: the Python one must
  // be the same exact version (its libraries are the ones this module runs on; no ABI promise across versions).
  m.attr("PINOCCHIO_VERSION") = PINOCCHIO_VERSION;
  const std::string running = nb::cast<std::string>(nb::module_::import_("pinocchio").attr("__version__"));
  if (running != PINOCCHIO_VERSION)
    throw nb::import_error(
      ("multibody_sim._native was built against Pinocchio " PINOCCHIO_VERSION " but Pinocchio " + running
       + " is installed (no ABI promise across versions): reinstall multibody-sim")
        .c_str());

  nb::class_<NativeModel>(m, "Model", "A pinocchio::Model and its Data, rebuilt from Pinocchio's binary archive.")
    .def(
      "__init__",
      [](NativeModel * self, nb::bytes archive) { new (self) NativeModel(archive.c_str(), archive.size()); },
      nb::arg("archive"),
      "From the bytes of model.saveToBinary(pin.serialization.StreamBuffer()).")
    .def_prop_ro("nq", [](const NativeModel & self) { return self.model.nq; })
    .def_prop_ro("nv", [](const NativeModel & self) { return self.model.nv; })
    .def_prop_ro("name", [](const NativeModel & self) { return self.model.name; })
    .def_prop_ro("njoints", [](const NativeModel & self) { return self.model.njoints; })
    .def(
      "aba",
      [](NativeModel & self, const Eigen::Ref<const Eigen::VectorXd> & q,
         const Eigen::Ref<const Eigen::VectorXd> & v, const Eigen::Ref<const Eigen::VectorXd> & tau) {
        using ConstRef = Eigen::Ref<const Eigen::VectorXd>;
        if (q.size() != self.model.nq || v.size() != self.model.nv || tau.size() != self.model.nv)
          throw std::invalid_argument("aba: q, v, tau must have nq, nv, nv entries");
        return Eigen::VectorXd(pinocchio::aba(
          self.model, self.data, ConstRef(q), ConstRef(v), ConstRef(tau), pinocchio::Convention::WORLD));
      },
      nb::arg("q"), nb::arg("v"), nb::arg("tau"),
      "Joint accelerations (nv,) by pinocchio::aba (WORLD convention), for checking the hand-over.")
    .def(
      "rk4_floor", &multibody_sim::rk4_floor, nb::arg("q0"), nb::arg("v0"), nb::arg("tau"), nb::arg("dt"),
      nb::arg("n"),
      "(q, v) after n RK4 steps of dt seconds under constant tau: the C++ floor of an RK4 step.");

#ifdef MULTIBODY_SIM_WITH_KERNEL
  multibody_sim::bind_scene(m);  // before the kernel, whose set_scene and set_policies take its classes
  multibody_sim::bind_contact(m);  // ... and set_contact
  multibody_sim::bind_kernel(m);
#endif
}
