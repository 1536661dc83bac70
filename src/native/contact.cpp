// The contact part of the `timestepping` step (see contact.hpp): scenes/contact.py's ContactModel.detect and
// .problem and integrators/timestepping.py's solve, in their order. Each section names the Python it renders.
#include "contact.hpp"
#include "model.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include <coal/collision_data.h>
#include <coal/shape/geometric_shapes.h>

#include "pinocchio/algorithm/cholesky.hpp"
#include "pinocchio/algorithm/constraint-cholesky.hpp"
#include "pinocchio/algorithm/crba.hpp"
#include "pinocchio/algorithm/geometry.hpp"
#include "pinocchio/algorithm/solvers/admm-solver.hpp"
#include "pinocchio/algorithm/solvers/pgs-solver.hpp"
#include "pinocchio/collision/collision.hpp"
#include "pinocchio/constraints.hpp"
#include "pinocchio/multibody/geometry.hpp"

namespace multibody_sim
{
  namespace
  {
    using Matrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

    // contact.ContactPoint
    struct Point
    {
      int pair = 0, index = 0;
      int joint1 = 0, joint2 = 0, body1 = 0, body2 = 0;
      pinocchio::SE3 placement1, placement2;
      Eigen::Vector3d position, normal;
      Eigen::Matrix3d rotation;
      double gap = 0.0, friction = 0.0, restitution = 0.0;
    };

    std::shared_ptr<coal::CollisionGeometry> make_shape(const ContactShape & s)  // contact.make_shape
    {
      switch (s.kind)
      {
      case ShapeKind::halfspace:
        return std::make_shared<coal::Halfspace>(coal::Vec3s(0.0, 0.0, 1.0), s.dims.at(0));
      case ShapeKind::box:
        return std::make_shared<coal::Box>(s.dims.at(0), s.dims.at(1), s.dims.at(2));
      case ShapeKind::sphere:
        return std::make_shared<coal::Sphere>(s.dims.at(0));
      case ShapeKind::cylinder:
        return std::make_shared<coal::Cylinder>(s.dims.at(0), s.dims.at(1));
      }
      throw std::invalid_argument("unknown shape kind");
    }
  } // namespace

  struct ContactWork
  {
    pinocchio::Data data;  // the contact's own Data (ContactModel.data)
    pinocchio::GeometryModel gm;
    pinocchio::GeometryData gd;
    bool has_limit = false, has_friction = false;
    pinocchio::JointLimitConstraintModel limit;
    pinocchio::JointFrictionConstraintModel friction;
    std::vector<pinocchio::ConstraintModel> models;
    std::vector<pinocchio::ConstraintData> datas;
    std::vector<std::vector<int64_t>> keys;
    std::vector<int> sizes;
    // The constraint set's structure (per model: a point's joints, the limits' selection, friction): while it
    // stays, the models and datas are updated in place instead of being built again.
    std::vector<int64_t> structure, next_structure;
    pinocchio::ConstraintCholeskyDecomposition cholesky;
    pinocchio::ADMMConstraintSolver admm;
    pinocchio::PGSConstraintSolver pgs;
    pinocchio::ADMMSolverSettings admm_settings;
    pinocchio::PGSSolverSettings pgs_settings;
    pinocchio::ADMMSolverResult admm_result;
    pinocchio::PGSSolverResult pgs_result;
    std::vector<Point> points;
    std::vector<int> chosen;
    std::vector<Eigen::Vector2d> tangent;
    Matrix J;
    Eigen::VectorXd g, correction, restitution, guess, impulses, generalized, minv, approach;
    std::vector<std::pair<int, double>> landings;

