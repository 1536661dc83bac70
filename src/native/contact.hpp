// The contact part of the `timestepping` step, rendered for the native kernel (methods.hpp calls it).
//
// The Python code is the specification: scenes/narrow_phase.py (the contact points: closed forms against the ground
// and between spheres and boxes, box against box by separating axes, coal for the other pairs, a few well-spread
// points per patch), scenes/contact.py (ContactModel.detect and .problem: the rows of J from the CRBA's joint
// Jacobians, G = Zᵀ D⁻¹ Z with Z = U⁻¹ Jᵀ on Pinocchio's tree-sparse Cholesky of M, the speculative /
// penetration-correction / restitution biases, limits selected by proximity, exact joint friction) and
// integrators/timestepping.py with integrators/cone_solver.py (cone_solver.hpp: the warm-started cone solve). The
// geometry arrives as data and every constant from the Python modules; the arithmetic is theirs, in their order
// (sums from +0.0 in index order, structural zeros skipped).
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "pinocchio/multibody.hpp"

#include "cone_solver.hpp"

namespace multibody_sim
{
  using Vec = Eigen::VectorXd;

  enum class ShapeKind : int
  {
    halfspace = 0,  // dims: (height,), normal +z
    box = 1,        // dims: full extents (x, y, z)
    sphere = 2,     // dims: (radius,)
    cylinder = 3,   // dims: (radius, length)
    capsule = 4,    // dims: (radius, length)
    mesh = 5,       // a convex hull: vertices (and its coal archive for the pairs coal computes)
  };

  struct ContactShape  // contact.Geometry with contact.ShapeData
  {
    ShapeKind kind = ShapeKind::sphere;
    int joint = 0;  // the joint it moves with (0: the world)
    int body = 0;   // its body's index in ContactModel.body_names (Trajectory.contacts' pair indices)
    Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();  // its pose in the joint's frame
    Eigen::Vector3d translation = Eigen::Vector3d::Zero();
    std::vector<double> dims;
    Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor> vertices;  // mesh: the hull's vertices
    Eigen::Matrix<std::uint8_t, Eigen::Dynamic, 1> archive;  // mesh: coal's binary archive of the hull
    Eigen::Vector3d centre = Eigen::Vector3d::Zero();  // bounding sphere, in the shape's frame
    double radius = 0.0;
  };

  // The Python modules' constants (ContactScene's constructor takes them from Python, by name): contact.py's and
  // narrow_phase.py's, then the time-stepper's (TimeStepping.solver_data: max_iterations and cone_solver.py's
  // settings).
  struct ContactConstants
  {
    double speculative_margin = 0.0, penetration_correction = 0.0, penetration_slop = 0.0;
    double max_correction_speed = 0.0, touching = 0.0, limit_margin = 0.0, speed_band = 0.0;
    double min_patch_spacing = 0.0, primitive_spacing = 0.0, patch_depth = 0.0, flat_disk = 0.0;
    double axis_tolerance = 0.0, parallel_edges = 0.0;  // narrow_phase.box_box's
    int max_patch_points = 0, max_iterations = 0;
    bool pgs = false;      // Gauss–Seidel sweeps as the solver's fallback, and no Newton before them
    double gravity = 0.0;  // |g| [m/s²]: approaches slower than |g| dt never bounce
    cone::Settings solver;
  };

  // One row's solver state (timestepping.ContactState): warm-start impulses by block key, counts, landings and
  // the active contacts of the latest step.
  struct ContactRow
  {
    std::vector<std::array<int64_t, 3>> keys;  // ("point", pair, feature) = (0, pair, feature);
    std::vector<Vec> impulses;                 // ("limit", joint, side) = (1, joint, side); ("friction", joint) = (2, joint, 0);
                                               // ("speed", joint, side) = (3, joint, side)
    int64_t steps = 0, unconverged = 0, iterations = 0, fallbacks = 0;
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
      const std::vector<int> & friction_joints,
      const Vec & friction_force,
      const std::vector<int> & speed_joints,
      const std::vector<double> & speed_limits,
      const std::vector<int> & speed_lines,
      const ContactConstants & constants);
    ~ContactScene();

    std::unique_ptr<ContactWork, void (*)(ContactWork *)> workspace(const pinocchio::Model & model) const;

    /// The contact part of TimeStepping.attempt from (q, v) with end velocity v_free before impulses: v_next,
    /// the contact work ½ λᵀJ(v⁺ + v_free), -λᵀb_corr and -λᵀb_rest, and (ledger line, work ½ λ J (v⁺ + v_free))
    /// of each velocity-limit row; `row` updated as the Python solver state is. `placed` holds the joint placements
    /// at q (oMi, as forwardKinematics(q) computes them: the step's ABA at q leaves them), which
    /// ContactModel.detect computes in its own Data. Returns whether there was a problem to solve (the Python
    /// step's evaluations: 2, else 1).
    bool step(ContactWork & work, const pinocchio::Model & model, const pinocchio::Data & placed, const Vec & q,
              const Vec & v, const Vec & v_free, double h, ContactRow & row, Vec & v_next, double & contact_work,
              double & correction, double & bounce, std::vector<std::pair<int, double>> & speed_work) const;

    /// ContactModel.kinetic_energy: T = ½ vᵀ M v [J] at the latest step's q, from its M (work's Data); given
    /// `raised` (nv,: what a step's servos added to the armature M was built with), ½ vᵀ (M − diag(raised)) v
    double kinetic_energy(ContactWork & work, const Vec & v, const Vec * raised = nullptr) const;

    int nv = 0;
    std::vector<ContactShape> shapes;
    std::vector<std::pair<int, int>> pairs;
    std::vector<int> pair_kinds;  // narrow_phase.pair_kind of each pair
    std::vector<double> pair_friction, pair_restitution;
    std::vector<int> limited_joints, friction_joints;
    Vec friction_force;  // F [N·m or N] per coordinate (0 where a joint has no exact friction)
    // the joints whose velocity limit is a constraint (their actuators' overspeed brakes), with v_max [rad/s or
    // m/s], the index of their actuator_overspeed line in the ledger, and their v index
    std::vector<int> speed_joints;
    std::vector<double> speed_limits;
    std::vector<int> speed_lines, speed_dofs;
    std::vector<std::vector<int>> supports;  // contact.ContactModel.supports: per joint, its supporting dofs
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
