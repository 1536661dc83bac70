"""MuJoCo as a peer for the studies in scripts/: the same URDF loaded with only what our dynamics models, and the
map between Pinocchio's (q, v) and MuJoCo's (qpos, qvel). A benchmark-only dependency (`pip install mujoco`)."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from typing import Any

import numpy as np
import pinocchio as pin

try:
    import mujoco
except ImportError:  # the studies say when they skip MuJoCo
    mujoco = None


def mujoco_model(robot: Any) -> Any:
    """MuJoCo model of the robot's URDF with only what our dynamics has: rigid bodies, joints and gravity.

    Visual and collision geometry go (their package:// paths would not resolve, and geometry costs time that has
    nothing to do with dynamics); a floating robot gets a free joint on its root body (MuJoCo welds a URDF's root);
    damping, armature and friction loss are zeroed (StateMap.set_damping puts ours back); equality constraints
    (panda's finger mimic), joint limits and contacts are disabled. The caller picks the integrator and step.
    """
    tree = ET.parse(robot.source["urdf_path"])
    for parent in tree.getroot().iter():
        for child in list(parent):
            if child.tag in ("visual", "collision", "transmission", "gazebo"):
                parent.remove(child)
    spec = mujoco.MjSpec.from_string(ET.tostring(tree.getroot(), encoding="unicode"))
    if robot.floating_base:
        spec.worldbody.first_body().add_freejoint()
    model = spec.compile()
    model.dof_damping[:] = 0.0
    model.dof_armature[:] = 0.0
    model.dof_frictionloss[:] = 0.0
    off = mujoco.mjtDisableBit
    model.opt.disableflags |= int(off.mjDSBL_EQUALITY) | int(off.mjDSBL_LIMIT) | int(off.mjDSBL_CONTACT)
    return model


class StateMap:
    """Pinocchio (q, v, v̇) ⇄ MuJoCo (qpos, qvel, qacc), joint by joint by name (talos's orders differ).

    Free joint: Pinocchio q = [p, (x y z w)], v = [Rᵀ ṗ, ω in the base frame]; MuJoCo qpos = [p, (w x y z)],
    qvel = [ṗ in the world frame, ω in the body frame]. So MuJoCo's linear acceleration is
    d/dt(R v_lin) = R (v̇_lin + ω × v_lin).
    """

    def __init__(self, robot: Any, model: Any):
        self.robot = robot
        self.nq_mj, self.nv_mj = model.nq, model.nv
        self.joints: list[tuple[str, int, int, int, int]] = []  # kind, Pinocchio idx_q, idx_v, MuJoCo qpos, dof
        free = [j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
        for name in robot.joint_names:
            joint = robot.model.joints[robot.model.getJointId(name)]
            kind = {(7, 6): "free", (1, 1): "scalar", (2, 1): "continuous"}.get((joint.nq, joint.nv))
            if kind is None:
                raise NotImplementedError(f"StateMap: joint '{name}' ({joint.shortname()}) is not mapped")
            j = free[0] if kind == "free" else model.joint(name).id
            self.joints.append((kind, joint.idx_q, joint.idx_v, model.jnt_qposadr[j], model.jnt_dofadr[j]))
        mapped = sum(6 if k == "free" else 1 for k, *_ in self.joints)
        if mapped != model.nv:
            raise NotImplementedError(f"MuJoCo has {model.nv} dofs, {mapped} mapped")

    def to_mujoco(self, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """MuJoCo (qpos, qvel) of the Pinocchio state (q, v)."""
        qpos, qvel = np.zeros(self.nq_mj), np.zeros(self.nv_mj)
        for kind, iq, iv, jq, jv in self.joints:
            if kind == "free":
                x, y, z, w = q[iq + 3 : iq + 7]
                rotation = pin.Quaternion(w, x, y, z).toRotationMatrix()
                qpos[jq : jq + 7] = [*q[iq : iq + 3], w, x, y, z]
                qvel[jv : jv + 3] = rotation @ v[iv : iv + 3]
                qvel[jv + 3 : jv + 6] = v[iv + 3 : iv + 6]
            elif kind == "continuous":
                qpos[jq], qvel[jv] = math.atan2(q[iq + 1], q[iq]), v[iv]
            else:
                qpos[jq], qvel[jv] = q[iq], v[iv]
        return qpos, qvel

    def to_pinocchio(self, qpos: np.ndarray, qvel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pinocchio (q, v) of the MuJoCo state (qpos, qvel)."""
        q, v = np.zeros(self.robot.nq), np.zeros(self.robot.nv)
        for kind, iq, iv, jq, jv in self.joints:
            if kind == "free":
                w, x, y, z = qpos[jq + 3 : jq + 7] / np.linalg.norm(qpos[jq + 3 : jq + 7])
                rotation = pin.Quaternion(w, x, y, z).toRotationMatrix()
                q[iq : iq + 7] = [*qpos[jq : jq + 3], x, y, z, w]
                v[iv : iv + 3] = rotation.T @ qvel[jv : jv + 3]
                v[iv + 3 : iv + 6] = qvel[jv + 3 : jv + 6]
            elif kind == "continuous":
                q[iq : iq + 2] = math.cos(qpos[jq]), math.sin(qpos[jq])
                v[iv] = qvel[jv]
            else:
                q[iq], v[iv] = qpos[jq], qvel[jv]
        return q, v

    def acceleration(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
        """MuJoCo qacc of the Pinocchio acceleration a at (q, v)."""
        qacc = np.zeros(self.nv_mj)
        for kind, iq, iv, _, jv in self.joints:
            if kind == "free":
                x, y, z, w = q[iq + 3 : iq + 7]
                rotation = pin.Quaternion(w, x, y, z).toRotationMatrix()
                v_lin, omega = v[iv : iv + 3], v[iv + 3 : iv + 6]
                qacc[jv : jv + 3] = rotation @ (a[iv : iv + 3] + np.cross(omega, v_lin))
                qacc[jv + 3 : jv + 6] = a[iv + 3 : iv + 6]
            else:
                qacc[jv] = a[iv]
        return qacc

    def set_damping(self, model: Any) -> None:
        """MuJoCo's dof damping = ours, dof by dof (a free joint's stays zero, as ours)."""
        for kind, _, iv, _, jv in self.joints:
            if kind != "free":
                model.dof_damping[jv] = self.robot.damping[iv]


def mj_set_state(model: Any, data: Any, qpos: np.ndarray, qvel: np.ndarray) -> None:
    """Reset MuJoCo's data to the state (qpos, qvel)."""
    mujoco.mj_resetData(model, data)
    data.qpos[:], data.qvel[:] = qpos, qvel