    ContactWork(const pinocchio::Model & model, const ContactScene & scene)
    : data(model)
    {
      for (size_t k = 0; k < scene.shapes.size(); ++k)
      {
        const ContactShape & s = scene.shapes[k];
        const pinocchio::SE3 placement(s.rotation, s.translation);
        gm.addGeometryObject(pinocchio::GeometryObject(
          "shape:" + std::to_string(k), static_cast<pinocchio::JointIndex>(s.joint),
          static_cast<pinocchio::FrameIndex>(s.joint), placement, make_shape(s)));
      }
      for (const auto & [a, b] : scene.pairs)
        gm.addCollisionPair(pinocchio::CollisionPair(static_cast<size_t>(a), static_cast<size_t>(b)));
      gd = pinocchio::GeometryData(gm);
      for (coal::CollisionRequest & request : gd.collisionRequests)
      {
        request.enable_contact = true;  // without it box–box normals are NaN
        request.security_margin = scene.constants.speculative_margin;
      }
      if (!scene.limited_joints.empty())
      {
        pinocchio::JointLimitConstraintModel::JointIndexVector ids(
          scene.limited_joints.begin(), scene.limited_joints.end());
        limit = pinocchio::JointLimitConstraintModel(model, ids);
        limit.setPositionLimitAndMargin(model.lowerPositionLimit, model.upperPositionLimit, scene.limit_margin);
        has_limit = true;
      }
      if (!scene.friction_joints.empty())
      {
        pinocchio::JointFrictionConstraintModel::JointIndexVector ids(
          scene.friction_joints.begin(), scene.friction_joints.end());
        const Eigen::VectorXd lower = -scene.friction_bound;
        friction = pinocchio::JointFrictionConstraintModel(model, ids, lower, scene.friction_bound);
        has_friction = true;
      }
      const ContactConstants & c = scene.constants;
      // timestepping.admm_settings / pgs_settings
      admm_settings.admm_update_rule = pinocchio::ADMMUpdateRule::SPECTRAL;
      admm_settings.anderson_capacity = static_cast<std::size_t>(c.anderson_capacity);
      admm_settings.max_iterations = static_cast<std::size_t>(c.max_iterations);
      admm_settings.absolute_feasibility_tol = c.tolerance;
      admm_settings.relative_feasibility_tol = c.tolerance;
      admm_settings.absolute_complementarity_tol = c.tolerance;
      admm_settings.relative_complementarity_tol = c.tolerance;
      pgs_settings.max_iterations = static_cast<std::size_t>(c.max_iterations);
      pgs_settings.absolute_feasibility_tol = c.tolerance;
      pgs_settings.relative_feasibility_tol = c.tolerance;
      pgs_settings.absolute_complementarity_tol = c.tolerance;
      pgs_settings.relative_complementarity_tol = c.tolerance;
    }

    // contact._patch_points: the indices of a patch's points the constraint uses
    void patch_points(const coal::ContactPatch & patch, const Eigen::Matrix3d & rotation, int max_points)
    {
      chosen.clear();
      const int n = static_cast<int>(patch.size());
      if (n <= max_points)
      {
        for (int i = 0; i < n; ++i)
          chosen.push_back(i);
        return;
      }
      tangent.resize(static_cast<size_t>(n));
      for (int i = 0; i < n; ++i)
      {
        const coal::Vec3s p = patch.getPoint(static_cast<size_t>(i));
        for (int r = 0; r < 2; ++r)  // ordered_matvec(rotation.T, p)[r]
        {
          double s = rotation(0, r) * p[0];
          s += rotation(1, r) * p[1];
          s += rotation(2, r) * p[2];
          tangent[static_cast<size_t>(i)][r] = s;
        }
      }
      static const int directions[8][2] = {{1, 0}, {-1, 0}, {0, 1}, {0, -1}, {1, 1}, {-1, -1}, {1, -1}, {-1, 1}};
      for (const auto & d : directions)
      {
        int best = 0;
        double top = 0.0;
        for (int i = 0; i < n; ++i)  // np.argmax: the first of the largest
        {
          const Eigen::Vector2d & t = tangent[static_cast<size_t>(i)];
          const double x = t[0] * d[0] + t[1] * d[1];
          if (i == 0 || x > top)
          {
            best = i;
            top = x;
          }
        }
        if (std::find(chosen.begin(), chosen.end(), best) == chosen.end())
          chosen.push_back(best);
        if (static_cast<int>(chosen.size()) == max_points)
          break;
      }
      std::sort(chosen.begin(), chosen.end());
    }
  };

