// sensors.Sensors.measure in C++: a scene's sensors' noiseless measurement at a tick, each operation in the Python
// kernel's order (the same Pinocchio calls on the same arguments; the few sums Python writes itself, as ordered.py
// orders them), so that both kernels give the same readings bit for bit. Included by methods.hpp and loop.hpp
// (engine.cpp) only.
#pragma once

#include <cmath>

#include "pinocchio/algorithm/frames.hpp"
#include "pinocchio/algorithm/kinematics.hpp"
#include "pinocchio/algorithm/rnea.hpp"

#include "sensors.hpp"

namespace multibody_sim
{
  namespace sensing
  {
    // pinocchio::forwardKinematics(model, data, q, v, a) on the joints the sensors read (w.kinematic_joints): its
    // own per-joint step (ForwardKinematicSecondStep) in its order, so those joints' placements, velocities and
    // accelerations are its, bit for bit, and the joints no sensor reads are skipped (go2's base IMU: 1 of 13).
    inline void kinematics(
      const pinocchio::Model & model, SensorWork & w, const Eigen::VectorXd & q, const Eigen::VectorXd & v,
      const Eigen::VectorXd & a)
    {
      using Step = pinocchio::impl::ForwardKinematicSecondStep<
        double, 0, pinocchio::JointCollectionDefaultTpl, Eigen::VectorXd, Eigen::VectorXd, Eigen::VectorXd>;
      pinocchio::Data & data = w.data;
      data.v[0].setZero();
      data.a[0].setZero();
      for (pinocchio::JointIndex i : w.kinematic_joints)
        Step::run(model.joints[i], data.joints[i], Step::ArgsType(model, data, q, v, a));
    }

    // The same joints' velocities and accelerations when the thread's step has just run its first ABA at (q, v),
    // written into that step's Data itself: ABA's first pass left each joint's calc (jdata: M, v, S, c), liMi and oMi
    // exactly as forwardKinematics' step computes them (the same calls in the same order: pinocchio/algorithm/aba.hxx,
    // kinematics.hxx), so only the rest of that step is done here, in its arithmetic: the readings are kinematics()'
    // bit for bit, at a fraction of its cost (no sin/cos, no placement products, nothing copied). The world-convention
    // ABA neither reads nor writes Data's v and a, which every other user of the step's Data computes before reading.
    // `velocities`: the step's data.v already holds them (a sample's energies computed them: Rows::settle, the same
    // recursion).
    struct AfterAba : pinocchio::fusion::JointUnaryVisitorBase<AfterAba>
    {
      typedef boost::fusion::vector<const pinocchio::Model &, pinocchio::Data &, const Eigen::VectorXd &, bool>
        ArgsType;

      template<typename JointModel>
      static void algo(const pinocchio::JointModelBase<JointModel> & jmodel,
                       pinocchio::JointDataBase<typename JointModel::JointDataDerived> & jdata,
                       const pinocchio::Model & model, pinocchio::Data & data, const Eigen::VectorXd & a,
                       bool velocities)
      {
        const pinocchio::JointIndex i = jmodel.id();
        const pinocchio::JointIndex parent = model.parents[i];
        if (!velocities)
        {
          data.v[i] = jdata.v();
          if (parent > 0)
            data.v[i] += data.liMi[i].actInv(data.v[parent]);
        }
        data.a[i] = jdata.S() * jmodel.JointMappedVelocitySelector(a) + jdata.c() + (data.v[i] ^ jdata.v());
        data.a[i] += data.liMi[i].actInv(data.a[parent]);
      }
    };

    // AfterAba's acceleration for a revolute joint about axis k (JointModelRevoluteTpl<double, 0, k>) whose velocity
    // data.v[i] is in place, written out: the visitor's operations in its order (S·q̈ + c + v ^ v_J, then liMi⁻¹ a_λ:
    // each of R's transposed products summed (r₀x₀ + r₁x₁) + r₂x₂, as Eigen evaluates them), without its temporaries
    // (ur5's tool0 IMU: six such joints per tick). tests/test_sensors.py compares the readings bit for bit with
    // forwardKinematics in the Python kernel.
    template<int k>
    inline void revolute_acceleration(const pinocchio::SE3 & liMi, const pinocchio::Motion & vi, double w, double qdd,
                                      const pinocchio::Motion & ap, pinocchio::Motion & out)
    {
      const double s = -w;  // v ^ v_J is v_J's motionAction on v: alphaCross(−w, ·) on both parts
      double y[6];
      const auto alpha_cross = [s](const double * in, double * o)
      {
        if constexpr (k == 0)
        {
          o[0] = 0.;
          o[1] = -s * in[2];
          o[2] = s * in[1];
        }
        else if constexpr (k == 1)
        {
          o[0] = s * in[2];
          o[1] = 0.;
          o[2] = -s * in[0];
        }
        else
        {
          o[0] = -s * in[1];
          o[1] = s * in[0];
          o[2] = 0.;
        }
      };
      alpha_cross(vi.linear().data(), y);
      alpha_cross(vi.angular().data(), y + 3);
      y[3 + k] += qdd;
      const Eigen::Vector3d & t = liMi.translation();
      const Eigen::Matrix3d & R = liMi.rotation();
      const double * l = ap.linear().data();
      const double * g = ap.angular().data();
      const double d[3] = {l[0] - (t[1] * g[2] - t[2] * g[1]), l[1] - (t[2] * g[0] - t[0] * g[2]),
                           l[2] - (t[0] * g[1] - t[1] * g[0])};
      for (int i = 0; i < 3; ++i)
      {
        out.linear()[i] = y[i] + ((R(0, i) * d[0] + R(1, i) * d[1]) + R(2, i) * d[2]);
        out.angular()[i] = y[3 + i] + ((R(0, i) * g[0] + R(1, i) * g[1]) + R(2, i) * g[2]);
      }
    }

