// A scene's sensors in the engine: their measurement at a tick (the end of a step), in the Python kernel's order
// (multibody_sim/sensors.py, Sensors.measure: its specification; the readings made of the measurements stay in Python).
// The structs arrive as named data from Sensors.native_data(); the measurement is measure.hpp's (engine.cpp only).
#pragma once

#include <algorithm>
#include <array>
#include <cstdint>
#include <vector>

#include <Eigen/Core>

#include "pinocchio/multibody.hpp"

namespace multibody_sim
{
  enum class SensorKind : int
  {
    imu = 0,
    frame_pose = 1,
    contact_force = 2,
    force_torque = 3,
    joint_position = 4,
    joint_velocity = 5,
    joint_torque = 6,
  };

  // One sensor (sensors.Placed, with its force-torque cut, sensors.Cut): _native.SensorItem.
  struct SensorItem
  {
    SensorKind kind = SensorKind::imu;
    int offset = 0;  // its first component in a tick's row
    int frame = -1;  // imu, frame_pose: the frame
    int body = -1;   // contact_force: the body's index among the contact model's bodies
    std::vector<int> q_index, v_index, q_count;  // joint_*: each joint's idx_q, idx_v, nq
    int cut_joint = 0;  // force_torque: the joint whose body is cut
    bool cut_whole = true;  // ... at the joint: its whole subtree
    Eigen::Matrix3d cut_rotation = Eigen::Matrix3d::Identity();  // the sensor frame in the joint's frame
    Eigen::Vector3d cut_translation = Eigen::Vector3d::Zero();
    double cut_mass = 0.0;  // the distal part's inertia in the joint's frame (cut_whole false)
    Eigen::Vector3d cut_lever = Eigen::Vector3d::Zero();
    Eigen::Matrix3d cut_inertia = Eigen::Matrix3d::Zero();
    std::vector<int> cut_children;  // the child joints hanging from the distal part
    std::vector<int> cut_frames;    // the frames on the distal part (contact forces on them count)
  };

  // A scene's sensors (sensors.Sensors.native_data()): _native.Sensors.
  struct Sensors
  {
    int width = 0;
    Eigen::Vector3d gravity = Eigen::Vector3d::Zero();
    std::vector<SensorItem> items;
    std::vector<int> contact_joints, contact_frames;  // per contact body: its joint, its frame on it (-1: none)
  };

  // One thread's workspace for the measurement (its own Data: the step's is left as the step left it).
  struct SensorWork
  {
    SensorWork(const pinocchio::Model & model, const Sensors & sensors)
    : data(model)
    , fext(model.njoints, pinocchio::Force::Zero())
    , parts(model.njoints)
    , a(Eigen::VectorXd::Zero(model.nv))
    , tau(Eigen::VectorXd::Zero(model.nv))
    {
      // The joints whose kinematics the sensors read: every joint for a force-torque sensor (its contact forces
      // are taken to joint frames before the RNEA), else the joints from the root to each imu's or frame_pose's.
      std::vector<bool> needed(static_cast<size_t>(model.njoints), false);
      for (const SensorItem & s : sensors.items)
      {
        if (s.kind == SensorKind::force_torque)
          std::fill(needed.begin(), needed.end(), true);
        else if ((s.kind == SensorKind::imu || s.kind == SensorKind::frame_pose) && s.frame >= 0)
          for (pinocchio::JointIndex j : model.supports[model.frames[static_cast<size_t>(s.frame)].parentJoint])
            needed[j] = true;
      }
      for (pinocchio::JointIndex j = 1; j < static_cast<pinocchio::JointIndex>(model.njoints); ++j)
        if (needed[j])
          kinematic_joints.push_back(j);
      bool force_torque = false;
      for (const SensorItem & s : sensors.items)
        force_torque = force_torque || s.kind == SensorKind::force_torque;
      deferrable = !kinematic_joints.empty() && !force_torque;
    }

    // Row j's tick waits for its kinematics (deferrable sensors on fixed steps): the next step's first ABA at the
    // tick's state computes most of them (sensing::kinematics_after_aba); a tick whose row takes no such step before
    // the engine returns gets them from a pass of its own (measure.hpp). Its other sensors are measured at once.
    void defer(size_t j, size_t rows, size_t slot, const Eigen::VectorXd & acceleration)
    {
      if (pending.size() != rows)
      {
        pending.assign(rows, -1);
        pending_a.assign(rows, Eigen::VectorXd::Zero(acceleration.size()));
      }
      pending[j] = static_cast<int64_t>(slot);
      pending_a[j] = acceleration;
    }

    bool waits(size_t j) const
    {
      return j < pending.size() && pending[j] >= 0;
    }

    pinocchio::Data data;
    // forwardKinematics(q, v, a)'s joints the sensors read, in its (the model's) order: a parent before its children
    std::vector<pinocchio::JointIndex> kinematic_joints;
    // Whether a tick's kinematics may wait for the next step's first ABA: kinematic sensors (imu, frame_pose) and no
    // force-torque sensor (its RNEA and contact forces need the whole pass at the tick)
    bool deferrable = false;
    std::vector<int64_t> pending;  // per row: where its waiting tick's measurement starts in `values` (-1: none)
    std::vector<Eigen::VectorXd> pending_a;  // ... and that tick's acceleration (v+ - v) / h
    pinocchio::container::aligned_vector<pinocchio::Force> fext;
    std::vector<std::vector<std::pair<int, pinocchio::Force>>> parts;  // per joint: (frame, force) in order
    Eigen::VectorXd a;
    Eigen::VectorXd tau;  // the torque the actuators deliver at the tick (joint_torque sensors)
    std::vector<double> times;  // the ticks since Engine::take_ticks: time, row, width values each
    std::vector<int64_t> rows;
    std::vector<double> values;
  };

  using ContactRows = std::vector<std::array<double, 11>>;
} // namespace multibody_sim
