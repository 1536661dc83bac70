"""The robot catalog: the named robots, where their files live (example-robot-data or the shipped models/ folder),
their natural bases and reference poses."""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..exceptions import ModelError

# The names a robot's everyday pose goes by in example-robot-data's SRDFs, in the order default_pose() prefers
# them when the catalog names no reference pose.
DEFAULT_POSE_NAMES = ("default", "standing", "half_sitting")


_ERD = "example-robot-data"
# Where one name is both a catalog robot and a shipped scene (four_bar, spring_chain), commands that take either
# take the scene; "robot:NAME" names the robot and "scene:NAME" the scene explicitly (load_scene strips it).
ROBOT_PREFIX = "robot:"


@dataclass(frozen=True)
class CatalogEntry:
    """A named robot: where its description lives, which base it naturally has and where its poses come from.

    Names, files, bases and reference poses follow example-robot-data's own Python loaders (robots_loader.py up
    to 4.x, which 6.x no longer ships); where this catalog departs from them, the description says so.

    Attributes:
        name: catalog name (what load_robot and the CLI accept).
        path: URDF (or SDF, converted: see sdformat.py) path relative to its provider's robots folder.
        floating_base: the robot's natural base (arms fixed, legged robots, humanoids and drones floating).
        provider: "example-robot-data" or "multibody-sim" (the repository's models/ folder).
        description: one line for `multibody-sim models`.
        srdf: the SRDF whose `<group_state>`s are the robot's named poses (relative to the robots folder), or None.
        reference_pose: the pose default_pose() returns (the loaders' reference posture) when the SRDF has it;
            otherwise "default", "standing" or "half_sitting" if present, else the neutral configuration.
        locked: joints locked at the reference pose (removed from the model), with the reason in the description.
        prune: a joint whose whole subtree (its child link and everything below) is removed from the URDF.
        base_rpy: a constant rotation [rad] (roll, pitch, yaw) of the base, for a model drawn with y up.
    """

    name: str
    path: str
    floating_base: bool
    provider: str
    description: str
    srdf: str | None = None
    reference_pose: str | None = None
    locked: tuple[str, ...] = ()
    prune: str | None = None
    base_rpy: tuple[float, float, float] | None = None


def _erd(name: str, path: str, floating: bool, description: str, srdf: str | None = None, **extra: Any) -> CatalogEntry:
    return CatalogEntry(name, path, floating, _ERD, description, srdf=srdf, **extra)


def _shipped(name: str, path: str, floating: bool, description: str) -> CatalogEntry:
    return CatalogEntry(name, path, floating, "multibody-sim", description)


_TALOS_SRDF = "talos_data/srdf/talos.srdf"
_ROMEO_HANDS = tuple(
    f"{side}{joint}"
    for side in "LR"
    for joint in ("Hand", "Finger12", "Finger13", "Finger21", "Finger22", "Finger23", "Finger31", "Finger32",
                  "Finger33", "Thumb1", "Thumb2", "Thumb3")
)  # fmt: skip

