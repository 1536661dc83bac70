// The contact part of the `timestepping` step, rendered for the native kernel (methods.hpp calls it).
//
// The Python code is the specification: scenes/contact.py (ContactModel.detect and .problem: coal collision with
// the speculative margin, contact patches capped at MAX_PATCH_POINTS, one point-contact constraint per patch
// point, joint limits selected by proximity, exact joint friction, the speculative / penetration-correction /
// restitution biases, the Delassus operator by ConstraintCholeskyDecomposition, M⁻¹ by pinocchio's cholesky) and
// integrators/timestepping.py (the cone solve warm-started per constraint block, the solver state). The geometry
// arrives as data (shape kinds, dimensions, joints, placements; pairs; coefficients) and every constant from the
// Python module; the arithmetic is theirs, in their order (sums in index order, as ordered.py forms them).
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <vector>

#include <Eigen/Core>

#include "pinocchio/multibody.hpp"

namespace multibody_sim
{
  using Vec = Eigen::VectorXd;

  enum class ShapeKind : int
  {
    halfspace = 0,  // dims: (height,), normal +z
    box = 1,        // dims: full extents (x, y, z)
    sphere = 2,     // dims: (radius,)
    cylinder = 3,   // dims: (radius, length)
  };

  struct ContactShape  // contact.Geometry
  {
    ShapeKind kind = ShapeKind::sphere;
    int joint = 0;  // the joint it moves with (0: the world)
    int body = 0;   // its body's index in ContactModel.body_names (Trajectory.contacts' pair indices)
    Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();  // its pose in the joint's frame
    Eigen::Vector3d translation = Eigen::Vector3d::Zero();
    std::vector<double> dims;
  };

  // contact.py's and timestepping.py's constants (ContactScene's constructor takes them from Python).
  struct ContactConstants
  {
    double speculative_margin = 0.0, penetration_correction = 0.0, penetration_slop = 0.0;
    double max_correction_speed = 0.0, touching = 0.0, delassus_damping = 0.0, tolerance = 0.0;
    int max_patch_points = 0, anderson_capacity = 0, max_iterations = 0;
    bool pgs = false;  // the solver: PGS, else ADMM (spectral rule, Anderson acceleration)
    double gravity = 0.0;  // |g| [m/s²]: approaches slower than |g| dt never bounce
  };

  // One row's solver state (timestepping.ContactState): warm-start impulses by block key, counts, landings and
  // the active contacts of the latest step.
  struct ContactRow
  {
    std::vector<std::vector<int64_t>> keys;  // ("point", pair, i) = (0, pair, i); ("limits", *idx) = (1, ...);
    std::vector<Vec> impulses;               // ("friction",) = (2,)
    int64_t steps = 0, unconverged = 0, iterations = 0;
    std::vector<std::pair<int, double>> landed;  // pair -> approach speed, in insertion order
    std::vector<std::array<double, 11>> active;  // ContactModel.records of the latest step
  };

  struct ContactWork;  // one thread's workspace (contact.cpp)

  /// The collision geometry and unilateral constraints of one scene (contact.ContactModel).
  class ContactScene
  {
  public:
    ContactScene(
      const pinocchio::Model & model,
      const std::vector<ContactShape> & shapes,
      const std::vector<std::pair<int, int>> & pairs,
      const std::vector<double> & pair_friction,
      const std::vector<double> & pair_restitution,
      const std::vector<int> & limited_joints,
      const Vec & limit_margin,
      const std::vector<int> & friction_joints,
      const Vec & friction_bound,
      const ContactConstants & constants);
    ~ContactScene();

    std::unique_ptr<ContactWork, void (*)(ContactWork *)> workspace(const pinocchio::Model & model) const;

    /// The contact part of TimeStepping.attempt from (q, v) with end velocity v_free before impulses: v_next,
    /// the contact work ½ λᵀJ(v⁺ + v_free), -λᵀb_corr and -λᵀb_rest; `row` updated as the Python solver state
    /// is. Returns whether there was a problem to solve (the Python step's evaluations: 2, else 1).
    bool step(ContactWork & work, const pinocchio::Model & model, const Vec & q, const Vec & v, const Vec & v_free,
              double h, ContactRow & row, Vec & v_next, double & contact_work, double & correction,
              double & bounce) const;

    int nv = 0;
    std::vector<ContactShape> shapes;
    std::vector<std::pair<int, int>> pairs;
    std::vector<double> pair_friction, pair_restitution;
    std::vector<int> limited_joints, friction_joints;
    Vec limit_margin, friction_bound;
    ContactConstants constants;
  };
} // namespace multibody_sim

namespace nanobind
{
  class module_;
}

namespace multibody_sim
{
  // The Python class _native.ContactScene (contact.cpp), added by module.cpp.
  void bind_contact(nanobind::module_ & m);
} // namespace multibody_sim