  ContactScene::ContactScene(
    const pinocchio::Model & model,
    const std::vector<ContactShape> & shapes_,
    const std::vector<std::pair<int, int>> & pairs_,
    const std::vector<double> & pair_friction_,
    const std::vector<double> & pair_restitution_,
    const std::vector<int> & limited_joints_,
    const Vec & limit_margin_,
    const std::vector<int> & friction_joints_,
    const Vec & friction_bound_,
    const ContactConstants & constants_)
  : nv(model.nv)
  , shapes(shapes_)
  , pairs(pairs_)
  , pair_friction(pair_friction_)
  , pair_restitution(pair_restitution_)
  , limited_joints(limited_joints_)
  , friction_joints(friction_joints_)
  , limit_margin(limit_margin_)
  , friction_bound(friction_bound_)
  , constants(constants_)
  {
    const int n = static_cast<int>(shapes.size());
    for (const ContactShape & s : shapes)
      if (s.joint < 0 || s.joint >= model.njoints)
        throw std::invalid_argument("a contact shape's joint is not in the model");
    for (const auto & [a, b] : pairs)
      if (a < 0 || b < 0 || a >= n || b >= n)
        throw std::invalid_argument("a contact pair names a shape that does not exist");
    if (pair_friction.size() != pairs.size() || pair_restitution.size() != pairs.size())
      throw std::invalid_argument("one friction and one restitution coefficient per contact pair");
    if (limit_margin.size() != model.nq || friction_bound.size() != model.nv)
      throw std::invalid_argument("the limits' margin must have nq entries and the friction bound nv");
    for (int j : limited_joints)
      if (j <= 0 || j >= model.njoints)
        throw std::invalid_argument("a limited joint is not in the model");
    for (int j : friction_joints)
      if (j <= 0 || j >= model.njoints)
        throw std::invalid_argument("a joint with exact friction is not in the model");
  }

  ContactScene::~ContactScene() = default;

  std::unique_ptr<ContactWork, void (*)(ContactWork *)> ContactScene::workspace(const pinocchio::Model & model) const
  {
    return std::unique_ptr<ContactWork, void (*)(ContactWork *)>(
      new ContactWork(model, *this), [](ContactWork * w) { delete w; });
  }