CATALOG: dict[str, CatalogEntry] = {
    e.name: e
    for e in [
        _shipped("pendulum", "pendulum/pendulum.urdf", False, "simple pendulum: 1 kg bob on a light 1 m rod"),
        _shipped("free_body", "free_body/free_body.urdf", True, "free rigid box with distinct principal inertias"),
        _shipped(
            "stiff_arm",
            "stiff_arm/stiff_arm.urdf",
            False,
            "stiff two-link arm: a 10 g tip on a heavily damped elbow (stiffness ratio ~1e8 at rest)",
        ),
        _shipped(
            "point_robot",
            "point_robot/point_robot.urdf",
            False,
            "planar point robot: a 1 kg puck on prismatic x, y joints in the horizontal plane (no gravity load)",
        ),
        _shipped(
            "spring_chain",
            "spring_chain/spring_chain.urdf",
            False,
            "five 1 kg carts on prismatic joints in series (scenes add the springs between them)",
        ),
        _shipped(
            "four_bar",
            "four_bar/four_bar.urdf",
            False,
            "four-bar linkage (Grashof crank-rocker) as an open tree: a scene's loop constraint closes it",
        ),
        # ---- example-robot-data: arms and hands (fixed base) ----
        _erd(
            "double_pendulum",
            "double_pendulum_description/urdf/double_pendulum.urdf",
            False,
            "planar double pendulum (q = 0 is upright; hanging is [pi, 0])",
        ),
        _erd(
            "double_pendulum_continuous",
            "double_pendulum_description/urdf/double_pendulum_continuous.urdf",
            False,
            "double pendulum with continuous joints (nq = 4, nv = 2)",
        ),
        _erd(
            "double_pendulum_simple",
            "double_pendulum_description/urdf/double_pendulum_simple.urdf",
            False,
            "double pendulum with plain cylinder links",
        ),
        _erd("asr_twodof", "asr_twodof_description/urdf/TwoDofs.urdf", False, "ASR two-degree-of-freedom planar arm"),
        _erd("ur3", "ur_description/urdf/ur3_robot.urdf", False, "Universal Robots UR3 arm"),
        _erd("ur3_gripper", "ur_description/urdf/ur3_gripper.urdf", False, "UR3 arm with a gripper body"),
        _erd("ur3_limited", "ur_description/urdf/ur3_joint_limited_robot.urdf", False, "UR3 arm, joints within ±pi"),
        _erd("ur5", "ur_description/urdf/ur5_robot.urdf", False, "Universal Robots UR5 arm"),
        _erd("ur5_gripper", "ur_description/urdf/ur5_gripper.urdf", False, "UR5 arm with a gripper body"),
        _erd("ur5_limited", "ur_description/urdf/ur5_joint_limited_robot.urdf", False, "UR5 arm, joints within ±pi"),
        _erd("ur10", "ur_description/urdf/ur10_robot.urdf", False, "Universal Robots UR10 arm"),
        _erd("ur10_limited", "ur_description/urdf/ur10_joint_limited_robot.urdf", False, "UR10 arm, joints within ±pi"),
        _erd(
            "panda",
            "panda_description/urdf/panda.urdf",
            False,
            "Franka Emika Panda arm with two fingers",
            "panda_description/srdf/panda.srdf",
            reference_pose="default",
        ),
        _erd(
            "panda_collision",
            "panda_description/urdf/panda_collision.urdf",
            False,
            "Panda with simple collision shapes",
            "panda_description/srdf/panda.srdf",
            reference_pose="default",
        ),
        _erd(
            "z1",
            "z1_description/urdf/z1.urdf",
            False,
            "Unitree Z1 arm",
            "z1_description/srdf/z1.srdf",
            reference_pose="arm_up",
        ),
        _erd(
            "kinova",
            "kinova_description/robots/kinova.urdf",
            False,
            "Kinova Jaco arm",
            "kinova_description/srdf/kinova.srdf",
            reference_pose="arm_up",
        ),
        _erd(
            "xarm7",
            "xarm_description/urdf/xarm7.urdf",
            False,
            "UFactory xArm7 arm",
            "xarm_description/srdf/xarm7.srdf",
            reference_pose="home",
        ),
        _erd(
            "so_arm",
            "so_arm_description/urdf/so101.urdf",
            False,
            "SO-ARM101 desktop arm (example-robot-data's loader put it on a free-flyer; an arm here is fixed)",
        ),
        _erd("so100", "so_arm_description/urdf/so100.urdf", False, "SO-ARM100 desktop arm (fixed base)"),
        _erd("so101", "so_arm_description/urdf/so101.urdf", False, "SO-ARM101 desktop arm (fixed base)"),
        _erd(
            "finger_edu",
            "finger_edu_description/robots/finger_edu.urdf",
            False,
            "ODRI Finger Edu: a three-joint finger hanging from its frame",
            "finger_edu_description/srdf/finger_edu.srdf",
            reference_pose="hanging",
        ),
        _erd(
            "allegro_right_hand",
            "allegro_hand_description/urdf/allegro_right_hand.urdf",
            False,
            "Wonik Allegro right hand, 16 joints",
        ),
        _erd(
            "allegro_left_hand",
            "allegro_hand_description/urdf/allegro_left_hand.urdf",
            False,
            "Wonik Allegro left hand, 16 joints",
        ),
        # Its SRDF names the joints "baxter/head_pan", ..., which the URDF calls "head_pan": none applies, and its
        # one state, "neutral", is all zeros, i.e. neutral().
        _erd("baxter", "baxter_description/urdf/baxter.urdf", False, "Rethink Baxter: two arms on a fixed torso"),
        _erd(
            "alex_nub_hands",
            "alex_description/urdf/alex_nub_hands.urdf",
            False,
            "Boardwalk Robotics Alex upper body with nub hands",
            "alex_description/srdf/alex_nub_hands.srdf",
            reference_pose="default",
        ),
        _erd(
            "alex_psyonic_hands",
            "alex_description/urdf/alex_psyonic_hands.urdf",
            False,
            "Alex upper body with PSYONIC hands",
            "alex_description/srdf/alex_psyonic_hands.srdf",
            reference_pose="default",
        ),
        _erd(
            "alex_sake_hands",
            "alex_description/urdf/alex_sake_hands.urdf",
            False,
            "Alex upper body with SAKE grippers",
            "alex_description/srdf/alex_sake_hands.srdf",
            reference_pose="default",
        ),
        _erd(
            "talos_arm",
            "talos_data/robots/talos_left_arm.urdf",
            False,
            "PAL Talos left arm",
            _TALOS_SRDF,
            reference_pose="half_sitting",
        ),
        _erd("tiago", "tiago_description/robots/tiago.urdf", False, "PAL TIAGo mobile manipulator (base welded)"),
        _erd("tiago_dual", "tiago_description/robots/tiago_dual.urdf", False, "PAL TIAGo with two arms (base welded)"),
        _erd(
            "tiago_no_hand",
            "tiago_description/robots/tiago_no_hand.urdf",
            False,
            "TIAGo without its hand (base welded)",
        ),
        _erd("tiago_pro", "tiago_pro_description/robots/tiago_pro.urdf", False, "PAL TIAGo Pro (base welded)"),
        # ---- example-robot-data: legged robots, humanoids and drones (floating base) ----
        _erd(
            "solo8",
            "solo_description/robots/solo.urdf",
            True,
            "ODRI Solo-8 quadruped",
            "solo_description/srdf/solo.srdf",
            reference_pose="standing",
        ),
        _erd(
            "solo12",
            "solo_description/robots/solo12.urdf",
            True,
            "ODRI Solo-12 quadruped",
            "solo_description/srdf/solo.srdf",
            reference_pose="standing",
        ),
        _erd(
            "bolt",
            "bolt_description/robots/bolt.urdf",
            True,
            "ODRI Bolt biped",
            "bolt_description/srdf/bolt.srdf",
            reference_pose="standing",
        ),
        _erd(
            "a1",
            "a1_description/urdf/a1.urdf",
            True,
            "Unitree A1 quadruped",
            "a1_description/srdf/a1.srdf",
            reference_pose="standing",
        ),
        _erd(
            "go1",
            "go1_description/urdf/go1.urdf",
            True,
            "Unitree Go1 quadruped",
            "go1_description/srdf/go1.srdf",
            reference_pose="standing",
        ),
        _erd(
            "go2",
            "go2_description/urdf/go2.urdf",
            True,
            "Unitree Go2 quadruped",
            "go2_description/srdf/go2.srdf",
            reference_pose="standing",
        ),
        _erd(
            "b1",
            "b1_description/urdf/b1.urdf",
            True,
            "Unitree B1 quadruped",
            "b1_description/srdf/b1.srdf",
            reference_pose="standing",
        ),
        _erd(
            "b1_z1",
            "b1_description/urdf/b1-z1.urdf",
            True,
            "Unitree B1 quadruped carrying a Z1 arm",
            "b1_description/srdf/b1-z1.srdf",
            reference_pose="standing_with_arm_home",
        ),
        _erd("laikago", "laikago_description/urdf/laikago.urdf", True, "Unitree Laikago quadruped"),
        _erd(
            "anymal",
            "anymal_b_simple_description/robots/anymal.urdf",
            True,
            "ANYbotics ANYmal B quadruped",
            "anymal_b_simple_description/srdf/anymal.srdf",
            reference_pose="standing",
        ),
        _erd(
            "anymal_kinova",
            "anymal_b_simple_description/robots/anymal-kinova.urdf",
            True,
            "ANYmal B carrying a Kinova arm",
            "anymal_b_simple_description/srdf/anymal-kinova.srdf",
            reference_pose="standing_with_arm_up",
        ),
        _erd(
            "anymal_c",
            "anymal_c_simple_description/urdf/anymal.urdf",
            True,
            "ANYbotics ANYmal C quadruped",
            "anymal_c_simple_description/srdf/anymal.srdf",
            reference_pose="standing",
        ),
        _erd(
            "hyq",
            "hyq_description/robots/hyq_no_sensors.urdf",
            True,
            "IIT HyQ hydraulic quadruped",
            "hyq_description/srdf/hyq.srdf",
            reference_pose="standing",
        ),
        _erd("quadruped", "quadruped_description/urdf/quadruped.urdf", True, "a small generic quadruped"),
        _erd(
            "centauro",
            "centauro_description/urdf/centauro.urdf",
            True,
            "IIT Centauro: four wheeled legs and two arms",
            "centauro_description/srdf/centauro.srdf",
            reference_pose="homing_nominal",  # the loaders named "homing_balanced", which its SRDF does not define
        ),
        _erd(
            "cassie",
            "cassie_description/robots/cassie_v2.sdf",
            True,
            "Agility Cassie biped, from its SDF: the achilles and plantar rods' loop closures and the leg springs "
            "are not modelled",
            "cassie_description/srdf/cassie_v2.srdf",
            reference_pose="standing",
        ),
        _erd(
            "talos",
            "talos_data/robots/talos_reduced.urdf",
            True,
            "PAL Talos humanoid (reduced)",
            _TALOS_SRDF,
            reference_pose="half_sitting",
        ),
        _erd(
            "talos_box",
            "talos_data/robots/talos_reduced_box.urdf",
            True,
            "Talos (reduced) with box collision shapes",
            _TALOS_SRDF,
            reference_pose="half_sitting",
        ),
        _erd(
            "talos_full",
            "talos_data/robots/talos_full_v2.urdf",
            True,
            "PAL Talos humanoid with hands and head",
            _TALOS_SRDF,
            reference_pose="half_sitting",
        ),
        _erd(
            "talos_full_box",
            "talos_data/robots/talos_full_v2_box.urdf",
            True,
            "Talos (full) with box collision shapes",
            _TALOS_SRDF,
            reference_pose="half_sitting",
        ),
        _erd(
            "talos_legs",
            "talos_data/robots/talos_reduced.urdf",
            True,
            "Talos legs and pelvis: the torso, arms and head removed (their mass too)",
            _TALOS_SRDF,
            reference_pose="half_sitting",
            prune="torso_1_joint",
        ),
        _erd(
            "icub",
            "icub_description/robots/icub.urdf",
            True,
            "IIT iCub humanoid; neck_yaw locked: the head is a point mass on its axis (M singular there)",
            "icub_description/srdf/icub.srdf",
            reference_pose="half_sitting",
            locked=("neck_yaw",),
        ),
        _erd(
            "icub_reduced",
            "icub_description/robots/icub_reduced.urdf",
            True,
            "iCub with fewer joints",
            "icub_description/srdf/icub.srdf",
            reference_pose="half_sitting",
        ),
        _erd(
            "romeo",
            "romeo_description/urdf/romeo.urdf",
            True,
            "Aldebaran Romeo humanoid; its massless hands' 24 joints are locked (a mass matrix needs mass)",
            "romeo_description/srdf/romeo.srdf",
            reference_pose="half_sitting",
            locked=_ROMEO_HANDS,
        ),
        _erd(
            "simple_humanoid",
            "simple_humanoid_description/urdf/simple_humanoid.urdf",
            True,
            "a simple humanoid (HRP-2-like)",
            "simple_humanoid_description/srdf/simple_humanoid.srdf",
            reference_pose="half_sitting",
        ),
        _erd(
            "simple_humanoid_classical",
            "simple_humanoid_description/urdf/simple_humanoid_classical.urdf",
            True,
            "the simple humanoid, classical joint conventions",
            "simple_humanoid_description/srdf/simple_humanoid_classical.srdf",
            reference_pose="half_sitting",
        ),
        _erd("g1", "g1_description/urdf/g1_29dof_rev_1_0.urdf", True, "Unitree G1 humanoid, 29 DoF"),
        _erd("g1_with_hands", "g1_description/urdf/g1_29dof_with_hand_rev_1_0.urdf", True, "Unitree G1 with its hands"),
        _erd(
            "alexander",
            "alexander_description/urdf/alexander_v1.lowerBodyOnly.urdf",
            True,
            "Alexander biped (lower body)",
            "alexander_description/srdf/alexander.srdf",
            reference_pose="default",
        ),
        _erd(
            "human",
            "human_description/robots/human.urdf",
            True,
            "a human body model (1.80 m, 75 kg); its y-up file turned upright",
            base_rpy=(math.pi / 2, 0.0, 0.0),
        ),
        _erd(
            "pr2",
            "pr2_description/urdf/pr2.urdf",
            True,
            "Willow Garage PR2",
            "pr2_description/srdf/pr2.srdf",
            reference_pose="tuck_left_arm",
        ),
        _erd("hector", "hector_description/robots/quadrotor_base.urdf", True, "Hector quadrotor"),
        _erd("iris", "iris_description/robots/iris_simple.urdf", True, "3DR Iris quadrotor"),
        _erd(
            "borinot",
            "borinot_description/urdf/borinot_flying_arm_2.urdf",
            True,
            "Borinot drone with a two-joint arm",
            "borinot_description/srdf/borinot_flying_arm_2.srdf",
            reference_pose="home",
        ),
        _erd(
            "hextilt",
            "hextilt_description/urdf/hextilt_flying_arm_5.urdf",
            True,
            "tilted-rotor hexacopter with a five-joint arm",
            "hextilt_description/srdf/hextilt_flying_arm_5.srdf",
            reference_pose="home",
        ),
    ]
}


