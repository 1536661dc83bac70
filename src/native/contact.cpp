// The contact part of the `timestepping` step (see contact.hpp): scenes/narrow_phase.py, scenes/contact.py's
// ContactModel.detect and .problem and integrators/timestepping.py's solve, in their order. Each section names the
// Python it renders.
#include "contact.hpp"
#include "model.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <string>

#include <boost/asio/streambuf.hpp>
#include <coal/collision_data.h>
#include <coal/serialization/archive.h>
#include <coal/serialization/convex.h>
#include <coal/shape/convex.h>
#include <coal/shape/geometric_shapes.h>

#include "pinocchio/algorithm/cholesky.hpp"
#include "pinocchio/algorithm/crba.hpp"
#include "pinocchio/algorithm/geometry.hpp"
#include "pinocchio/collision/collision.hpp"
#include "pinocchio/multibody/geometry.hpp"

namespace multibody_sim
{
  namespace
  {
    using Matrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
    using Vector3 = Eigen::Vector3d;

    // narrow_phase's pair kinds
    enum PairKind : int
    {
      SPHERE_GROUND = 0,
      BOX_GROUND = 1,
      CYLINDER_GROUND = 2,
      CAPSULE_GROUND = 3,
      MESH_GROUND = 4,
      SPHERE_SPHERE = 5,
      SPHERE_BOX = 6,
      BOX_SPHERE = 7,
      BOX_BOX = 8,
      COAL = 9,
    };

    int pair_kind(ShapeKind a, ShapeKind b)  // narrow_phase.pair_kind
    {
      if (a == ShapeKind::halfspace)
        switch (b)
        {
        case ShapeKind::sphere:
          return SPHERE_GROUND;
        case ShapeKind::box:
          return BOX_GROUND;
        case ShapeKind::cylinder:
          return CYLINDER_GROUND;
        case ShapeKind::capsule:
          return CAPSULE_GROUND;
        case ShapeKind::mesh:
          return MESH_GROUND;
        default:
          return COAL;
        }
      if (a == ShapeKind::sphere && b == ShapeKind::sphere)
        return SPHERE_SPHERE;
      if (a == ShapeKind::sphere && b == ShapeKind::box)
        return SPHERE_BOX;
      if (a == ShapeKind::box && b == ShapeKind::sphere)
        return BOX_SPHERE;
      if (a == ShapeKind::box && b == ShapeKind::box)
        return BOX_BOX;
      return COAL;
    }

    // A mesh hull from coal's archive (contact.ContactModel.native_data); throws what Boost and coal throw on a bad one.
    std::shared_ptr<coal::CollisionGeometry> load_hull(const ContactShape & s)
    {
      auto hull = std::make_shared<coal::Convex<coal::Triangle>>();
      boost::asio::streambuf buffer;
      buffer.sputn(reinterpret_cast<const char *>(s.archive.data()), static_cast<std::streamsize>(s.archive.size()));
      coal::serialization::loadFromBuffer(*hull, buffer);
      return hull;
    }