  bool ContactScene::step(
    ContactWork & w, const pinocchio::Model & model, const Vec & q, const Vec & v, const Vec & v_free, double h,
    ContactRow & row, Vec & v_next, double & contact_work, double & correction, double & bounce) const
  {
    const ContactConstants & c = constants;
    pinocchio::Data & data = w.data;
    // ---- ContactModel.detect --------------------------------------------------------------------------------
    pinocchio::updateGeometryPlacements(model, data, w.gm, w.gd, q);
    w.points.clear();
    if (!pairs.empty())
    {
      pinocchio::computeCollisions(w.gm, w.gd, false);
      for (size_t k = 0; k < pairs.size(); ++k)
      {
        if (!w.gd.collisionResults[k].isCollision())
          continue;
        pinocchio::computeContactPatch(w.gm, w.gd, k);
        const coal::ContactPatchResult & patches = w.gd.contactPatchResults[k];
        if (patches.numContactPatches() == 0)
          continue;
        const coal::ContactPatch & patch = patches.getContactPatch(0);
        const Eigen::Vector3d normal = patch.getNormal();
        const Eigen::Matrix3d rotation =
          Eigen::Quaterniond::FromTwoVectors(Eigen::Vector3d::UnitZ(), normal).toRotationMatrix();
        const ContactShape &g1 = shapes[static_cast<size_t>(pairs[k].first)],
                           &g2 = shapes[static_cast<size_t>(pairs[k].second)];
        w.patch_points(patch, rotation, c.max_patch_points);
        for (int i : w.chosen)
        {
          const Eigen::Vector3d p1 = patch.getPointShape1(static_cast<size_t>(i));
          const Eigen::Vector3d p2 = patch.getPointShape2(static_cast<size_t>(i));
          Point p;
          p.pair = static_cast<int>(k);
          p.index = i;
          p.joint1 = g1.joint;
          p.joint2 = g2.joint;
          p.body1 = g1.body;
          p.body2 = g2.body;
          p.placement1 = data.oMi[static_cast<size_t>(g1.joint)].actInv(pinocchio::SE3(rotation, p1));
          p.placement2 = data.oMi[static_cast<size_t>(g2.joint)].actInv(pinocchio::SE3(rotation, p2));
          p.position = 0.5 * (p1 + p2);
          p.normal = normal;
          p.rotation = rotation;
          const Eigen::Vector3d d = p2 - p1;
          double gap = normal[0] * d[0];  // ordered_dot
          gap += normal[1] * d[1];
          gap += normal[2] * d[2];
          p.gap = gap;
          p.friction = pair_friction[k];
          p.restitution = pair_restitution[k];
          w.points.push_back(p);
        }
      }
    }
    // ---- ContactModel.problem --------------------------------------------------------------------------------
    w.keys.clear();
    w.sizes.clear();
    w.next_structure.clear();
    for (const Point & p : w.points)
    {
      w.keys.push_back({0, p.pair, p.index});
      w.sizes.push_back(3);
      w.next_structure.insert(w.next_structure.end(), {0, p.joint1, p.joint2});
    }
    int limit_rows = 0;
    if (w.has_limit)
    {
      w.limit.makeSelectionFilteredByLimitProximity(q);
      limit_rows = w.limit.residualSize();
      if (limit_rows)
      {
        std::vector<int64_t> key{1};
        for (auto idx : w.limit.active_idx_in_activable())
          key.push_back(static_cast<int64_t>(idx));
        w.next_structure.insert(w.next_structure.end(), key.begin(), key.end());
        w.keys.push_back(std::move(key));
        w.sizes.push_back(limit_rows);
      }
    }
    if (w.has_friction)
    {
      w.friction.setTimeStep(h);
      w.keys.push_back({2});
      w.sizes.push_back(w.friction.residualSize());
      w.next_structure.push_back(2);
    }
    if (w.keys.empty())  // nothing to solve: TimeStepping.attempt's `problem is None`
    {
      v_next = v_free;
      contact_work = correction = bounce = 0.0;
      row.keys.clear();
      row.impulses.clear();
      row.landed.clear();
      row.active.clear();
      return false;
    }
    const size_t n_models = w.keys.size();
    if (w.next_structure != w.structure || w.models.size() != n_models)
    {  // a new constraint set: Python's models (a point contact per point, copies of the limits and friction)
      w.models.clear();
      for (const Point & p : w.points)
        w.models.emplace_back(pinocchio::PointContactConstraintModel(
          model, static_cast<pinocchio::JointIndex>(p.joint1), p.placement1,
          static_cast<pinocchio::JointIndex>(p.joint2), p.placement2));
      if (limit_rows)
        w.models.emplace_back(w.limit);
      if (w.has_friction)
        w.models.emplace_back(w.friction);
      w.datas.clear();
      for (const pinocchio::ConstraintModel & cm : w.models)
        w.datas.push_back(cm.createData());
      w.structure.swap(w.next_structure);
    }
    else
    {  // the same set: this step's placements, selection and time step (the models hold nothing else)
      size_t k = 0;
      for (const Point & p : w.points)
      {
        auto & point = boost::get<pinocchio::PointContactConstraintModel>(w.models[k++].toVariant());
        point.joint1_placement = p.placement1;
        point.joint2_placement = p.placement2;
      }
      if (limit_rows)
        boost::get<pinocchio::JointLimitConstraintModel>(w.models[k++].toVariant()) = w.limit;
      if (w.has_friction)
        boost::get<pinocchio::JointFrictionConstraintModel>(w.models[k++].toVariant()) = w.friction;
    }
    for (size_t k = 0; k < w.points.size(); ++k)
      boost::get<pinocchio::PointContactConstraintModel>(w.models[k].toVariant()).setFriction(w.points[k].friction);
    pinocchio::crba(model, data, q, pinocchio::Convention::WORLD);
    data.q_in = q;
    for (size_t k = 0; k < n_models; ++k)
      w.models[k].calc(model, data, w.datas[k]);
    w.cholesky.rebuild(model, data, w.models, w.datas);  // = the constructor's work, on the kept storage
    w.cholesky.compute(model, data, w.models, w.datas, c.delassus_damping);
    int m = 0;
    for (int s : w.sizes)
      m += s;
    w.J.setZero(m, model.nv);
    pinocchio::getConstraintsJacobian(model, data, w.models, w.datas, w.J);
    const int nv = model.nv;
    w.g.resize(m);
    for (int r = 0; r < m; ++r)  // ordered_matvec(J, v_free)
    {
      double s = w.J(r, 0) * v_free[0];
      for (int i = 1; i < nv; ++i)
        s += w.J(r, i) * v_free[i];
      w.g[r] = s;
    }
    w.correction.setZero(m);
    w.restitution.setZero(m);
    w.landings.clear();
    const int n_points = static_cast<int>(w.points.size());
    if (n_points)
    {
      const double threshold = -c.gravity * h;
      for (int k = 0; k < n_points; ++k)
      {
        const Point & p = w.points[static_cast<size_t>(k)];
        const int r = 3 * k + 2;
        double approach = w.J(r, 0) * v[0];  // ordered_matvec(J[2::3], v): the normal velocity at the start
        for (int i = 1; i < nv; ++i)
          approach += w.J(r, i) * v[i];
        double bias;
        if (p.gap < 0.0)
        {
          const double push = c.penetration_correction * std::min(p.gap + c.penetration_slop, 0.0) / h;
          w.correction[r] = std::max(push, -c.max_correction_speed);
          bias = w.correction[r];
        }
        else
          bias = p.gap / h;
        if (p.restitution > 0.0)
        {
          if (p.gap < c.touching)
          {
            double speed = approach;
            for (const auto & [pair, u] : row.landed)
              if (pair == p.pair)
                speed = u;
            if (speed < threshold)
            {
              w.restitution[r] = p.restitution * speed;
              bias = std::min(bias, 0.0) + w.restitution[r];
            }
          }
          else if (w.g[r] + bias < 0.0 && approach < threshold)  // lands within this step
          {
            bool found = false;
            for (auto & [pair, u] : w.landings)
              if (pair == p.pair)
              {
                u = std::min(u, approach);
                found = true;
              }
            if (!found)
              w.landings.emplace_back(p.pair, std::min(0.0, approach));
          }
        }
        w.g[r] += bias;
      }
    }
    if (limit_rows)
    {
      const auto & ld = boost::get<pinocchio::JointLimitConstraintData>(w.datas[static_cast<size_t>(n_points)].toVariant());
      const int r0 = 3 * n_points;
      for (int i = 0; i < limit_rows; ++i)
      {
        const double distance = ld.constraint_residual[i];
        const double push = c.penetration_correction * std::min(distance + c.penetration_slop, 0.0) / h;
        w.correction[r0 + i] = std::max(push, -c.max_correction_speed);
        w.g[r0 + i] += distance >= 0.0 ? distance / h : w.correction[r0 + i];
      }
    }
    // ---- TimeStepping._solve: warm-started from the blocks seen last step -----------------------------------
    w.guess.setZero(m);
    {
      int start = 0;
      for (size_t b = 0; b < w.keys.size(); ++b)
      {
        for (size_t o = 0; o < row.keys.size(); ++o)
          if (row.keys[o] == w.keys[b])
          {
            if (row.impulses[o].size() == w.sizes[b])
              w.guess.segment(start, w.sizes[b]) = row.impulses[o];
            break;
          }
        start += w.sizes[b];
      }
    }
    auto delassus = w.cholesky.getDelassusOperatorCholeskyExpression();
    bool converged;
    std::size_t iterations;
    if (c.pgs)
    {
      w.pgs_result.setConstraintImpulseGuess(w.guess);
      converged = w.pgs.solve(delassus, w.g, w.models, w.datas, w.pgs_settings, w.pgs_result);
      w.impulses.resize(m);
      w.pgs_result.retrieveConstraintImpulses(w.impulses);
      iterations = w.pgs_result.iterations;
    }
    else
    {
      w.admm_result.setConstraintImpulseGuess(w.guess);
      converged = w.admm.solve(delassus, w.g, w.models, w.datas, w.admm_settings, w.admm_result);
      w.impulses.resize(m);
      w.admm_result.retrieveConstraintImpulses(w.impulses);
      iterations = w.admm_result.iterations;
    }
    row.steps += 1;
    row.iterations += static_cast<int64_t>(iterations);
    row.unconverged += converged ? 0 : 1;
    row.keys.swap(w.keys);  // (w.keys is rebuilt next step)
    row.impulses.resize(row.keys.size());
    {
      int start = 0;
      for (size_t b = 0; b < row.keys.size(); ++b)
      {
        row.impulses[b] = w.impulses.segment(start, w.sizes[b]);
        start += w.sizes[b];
      }
    }
    // ---- TimeStepping.attempt: v⁺ = v_free + M⁻¹ Jᵀ λ and the contact's energies -----------------------------
    w.generalized.resize(nv);
    for (int i = 0; i < nv; ++i)  // ordered_matvec(J.T, λ)
    {
      double s = w.J(0, i) * w.impulses[0];
      for (int r = 1; r < m; ++r)
        s += w.J(r, i) * w.impulses[r];
      w.generalized[i] = s;
    }
    pinocchio::cholesky::decompose(model, data);  // ContactModel.inverse_mass_times
    w.minv = w.generalized;
    pinocchio::cholesky::solve(model, data, w.minv);
    v_next.resize(nv);
    for (int i = 0; i < nv; ++i)
      v_next[i] = v_free[i] + w.minv[i];
    double s = w.generalized[0] * (v_next[0] + v_free[0]);
    for (int i = 1; i < nv; ++i)
      s += w.generalized[i] * (v_next[i] + v_free[i]);
    contact_work = 0.5 * s;
    double corr = w.impulses[0] * w.correction[0], rest = w.impulses[0] * w.restitution[0];
    for (int r = 1; r < m; ++r)
    {
      corr += w.impulses[r] * w.correction[r];
      rest += w.impulses[r] * w.restitution[r];
    }
    correction = -corr;
    bounce = -rest;
    // ContactModel.records: pair, point, normal, impulse on body 2 in world axes
    row.active.resize(w.points.size());
    for (size_t k = 0; k < w.points.size(); ++k)
    {
      const Point & p = w.points[k];
      std::array<double, 11> & out = row.active[k];
      out[0] = p.body1;
      out[1] = p.body2;
      for (int r = 0; r < 3; ++r)
      {
        out[2 + r] = p.position[r];
        out[5 + r] = p.normal[r];
        double x = p.rotation(r, 0) * w.impulses[3 * k];
        x += p.rotation(r, 1) * w.impulses[3 * k + 1];
        x += p.rotation(r, 2) * w.impulses[3 * k + 2];
        out[8 + r] = x;
      }
    }
    row.landed = w.landings;
    return true;
  }
} // namespace multibody_sim