def example_robot_data_share() -> Path:
    """The folder that holds `example-robot-data/robots` (its package:// root).

    Raises:
        ModelError: example-robot-data is not installed.
    """
    import importlib.metadata  # here, as lxml below: what `import multibody_sim` need not pay

    candidates = []
    try:
        dist = importlib.metadata.distribution(_ERD)
        candidates.append(Path(str(dist.locate_file("cmeel.prefix/share"))))
    except importlib.metadata.PackageNotFoundError:
        pass
    candidates += [Path(p) / "cmeel.prefix" / "share" for p in sys.path if p]
    for share in candidates:
        if (share / _ERD / "robots").is_dir():
            return share.resolve()
    raise ModelError("example-robot-data is not installed (pip install example-robot-data)")


def shipped_models_dir() -> Path:
    """The repository's models/ folder, as installed in the package (multibody_sim.models)."""
    import importlib.resources  # here, as tempfile below: what `import multibody_sim` need not pay

    return Path(str(importlib.resources.files("multibody_sim.models")))


def catalog_urdf(entry: CatalogEntry) -> tuple[Path, list[Path]]:
    """(URDF path, package directories) of a catalog entry."""
    if entry.provider == _ERD:
        share = example_robot_data_share()
        return share / _ERD / "robots" / entry.path, [share]
    models = shipped_models_dir()
    return models / entry.path, [models]


def catalog_srdf(entry: CatalogEntry) -> Path | None:
    """The SRDF of a catalog entry (its named poses), or None when it has none."""
    if entry.srdf is None:
        return None
    return example_robot_data_share() / _ERD / "robots" / entry.srdf


def default_pose_name(poses: dict[str, np.ndarray], preferred: str | None = None) -> str | None:
    """The pose default_pose() returns: `preferred` (a catalog entry's reference pose) when the SRDF has it, else
    the first of DEFAULT_POSE_NAMES there, else None (the neutral configuration)."""
    for name in (preferred, *DEFAULT_POSE_NAMES):
        if name is not None and name in poses:
            return name
    return None