    // contact.make_shape; a mesh stands as its bounding sphere until a pair needs coal with it (ContactWork.hulls)
    std::shared_ptr<coal::CollisionGeometry> make_shape(const ContactShape & s)
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
      case ShapeKind::capsule:
        return std::make_shared<coal::Capsule>(s.dims.at(0), s.dims.at(1));
      case ShapeKind::mesh:
        return std::make_shared<coal::Sphere>(s.radius);
      }
      throw std::invalid_argument("unknown shape kind");
    }

    // narrow_phase.Candidate
    struct Candidate
    {
      int feature = 0;
      Vector3 p1, p2;
      double gap = 0.0;
    };

    // narrow_phase.transform for one point: ((R0 x + R1 y) + R2 z) + t per coordinate
    inline Vector3 transform(const Eigen::Matrix3d & R, const Vector3 & t, const Vector3 & l)
    {
      Vector3 out;
      for (int r = 0; r < 3; ++r)
        out[r] = ((R(r, 0) * l[0] + R(r, 1) * l[1]) + R(r, 2) * l[2]) + t[r];
      return out;
    }

    inline double norm3(double a, double b, double c)  // sqrt((a a + b b) + c c)
    {
      return std::sqrt((a * a + b * b) + c * c);
    }
  } // namespace

  // contact.ContactPoint
  struct Point
  {
    int pair = 0, feature = 0;
    int joint1 = 0, joint2 = 0, body1 = 0, body2 = 0;
    Vector3 p1, p2, position, normal;
    Eigen::Matrix3d rotation;
    double gap = 0.0, friction = 0.0, restitution = 0.0;
  };

  struct ContactWork
  {
    pinocchio::Data data;  // the contact's own Data (ContactModel.data)
    pinocchio::GeometryModel gm;
    pinocchio::GeometryData gd;
    cone::Solver solver;
    std::vector<Candidate> found, patch;
    std::vector<int> chosen;
    std::vector<double> nearest;
    std::vector<Vector3> midpoints;
    std::vector<Point> points;
    // (sign, v index, joint, distance) of each selected limit
    struct Limit
    {
      double sign;
      int iv, joint;
      double distance;
    };
    std::vector<Limit> limits;
    // (sign, v index, joint, v_max, ledger line, side) of each velocity-limit row, in the order they joined
    struct Speed
    {
      double sign;
      int iv, joint;
      double vmax;
      int line, side;
    };
    std::vector<Speed> speeds;
    std::vector<std::array<int64_t, 3>> keys;
    std::vector<int> sizes;
    std::vector<std::vector<int>> row_support;  // per row: the dofs where its J row (and Z column) may be nonzero
    std::vector<cone::Block> blocks;
    Matrix J, G;
    Matrix Z, W;  // nv x m
    Eigen::VectorXd g, free, correction, restitution, guess, impulses, generalized, minv, Dinv, acc;
    Eigen::VectorXd mass_v;  // M v (ContactScene::kinetic_energy)
    std::vector<std::pair<int, double>> landings;
    std::vector<int> union_, last;
    // the contact frame of the normal +z (the ground's), as every other normal's is computed
    const Eigen::Matrix3d up =
      Eigen::Quaterniond::FromTwoVectors(Eigen::Vector3d::UnitZ(), Eigen::Vector3d::UnitZ()).toRotationMatrix();

    // ContactModel.speeding: the velocity-limit rows of each joint whose velocity is beyond (1 - band) v_max, in
    // joint order, lower side first, but for those selected already; appended to `speeds` (and their keys). Returns
    // how many were added.
    size_t select_speeds(const ContactScene & scene, const Vec & velocity, double band)
    {
      const size_t selected = speeds.size();
      for (size_t k = 0; k < scene.speed_joints.size(); ++k)
      {
        const int jid = scene.speed_joints[k], iv = scene.speed_dofs[k];
        const double vmax = scene.speed_limits[k], reach = (1.0 - band) * vmax;
        bool lower = false, upper = false;
        for (size_t o = 0; o < selected; ++o)
          if (speeds[o].joint == jid)
            (speeds[o].side ? upper : lower) = true;
        if (velocity[iv] < -reach && !lower)
          add_speed({1.0, iv, jid, vmax, scene.speed_lines[k], 0});
        if (velocity[iv] > reach && !upper)
          add_speed({-1.0, iv, jid, vmax, scene.speed_lines[k], 1});
      }
      return speeds.size() - selected;
    }

    void add_speed(const Speed & sp)  // a velocity-limit row with its warm-start key ("speed", joint, side)
    {
      speeds.push_back(sp);
      keys.push_back({3, sp.joint, sp.side});
      sizes.push_back(1);
    }

    // The rows of speeds[from:] appended to the assembled problem (J, Z, W, G, g and its parts, the blocks), each
    // entry as ContactModel.problem forms it with every row at once: a selection row's Z column by the same
    // back substitution, G(a, r) = Σ_k Z(k, a) W(k, r) over the shared support in index order, u = v_max ± v⁺.
    // Returns the problem's rows.
    int append_speed_rows(size_t from, const std::vector<std::vector<int>> & supports, const Vec & v_free)
    {
      const int old = static_cast<int>(g.size()), added = static_cast<int>(speeds.size() - from);
      const int m = old + added, nv = static_cast<int>(v_free.size());
      J.conservativeResize(m, nv);
      J.bottomRows(added).setZero();
      Z.conservativeResize(nv, m);
      Z.rightCols(added).setZero();
      W.conservativeResize(nv, m);
      W.rightCols(added).setZero();
      G.conservativeResize(m, m);
      row_support.resize(static_cast<size_t>(m));
      free.conservativeResize(m);
      g.conservativeResize(m);
      correction.conservativeResize(m);
      restitution.conservativeResize(m);
      for (int r = old; r < m; ++r)
      {
        const Speed & sp = speeds[from + static_cast<size_t>(r - old)];
        J(r, sp.iv) = sp.sign;
        const std::vector<int> & S = row_support[static_cast<size_t>(r)] = supports[static_cast<size_t>(sp.joint)];
        for (int col : S)
          Z(col, r) = J(r, col);
        for (int a = static_cast<int>(S.size()) - 1; a >= 0; --a)
        {
          const int k = S[static_cast<size_t>(a)];
          const int end = k + data.nvSubtree_fromRow[static_cast<size_t>(k)];
          double s = 0.0;
          for (size_t b = static_cast<size_t>(a) + 1; b < S.size() && S[b] < end; ++b)
            s += data.U(k, S[b]) * Z(S[b], r);
          Z(k, r) = Z(k, r) - s;
        }
        for (int col : S)
          W(col, r) = (1.0 / data.D[col]) * Z(col, r);
        for (int a = 0; a <= r; ++a)
        {
          const std::vector<int> & Sa = row_support[static_cast<size_t>(a)];
          double s = 0.0;
          size_t i = 0, j = 0;
          while (i < Sa.size() && j < S.size())
          {
            if (Sa[i] < S[j])
              ++i;
            else if (S[j] < Sa[i])
              ++j;
            else
            {
              s += Z(Sa[i], a) * W(Sa[i], r);
              ++i;
              ++j;
            }
          }
          G(a, r) = s;
          G(r, a) = s;
        }
        double s = 0.0;
        for (int col : S)
          s += J(r, col) * v_free[col];
        free[r] = s;
        g[r] = s + sp.vmax;
        correction[r] = 0.0;
        restitution[r] = 0.0;
        blocks.push_back(cone::Block{cone::HALFLINE, r, 0.0});
      }
      return m;
    }

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
      solver.settings = scene.constants.solver;
    }

    // The mesh hulls from their archives, once a pair needs coal with one (most hulls only ever meet the ground,
    // whose pairs the narrow phase computes from their vertices): the geometry data rebuilt on them, placed where
    // the current kinematics put them.
    void hulls(const pinocchio::Model & model, const pinocchio::Data & placed, const ContactScene & scene)
    {
      if (hulls_loaded)
        return;
      for (size_t k = 0; k < scene.shapes.size(); ++k)
        if (scene.shapes[k].kind == ShapeKind::mesh)
          gm.geometryObjects[k].geometry = load_hull(scene.shapes[k]);
      gd = pinocchio::GeometryData(gm);
      for (coal::CollisionRequest & request : gd.collisionRequests)
      {
        request.enable_contact = true;
        request.security_margin = scene.constants.speculative_margin;
      }
      pinocchio::updateGeometryPlacements(model, placed, gm, gd);
      hulls_loaded = true;
    }

    bool hulls_loaded = false;
  };

  namespace
  {
    // ---- narrow_phase.py ------------------------------------------------------------------------------------------
    // _ground: the candidates of lowest points (already lowered) against z >= height
    void ground_point(std::vector<Candidate> & out, const Vector3 & p2, double height, int feature, double margin)
    {
      const double gap = p2[2] - height;
      if (gap < margin)
        out.push_back(Candidate{feature, Vector3(p2[0], p2[1], height), p2, gap});
    }

    // narrow_phase.cylinder_rims
    void cylinder_rims(const Eigen::Matrix3d & R, const Vector3 & t, double radius, double half, double flat,
                       Vector3 (&out)[8])
    {
      const Vector3 a = R.col(2);
      const double px = a[2] * a[0], py = a[2] * a[1], pz = a[2] * a[2] - 1.0;
      const double norm2 = (px * px + py * py) + pz * pz;
      Vector3 u, w;
      if (norm2 <= flat)
      {
        u = R.col(0);
        w = R.col(1);
      }
      else
      {
        const double norm = std::sqrt(norm2);
        u = Vector3(px / norm, py / norm, pz / norm);
        w = Vector3(a[1] * u[2] - a[2] * u[1], a[2] * u[0] - a[0] * u[2], a[0] * u[1] - a[1] * u[0]);
      }
      for (int end = 0; end < 2; ++end)
      {
        const double sign = end == 0 ? 1.0 : -1.0;
        Vector3 centre;
        for (int r = 0; r < 3; ++r)
          centre[r] = t[r] + (sign * half) * a[r];
        const Vector3 * dirs[4] = {&u, &u, &w, &w};
        const double signs[4] = {1.0, -1.0, 1.0, -1.0};
        for (int k = 0; k < 4; ++k)
          for (int r = 0; r < 3; ++r)
            out[4 * end + k][r] = centre[r] + (signs[k] * radius) * (*dirs[k])[r];
      }
    }

    // narrow_phase.ground_candidates
    void ground_candidates(int kind, double height, const Eigen::Matrix3d & R, const Vector3 & t,
                           const ContactShape & shape, const ContactConstants & c, std::vector<Candidate> & out)
    {
      const double margin = c.speculative_margin;
      const std::vector<double> & dims = shape.dims;
      switch (kind)
      {
      case SPHERE_GROUND:
        ground_point(out, Vector3(t[0], t[1], t[2] - dims[0]), height, 0, margin);
        return;
      case BOX_GROUND:
      {
        const double half[3] = {0.5 * dims[0], 0.5 * dims[1], 0.5 * dims[2]};
        for (int k = 0; k < 8; ++k)  // BOX_CORNERS: x fastest, then y, then z
        {
          const Vector3 local((k & 1 ? 1.0 : -1.0) * half[0], (k & 2 ? 1.0 : -1.0) * half[1],
                              (k & 4 ? 1.0 : -1.0) * half[2]);
          ground_point(out, transform(R, t, local), height, k, margin);
        }
        return;
      }
      case CAPSULE_GROUND:
      {
        const double half = 0.5 * dims[1];
        for (int k = 0; k < 2; ++k)
        {
          Vector3 end = transform(R, t, Vector3(0.0, 0.0, k == 0 ? half : -half));
          end[2] = end[2] - dims[0];
          ground_point(out, end, height, k, margin);
        }
        return;
      }
      case CYLINDER_GROUND:
      {
        Vector3 rims[8];
        cylinder_rims(R, t, dims[0], 0.5 * dims[1], c.flat_disk, rims);
        for (int k = 0; k < 8; ++k)
          ground_point(out, rims[k], height, k, margin);
        return;
      }
      default:  // MESH_GROUND: the z of every vertex first
      {
        const auto & V = shape.vertices;
        for (int k = 0; k < V.rows(); ++k)
        {
          const double z = ((R(2, 0) * V(k, 0) + R(2, 1) * V(k, 1)) + R(2, 2) * V(k, 2)) + t[2];
          if (z - height < margin)
            ground_point(out, transform(R, t, V.row(k).transpose()), height, k, margin);
        }
      }
      }
    }

    // narrow_phase.sphere_box: (candidates with p1 on the box, p2 on the sphere) and the normal from the box
    void sphere_box(const Vector3 & c, double r, const Eigen::Matrix3d & R, const Vector3 & t, const double (&half)[3],
                    double margin, std::vector<Candidate> & out, Vector3 & normal)
    {
      const Vector3 d = c - t;
      Vector3 local, clamped;
      for (int i = 0; i < 3; ++i)
        local[i] = (R(0, i) * d[0] + R(1, i) * d[1]) + R(2, i) * d[2];
      for (int i = 0; i < 3; ++i)
      {
        const double x = local[i] < -half[i] ? -half[i] : local[i];
        clamped[i] = x > half[i] ? half[i] : x;
      }
      Vector3 n_local = Vector3::Zero(), surface;
      double gap;
      if (clamped == local)
      {
        double depths[3];
        int axis = 0;
        for (int i = 0; i < 3; ++i)
        {
          depths[i] = half[i] - std::abs(local[i]);
          if (depths[i] < depths[axis])
            axis = i;
        }
        const double sign = local[axis] >= 0.0 ? 1.0 : -1.0;
        n_local[axis] = sign;
        surface = local;
        surface[axis] = sign * half[axis];
        gap = -depths[axis] - r;
      }
      else
      {
        const Vector3 diff = local - clamped;
        const double dist = norm3(diff[0], diff[1], diff[2]);
        n_local = Vector3(diff[0] / dist, diff[1] / dist, diff[2] / dist);
        surface = clamped;
        gap = dist - r;
      }
      for (int i = 0; i < 3; ++i)
        normal[i] = (R(i, 0) * n_local[0] + R(i, 1) * n_local[1]) + R(i, 2) * n_local[2];
      if (gap >= margin)
        return;
      Vector3 on_sphere;
      for (int i = 0; i < 3; ++i)
        on_sphere[i] = c[i] - r * normal[i];
      out.push_back(Candidate{0, transform(R, t, surface), on_sphere, gap});
    }

    // ---- narrow_phase.box_box ------------------------------------------------------------------------------------
    inline double dot3(const double * u, const double * v)  // narrow_phase._dot
    {
      return (u[0] * v[0] + u[1] * v[1]) + u[2] * v[2];
    }

    struct Box  // a box's pose and half extents, its axes as rows (a[i] = R.col(i))
    {
      double a[3][3];
      const Eigen::Matrix3d * R;
      const Vector3 * t;
      double half[3];
    };

    Box make_box(const Eigen::Matrix3d & R, const Vector3 & t, const std::vector<double> & dims)
    {
      Box b;
      for (int i = 0; i < 3; ++i)
      {
        for (int r = 0; r < 3; ++r)
          b.a[i][r] = R(r, i);
        b.half[i] = 0.5 * dims[static_cast<size_t>(i)];
      }
      b.R = &R;
      b.t = &t;
      return b;
    }

    // narrow_phase._separation
    double separation(const double * d, const Box & A, const Box & B, const double * n)
    {
      const double r1 = (A.half[0] * std::abs(dot3(A.a[0], n)) + A.half[1] * std::abs(dot3(A.a[1], n)))
                        + A.half[2] * std::abs(dot3(A.a[2], n));
      const double r2 = (B.half[0] * std::abs(dot3(B.a[0], n)) + B.half[1] * std::abs(dot3(B.a[1], n)))
                        + B.half[2] * std::abs(dot3(B.a[2], n));
      return std::abs(dot3(d, n)) - (r1 + r2);
    }

    struct PolygonPoint  // narrow_phase._face_contact's polygon: a point in the reference frame, its edge's label
    {
      double x[3];
      int label;
    };

    // narrow_phase._clip: `in` (n points) into `out`, returns the new count
    int clip(const PolygonPoint * in, int n, int p, double sigma, double h, int label, PolygonPoint * out)
    {
      int m = 0;
      for (int k = 0; k < n; ++k)
      {
        const PolygonPoint & P = in[k];
        const PolygonPoint & Q = in[(k + 1) % n];
        const double fP = sigma * P.x[p] - h, fQ = sigma * Q.x[p] - h;
        if (fP <= 0.0)
          out[m++] = P;
        if ((fP <= 0.0) != (fQ <= 0.0))
        {
          const double t = fP / (fP - fQ);
          PolygonPoint X;
          for (int r = 0; r < 3; ++r)
            X.x[r] = P.x[r] + t * (Q.x[r] - P.x[r]);
          X.x[p] = sigma * h;
          X.label = fP <= 0.0 ? label : P.label;
          out[m++] = X;
        }
      }
      return m;
    }

    constexpr int FACE_POINTS = 64, EDGE_FEATURES = 72 * FACE_POINTS;  // narrow_phase's

    // narrow_phase._face_contact: candidates with p1 on the reference box Ref, p2 on the incident box Inc
    Vector3 face_contact(const Box & Ref, int axis, double sign, const Box & Inc, int ref, double margin,
                         std::vector<Candidate> & out)
    {
      const Eigen::Matrix3d & Rr = *Ref.R;
      const Vector3 & tr = *Ref.t;
      const double outward[3] = {sign * Rr(0, axis), sign * Rr(1, axis), sign * Rr(2, axis)};
      double dots[3];
      for (int j = 0; j < 3; ++j)
        dots[j] = dot3(Inc.a[j], outward);
      int j = 0;
      for (int k = 1; k < 3; ++k)
        if (std::abs(dots[k]) > std::abs(dots[j]))
          j = k;
      const double s = dots[j] >= 0.0 ? -1.0 : 1.0;
      const int ju = (j + 1) % 3, jv = (j + 2) % 3;
      PolygonPoint buffers[2][8];
      int n = 4;
      const double cu[4] = {1.0, -1.0, -1.0, 1.0}, cv[4] = {1.0, 1.0, -1.0, -1.0};
      for (int label = 0; label < 4; ++label)
      {
        Vector3 corner;
        corner[j] = s * Inc.half[j];
        corner[ju] = cu[label] * Inc.half[ju];
        corner[jv] = cv[label] * Inc.half[jv];
        const Vector3 world = transform(*Inc.R, *Inc.t, corner);
        const double w[3] = {world[0] - tr[0], world[1] - tr[1], world[2] - tr[2]};
        PolygonPoint & P = buffers[0][label];
        for (int r = 0; r < 3; ++r)
          P.x[r] = (Rr(0, r) * w[0] + Rr(1, r) * w[1]) + Rr(2, r) * w[2];
        P.label = label;
      }
      const int sides[4] = {(axis + 1) % 3, (axis + 1) % 3, (axis + 2) % 3, (axis + 2) % 3};
      const double sigmas[4] = {1.0, -1.0, 1.0, -1.0};
      int current = 0;
      for (int side = 0; side < 4 && n > 0; ++side)
      {
        n = clip(buffers[current], n, sides[side], sigmas[side], Ref.half[sides[side]], 4 + side,
                 buffers[1 - current]);
        current = 1 - current;
      }
      const int code = ((6 * ref + 2 * axis + (sign < 0.0 ? 1 : 0)) * 6 + 2 * j + (s < 0.0 ? 1 : 0)) * FACE_POINTS;
      const PolygonPoint * polygon = buffers[current];
      for (int k = 0; k < n; ++k)
      {
        const PolygonPoint & X = polygon[k];
        const double gap = sign * X.x[axis] - Ref.half[axis];
        if (gap >= margin)
          continue;
        Vector3 on_face(X.x[0], X.x[1], X.x[2]);
        on_face[axis] = sign * Ref.half[axis];
        const int before = polygon[(k + n - 1) % n].label;
        out.push_back(Candidate{code + 8 * before + X.label, transform(Rr, tr, on_face),
                                transform(Rr, tr, Vector3(X.x[0], X.x[1], X.x[2])), gap});
      }
      return Vector3(outward[0], outward[1], outward[2]);
    }

    // narrow_phase._edge_contact
    Vector3 edge_contact(const Box & A, const Box & B, int i, int j, const double * axis, const double * d, double gap,
                         std::vector<Candidate> & out)
    {
      double n[3] = {axis[0], axis[1], axis[2]};
      if (dot3(d, n) < 0.0)
        for (double & x : n)
          x = -x;
      Vector3 local1 = Vector3::Zero(), local2 = Vector3::Zero();
      int id1 = 4 * i, id2 = 4 * j;
      for (int q = 0; q < 2; ++q)
      {
        const int k = (i + 1 + q) % 3, bit = q == 0 ? 2 : 1;
        const bool up = dot3(A.a[k], n) > 0.0;
        local1[k] = up ? A.half[k] : -A.half[k];
        id1 += up ? bit : 0;
      }
      for (int q = 0; q < 2; ++q)
      {
        const int k = (j + 1 + q) % 3, bit = q == 0 ? 2 : 1;
        const bool up = dot3(B.a[k], n) <= 0.0;
        local2[k] = up ? B.half[k] : -B.half[k];
        id2 += up ? bit : 0;
      }
      const Vector3 pA = transform(*A.R, *A.t, local1), pB = transform(*B.R, *B.t, local2);
      const double r[3] = {pB[0] - pA[0], pB[1] - pA[1], pB[2] - pA[2]};
      const double c = dot3(A.a[i], B.a[j]);
      const double ur = dot3(A.a[i], r), wr = dot3(B.a[j], r);
      const double denom = 1.0 - c * c;
      const double s1 = (ur - c * wr) / denom, s2 = (c * ur - wr) / denom;
      local1[i] = std::min(std::max(s1, -A.half[i]), A.half[i]);
      local2[j] = std::min(std::max(s2, -B.half[j]), B.half[j]);
      out.push_back(Candidate{EDGE_FEATURES + 12 * id1 + id2, transform(*A.R, *A.t, local1),
                              transform(*B.R, *B.t, local2), gap});
      return Vector3(n[0], n[1], n[2]);
    }

    // narrow_phase.box_box: the candidates and the normal from box 1 to box 2
    Vector3 box_box(const Box & A, const Box & B, const ContactConstants & c, std::vector<Candidate> & out)
    {
      const Vector3 & t1 = *A.t;
      const Vector3 & t2 = *B.t;
      const double d[3] = {t2[0] - t1[0], t2[1] - t1[1], t2[2] - t1[2]};
      const double inf = std::numeric_limits<double>::infinity();
      double best = -inf, best2 = -inf;
      int axis = 0, axis2 = 0;
      bool on2 = false;
      for (int i = 0; i < 3; ++i)
      {
        const double sep = separation(d, A, B, A.a[i]);
        if (sep > best)
        {
          best = sep;
          axis = i;
        }
      }
      for (int j = 0; j < 3; ++j)
      {
        const double sep = separation(d, A, B, B.a[j]);
        if (sep > best2)
        {
          best2 = sep;
          axis2 = j;
        }
      }
      if (best2 > best + c.axis_tolerance)
      {
        best = best2;
        axis = axis2;
        on2 = true;
      }
      int edge_i = -1, edge_j = -1;
      double edge_best = -inf, edge_n[3] = {0.0, 0.0, 0.0};
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
        {
          const double *u = A.a[i], *w = B.a[j];
          const double L[3] = {u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]};
          const double norm2 = (L[0] * L[0] + L[1] * L[1]) + L[2] * L[2];
          if (norm2 < c.parallel_edges)
            continue;
          const double norm = std::sqrt(norm2);
          const double n[3] = {L[0] / norm, L[1] / norm, L[2] / norm};
          const double sep = separation(d, A, B, n);
          if (sep > edge_best)
          {
            edge_i = i;
            edge_j = j;
            edge_best = sep;
            for (int r = 0; r < 3; ++r)
              edge_n[r] = n[r];
          }
        }
      const Vector3 up(0.0, 0.0, 1.0);
      if (edge_i >= 0 && edge_best > best + c.axis_tolerance)
      {
        if (edge_best >= c.speculative_margin)
          return up;
        return edge_contact(A, B, edge_i, edge_j, edge_n, d, edge_best, out);
      }
      if (best >= c.speculative_margin)
        return up;
      if (on2)
      {
        const double sign = dot3(d, B.a[axis]) >= 0.0 ? -1.0 : 1.0;
        const size_t first = out.size();
        const Vector3 outward = face_contact(B, axis, sign, A, 1, c.speculative_margin, out);
        for (size_t k = first; k < out.size(); ++k)
          std::swap(out[k].p1, out[k].p2);
        return -outward;
      }
      const double sign = dot3(d, A.a[axis]) >= 0.0 ? 1.0 : -1.0;
      return face_contact(A, axis, sign, B, 0, c.speculative_margin, out);
    }

    // ContactProblem.velocity_scale: max(np.max(np.abs(free)), |g| h), NaN as numpy and Python propagate it
    inline double velocity_scale(const Eigen::VectorXd & free, double floor)
    {
      double scale = 0.0;
      for (Eigen::Index r = 0; r < free.size(); ++r)
      {
        const double x = std::abs(free[r]);
        scale = r == 0 ? x : (x > scale || std::isnan(x) ? x : scale);
      }
      return floor > scale ? floor : scale;
    }

    // contact._penetration_correction: the bias b_corr ≤ 0 of a gap over a step h
    inline double penetration_correction(double gap, double h, const ContactConstants & c)
    {
      const double push = c.penetration_correction * std::min(gap + c.penetration_slop, 0.0) / h;
      return std::max(push, -c.max_correction_speed);
    }

    // narrow_phase._plane_distance2
    inline double plane_distance2(const Vector3 & a, const Vector3 & p, const Vector3 & n)
    {
      const double d0 = a[0] - p[0], d1 = a[1] - p[1], d2 = a[2] - p[2];
      const double along = (n[0] * d0 + n[1] * d1) + n[2] * d2;
      return ((d0 * d0 + d1 * d1) + d2 * d2) - along * along;
    }
  } // namespace

  ContactScene::ContactScene(
    const pinocchio::Model & model,
    const std::vector<ContactShape> & shapes_,
    const std::vector<std::pair<int, int>> & pairs_,
    const std::vector<double> & pair_friction_,
    const std::vector<double> & pair_restitution_,
    const std::vector<int> & limited_joints_,
    const std::vector<int> & friction_joints_,
    const Vec & friction_force_,
    const std::vector<int> & speed_joints_,
    const std::vector<double> & speed_limits_,
    const std::vector<int> & speed_lines_,
    const ContactConstants & constants_)
  : nv(model.nv)
  , shapes(shapes_)
  , pairs(pairs_)
  , pair_friction(pair_friction_)
  , pair_restitution(pair_restitution_)
  , limited_joints(limited_joints_)
  , friction_joints(friction_joints_)
  , friction_force(friction_force_)
  , speed_joints(speed_joints_)
  , speed_limits(speed_limits_)
  , speed_lines(speed_lines_)
  , constants(constants_)
  {
    const int n = static_cast<int>(shapes.size());
    for (const ContactShape & s : shapes)
      if (s.joint < 0 || s.joint >= model.njoints)
        throw std::invalid_argument("a contact shape's joint is not in the model");
    for (const auto & [a, b] : pairs)
    {
      if (a < 0 || b < 0 || a >= n || b >= n)
        throw std::invalid_argument("a contact pair names a shape that does not exist");
      pair_kinds.push_back(pair_kind(shapes[static_cast<size_t>(a)].kind, shapes[static_cast<size_t>(b)].kind));
      if (pair_kinds.back() == MESH_GROUND && shapes[static_cast<size_t>(b)].vertices.rows() == 0)
        throw std::invalid_argument("a mesh shape has no vertices");
    }
    if (pair_friction.size() != pairs.size() || pair_restitution.size() != pairs.size())
      throw std::invalid_argument("one friction and one restitution coefficient per contact pair");
    if (friction_force.size() != model.nv)
      throw std::invalid_argument("the friction forces must have nv entries");
    for (int j : limited_joints)
      if (j <= 0 || j >= model.njoints || model.joints[static_cast<size_t>(j)].nq() != 1
          || model.joints[static_cast<size_t>(j)].nv() != 1)
        throw std::invalid_argument("a limited joint is not a one-coordinate joint of the model");
    for (int j : friction_joints)
      if (j <= 0 || j >= model.njoints)
        throw std::invalid_argument("a joint with exact friction is not in the model");
    if (speed_limits.size() != speed_joints.size() || speed_lines.size() != speed_joints.size())
      throw std::invalid_argument("one velocity limit and one ledger line per velocity-limited joint");
    for (size_t k = 0; k < speed_joints.size(); ++k)
    {
      const int j = speed_joints[k];
      if (j <= 0 || j >= model.njoints || model.joints[static_cast<size_t>(j)].nv() != 1)
        throw std::invalid_argument("a velocity-limited joint is not a one-dof joint of the model");
      if (!(speed_limits[k] > 0.0) || speed_lines[k] < 0)
        throw std::invalid_argument("a velocity limit must be > 0 with a ledger line");
      speed_dofs.push_back(model.joints[static_cast<size_t>(j)].idx_v());
    }
    supports.assign(static_cast<size_t>(model.njoints), {});
    for (int j = 1; j < model.njoints; ++j)
    {
      std::vector<int> & dofs = supports[static_cast<size_t>(j)];
      for (auto jj : model.supports[static_cast<size_t>(j)])
        if (jj > 0)
          for (int k = 0; k < model.joints[jj].nv(); ++k)
            dofs.push_back(model.joints[jj].idx_v() + k);
      std::sort(dofs.begin(), dofs.end());
    }
  }

  ContactScene::~ContactScene() = default;

  // ContactModel.kinetic_energy: M (crba's upper triangle, armature included) times v, each row's products in
  // column order from +0.0 (cone_solver.matvec; column by column here, each row's sum in that order), then vᵀ (M v)
  // in index order from +0.0 (zsum), halved. With `raised`, each row of M v less raised · v (rounded, then
  // subtracted) before that sum: T under the model's own armature where M has a step's servo terms on its diagonal.
  double ContactScene::kinetic_energy(ContactWork & w, const Vec & v, const Vec * raised) const
  {
    const auto & M = w.data.M;
    w.mass_v.setZero(nv);
    for (int c = 0; c < nv; ++c)
    {
      const double x = v[c];
      for (int r = 0; r <= c; ++r)  // column c's upper part
        w.mass_v[r] += M(r, c) * x;
      for (int r = c + 1; r < nv; ++r)  // below the diagonal: row c's upper part, by symmetry
        w.mass_v[r] += M(c, r) * x;
    }
    if (raised)
      for (int r = 0; r < nv; ++r)
        w.mass_v[r] -= (*raised)[r] * v[r];
    double sum = 0.0;
    for (int r = 0; r < nv; ++r)
      sum += v[r] * w.mass_v[r];
    return sum * .5;
  }

  std::unique_ptr<ContactWork, void (*)(ContactWork *)> ContactScene::workspace(const pinocchio::Model & model) const
  {
    return std::unique_ptr<ContactWork, void (*)(ContactWork *)>(
      new ContactWork(model, *this), [](ContactWork * w) { delete w; });
  }

  bool ContactScene::step(
    ContactWork & w, const pinocchio::Model & model, const pinocchio::Data & placed, const Vec & q, const Vec & v,
    const Vec & v_free, double h, ContactRow & row, Vec & v_next, double & contact_work, double & correction,
    double & bounce, std::vector<std::pair<int, double>> & speed_work) const
  {
    const ContactConstants & c = constants;
    pinocchio::Data & data = w.data;
    const int nv = model.nv;
    // ---- ContactModel.detect ----------------------------------------------------------------------------------
    w.points.clear();
    if (!pairs.empty())
    {
      pinocchio::updateGeometryPlacements(model, placed, w.gm, w.gd);  // forwardKinematics(q)'s placements
      for (size_t k = 0; k < pairs.size(); ++k)
      {
        const int a = pairs[k].first, b = pairs[k].second, kind = pair_kinds[k];
        const ContactShape &s1 = shapes[static_cast<size_t>(a)], &s2 = shapes[static_cast<size_t>(b)];
        const pinocchio::SE3 M1 = w.gd.oMg[static_cast<size_t>(a)], M2 = w.gd.oMg[static_cast<size_t>(b)];
        const Eigen::Matrix3d R1 = M1.rotation(), R2 = M2.rotation();
        const Vector3 t1 = M1.translation(), t2 = M2.translation();
        // ContactModel._pair_candidates: bounding spheres first
        const Vector3 c2 = transform(R2, t2, s2.centre);
        if (s1.kind == ShapeKind::halfspace)
        {
          if ((c2[2] - s1.dims[0]) - s2.radius >= c.speculative_margin)
            continue;
        }
        else
        {
          const Vector3 c1 = transform(R1, t1, s1.centre);
          const Vector3 d = c2 - c1;
          if (norm3(d[0], d[1], d[2]) - (s1.radius + s2.radius) >= c.speculative_margin)
            continue;
        }
        w.found.clear();
        Vector3 normal(0.0, 0.0, 1.0);
        if (kind <= MESH_GROUND)
          ground_candidates(kind, s1.dims[0], R2, t2, s2, c, w.found);
        else if (kind == SPHERE_SPHERE)
        {  // narrow_phase.sphere_sphere
          const Vector3 d = t2 - t1;
          const double dist = norm3(d[0], d[1], d[2]);
          if (dist > 0.0)
            normal = Vector3(d[0] / dist, d[1] / dist, d[2] / dist);
          const double gap = (dist - s1.dims[0]) - s2.dims[0];
          if (gap < c.speculative_margin)
          {
            Vector3 p1, p2;
            for (int r = 0; r < 3; ++r)
            {
              p1[r] = t1[r] + s1.dims[0] * normal[r];
              p2[r] = t2[r] - s2.dims[0] * normal[r];
            }
            w.found.push_back(Candidate{0, p1, p2, gap});
          }
        }
        else if (kind == SPHERE_BOX || kind == BOX_SPHERE)
        {
          const bool sphere_first = kind == SPHERE_BOX;
          const ContactShape & box = sphere_first ? s2 : s1;
          const ContactShape & ball = sphere_first ? s1 : s2;
          const double half[3] = {0.5 * box.dims[0], 0.5 * box.dims[1], 0.5 * box.dims[2]};
          sphere_box(sphere_first ? t1 : t2, ball.dims[0], sphere_first ? R2 : R1, sphere_first ? t2 : t1, half,
                     c.speculative_margin, w.found, normal);
          if (sphere_first)
          {
            for (Candidate & x : w.found)
              std::swap(x.p1, x.p2);
            normal = -normal;
          }
        }
        else if (kind == BOX_BOX)
          normal = box_box(make_box(R1, t1, s1.dims), make_box(R2, t2, s2.dims), c, w.found);
        else
        {  // narrow_phase.coal_candidates
          if (s1.kind == ShapeKind::mesh || s2.kind == ShapeKind::mesh)
            w.hulls(model, placed, *this);
          if (!pinocchio::computeCollision(w.gm, w.gd, k))
            continue;
          pinocchio::computeContactPatch(w.gm, w.gd, k);
          const coal::ContactPatchResult & patches = w.gd.contactPatchResults[k];
          if (patches.numContactPatches() == 0)
            continue;
          const coal::ContactPatch & patch = patches.getContactPatch(0);
          normal = patch.getNormal();
          for (size_t i = 0; i < patch.size(); ++i)
          {
            const Vector3 p1 = patch.getPointShape1(i), p2 = patch.getPointShape2(i);
            const Vector3 d = p2 - p1;
            w.found.push_back(Candidate{static_cast<int>(i), p1, p2, (normal[0] * d[0] + normal[1] * d[1]) + normal[2] * d[2]});
          }
        }
        if (w.found.empty())
          continue;
        // narrow_phase.select
        const double spacing =
          (s1.kind == ShapeKind::mesh || s2.kind == ShapeKind::mesh) ? c.min_patch_spacing : c.primitive_spacing;
        w.patch.clear();
        if (w.found.size() <= 1)
          w.patch = w.found;
        else
        {
          double deepest = w.found[0].gap;
          for (const Candidate & x : w.found)
            deepest = x.gap < deepest ? x.gap : deepest;
          for (const Candidate & x : w.found)
            if (x.gap <= deepest + c.patch_depth)
              w.patch.push_back(x);
        }
        w.chosen.clear();
        const int n = static_cast<int>(w.patch.size());
        if (n <= 1 || w.found.size() <= 1)
          for (int i = 0; i < n; ++i)
            w.chosen.push_back(i);
        else
        {
          int first = 0;
          for (int i = 1; i < n; ++i)  // np.argmin: the first of the smallest
            if (w.patch[static_cast<size_t>(i)].gap < w.patch[static_cast<size_t>(first)].gap)
              first = i;
          w.midpoints.resize(static_cast<size_t>(n));
          for (int i = 0; i < n; ++i)
          {
            const Candidate & x = w.patch[static_cast<size_t>(i)];
            for (int r = 0; r < 3; ++r)
              w.midpoints[static_cast<size_t>(i)][r] = 0.5 * (x.p1[r] + x.p2[r]);
          }
          w.nearest.resize(static_cast<size_t>(n));
          for (int i = 0; i < n; ++i)
            w.nearest[static_cast<size_t>(i)] =
              plane_distance2(w.midpoints[static_cast<size_t>(i)], w.midpoints[static_cast<size_t>(first)], normal);
          w.nearest[static_cast<size_t>(first)] = -1.0;
          w.chosen.push_back(first);
          const double spacing2 = spacing * spacing;
          while (static_cast<int>(w.chosen.size()) < c.max_patch_points)
          {
            int best = 0;
            for (int i = 1; i < n; ++i)  // np.argmax: the first of the largest
              if (w.nearest[static_cast<size_t>(i)] > w.nearest[static_cast<size_t>(best)])
                best = i;
            if (!(w.nearest[static_cast<size_t>(best)] >= spacing2))
              break;
            w.chosen.push_back(best);
            for (int i = 0; i < n; ++i)  // np.minimum
            {
              const double d =
                plane_distance2(w.midpoints[static_cast<size_t>(i)], w.midpoints[static_cast<size_t>(best)], normal);
              double & x = w.nearest[static_cast<size_t>(i)];
              x = (d < x || std::isnan(d)) ? d : x;
            }
            w.nearest[static_cast<size_t>(best)] = -1.0;
          }
          std::sort(w.chosen.begin(), w.chosen.end());
        }
        const bool up = normal[0] == 0.0 && normal[1] == 0.0 && normal[2] == 1.0 && !std::signbit(normal[0])
                        && !std::signbit(normal[1]);  // the ground's +z, bit for bit: its frame is computed once
        const Eigen::Matrix3d rotation =
          up ? w.up : Eigen::Quaterniond::FromTwoVectors(Eigen::Vector3d::UnitZ(), normal).toRotationMatrix();
        for (int i : w.chosen)
        {
          const Candidate & x = w.patch[static_cast<size_t>(i)];
          Point p;
          p.pair = static_cast<int>(k);
          p.feature = x.feature;
          p.joint1 = s1.joint;
          p.joint2 = s2.joint;
          p.body1 = s1.body;
          p.body2 = s2.body;
          p.p1 = x.p1;
          p.p2 = x.p2;
          for (int r = 0; r < 3; ++r)
            p.position[r] = 0.5 * (x.p1[r] + x.p2[r]);
          p.normal = normal;
          p.rotation = rotation;
          p.gap = x.gap;
          p.friction = pair_friction[k];
          p.restitution = pair_restitution[k];
          w.points.push_back(p);
        }
      }
    }
    // ---- ContactModel.problem --------------------------------------------------------------------------------
    w.keys.clear();
    w.sizes.clear();
    for (const Point & p : w.points)
    {
      w.keys.push_back({0, p.pair, p.feature});
      w.sizes.push_back(3);
    }
    w.limits.clear();
    for (int jid : limited_joints)
    {
      const auto & joint = model.joints[static_cast<size_t>(jid)];
      const int iq = joint.idx_q(), iv = joint.idx_v();
      const double below = q[iq] - model.lowerPositionLimit[iq], above = model.upperPositionLimit[iq] - q[iq];
      if (below < c.limit_margin)
      {
        w.limits.push_back({1.0, iv, jid, below});
        w.keys.push_back({1, jid, 0});
        w.sizes.push_back(1);
      }
      if (above < c.limit_margin)
      {
        w.limits.push_back({-1.0, iv, jid, above});
        w.keys.push_back({1, jid, 1});
        w.sizes.push_back(1);
      }
    }
    for (int jid : friction_joints)
    {
      w.keys.push_back({2, jid, 0});
      w.sizes.push_back(1);
    }
    w.speeds.clear();  // the velocity limits the free velocity comes within the band of (appended after assembly)
    w.select_speeds(*this, v_free, c.speed_band);
    speed_work.clear();
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
    const int n_points = static_cast<int>(w.points.size());
    const int n_limits = static_cast<int>(w.limits.size());
    int m = 3 * n_points + n_limits + static_cast<int>(friction_joints.size());  // then the speeds' rows
    pinocchio::crba(model, data, q, pinocchio::Convention::WORLD);
    pinocchio::cholesky::decompose(model, data);
    // ---- J, row by row on its support (ContactModel._point_rows)
    w.J.setZero(m, nv);
    w.row_support.resize(static_cast<size_t>(m));
    for (int k = 0; k < n_points; ++k)
    {
      const Point & p = w.points[static_cast<size_t>(k)];
      const std::vector<int> &S1 = supports[static_cast<size_t>(p.joint1)], &S2 = supports[static_cast<size_t>(p.joint2)];
      w.union_.clear();
      std::set_union(S1.begin(), S1.end(), S2.begin(), S2.end(), std::back_inserter(w.union_));
      size_t i1 = 0, i2 = 0;
      for (int col : w.union_)
      {
        const bool in1 = p.joint1 && i1 < S1.size() && S1[i1] == col, in2 = p.joint2 && i2 < S2.size() && S2[i2] == col;
        if (i1 < S1.size() && S1[i1] == col)
          ++i1;
        if (i2 < S2.size() && S2[i2] == col)
          ++i2;
        const auto lin = data.J.col(col).head<3>();
        const auto ang = data.J.col(col).tail<3>();
        double wv[3] = {0.0, 0.0, 0.0};
        if (in2)
        {
          const Vector3 & x = p.p2;
          wv[0] = lin[0] + (ang[1] * x[2] - ang[2] * x[1]);
          wv[1] = lin[1] + (ang[2] * x[0] - ang[0] * x[2]);
          wv[2] = lin[2] + (ang[0] * x[1] - ang[1] * x[0]);
        }
        if (in1)
        {
          const Vector3 & x = p.p1;
          wv[0] = wv[0] - (lin[0] + (ang[1] * x[2] - ang[2] * x[1]));
          wv[1] = wv[1] - (lin[1] + (ang[2] * x[0] - ang[0] * x[2]));
          wv[2] = wv[2] - (lin[2] + (ang[0] * x[1] - ang[1] * x[0]));
        }
        for (int r = 0; r < 3; ++r)
          w.J(3 * k + r, col) = (p.rotation(0, r) * wv[0] + p.rotation(1, r) * wv[1]) + p.rotation(2, r) * wv[2];
      }
      for (int r = 0; r < 3; ++r)
        w.row_support[static_cast<size_t>(3 * k + r)] = w.union_;
    }
    int r0 = 3 * n_points;
    for (const auto & L : w.limits)
    {
      w.J(r0, L.iv) = L.sign;
      w.row_support[static_cast<size_t>(r0)] = supports[static_cast<size_t>(L.joint)];
      ++r0;
    }
    for (int jid : friction_joints)
    {
      w.J(r0, model.joints[static_cast<size_t>(jid)].idx_v()) = 1.0;
      w.row_support[static_cast<size_t>(r0)] = supports[static_cast<size_t>(jid)];
      ++r0;
    }
    // ---- G = Zᵀ D⁻¹ Z, Z = U⁻¹ Jᵀ on each row's support. Z and W = D⁻¹ Z are nv x m, row-major and zero off the
    // supports; consecutive rows with one support (a point's three, a foot's points) are substituted together, each
    // column's sums in Python's order. G's row a gathers Z(k, a) W(k, b) over k in a's support for every b >= a at
    // once: a k off b's support adds an exact zero, which leaves a sum started at +0.0 as it was (Python adds them all).
    w.Z.setZero(nv, m);
    w.W.setZero(nv, m);
    w.Dinv.resize(nv);
    w.acc.resize(m);
    for (int k = 0; k < nv; ++k)
      w.Dinv[k] = 1.0 / data.D[k];
    for (int r0 = 0; r0 < m;)
    {
      const std::vector<int> & S = w.row_support[static_cast<size_t>(r0)];
      int r1 = r0 + 1;
      while (r1 < m && w.row_support[static_cast<size_t>(r1)] == S)
        ++r1;
      const int width = r1 - r0;
      for (int col : S)
        for (int r = r0; r < r1; ++r)
          w.Z(col, r) = w.J(r, col);
      double * acc = w.acc.data();
      for (int a = static_cast<int>(S.size()) - 1; a >= 0; --a)
      {
        const int k = S[static_cast<size_t>(a)];
        const int end = k + data.nvSubtree_fromRow[static_cast<size_t>(k)];
        double * zk = &w.Z(k, r0);
        if (width == 1)  // a row alone (a joint's friction or limit): its sum in a register
        {
          double sum = 0.0;
          for (size_t b = static_cast<size_t>(a) + 1; b < S.size() && S[b] < end; ++b)
            sum += data.U(k, S[b]) * w.Z(S[b], r0);
          zk[0] = zk[0] - sum;
          continue;
        }
        for (int r = 0; r < width; ++r)
          acc[r] = 0.0;
        for (size_t b = static_cast<size_t>(a) + 1; b < S.size() && S[b] < end; ++b)
        {
          const double u = data.U(k, S[b]);
          const double * zb = &w.Z(S[b], r0);
          for (int r = 0; r < width; ++r)
            acc[r] += u * zb[r];
        }
        for (int r = 0; r < width; ++r)
          zk[r] = zk[r] - acc[r];
      }
      for (int col : S)
        for (int r = r0; r < r1; ++r)
          w.W(col, r) = w.Dinv[col] * w.Z(col, r);
      r0 = r1;
    }
    w.last.assign(static_cast<size_t>(nv), 0);  // per dof: the last row whose support holds it (W(k, b) = 0 past it)
    for (int r = 0; r < m; ++r)
      for (int k : w.row_support[static_cast<size_t>(r)])
        w.last[static_cast<size_t>(k)] = r;
    w.G.setZero(m, m);
    for (int a = 0; a < m; ++a)
    {
      double * Ga = &w.G(a, 0);
      for (int k : w.row_support[static_cast<size_t>(a)])
      {
        const double z = w.Z(k, a);
        const double * Wk = &w.W(k, 0);
        const int last = w.last[static_cast<size_t>(k)];
        for (int b = a; b <= last; ++b)
          Ga[b] += z * Wk[b];
      }
      for (int b = a + 1; b < m; ++b)
        w.G(b, a) = Ga[b];
    }
    // ---- g = J v_free + b
    w.free.resize(m);
    for (int r = 0; r < m; ++r)
    {
      double s = 0.0;
      for (int col : w.row_support[static_cast<size_t>(r)])
        s += w.J(r, col) * v_free[col];
      w.free[r] = s;
    }
    w.g = w.free;
    w.correction.setZero(m);
    w.restitution.setZero(m);
    w.landings.clear();
    if (n_points)
    {
      const double threshold = -c.gravity * h;
      for (int k = 0; k < n_points; ++k)
      {
        const Point & p = w.points[static_cast<size_t>(k)];
        const int r = 3 * k + 2;
        double approach = 0.0;  // the normal velocity at the step's start
        for (int col : w.row_support[static_cast<size_t>(r)])
          approach += w.J(r, col) * v[col];
        double bias;
        if (p.gap < 0.0)
        {
          bias = w.correction[r] = penetration_correction(p.gap, h, c);
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
    r0 = 3 * n_points;
    for (const auto & L : w.limits)  // the distance to the limit as a contact's gap
    {
      w.correction[r0] = penetration_correction(L.distance, h, c);
      w.g[r0] += L.distance >= 0.0 ? L.distance / h : w.correction[r0];
      ++r0;
    }
    w.blocks.clear();
    for (int k = 0; k < n_points; ++k)
      w.blocks.push_back(cone::Block{cone::CONE, 3 * k, w.points[static_cast<size_t>(k)].friction});
    for (int k = 0; k < n_limits; ++k)
      w.blocks.push_back(cone::Block{cone::HALFLINE, 3 * n_points + k, 0.0});
    for (size_t k = 0; k < friction_joints.size(); ++k)
      w.blocks.push_back(cone::Block{
        cone::INTERVAL, 3 * n_points + n_limits + static_cast<int>(k),
        friction_force[model.joints[static_cast<size_t>(friction_joints[k])].idx_v()] * h});
    if (!w.speeds.empty())  // the velocity-limit rows, last
      m = w.append_speed_rows(0, supports, v_free);
    double scale = velocity_scale(w.free, c.gravity * h);
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
    cone::Solution solution =
      w.solver.solve(w.G, w.g, w.blocks, w.guess, scale, c.max_iterations, c.pgs, w.impulses);
    int iterations = solution.iterations;
    // ---- TimeStepping.attempt: v⁺ = v_free + M⁻¹ Jᵀ λ, and again with the velocity-limit rows ContactModel.speeding
    // adds (the joints past their limit at v⁺ without their row), warm-started from the impulses so far, until none
    const auto end_velocity = [&]() {
      w.generalized.setZero(nv);
      for (int r = 0; r < m; ++r)  // matvec(J.T, λ): per coordinate, the rows in order (structural zeros skipped)
        for (int col : w.row_support[static_cast<size_t>(r)])
          w.generalized[col] += w.J(r, col) * w.impulses[r];
      w.minv = w.generalized;
      pinocchio::cholesky::solve(model, data, w.minv);  // ContactModel.inverse_mass_times
      v_next.resize(nv);
      for (int i = 0; i < nv; ++i)
        v_next[i] = v_free[i] + w.minv[i];
    };
    end_velocity();
    for (;;)
    {
      const size_t selected = w.speeds.size();
      if (w.select_speeds(*this, v_next, 0.0) == 0)
        break;
      m = w.append_speed_rows(selected, supports, v_free);
      scale = velocity_scale(w.free, c.gravity * h);
      w.guess.setZero(m);
      w.guess.head(w.impulses.size()) = w.impulses;
      solution = w.solver.solve(w.G, w.g, w.blocks, w.guess, scale, c.max_iterations, c.pgs, w.impulses);
      iterations += solution.iterations;
      end_velocity();
    }
    row.steps += 1;
    row.iterations += iterations;
    row.unconverged += solution.converged ? 0 : 1;
    row.fallbacks += solution.fallback ? 1 : 0;
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
    // ---- TimeStepping.attempt: the contact's energies; each velocity-limit row's work for its actuator's line ----
    const int n_fixed = m - static_cast<int>(w.speeds.size());
    for (size_t k = 0; k < w.speeds.size(); ++k)
    {
      const ContactWork::Speed & sp = w.speeds[k];
      const double lam = w.impulses[n_fixed + static_cast<int>(k)];
      speed_work.emplace_back(sp.line, 0.5 * ((sp.sign * lam) * (v_next[sp.iv] + v_free[sp.iv])));
    }
    double s = 0.0;
    for (int i = 0; i < nv; ++i)
      s += w.generalized[i] * (v_next[i] + v_free[i]);
    contact_work = 0.5 * s;
    double corr = 0.0, rest = 0.0;
    for (int r = 0; r < m; ++r)
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
    Eigen::VectorXd friction_force;
    std::vector<int> speed_joints, speed_lines;
    std::vector<double> speed_limits;
    multibody_sim::ContactConstants constants;
  };
  using Bytes = Eigen::Matrix<std::uint8_t, Eigen::Dynamic, 1>;
} // namespace

void multibody_sim::bind_contact(nb::module_ & m)  // called by module.cpp
{
  using namespace multibody_sim;
  nb::class_<ContactRow>(m, "ContactRow", "One row's contact solver state (a snapshot's part).")
    .def(nb::init<>())
    .def_prop_ro("steps", [](const ContactRow & r) { return r.steps; })
    .def_prop_ro("unconverged", [](const ContactRow & r) { return r.unconverged; })
    .def_prop_ro("iterations", [](const ContactRow & r) { return r.iterations; })
    .def_prop_ro("fallbacks", [](const ContactRow & r) { return r.fallbacks; });
  Struct<ContactShape>(m, "ContactShape", "A collision shape (contact.Geometry, contact.ShapeData) and its joint.")
    .choice("kind", &ContactShape::kind,
            {{"halfspace", ShapeKind::halfspace}, {"box", ShapeKind::box}, {"sphere", ShapeKind::sphere},
             {"cylinder", ShapeKind::cylinder}, {"capsule", ShapeKind::capsule}, {"mesh", ShapeKind::mesh}})
    .field("joint", &ContactShape::joint, "int")
    .field("body", &ContactShape::body, "int")
    .field("rotation", &ContactShape::rotation, "a 3 x 3 float array")
    .field("translation", &ContactShape::translation, "3 floats")
    .field("dimensions", &ContactShape::dims, "list[float]")
    .field("vertices", &ContactShape::vertices, "an n x 3 float array (a mesh hull's vertices)")
    .field("archive", &ContactShape::archive, "a uint8 array (coal's archive of a mesh hull)")
    .field("centre", &ContactShape::centre, "3 floats (its bounding sphere's centre)")
    .field("radius", &ContactShape::radius, "float (its bounding sphere's radius)")
    .finish([](ContactShape & s) {
      const size_t need = s.kind == ShapeKind::box ? 3
                        : (s.kind == ShapeKind::cylinder || s.kind == ShapeKind::capsule) ? 2
                        : s.kind == ShapeKind::mesh ? 0 : 1;
      if (s.dims.size() != need)
        throw std::invalid_argument(
          "ContactShape.dimensions disagree with its kind (box 3, cylinder and capsule 2, mesh 0, else 1)");
      if (s.kind == ShapeKind::mesh && (s.vertices.rows() == 0 || s.archive.size() == 0))
        throw std::invalid_argument("a mesh ContactShape needs its hull's vertices and coal archive");
    });
  Struct<cone::Settings>(m, "SolverSettings", "cone_solver.py's constants (TimeStepping.solver_data()'s solver).")
    .field("tolerance", &cone::Settings::tolerance, "float")
    .field("fallback_tolerance", &cone::Settings::fallback_tolerance, "float")
    .field("regularization", &cone::Settings::regularization, "float")
    .field("damping", &cone::Settings::damping, "float")
    .field("armijo", &cone::Settings::armijo, "float")
    .field("shortest_step", &cone::Settings::shortest_step, "float")
    .field("proximal", &cone::Settings::proximal, "float")
    .field("relaxation", &cone::Settings::relaxation, "float")
    .field("rho_power", &cone::Settings::rho_power, "float")
    .field("rho_step", &cone::Settings::rho_step, "float")
    .field("rho_balance", &cone::Settings::rho_balance, "float")
    .field("rho_min", &cone::Settings::rho_min, "float")
    .field("rho_max", &cone::Settings::rho_max, "float")
    .field("newton_iterations", &cone::Settings::newton_iterations, "int")
    .field("fallback_rounds", &cone::Settings::fallback_rounds, "int")
    .field("local_iterations", &cone::Settings::local_iterations, "int")
    .finish();
  Struct<ContactConstants>(m, "ContactConstants", "contact.py's and narrow_phase.py's constants, the solver's settings.")
    .field("speculative_margin", &ContactConstants::speculative_margin, "float")
    .field("penetration_correction", &ContactConstants::penetration_correction, "float")
    .field("penetration_slop", &ContactConstants::penetration_slop, "float")
    .field("max_correction_speed", &ContactConstants::max_correction_speed, "float")
    .field("touching", &ContactConstants::touching, "float")
    .field("limit_margin", &ContactConstants::limit_margin, "float")
    .field("speed_band", &ContactConstants::speed_band, "float")
    .field("max_patch_points", &ContactConstants::max_patch_points, "int")
    .field("min_patch_spacing", &ContactConstants::min_patch_spacing, "float")
    .field("primitive_spacing", &ContactConstants::primitive_spacing, "float")
    .field("patch_depth", &ContactConstants::patch_depth, "float")
    .field("flat_disk", &ContactConstants::flat_disk, "float")
    .field("axis_tolerance", &ContactConstants::axis_tolerance, "float")
    .field("parallel_edges", &ContactConstants::parallel_edges, "float")
    .field("pgs", &ContactConstants::pgs, "bool")
    .field("gravity", &ContactConstants::gravity, "float")
    .field("max_iterations", &ContactConstants::max_iterations, "int")
    .field("solver", &ContactConstants::solver, "SolverSettings")
    .finish();
  auto fields = std::make_shared<Fields<ContactData>>("ContactScene");
  fields->member("shapes", &ContactData::shapes, "list[ContactShape]")
    .member("pairs", &ContactData::pairs, "list[tuple[int, int]]")
    .member("friction", &ContactData::friction, "list[float]")
    .member("restitution", &ContactData::restitution, "list[float]")
    .member("limited_joints", &ContactData::limited_joints, "list[int]")
    .member("friction_joints", &ContactData::friction_joints, "list[int]")
    .member("friction_force", &ContactData::friction_force, "an array of nv floats")
    .member("speed_joints", &ContactData::speed_joints, "list[int]")
    .member("speed_limits", &ContactData::speed_limits, "list[float]")
    .member("speed_lines", &ContactData::speed_lines, "list[int]")
    .member("constants", &ContactData::constants, "ContactConstants");
  nb::class_<ContactScene>(m, "ContactScene", "A scene's collision geometry and unilateral constraints.")
    .def(
      "__init__",
      [fields](ContactScene * self, const NativeModel & model, nb::kwargs kwargs) {
        const ContactData d = fields->parse(kwargs);
        new (self) ContactScene(
          model.model, d.shapes, d.pairs, d.friction, d.restitution, d.limited_joints, d.friction_joints,
          d.friction_force, d.speed_joints, d.speed_limits, d.speed_lines, d.constants);
      },
      nb::arg("model"), nb::arg("kwargs"),
      "From the scene's model and the contact model's named data (kernels/native.contact_data()).")
    .attr("fields") = fields->names();
}