    inline void kinematics_after_aba(const pinocchio::Model & model, pinocchio::Data & step, const SensorWork & w,
                                     const Eigen::VectorXd & v, const Eigen::VectorXd & a, bool velocities)
    {
      step.v[0].setZero();
      step.a[0].setZero();
      for (pinocchio::JointIndex i : w.kinematic_joints)
      {
        const auto & joint = model.joints[i].toVariant();
        const pinocchio::JointIndex parent = model.parents[i];
        const int iv = model.joints[i].idx_v();
        if (velocities && boost::get<pinocchio::JointModelRX>(&joint))
          revolute_acceleration<0>(step.liMi[i], step.v[i], v[iv], a[iv], step.a[parent], step.a[i]);
        else if (velocities && boost::get<pinocchio::JointModelRY>(&joint))
          revolute_acceleration<1>(step.liMi[i], step.v[i], v[iv], a[iv], step.a[parent], step.a[i]);
        else if (velocities && boost::get<pinocchio::JointModelRZ>(&joint))
          revolute_acceleration<2>(step.liMi[i], step.v[i], v[iv], a[iv], step.a[parent], step.a[i]);
        else
          AfterAba::run(model.joints[i], step.joints[i], AfterAba::ArgsType(model, step, a, velocities));
      }
    }

    // The sum of the contact impulses on `body` over h (Sensors._contact_force).
    inline Eigen::Vector3d contact_force(int body, const ContactRows * contacts, double h)
    {
      Eigen::Vector3d total = Eigen::Vector3d::Zero();
      if (contacts)
        for (const auto & row : *contacts)
        {
          const Eigen::Vector3d impulse(row[8], row[9], row[10]);
          if (static_cast<int>(row[1]) == body)
            total = total + impulse;
          if (static_cast<int>(row[0]) == body)
            total = total - impulse;
        }
      return total / h;
    }

    // Sensors._external: per joint the contact forces on its body, in its frame, and each one with its frame.
    inline void external(const Sensors & sensors, SensorWork & w, const ContactRows * contacts, double h)
    {
      for (size_t j = 0; j < w.fext.size(); ++j)
      {
        w.fext[j] = pinocchio::Force::Zero();
        w.parts[j].clear();
      }
      if (!contacts)
        return;
      for (const auto & row : *contacts)
      {
        const Eigen::Vector3d force = Eigen::Vector3d(row[8], row[9], row[10]) / h;
        const pinocchio::SE3 at(Eigen::Matrix3d::Identity(), Eigen::Vector3d(row[2], row[3], row[4]));
        const int sides[2] = {1, 0};
        const double signs[2] = {1.0, -1.0};
        for (int k = 0; k < 2; ++k)
        {
          const int body = static_cast<int>(row[sides[k]]);
          const int joint = sensors.contact_joints[static_cast<size_t>(body)];
          if (!joint)
            continue;
          const pinocchio::Force world = at.act(pinocchio::Force(signs[k] * force, Eigen::Vector3d::Zero()));
          const pinocchio::Force local = w.data.oMi[static_cast<size_t>(joint)].actInv(world);
          w.fext[static_cast<size_t>(joint)] = w.fext[static_cast<size_t>(joint)] + local;
          w.parts[static_cast<size_t>(joint)].emplace_back(sensors.contact_frames[static_cast<size_t>(body)], local);
        }
      }
    }

    // Sensors._cut_wrench: the wrench across a force-torque sensor's cut, at its frame in its axes.
    inline pinocchio::Force cut_wrench(const SensorItem & s, SensorWork & w)
    {
      const pinocchio::SE3 placement(s.cut_rotation, s.cut_translation);
      const size_t j = static_cast<size_t>(s.cut_joint);
      if (s.cut_whole)
        return placement.actInv(w.data.f[j]);
      const pinocchio::Inertia inertia(s.cut_mass, s.cut_lever, pinocchio::Symmetric3(s.cut_inertia));
      const pinocchio::Motion & velocity = w.data.v[j];
      pinocchio::Force wrench = inertia * w.data.a_gf[j] + velocity.cross(inertia * velocity);
      for (int child : s.cut_children)
        wrench = wrench + w.data.liMi[static_cast<size_t>(child)].act(w.data.f[static_cast<size_t>(child)]);
      for (const auto & [frame, force] : w.parts[j])
        for (int distal : s.cut_frames)
          if (frame == distal)
          {
            wrench = wrench - force;
            break;
          }
      return placement.actInv(wrench);
    }
  } // namespace sensing

