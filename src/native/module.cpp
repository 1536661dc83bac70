// multibody_sim._native: the compiled side of multibody-sim (see multibody_sim/native.py, which loads it): the
// module's bindings.
//
// Here: the model hand-over (Pinocchio's binary serialization, bytes -> NativeModel), the build's version, the floor
// measurement (an RK4 loop of Pinocchio calls, scripts/bench_native_floor.py), and the stepping kernel's class
// (_native.Kernel over the engine, engine.cpp) with the named structs it takes (structs.hpp); a scene's and a contact
// model's classes bind themselves (bind_scene in scene.cpp, bind_contact in contact.cpp).
#include <cstdint>
#include <sstream>
#include <stdexcept>
#include <string>
#include <unordered_map>

#include <boost/archive/binary_iarchive.hpp>
#include <boost/iostreams/device/array.hpp>
#include <boost/iostreams/stream_buffer.hpp>

#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/shared_ptr.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/tuple.h>
#include <nanobind/stl/variant.h>
#include <nanobind/stl/vector.h>

#include <pinocchio/algorithm/aba.hpp>
#include <pinocchio/algorithm/joint-configuration.hpp>
#include <pinocchio/config.hpp>
#include <pinocchio/serialization.hpp>

#include "model.hpp"
#ifdef MULTIBODY_SIM_WITH_KERNEL
#include "kernel.hpp"
#include "noise.hpp"
#include "readings.hpp"
#include "structs.hpp"
#endif

namespace nb = nanobind;

namespace multibody_sim
{
#ifdef MULTIBODY_SIM_WITH_KERNEL
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

#ifdef MULTIBODY_SIM_WITH_KERNEL
// ---- the stepping kernel's class and the named structs it takes (kernels/native.py is their only user) ----------
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

  // The samples the engine wrote, as one recording.ContactChunk per row appended to the store's `contacts` dict
  // (row b -> [chunk, ...]): (samples written (w,), each contact row's sample (k,), rows (k, 11)). Dict and list
  // operations run no Python code, so a signal handler (Ctrl-C) never sees the samples counted without their
  // contacts; one chunk per row and call, not one array per sample (made here under the GIL, after the threads).
  void write_contacts(nb::dict contacts, std::vector<multibody_sim::ContactRecord> & records)
  {
    struct Chunk  // one row's records: sizes counted first, then filled in one pass over the records
    {
      int64_t b = 0;
      size_t w = 0, k = 0;  // samples written, contact rows
      int64_t *written = nullptr, *sample = nullptr;
      double * rows = nullptr;
    };
    std::vector<Chunk> chunks;  // the rows in the order first written
    std::unordered_map<int64_t, size_t> index;  // row -> its chunk
    for (const multibody_sim::ContactRecord & r : records)
    {
      auto [it, added] = index.try_emplace(r.b, chunks.size());
      if (added)
        chunks.push_back(Chunk{r.b});
      chunks[it->second].w += 1;
      chunks[it->second].k += r.rows.size();
    }
    for (Chunk & ch : chunks)
    {
      ch.written = new int64_t[ch.w];
      ch.sample = new int64_t[ch.k];
      ch.rows = new double[ch.k * 11];
      ch.w = ch.k = 0;  // counted again as filled
    }
    for (const multibody_sim::ContactRecord & r : records)
    {
      Chunk & ch = chunks[index[r.b]];
      ch.written[ch.w++] = r.i;
      for (const auto & row : r.rows)
      {
        ch.sample[ch.k] = r.i;
        std::copy(row.begin(), row.end(), ch.rows + 11 * ch.k);
        ++ch.k;
      }
    }
    auto owned = [](auto * buffer) {
      return nb::capsule(buffer, [](void * p) noexcept { delete[] static_cast<decltype(buffer)>(p); });
    };
    for (const Chunk & ch : chunks)
    {
      nb::int_ key(ch.b);
      if (!contacts.contains(key))
        contacts[key] = nb::list();
      nb::list held = nb::borrow<nb::list>(contacts[key]);
      held.append(nb::make_tuple(nb::ndarray<nb::numpy, int64_t, nb::ndim<1>>(ch.written, {ch.w}, owned(ch.written)),
                                 nb::ndarray<nb::numpy, int64_t, nb::ndim<1>>(ch.sample, {ch.k}, owned(ch.sample)),
                                 nb::ndarray<nb::numpy, double, nb::ndim<2>>(ch.rows, {ch.k, 11}, owned(ch.rows))));
    }
    records.clear();
  }