// ---- Python bindings: _native.ContactScene and its named data (kernels/native.py is their only user) ------------
#include <nanobind/eigen/dense.h>
#include <nanobind/nanobind.h>
#include <nanobind/stl/pair.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/vector.h>

#include "structs.hpp"

namespace nb = nanobind;

namespace
{
  // ContactModel.native_data(): the geometry and constraints, by name
  struct ContactData
  {
    std::vector<multibody_sim::ContactShape> shapes;
    std::vector<std::pair<int, int>> pairs;
    std::vector<double> friction, restitution;
    std::vector<int> limited_joints, friction_joints;
    Eigen::VectorXd limit_margin, friction_bound;
    multibody_sim::ContactConstants constants;
  };
} // namespace

void multibody_sim::bind_contact(nb::module_ & m)  // called by module.cpp
{
  using namespace multibody_sim;
  nb::class_<ContactRow>(m, "ContactRow", "One row's contact solver state (a snapshot's part).")
    .def(nb::init<>())
    .def_prop_ro("steps", [](const ContactRow & r) { return r.steps; })
    .def_prop_ro("unconverged", [](const ContactRow & r) { return r.unconverged; })
    .def_prop_ro("iterations", [](const ContactRow & r) { return r.iterations; });
  Struct<ContactShape>(m, "ContactShape", "A collision shape (contact.Geometry) and the joint it moves with.")
    .choice("kind", &ContactShape::kind,
            {{"halfspace", ShapeKind::halfspace}, {"box", ShapeKind::box}, {"sphere", ShapeKind::sphere},
             {"cylinder", ShapeKind::cylinder}})
    .field("joint", &ContactShape::joint, "int")
    .field("body", &ContactShape::body, "int")
    .field("rotation", &ContactShape::rotation, "a 3 x 3 float array")
    .field("translation", &ContactShape::translation, "3 floats")
    .field("dimensions", &ContactShape::dims, "list[float]")
    .finish([](ContactShape & s) {
      const size_t need = s.kind == ShapeKind::box ? 3 : (s.kind == ShapeKind::cylinder ? 2 : 1);
      if (s.dims.size() != need)
        throw std::invalid_argument("ContactShape.dimensions disagree with its kind (box 3, cylinder 2, else 1)");
    });
  Struct<ContactConstants>(m, "ContactConstants", "contact.py's and timestepping.py's constants of a contact step.")
    .field("speculative_margin", &ContactConstants::speculative_margin, "float")
    .field("penetration_correction", &ContactConstants::penetration_correction, "float")
    .field("penetration_slop", &ContactConstants::penetration_slop, "float")
    .field("max_correction_speed", &ContactConstants::max_correction_speed, "float")
    .field("touching", &ContactConstants::touching, "float")
    .field("delassus_damping", &ContactConstants::delassus_damping, "float")
    .field("tolerance", &ContactConstants::tolerance, "float")
    .field("max_patch_points", &ContactConstants::max_patch_points, "int")
    .field("anderson_capacity", &ContactConstants::anderson_capacity, "int")
    .field("max_iterations", &ContactConstants::max_iterations, "int")
    .field("pgs", &ContactConstants::pgs, "bool")
    .field("gravity", &ContactConstants::gravity, "float")
    .finish();
  auto fields = std::make_shared<Fields<ContactData>>("ContactScene");
  fields->member("shapes", &ContactData::shapes, "list[ContactShape]")
    .member("pairs", &ContactData::pairs, "list[tuple[int, int]]")
    .member("friction", &ContactData::friction, "list[float]")
    .member("restitution", &ContactData::restitution, "list[float]")
    .member("limited_joints", &ContactData::limited_joints, "list[int]")
    .member("limit_margin", &ContactData::limit_margin, "an array of nq floats")
    .member("friction_joints", &ContactData::friction_joints, "list[int]")
    .member("friction_bound", &ContactData::friction_bound, "an array of nv floats")
    .member("constants", &ContactData::constants, "ContactConstants");
  nb::class_<ContactScene>(m, "ContactScene", "A scene's collision geometry and unilateral constraints.")
    .def(
      "__init__",
      [fields](ContactScene * self, const NativeModel & model, nb::kwargs kwargs) {
        const ContactData d = fields->parse(kwargs);
        new (self) ContactScene(
          model.model, d.shapes, d.pairs, d.friction, d.restitution, d.limited_joints, d.limit_margin,
          d.friction_joints, d.friction_bound, d.constants);
      },
      nb::arg("model"), nb::arg("kwargs"),
      "From the scene's model and the contact model's named data (kernels/native.contact_data()).")
    .attr("fields") = fields->names();
}
