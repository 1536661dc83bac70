// The engine (kernel.hpp): one run's rows split over threads, each running loop.hpp's Core.advance on its own rows
// with methods.hpp's arithmetic, joined once per advance(); the rows' states by row for Core's own code (records,
// stops, torques, Stepper's undo point); Pinocchio's integrate without its per-joint visitor on vector-space joints.
#include "loop.hpp"

#include <algorithm>
#include <condition_variable>
#include <exception>
#include <functional>
#include <limits>
#include <mutex>
#include <thread>
#include <type_traits>

namespace multibody_sim
{
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
    bool damped,
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
  , damped_(damped)
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

  void Engine::set_actuators(std::shared_ptr<const SceneActuators> actuators)
  {
    const int contact_flows = method_.kind == Kind::timestepping ? 4 : 0;
    if (actuators && (actuators->nv != model_.nv || n_robot_flows_ + actuators->n_flows() + contact_flows > n_ledger_))
      throw std::invalid_argument("the scene's actuators disagree with the model's sizes or the ledger");
    actuators_ = actuators;
    n_actuator_flows_ = actuators ? actuators->n_flows() : 0;
    actuated_dof_.assign(static_cast<size_t>(model_.nv), 0);
    if (actuators)
      for (const ActuatorTerm & a : actuators->terms)
        actuated_dof_[static_cast<size_t>(a.dof)] = 1;
    for (auto & th : threads_)
    {
      th->tact = Vec::Zero(model_.nv);
      if (actuators && actuators->servos)
      {
        th->servo_model = model_;
        th->servo = actuators->workspace();
      }
      th->select(0);
    }
  }