  // A contact run's evaluations beyond the core's count, per running position of the Python core (`rows`, the rows
  // stopped in this call included: NativeCore._take_pending compacts both) into `extra`.
  void write_extra_evaluations(const multibody_sim::Engine & engine, const Ints & rows, Ints & extra)
  {
    if (!engine.uneven_evaluations())
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

  // The run's settings and its rows' initial states (NativeKernel.native_data()): _native.RunSettings, the last
  // argument of the Kernel's constructor.
  struct RunSettings
  {
    Eigen::VectorXd damping;  // (nv,)
    bool damped = false;  // whether the damping term is in play (its ledger line)
    int n_ledger = 0;  // the ledger's entries
    double rtol = 0.0, atol = 0.0;  // adaptive methods' tolerances (NaN: none)
    multibody_sim::RowMatrix Q0, V0;  // (B, nq), (B, nv)
    int num_threads = 1;  // the threads the rows are split over
  };

  // What advance() reads and writes beside the loop state and the store (NativeCore builds it at each call):
  // _native.AdvanceIO.
  struct AdvanceIO
  {
    multibody_sim::Sampler sampler;  // None: no samples
    nb::list stops;  // appends a StopEvent per row it stops
    nb::dict contacts;  // the store's contacts dict (write_contacts)
    Ints rows;  // the Python core's running rows (the rows stopped in this call included)
    Ints extra_evaluations;  // out: per running position, the evaluations beyond the core's count
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
    if (code == multibody_sim::STOP_DIVERGED)
      return "diverged";
    if (code == multibody_sim::STOP_FAILED)
      return "failed";
    return code == multibody_sim::STOP_COLLAPSED ? "collapsed" : "control";
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

void multibody_sim::bind_kernel(nb::module_ & m)  // called by NB_MODULE below
{
  using namespace multibody_sim;
  Struct<ZigguratTables>(m, "ZigguratTables", "The noise's ziggurat tables (noise.native_tables(): multibody_sim/noise.py).")
    .field("width", &ZigguratTables::width, "list[float]")
    .field("inside", &ZigguratTables::inside, "list[int]")
    .field("density", &ZigguratTables::density, "list[float]")
    .field("rise", &ZigguratTables::rise, "list[float]")
    .field("edge", &ZigguratTables::edge, "float")
    .finish([](ZigguratTables & z) {
      if (z.width.size() != 256 || z.inside.size() != 256 || z.density.size() != 257 || z.rise.size() != 256)
        throw nb::value_error("ZigguratTables: width, inside and rise need 256 entries, density 257");
    });
  m.def(
    "fill_normals",
    [](nb::ndarray<uint64_t, nb::shape<4>, nb::c_contig, nb::device::cpu> state, Doubles out,
       const ZigguratTables & tables) {
      fill_normals(state.data(), out.data(), out.size(), tables);
    },
    nb::arg("state").noconvert(), nb::arg("out").noconvert(), nb::arg("tables"),
    "noise.NormalStream.fill: the next out.size standard normal draws of the stream at `state` (4 uint64 words, "
    "advanced in place) into `out` (float64, C order).");
  m.def(
    "ledger_sums",
    [](Doubles flows, nb::ndarray<const bool, nb::ndim<1>, nb::c_contig, nb::device::cpu> is_work, Doubles work,
       Doubles dissipated) {
      const size_t width = is_work.shape(0);
      const size_t rows = width ? flows.size() / width : 0;
      if (!width || flows.size() != rows * width || work.size() != rows || dissipated.size() != rows)
        throw nb::value_error("ledger_sums: flows (..., m), is_work (m,), work and dissipated (...,)");
      const bool * mask = is_work.data();
      for (size_t r = 0; r < rows; ++r)  // each side's columns added in order from +0.0 (recording._columns_sum)
      {
        const double * row = flows.data() + r * width;
        double w = 0.0, d = 0.0;
        for (size_t j = 0; j < width; ++j)
          if (mask[j])
            w = w + row[j];
          else
            d = d + row[j];
        work.data()[r] = w;
        dissipated.data()[r] = d;
      }
    },
    nb::arg("flows").noconvert(), nb::arg("is_work").noconvert(), nb::arg("work").noconvert(),
    nb::arg("dissipated").noconvert(),
    "recording.ledger_sums' column sums in one pass over C-ordered flows (..., m): into work and dissipated (...,).");
  Struct<ReadingItem>(m, "ReadingItem", "One sensor as SensorStream reads it (SensorStream.native_data()'s items).")
    .field("offset", &ReadingItem::offset, "int")
    .field("width", &ReadingItem::width, "int")
    .field("stride", &ReadingItem::stride, "int")
    .field("latency", &ReadingItem::latency, "int")
    .field("history", &ReadingItem::history, "int")
    .field("spoiled", &ReadingItem::spoiled, "bool")
    .field("bias", &ReadingItem::bias, "list[float]")
    .field("noise", &ReadingItem::noise, "list[float]")
    .finish();
  Struct<ReadingLayout>(m, "ReadingLayout", "A run's sensors as SensorStream reads them (SensorStream.native_data()).")
    .field("width", &ReadingLayout::width, "int")
    .field("history", &ReadingLayout::history, "int")
    .field("items", &ReadingLayout::items, "list[ReadingItem]")
    .field("tables", &ReadingLayout::tables, "ZigguratTables")
    .finish(check_readings);
  m.def(
    "make_readings",
    [](const ReadingLayout & layout, nb::ndarray<const double, nb::ndim<2>, nb::c_contig, nb::device::cpu> measurements,
       Doubles out, Doubles apart, int64_t count, Doubles latest, Doubles history,
       nb::ndarray<uint64_t, nb::c_contig, nb::device::cpu> states) {
      const size_t m = measurements.shape(0), w = static_cast<size_t>(layout.width);
      if (measurements.shape(1) != w || out.size() != m * w || latest.size() != w
          || history.size() != static_cast<size_t>(layout.history) || states.size() != 4 * layout.items.size()
          || count < 0)
        throw nb::value_error("make_readings: measurements and out (m, width), latest (width,), history (the layout's "
                              "history), states (one stream of 4 words per sensor) and count >= 0");
      if (apart.size() != strided_readings(layout, count, m))
        throw nb::value_error("make_readings: `apart` must hold the strided sensors' readings of these ticks");
      make_readings(layout, measurements.data(), m, out.data(), apart.data(), count, latest.data(), history.data(),
                    states.data());
    },
    nb::arg("layout"), nb::arg("measurements"), nb::arg("out").noconvert(), nb::arg("apart").noconvert(),
    nb::arg("count"), nb::arg("latest").noconvert(), nb::arg("history").noconvert(), nb::arg("states").noconvert(),
    "readings.SensorStream._read_python for one row (src/native/readings.hpp): its m new ticks' measurements "
    "(m, width), "
    "the first `count` ticks after the row's start, into readings: the every-tick sensors' in their columns of "
    "`out` (m, width; it may be the measurements), the strided ones' one after the other in `apart`; the row's "
    "`latest` readings, `history` and streams' `states` advanced in place.");
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
  Struct<SensorItem>(m, "SensorItem", "One sensor and, for a force-torque sensor, its cut (sensors.Placed, Cut).")
    .choice("kind", &SensorItem::kind,
            {{"imu", SensorKind::imu}, {"frame_pose", SensorKind::frame_pose},
             {"contact_force", SensorKind::contact_force}, {"force_torque", SensorKind::force_torque},
             {"joint_position", SensorKind::joint_position}, {"joint_velocity", SensorKind::joint_velocity},
             {"joint_torque", SensorKind::joint_torque}})
    .field("offset", &SensorItem::offset, "int")
    .field("frame", &SensorItem::frame, "int")
    .field("body", &SensorItem::body, "int")
    .field("q_index", &SensorItem::q_index, "list[int]")
    .field("v_index", &SensorItem::v_index, "list[int]")
    .field("q_count", &SensorItem::q_count, "list[int]")
    .field("cut_joint", &SensorItem::cut_joint, "int")
    .field("cut_whole", &SensorItem::cut_whole, "bool")
    .field("cut_rotation", &SensorItem::cut_rotation, "a 3 x 3 float array")
    .field("cut_translation", &SensorItem::cut_translation, "3 floats")
    .field("cut_mass", &SensorItem::cut_mass, "float")
    .field("cut_lever", &SensorItem::cut_lever, "3 floats")
    .field("cut_inertia", &SensorItem::cut_inertia, "a 3 x 3 float array")
    .field("cut_children", &SensorItem::cut_children, "list[int]")
    .field("cut_frames", &SensorItem::cut_frames, "list[int]")
    .finish([](SensorItem & s) {
      if (s.q_index.size() != s.v_index.size() || s.q_index.size() != s.q_count.size())
        throw std::invalid_argument("SensorItem.q_index, v_index and q_count must have one entry per joint");
    });
  Struct<Sensors>(m, "Sensors", "A scene's sensors as the engine measures them (sensors.Sensors.native_data()).")
    .field("width", &Sensors::width, "int")
    .field("gravity", &Sensors::gravity, "3 floats")
    .field("items", &Sensors::items, "list[SensorItem]")
    .field("contact_joints", &Sensors::contact_joints, "list[int]")
    .field("contact_frames", &Sensors::contact_frames, "list[int]")
    .finish([](Sensors & s) {
      if (s.contact_joints.size() != s.contact_frames.size())
        throw std::invalid_argument("Sensors.contact_joints and contact_frames must have one entry per body");
    });
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
  Struct<RowPhysics>(
    m, "RowPhysics",
    "One row's own model, damping, force elements, contact scene, actuators and sensors (set_rows).")
    .field("model", &RowPhysics::model, "Model")
    .field("damping", &RowPhysics::damping, "an array of nv floats")
    .optional("scene", &RowPhysics::scene, "SceneForces or None")
    .optional("contact", &RowPhysics::contact, "ContactScene or None")
    .optional("actuators", &RowPhysics::actuators, "SceneActuators or None")
    .optional("sensors", &RowPhysics::sensors, "Sensors or None (the engine's)")
    .finish([](RowPhysics & r) {
      if (!r.model)
        throw std::invalid_argument("RowPhysics.model must be a Model");
    });
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
  Struct<RunSettings>(m, "RunSettings", "The run's settings and initial states (NativeKernel.native_data()).")
    .field("damping", &RunSettings::damping, "a float64 array (nv,)")
    .field("damped", &RunSettings::damped, "bool")
    .field("n_ledger", &RunSettings::n_ledger, "int")
    .field("rtol", &RunSettings::rtol, "float")
    .field("atol", &RunSettings::atol, "float")
    .field("Q0", &RunSettings::Q0, "a float64 array (B, nq)")
    .field("V0", &RunSettings::V0, "a float64 array (B, nv)")
    .field("num_threads", &RunSettings::num_threads, "int")
    .finish();
  Struct<AdvanceIO>(m, "AdvanceIO", "What Kernel.advance() reads and writes beside the loop state and the store.")
    .nullable("sampler", &AdvanceIO::sampler, "Sampler or None")
    .field("stops", &AdvanceIO::stops, "list")
    .field("contacts", &AdvanceIO::contacts, "dict")
    .field("rows", &AdvanceIO::rows, "a C-contiguous int64 array")
    .field("extra_evaluations", &AdvanceIO::extra_evaluations, "a C-contiguous int64 array")
    .finish();

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
    .def_ro("error", &StopEvent::error, "collapsed: the error norm (NaN: not judged)")
    .def_ro("message", &StopEvent::message, "failed: the library's exception, worded as the Python kernel does");
  nb::class_<Advance>(m, "Advance", "What Kernel.advance() did.")
    .def_ro("status", &Advance::status)
    .def_ro("taken", &Advance::taken)
    .def_ro("need", &Advance::need);

  nb::class_<Engine>(m, "Kernel", "The native stepping kernel of one run (multibody_sim.kernels.native drives it).")
    .def(
      "__init__",
      [](Engine * self, const NativeModel & model, const Method & method, const Chart & chart,
         const std::variant<ConstantStepData, PIControllerData> & control, const RunSettings & run) {
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
          c.rtol = run.rtol;
          c.atol = run.atol;
        }
        const pinocchio::Model & robot = model.model;
        if (run.Q0.cols() != robot.nq || run.V0.cols() != robot.nv || run.Q0.rows() != run.V0.rows()
            || run.damping.size() != robot.nv)
          throw std::invalid_argument("RunSettings: Q0, V0 or damping disagree with the model's sizes");
        new (self) Engine(
          robot, method, chart.blocks, chart.half_series, run.damping, run.damped, run.n_ledger, c, run.Q0, run.V0,
          run.num_threads);
      },
      nb::arg("model"), nb::kw_only(), nb::arg("method"), nb::arg("chart"), nb::arg("control"), nb::arg("run"),
      "The engine of one run: the robot, its method, chart map and step-size controller, and the run's settings and "
      "initial states (named structs).")
    .def(
      "advance",
      [](Engine & self, double t_stop, int64_t limit, double tolerance, LoopState & state, const StoreArrays & store,
         AdvanceIO & io) {
        CoreState s;
        static_cast<LoopState &>(s) = state;
        s.t = self.t;
        s.instant = self.instant;
        s.last_control = self.last_control;
        const Store arrays = store_of(store);
        AdvanceResult result;
        {
          nb::gil_scoped_release release;
          result = self.advance(t_stop, limit, tolerance, io.sampler, arrays, s);
        }
        // The state comes back in `state` and the stops in `io.stops` before this call returns: no Python code runs
        // in between, so a signal handler (Ctrl-C) that runs when it returns never sees the work half recorded.
        self.t = s.t;
        self.instant = s.instant;
        self.last_control = s.last_control;
        state = s;
        for (const StopEvent & ev : result.stops)
          io.stops.append(nb::cast(ev));
        write_contacts(io.contacts, result.records);
        write_extra_evaluations(self, io.rows, io.extra_evaluations);
        return Advance{status_name(result.status), result.taken, result.need};
      },
      nb::arg("t_stop"), nb::arg("limit"), nb::arg("tolerance"), nb::kw_only(), nb::arg("state"), nb::arg("store"),
      nb::arg("io"),
      "Core.advance towards t_stop, at most `limit` accepted steps, with the landing `tolerance`: advances `state` "
      "(a LoopState) in place, appends the rows that stop to `io.stops` (StopEvent), their contacts to "
      "`io.contacts` (the store's dict of ContactChunks) and the evaluations beyond the core's count of the running `io.rows` to "
      "`io.extra_evaluations` (an AdvanceIO).")
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
      "Write run rows `rows` as sample i of the store, their contacts into `contacts` (the store's dict of ContactChunks).")
    .def(
      "set_contact",
      [](Engine & self, std::shared_ptr<ContactScene> contact, std::vector<bool> flow_work) {
        self.set_contact(contact, flow_work);
      },
      nb::arg("contact"), nb::arg("flow_work"),
      "A contact scene's geometry and constraints (_native.ContactScene) for the timestepping kind; flow_work: "
      "per ledger entry before the contact's four, whether it is work (else dissipated).")
    .def("set_rows", &Engine::set_rows, nb::arg("rows"),
         "Each run row's own physics (RowPhysics, a randomised scene's rows), after set_scene and set_contact.")
    .def_prop_ro("has_contact", &Engine::has_contact)
    .def(
      "set_sensors",
      [](Engine & self, std::shared_ptr<Sensors> sensors, int64_t every, std::vector<int64_t> done) {
        const pinocchio::Model & model = self.model();
        const auto within = [](int i, int n) { return 0 <= i && i < n; };
        bool valid = true;
        for (const SensorItem & item : sensors->items)
        {
          valid = valid && within(item.offset, sensors->width + 1) && item.frame < static_cast<int>(model.nframes)
                  && within(item.cut_joint, model.njoints) && item.body < static_cast<int>(sensors->contact_joints.size());
          for (size_t i = 0; i < item.q_index.size(); ++i)
            valid = valid && within(item.q_index[i] + item.q_count[i] - 1, model.nq) && within(item.v_index[i], model.nv);
          for (int k : item.cut_children)
            valid = valid && within(k, model.njoints);
        }
        for (int j : sensors->contact_joints)
          valid = valid && within(j, model.njoints);
        if (!valid)
          throw std::invalid_argument("set_sensors: a sensor's offset, frame, body, joint or coordinate is out of range");
        self.set_sensors(sensors, every, done);
      },
      nb::arg("sensors"), nb::arg("every"), nb::arg("done"),
      "A scene's sensors (_native.Sensors) tick at the end of every `every`-th step of a row, counted from its "
      "start (`done`: the steps each row took before, (B,)); take_ticks() collects their measurements.")
    .def("tick_count", &Engine::tick_count, "The ticks since the last take_ticks: how many.")
    .def(
      "take_ticks",
      [](Engine & self, Doubles out)
      {
        if (out.ndim() != 2)
          throw std::invalid_argument("take_ticks: `out` must have shape (room >= tick_count(), the sensors' width)");
        return self.take_ticks(out.data(), static_cast<int64_t>(out.shape(0)), static_cast<int64_t>(out.shape(1)));
      },
      nb::arg("out"),
      "The ticks since the last call: times (n,), rows (n,); their measurements into out[:n] (out: (room >= n, "
      "width), C-ordered; see tick_count).")
    .def("contact_row", &Engine::contact_row)
    .def(
      "set_actuators", [](Engine & self, std::shared_ptr<SceneActuators> actuators) { self.set_actuators(actuators); },
      nb::arg("actuators"), "A scene's actuators (_native.SceneActuators) join the dynamics (scene.cpp).")
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
#endif

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