  // Which of a tick's sensors measure_sensors measures: all of them; all but the imu and frame_pose sensors (whose
  // kinematics wait for the next step's first ABA: SensorWork::deferred); or only those, from the step's Data as
  // sensing::kinematics_after_aba left it (or w.data as sensing::kinematics did).
  enum class SensorPart
  {
    all,
    now,
    kinematic,
  };

  inline void measure_sensors(
    const Sensors & sensors,
    const pinocchio::Model & model,
    SensorWork & w,
    const Eigen::VectorXd & q,
    const Eigen::VectorXd & v,
    const Eigen::VectorXd & a,
    const Eigen::VectorXd & tau,
    const ContactRows * contacts,
    double h,
    double * out,
    SensorPart part = SensorPart::all,
    pinocchio::Data * kinematics = nullptr)  // (SensorPart::kinematic: where the kinematics are; default w.data)
  {
    pinocchio::Data & data = kinematics ? *kinematics : w.data;
    bool dynamics = false;
    if (part == SensorPart::all && !w.kinematic_joints.empty())
      sensing::kinematics(model, w, q, v, a);
    for (const SensorItem & s : sensors.items)
    {
      const bool kinematic = s.kind == SensorKind::imu || s.kind == SensorKind::frame_pose;
      if ((part == SensorPart::now && kinematic) || (part == SensorPart::kinematic && !kinematic))
        continue;
      double * row = out + s.offset;
      switch (s.kind)
      {
      case SensorKind::imu:
      {
        const pinocchio::SE3 & placement =
          pinocchio::updateFramePlacement(model, data, static_cast<pinocchio::FrameIndex>(s.frame));
        // getFrameClassicalAcceleration(LOCAL) as Pinocchio computes it, its frame velocity kept for the angular
        // rate (getFrameVelocity(LOCAL): the same call)
        const pinocchio::Frame & frame = model.frames[static_cast<size_t>(s.frame)];
        const pinocchio::Motion velocity =
          pinocchio::getFrameVelocity(model, data, frame.parentJoint, frame.placement, pinocchio::LOCAL);
        pinocchio::Motion classical =
          pinocchio::getFrameAcceleration(model, data, frame.parentJoint, frame.placement, pinocchio::LOCAL);
        classical.linear() += velocity.angular().cross(velocity.linear());
        const Eigen::Vector3d acceleration = classical.linear();
        const Eigen::Matrix3d & R = placement.rotation();
        for (int i = 0; i < 3; ++i)  // ordered_matvec(R.T, g): each product rounded, added in column order
        {
          double sum = R(0, i) * sensors.gravity[0];
          sum = sum + R(1, i) * sensors.gravity[1];
          sum = sum + R(2, i) * sensors.gravity[2];
          row[i] = acceleration[i] - sum;
        }
        for (int i = 0; i < 3; ++i)
          row[3 + i] = velocity.angular()[i];
        break;
      }
      case SensorKind::frame_pose:
      {
        const pinocchio::SE3 & placement =
          pinocchio::updateFramePlacement(model, data, static_cast<pinocchio::FrameIndex>(s.frame));
        const Eigen::Quaterniond quaternion(placement.rotation());
        for (int i = 0; i < 3; ++i)
          row[i] = placement.translation()[i];
        for (int i = 0; i < 4; ++i)
          row[3 + i] = quaternion.coeffs()[i];
        break;
      }
      case SensorKind::contact_force:
      {
        const Eigen::Vector3d force = sensing::contact_force(s.body, contacts, h);
        for (int i = 0; i < 3; ++i)
          row[i] = force[i];
        break;
      }
      case SensorKind::force_torque:
      {
        if (!dynamics)
        {
          sensing::external(sensors, w, contacts, h);
          pinocchio::rnea(model, data, q, v, a, w.fext);
          dynamics = true;
        }
        const pinocchio::Force wrench = sensing::cut_wrench(s, w);
        for (int i = 0; i < 3; ++i)
        {
          row[i] = wrench.linear()[i];
          row[3 + i] = wrench.angular()[i];
        }
        break;
      }
      default:  // joint_*
        for (size_t i = 0; i < s.q_index.size(); ++i)
        {
          const int iq = s.q_index[i], iv = s.v_index[i];
          if (s.kind == SensorKind::joint_position)
            row[i] = s.q_count[i] == 1 ? q[iq] : std::atan2(q[iq + 1], q[iq]);
          else if (s.kind == SensorKind::joint_velocity)
            row[i] = v[iv];
          else
            row[i] = tau[iv];
        }
      }
    }
  }
} // namespace multibody_sim