  void Engine::set_scene(std::shared_ptr<const SceneForces> scene)
  {
    const int contact_flows = method_.kind == Kind::timestepping ? 4 : 0;  // the time-stepper's, last
    const int before = n_robot_flows_ + n_actuator_flows_;  // the robot's and the actuators' entries come first
    if (scene && (scene->nv != model_.nv || before + scene->n_flows() + contact_flows != n_ledger_))
      throw std::invalid_argument("the scene's elements disagree with the model's sizes or the ledger");
    scene_ = scene;
    for (auto & th : threads_)
    {
      th->sw = scene ? scene->workspace(model_) : nullptr;
      th->select(0);
    }
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

  void Engine::set_sensors(std::shared_ptr<const Sensors> sensors, int64_t every, const std::vector<int64_t> & done)
  {
    size_t B = 0;
    for (auto & th : threads_)
      B += th->rows.size();
    if (sensors && (every < 1 || done.size() != B))
      throw std::invalid_argument("set_sensors: every must be >= 1 and done hold one count per row");
    check_row_sensors(sensors.get(), rows_);
    sensors_ = sensors;
    sensor_every_ = every;
    sensor_done_ = done;
    sensor_torques_ = false;
    if (sensors)
      for (const SensorItem & item : sensors->items)
        sensor_torques_ = sensor_torques_ || item.kind == SensorKind::joint_torque;
    for (auto & th : threads_)
      th->sensw = sensors ? std::make_unique<SensorWork>(model_, *sensors) : nullptr;
  }

  int64_t Engine::tick_count() const
  {
    size_t n = 0;
    for (const auto & th : threads_)
      if (th->sensw)
        n += th->sensw->times.size();
    return static_cast<int64_t>(n);
  }

  std::tuple<Vec, Eigen::Matrix<int64_t, Eigen::Dynamic, 1>> Engine::take_ticks(double * out, int64_t room,
                                                                                int64_t width)
  {
    const int64_t n = tick_count();
    if (width != (sensors_ ? sensors_->width : 0) || n > room)
      throw std::invalid_argument("take_ticks: `out` must have shape (room >= tick_count(), the sensors' width)");
    Vec times(static_cast<Eigen::Index>(n));
    Eigen::Matrix<int64_t, Eigen::Dynamic, 1> rows(static_cast<Eigen::Index>(n));  // an array, not a list of ints
    Eigen::Index k = 0;
    for (auto & th : threads_)
    {
      if (!th->sensw)
        continue;
      SensorWork & w = *th->sensw;
      const size_t count = w.times.size();
      std::copy(w.times.begin(), w.times.end(), times.data() + k);
      std::copy(w.rows.begin(), w.rows.end(), rows.data() + k);
      std::copy(w.values.begin(), w.values.end(), out + k * width);  // row-major: the ticks' rows in order
      k += static_cast<Eigen::Index>(count);
      w.times.clear();
      w.rows.clear();
      w.values.clear();
    }
    return {std::move(times), std::move(rows)};
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
            th->select(j);
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
    if (contact)
      for (int line : contact->speed_lines)
        if (line < 0 || line >= n_ledger_ - 4)
          throw std::invalid_argument("a velocity limit's ledger line is not one of the scene's smooth flows");
    contact_ = contact;
    flow_work_ = flow_work;
    for (auto & th : threads_)
    {
      if (contact)
        th->cw = contact->workspace(model_);
      else
        th->cw.reset();
      th->select(0);
    }
  }

  namespace
  {
    // Whether two scenes' force elements have the same terms (their coefficients may differ).
    bool same_terms(const SceneForces & a, const SceneForces & b)
    {
      const auto dofs = [](const std::vector<CoefficientTerm> & x, const std::vector<CoefficientTerm> & y) {
        if (x.size() != y.size())
          return false;
        for (size_t i = 0; i < x.size(); ++i)
          if (x[i].dof != y[i].dof)
            return false;
        return true;
      };
      return a.nv == b.nv && a.zero_all == b.zero_all && a.springs.size() == b.springs.size()
             && a.circular.size() == b.circular.size() && dofs(a.damped, b.damped) && dofs(a.rough, b.rough)
             && dofs(a.ledger_damped, b.ledger_damped) && dofs(a.ledger_rough, b.ledger_rough)
             && a.wrenches.size() == b.wrenches.size() && a.others == b.others
             && a.push_models.size() == b.push_models.size() && a.energies.size() == b.energies.size();
    }

    // Whether two contact scenes have the same shapes, pairs and constraints (their coefficients may differ, the
    // joint friction forces included: a step reads them from its row's scene; a thread's workspace holds the shapes).
    bool same_contact(const ContactScene & a, const ContactScene & b)
    {
      if (a.nv != b.nv || a.shapes.size() != b.shapes.size() || a.pairs != b.pairs
          || a.limited_joints != b.limited_joints || a.friction_joints != b.friction_joints
          || a.speed_joints != b.speed_joints || a.speed_lines != b.speed_lines)
        return false;
      for (size_t k = 0; k < a.shapes.size(); ++k)
        if (a.shapes[k].kind != b.shapes[k].kind || a.shapes[k].joint != b.shapes[k].joint
            || a.shapes[k].dims != b.shapes[k].dims || a.shapes[k].rotation != b.shapes[k].rotation
            || a.shapes[k].translation != b.shapes[k].translation)
          return false;
      return true;
    }

    // Whether two scenes' actuators drive the same joints with the same kinds and ledger lines (their gains, limits
    // and curves may differ).
    bool same_actuators(const SceneActuators & a, const SceneActuators & b)
    {
      if (a.nv != b.nv || a.servos != b.servos || a.n_limited != b.n_limited || a.n_braked != b.n_braked
          || a.max_revisions != b.max_revisions || a.terms.size() != b.terms.size())
        return false;
      for (size_t k = 0; k < a.terms.size(); ++k)
        if (a.terms[k].dof != b.terms[k].dof || a.terms[k].iq != b.terms[k].iq || a.terms[k].kind != b.terms[k].kind
            || a.terms[k].limited != b.terms[k].limited || (a.terms[k].brake_gain > 0.0) != (b.terms[k].brake_gain > 0.0))
          return false;
      return true;
    }

    // Whether two scenes' sensors measure the same things at the same places (their cuts' masses may differ).
    bool same_sensors(const Sensors & a, const Sensors & b)
    {
      if (a.width != b.width || a.gravity != b.gravity || a.items.size() != b.items.size()
          || a.contact_joints != b.contact_joints || a.contact_frames != b.contact_frames)
        return false;
      for (size_t k = 0; k < a.items.size(); ++k)
      {
        const SensorItem & x = a.items[k];
        const SensorItem & y = b.items[k];
        if (x.kind != y.kind || x.offset != y.offset || x.frame != y.frame || x.body != y.body
            || x.q_index != y.q_index || x.v_index != y.v_index || x.q_count != y.q_count || x.cut_joint != y.cut_joint
            || x.cut_whole != y.cut_whole || x.cut_rotation != y.cut_rotation || x.cut_translation != y.cut_translation
            || x.cut_children != y.cut_children || x.cut_frames != y.cut_frames)
          return false;
      }
      return true;
    }
  } // namespace

  void Engine::check_row_sensors(const Sensors * sensors, const std::vector<RowPhysics> & rows)
  {
    for (const RowPhysics & r : rows)
      if (r.sensors && (!sensors || !same_sensors(*r.sensors, *sensors)))
        throw std::invalid_argument("a row's sensors disagree with the engine's (set_sensors)");
  }

  void Engine::set_rows(const std::vector<RowPhysics> & rows)
  {
    int64_t B = 0;
    for (const auto & th : threads_)
      B += static_cast<int64_t>(th->rows.size());
    if (static_cast<int64_t>(rows.size()) != B)
      throw std::invalid_argument("set_rows: one RowPhysics per run row is needed");
    for (const RowPhysics & r : rows)
    {
      const pinocchio::Model * m = r.model ? &r.model->model : nullptr;
      if (!m || m->nq != model_.nq || m->nv != model_.nv || m->njoints != model_.njoints
          || m->parents != model_.parents)
        throw std::invalid_argument("set_rows: a row's model is not the engine's robot");
      if (r.damping.size() != model_.nv || (!damped_ && (r.damping.array() != 0.0).any()))
        throw std::invalid_argument("set_rows: a row's damping disagrees with the engine's (size, or damped)");
      if (static_cast<bool>(r.scene) != static_cast<bool>(scene_) || (r.scene && !same_terms(*r.scene, *scene_)))
        throw std::invalid_argument("set_rows: a row's force elements disagree with the engine's");
      if (static_cast<bool>(r.contact) != static_cast<bool>(contact_)
          || (r.contact && !same_contact(*r.contact, *contact_)))
        throw std::invalid_argument("set_rows: a row's contact scene disagrees with the engine's");
      if (static_cast<bool>(r.actuators) != static_cast<bool>(actuators_)
          || (r.actuators && !same_actuators(*r.actuators, *actuators_)))
        throw std::invalid_argument("set_rows: a row's actuators disagree with the engine's");
    }
    if (sensors_)
      check_row_sensors(sensors_.get(), rows);
    rows_ = rows;
    for (auto & th : threads_)
    {
      th->own.clear();
      th->own_plain.clear();
      th->own_servo.clear();
      for (int64_t b : th->rows)
      {
        const RowPhysics & r = rows_[static_cast<size_t>(b)];
        th->own.push_back(&r);
        th->own_plain.push_back((r.model->model.armature.array() == 0.0).all());
        if (actuators_ && actuators_->servos)  // the row's servos raise its own model's armature
          th->own_servo.push_back(r.model->model);
      }
      th->select(0);
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
