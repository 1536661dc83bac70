"""The robot catalog and load_robot(): locating URDFs, resolving package:// URIs, checking files."""

from __future__ import annotations

import contextlib
import difflib
import hashlib
import math
import os
import stat
import sys
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from .exceptions import InvalidArgumentError, ModelError, RobotNotFoundError
from .robot import Robot
from .safety import printable

# The names a robot's everyday pose goes by in example-robot-data's SRDFs, in the order default_pose() prefers
# them when the catalog names no reference pose.
DEFAULT_POSE_NAMES = ("default", "standing", "half_sitting")

SUPPORTED_JOINT_TYPES = ("continuous", "fixed", "floating", "planar", "prismatic", "revolute")
MAX_URDF_BYTES = 32 * 1024 * 1024  # the largest catalog URDF is ~200 kB; anything this big is not a robot
# Refused before parsing: 28 MB of tiny elements cost libxml2 4-6 s and 600-900 MB, and yourdfpy more. The
# largest catalog URDF (talos) has ~2000 elements; 100k parse in ~0.1 s and ~37 MB.
MAX_XML_ELEMENTS = 100_000
# The largest catalog robot has 78 links (anymal_c). Pinocchio's URDF parser recurses along chains and
# overflows an 8 MiB stack near 4000 links (a crash, not an error), and a 8000-link star takes ~20 s to build.
MAX_LINKS = 1000
MAX_JOINTS = 1000
# Pinocchio's Data (created with every Robot) takes ~64 nv^3 bytes: 136 MB and 0.3 s at 128 dof, 1.7 GB at 300,
# out of memory near 1000. The largest example-robot-data model has 107 (tiago_dual on a free-flyer).
MAX_DOFS = 128
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


def load_robot(
    source: str | os.PathLike[str],
    *,
    floating_base: bool | None = None,
    damping: bool = True,
    package_dirs: list[str | os.PathLike[str]] | None = None,
    allowed_roots: list[str | os.PathLike[str]] | None = None,
    srdf: str | os.PathLike[str] | None = None,
) -> Robot:
    """Load a robot by catalog name or file path (URDF, or SDF converted to URDF) into Pinocchio.

    Files are untrusted input: no DTD or entity is expanded, nothing is fetched, files over MAX_URDF_BYTES, with
    more than MAX_XML_ELEMENTS elements, MAX_LINKS links, MAX_JOINTS joints or MAX_DOFS degrees of freedom are
    refused before they cost time or memory, and mesh paths must resolve (symlinks followed) inside the allowed
    folders: the file's folder, package_dirs and allowed_roots. SRDF files follow the same rules.

    Args:
        source: a catalog name (`multibody-sim models` lists them) or a path to a URDF (or SDF) file; a leading
            "robot:" is allowed (the CLI needs it for names that are also scenes: robot:four_bar).
        floating_base: True adds a free-flyer root joint, False welds the root to the world; None takes the
            catalog entry's natural base (fixed for files).
        damping: apply the URDF's joint viscous damping (tau = -D v); False ignores it.
        package_dirs: folders that `package://NAME/...` URIs resolve against; mesh paths must stay inside them
            or the URDF's folder. Catalog robots add their own.
        allowed_roots: further folders mesh paths may resolve into (e.g. a `../meshes` folder beside the
            URDF's), without being package roots; the CLI's `--allow-root`.
        srdf: an SRDF file whose `<group_state>`s become the robot's named poses (robot.poses, robot.pose(name),
            robot.default_pose()); catalog robots come with example-robot-data's where it ships one.

    Raises:
        InvalidArgumentError: an argument has the wrong type, or a folder given does not exist.
        RobotNotFoundError: source is neither a catalog name nor an existing file.
        ModelError: the file (or the SRDF) is malformed, too large, reaches outside the allowed folders or
            describes something that cannot be simulated.
    """
    if not isinstance(source, (str, os.PathLike)):
        raise InvalidArgumentError(f"source must be a catalog name or a URDF path, got {type(source).__name__}")
    for flag, value, allowed in (("floating_base", floating_base, "True, False or None"), ("damping", damping, "")):
        if not (isinstance(value, (bool, np.bool_)) or (value is None and allowed)):
            raise InvalidArgumentError(f"{flag} must be {allowed or 'True or False'}, got {value!r}")
    if srdf is not None and not isinstance(srdf, (str, os.PathLike)):
        raise InvalidArgumentError(f"srdf must be a path to an SRDF file, got {type(srdf).__name__}")
    dirs = folder_list("package_dirs", package_dirs)
    extra_roots = folder_list("allowed_roots", allowed_roots)
    name = os.fspath(source).removeprefix(ROBOT_PREFIX)  # the prefix only says "the robot, not the scene"
    arguments: dict[str, Any] = {
        "source": name,
        "floating_base": None if floating_base is None else bool(floating_base),
        "damping": bool(damping),
        "package_dirs": [os.fspath(p) for p in package_dirs or []],
    }
    # Only when given: metadata written before these options existed stays comparable.
    if allowed_roots:
        arguments["allowed_roots"] = [os.fspath(p) for p in allowed_roots]
    if srdf is not None:
        arguments["srdf"] = os.fspath(srdf)
    entry = CATALOG.get(name)
    srdf_path = Path(srdf).expanduser().resolve() if srdf is not None else None
    if entry is not None:
        path, extra_dirs = catalog_urdf(entry)
        dirs += extra_dirs
        floating = entry.floating_base if floating_base is None else bool(floating_base)
        if srdf_path is None and entry.srdf is not None:
            srdf_path = example_robot_data_share() / _ERD / "robots" / entry.srdf
    else:
        path = Path(name).expanduser()
        if not path.is_file():
            raise _not_found(name, path)
        floating = bool(floating_base)
        name = path.stem
    try:
        # The checks test finiteness themselves: numpy's overflow warnings on a hostile file's 1e308s would only
        # add lines to stderr.
        with np.errstate(all="ignore"):
            return _load(path.resolve(), name, floating, bool(damping), dirs, extra_roots, arguments, entry, srdf_path)
    except ModelError as exc:
        # Messages quote names and paths from the file: never let them carry line breaks, terminal escapes
        # or megabytes to the user's terminal.
        shown = printable(str(exc))
        if shown == str(exc):
            raise
        raise ModelError(shown) from None


def _load(
    path: Path,
    name: str,
    floating: bool,
    damping: bool,
    dirs: list[Path],
    extra_roots: list[Path],
    arguments: dict[str, Any],
    entry: CatalogEntry | None,
    srdf_path: Path | None,
) -> Robot:
    if path.suffix.lower() in MJCF_SUFFIXES:
        xml = read_xml_file(path, "MJCF")
        root = parse_xml(xml, path, "MJCF", "(the largest catalog robot has about 2000)")
        if root.tag == "mujoco":
            return _load_mjcf(path, xml, root, name, damping, dirs, extra_roots, arguments, srdf_path)
    xml = read_xml_file(path, "SDF" if path.suffix.lower() == ".sdf" else "URDF")
    derivation = _derivation(xml, path, entry)
    urdf = derived_urdf(xml, path, derivation)
    description = parse_urdf(urdf, path)
    check_urdf(description, path, package_dirs=[path.parent, *dirs], allowed_roots=extra_roots)
    model = _build_model(urdf, path, floating)
    if entry is not None and entry.base_rpy is not None:
        _rotate_base(model, entry.base_rpy)
    if model.nv > MAX_DOFS:  # before Robot() creates Pinocchio's Data, whose size grows as nv^3
        raise ModelError(
            f"{path}: the robot has {model.nv} degrees of freedom, more than the {MAX_DOFS} this simulator accepts"
        )
    _check_model_numbers(model, path)
    _check_body_inertias(model, path)
    poses: dict[str, np.ndarray] = {}
    if srdf_path is not None:
        from .srdf import read_poses

        poses = read_poses(srdf_path, model)
    default = default_pose_name(poses, entry.reference_pose if entry is not None else None)
    if entry is not None and entry.locked:
        model, poses = _lock(model, entry.locked, poses[default] if default else pin.neutral(model), poses)
    source: dict[str, Any] = {
        "load_robot": arguments,
        "urdf_path": str(path),
        "urdf_sha256": hashlib.sha256(xml).hexdigest(),
    }
    if derivation is not None:
        source["derivation"] = derivation
    if srdf_path is not None:
        source["srdf_path"] = str(srdf_path)
    robot = Robot(
        model,
        name=name,
        floating_base=floating,
        damping=damping,
        source=source,
        poses=poses,
        default_pose=default,
    )
    _check_mass_matrix(robot, path)
    return robot


MJCF_SUFFIXES = (".xml", ".mjcf")  # files with these suffixes whose root element is <mujoco> are MJCF
# MJCF elements whose `file` attribute names a file MuJoCo (or a viewer) would read, and the <compiler> attribute
# holding the folder it is relative to.
_MJCF_FILES = {"mesh": "meshdir", "texture": "texturedir", "hfield": "assetdir", "skin": "assetdir"}


def _load_mjcf(
    path: Path,
    xml: bytes,
    root: Any,
    name: str,
    damping: bool,
    dirs: list[Path],
    extra_roots: list[Path],
    arguments: dict[str, Any],
    srdf_path: Path | None,
) -> Robot:
    """A MuJoCo XML file through Pinocchio's MJCF parser, behind the URDF checks (see check_mjcf).

    The base is the file's: floating when its root body has a free joint; a floating_base argument that says
    otherwise is refused. Gravity comes from its <option gravity> (Pinocchio's parser ignores it); what ABA does not
    model (contacts, actuators, tendons, equality constraints, joint limits as constraints, springs, friction loss)
    is left out, as it is from URDFs.
    """
    free = check_mjcf(root, path, package_dirs=[path.parent, *dirs], allowed_roots=extra_roots)
    requested = arguments["floating_base"]
    if requested is not None and bool(requested) != free:
        # Pinocchio's MJCF parser neither adds a root joint to a model whose bodies hang from the world by their
        # own joints nor removes one: the file decides.
        said = "has a free joint" if free else "has no free joint"
        raise ModelError(
            f"{path}: an MJCF file declares its base (its root body {said}): floating_base={requested} cannot change "
            "it; leave floating_base=None or edit the file's <freejoint/>"
        )
    error: BaseException | None = None
    with _captured_stderr() as logged:
        try:
            model = pin.buildModelFromMJCF(str(path))
        except (RuntimeError, ValueError, TypeError, OverflowError) as exc:
            error = exc
    if error is not None:
        # Pinocchio's exceptions name its source file and function, then "message:", then the reason.
        text = [line.strip() for line in str(error).strip().splitlines()]
        after = [text[i + 1] for i, line in enumerate(text[:-1]) if line == "message:"]
        reason = after[0] if after else (text[0] if text else type(error).__name__)
        raise ModelError(f"{path}: Pinocchio cannot build the model ({reason})") from None
    if "".join(logged):
        sys.stderr.write("".join(logged))
    gravity = root.find("option")
    if gravity is not None and gravity.get("gravity") is not None:  # Pinocchio's parser keeps -9.81 m/s² z
        model.gravity.linear = _mjcf_numbers(gravity.get("gravity"), 3, path, "<option gravity>")
    if model.nv > MAX_DOFS:
        raise ModelError(
            f"{path}: the robot has {model.nv} degrees of freedom, more than the {MAX_DOFS} this simulator accepts"
        )
    _check_model_numbers(model, path)
    _check_body_inertias(model, path)
    poses: dict[str, np.ndarray] = {}
    if srdf_path is not None:
        from .srdf import read_poses

        poses = read_poses(srdf_path, model)
    source: dict[str, Any] = {
        "load_robot": arguments,
        "urdf_path": str(path),
        "urdf_sha256": hashlib.sha256(xml).hexdigest(),
        "format": "mjcf",
    }
    if srdf_path is not None:
        source["srdf_path"] = str(srdf_path)
    floating = free
    robot = Robot(
        model,
        name=name,
        floating_base=floating,
        damping=damping,
        source=source,
        poses=poses,
        default_pose=default_pose_name(poses),
    )
    _check_mass_matrix(robot, path)
    return robot


def check_mjcf(root: Any, path: Path, *, package_dirs: list[Path], allowed_roots: list[Path] | None = None) -> bool:
    """Refuse what Pinocchio's MJCF parser would mis-read or what reaches outside the allowed folders.

    No <include> (Pinocchio's parser does not follow them: inline the included file), at most MAX_LINKS bodies and
    MAX_JOINTS joints, and every file a <mesh>, <texture>, <hfield> or <skin> names (relative to the
    <compiler>'s meshdir, texturedir or assetdir, themselves relative to the file's folder) inside the allowed
    folders.

    Returns:
        Whether the root body has a free joint (a floating base).
    """
    if root.find(".//include") is not None:
        raise ModelError(
            f"{path}: <include> is not supported (Pinocchio's MJCF parser does not follow it): inline the included file"
        )
    for kind, xpath, limit in (
        ("bodie", "count(//body)", MAX_LINKS),
        ("joint", "count(//joint|//freejoint)", MAX_JOINTS),
    ):
        count = int(root.xpath(xpath))
        if count > limit:
            raise ModelError(f"{path}: the robot has {count} {kind}s, more than the {limit} this simulator accepts")
    compiler = root.find("compiler")
    folders = {key: compiler.get(key) if compiler is not None else None for key in set(_MJCF_FILES.values())}
    package_roots = [Path(os.path.realpath(p)) for p in package_dirs]
    roots = package_roots + [Path(os.path.realpath(p)) for p in allowed_roots or []]
    for tag, folder_key in _MJCF_FILES.items():
        for element in root.iter(tag):
            name = element.get("file")
            if not name:
                continue
            folder = folders[folder_key] or folders["assetdir"] or ""
            candidate = (path.parent / folder / name) if not os.path.isabs(name) else Path(name)
            _resolve_uri(str(candidate.absolute()), path, package_roots, roots, tag)
    worldbody = root.find("worldbody")
    first = worldbody.find("body") if worldbody is not None else None
    return first is not None and (
        first.find("freejoint") is not None or any(j.get("type") == "free" for j in first.findall("joint"))
    )


def _mjcf_numbers(text: str, count: int, path: Path, where: str) -> np.ndarray:
    try:
        values = np.array([float(v) for v in text.split()], dtype=float)
    except ValueError:
        raise ModelError(f"{path}: {where}: '{text}' is not a list of numbers") from None
    if values.shape != (count,) or not np.all(np.isfinite(values)):
        raise ModelError(f"{path}: {where}: expected {count} finite numbers, got '{text}'")
    return values


def default_pose_name(poses: dict[str, np.ndarray], preferred: str | None = None) -> str | None:
    """The pose default_pose() returns: `preferred` (a catalog entry's reference pose) when the SRDF has it, else
    the first of DEFAULT_POSE_NAMES there, else None (the neutral configuration)."""
    for name in (preferred, *DEFAULT_POSE_NAMES):
        if name is not None and name in poses:
            return name
    return None


def _derivation(xml: bytes, path: Path, entry: CatalogEntry | None) -> str | None:
    """How the URDF the model is built from derives from the file read: None (it is the file), "sdf" (converted
    from SDFormat) or "prune:JOINT" (a catalog entry's subtree removed)."""
    if entry is not None and entry.prune is not None:
        return f"prune:{entry.prune}"
    if path.suffix.lower() == ".sdf":
        return "sdf"
    return None


def derived_urdf(xml: bytes, path: Path, derivation: str | None) -> bytes:
    """The URDF a robot's model is built from, given the bytes of its file and its source's "derivation".

    The viewer builds its meshes from the same text (`robot.source["derivation"]`).
    """
    if derivation is None:
        return xml
    if derivation == "sdf":
        from .sdformat import sdf_to_urdf

        return sdf_to_urdf(parse_xml(xml, path, "SDF", "(the largest catalog robot has about 2000)"), path).urdf
    if derivation.startswith("prune:"):
        return _prune(xml, path, derivation.removeprefix("prune:"))
    raise ModelError(f"{path}: unknown derivation '{derivation}' (expected sdf or prune:JOINT)")


def mesh_roots(source: dict[str, Any]) -> list[Path]:
    """Folders a robot's meshes may come from (its `source`: Robot.source): the URDF's folder, its package
    directories and allowed roots, the catalog's package directory."""
    arguments = source.get("load_robot", {})
    roots = [Path(source["urdf_path"]).parent] if source.get("urdf_path") else []
    roots += [Path(p) for p in arguments.get("package_dirs", []) or []]
    roots += [Path(p) for p in arguments.get("allowed_roots", []) or []]
    name = arguments.get("source")
    if name in CATALOG:
        roots += catalog_urdf(CATALOG[name])[1]
    return [r.resolve() for r in roots]


def build_geometry(source: dict[str, Any], model: pin.Model, kind: str, **loader: Any) -> pin.GeometryModel:
    """The visual or collision geometry of a robot's URDF (or MJCF) on `model` (its own, or a scene's built from
    it: shapes attach to the links of the same names), from the file its `source` (Robot.source) records: checked
    unchanged (SHA-256), derived as the model was (catalog pruning, SDFormat), meshes resolved in mesh_roots().

    Args:
        kind: "visual" or "collision".
        **loader: Pinocchio's builder options (mesh_loader).

    Raises:
        ModelError: the file cannot be read, or changed since the robot was loaded.
        RuntimeError, ValueError: Pinocchio cannot build it (e.g. a mesh file that is not there).
    """
    path = Path(source["urdf_path"])
    try:
        xml = path.read_bytes()
    except OSError as exc:
        raise ModelError(f"{path}: cannot read the URDF for its {kind} meshes ({exc.strerror})") from None
    expected = source.get("urdf_sha256")
    if expected and hashlib.sha256(xml).hexdigest() != expected:
        raise ModelError(f"{path}: the URDF changed after the robot was loaded (SHA-256 differs); reload it")
    geometry_type = pin.GeometryType.VISUAL if kind == "visual" else pin.GeometryType.COLLISION
    if source.get("format") == "mjcf":  # checked at load like a URDF; Pinocchio reads it from its path
        return pin.buildGeomFromMJCF(model, str(path), geometry_type)
    return pin.buildGeomFromUrdfString(
        model,
        derived_urdf(xml, path, source.get("derivation")).decode("utf-8"),
        geometry_type,
        package_dirs=[str(r) for r in mesh_roots(source)],
        **loader,
    )


def _prune(xml: bytes, path: Path, joint: str) -> bytes:
    """The URDF without `joint`, its child link and everything below it (transmissions and gazebo blocks of the
    removed parts too)."""
    root = parse_xml(xml, path, "URDF", "(the largest catalog robot has about 2000)")
    joints = root.findall("joint")
    cut = next((j for j in joints if j.get("name") == joint), None)
    if cut is None or cut.find("child") is None:
        raise ModelError(f"{path}: no joint '{joint}' to cut the tree at")
    below: dict[str, list[Any]] = {}
    for element in joints:
        parent = element.find("parent")
        if parent is not None:
            below.setdefault(str(parent.get("link")), []).append(element)
    removed_links, removed_joints = set(), {joint}
    stack = [str(cut.find("child").get("link"))]
    while stack:
        link = stack.pop()
        if link in removed_links:
            continue
        removed_links.add(link)
        for element in below.get(link, []):
            removed_joints.add(str(element.get("name")))
            child = element.find("child")
            if child is not None:
                stack.append(str(child.get("link")))
    for element in list(root):
        tag, name = element.tag, element.get("name")
        gone = (tag == "link" and name in removed_links) or (tag == "joint" and name in removed_joints)
        gone |= tag == "gazebo" and element.get("reference") in removed_links | removed_joints
        gone |= tag == "transmission" and any(j.get("name") in removed_joints for j in element.findall("joint"))
        if gone:
            root.remove(element)
    from lxml import etree

    return etree.tostring(root, xml_declaration=True, encoding="utf-8")


def _rotate_base(model: pin.Model, rpy: tuple[float, float, float]) -> None:
    """Turn the robot by a constant rotation at its base: every joint and frame attached to the world."""
    turn = pin.SE3(pin.rpy.rpyToMatrix(*rpy), np.zeros(3))
    for jid in range(1, model.njoints):
        if model.parents[jid] == 0:
            model.jointPlacements[jid] = turn * model.jointPlacements[jid]
    for fid in range(1, len(model.frames)):
        frame = model.frames[fid]
        if frame.parentJoint == 0:
            frame.placement = turn * frame.placement
            model.frames[fid] = frame


def _lock(
    model: pin.Model, names: tuple[str, ...], reference: np.ndarray, poses: dict[str, np.ndarray]
) -> tuple[pin.Model, dict[str, np.ndarray]]:
    """The model without the named joints (locked where `reference` has them) and the poses on it."""
    ids = [model.getJointId(name) for name in names if model.existJointName(name)]
    if len(ids) != len(names):
        missing = [name for name in names if not model.existJointName(name)]
        raise ModelError(f"cannot lock joints the model does not have: {', '.join(missing)}")
    reduced = pin.buildReducedModel(model, ids, reference)
    return reduced, {name: reduce_configuration(model, reduced, q) for name, q in poses.items()}


def reduce_configuration(full: pin.Model, reduced: pin.Model, q: np.ndarray) -> np.ndarray:
    """A configuration of `full` on `reduced`, a model with some of its joints removed: each joint of `reduced`
    takes its coordinates from the joint of the same name in `full` (joints without coordinates are skipped)."""
    out = pin.neutral(reduced)
    for jid in range(1, reduced.njoints):
        joint = reduced.joints[jid]
        if joint.nq == 0 or not full.existJointName(reduced.names[jid]):
            continue
        source = full.joints[full.getJointId(reduced.names[jid])]
        if source.nq == joint.nq:
            out[joint.idx_q : joint.idx_q + joint.nq] = q[source.idx_q : source.idx_q + source.nq]
    return out


def folder_list(argument: str, folders: Any) -> list[Path]:
    """The resolved folders of a package_dirs / allowed_roots argument, or InvalidArgumentError."""
    if folders is None:
        return []
    # A single path would otherwise be iterated letter by letter.
    if isinstance(folders, (str, bytes, os.PathLike)) or not isinstance(folders, (list, tuple)):
        raise InvalidArgumentError(f"{argument} must be a list of folders, got {type(folders).__name__}")
    resolved = []
    for folder in folders:
        if not isinstance(folder, (str, os.PathLike)):
            raise InvalidArgumentError(f"{argument} entries must be folder paths, got {type(folder).__name__}")
        if not Path(folder).expanduser().is_dir():
            raise InvalidArgumentError(f"{argument}: '{os.fspath(folder)}' is not a folder")
        resolved.append(Path(folder).expanduser().resolve())
    return resolved


def _not_found(name: str, path: Path) -> Exception:
    looks_like_path = os.sep in name or name.lower().endswith((".urdf", ".xml"))
    if looks_like_path:
        return ModelError(f"{name}: URDF file not found")
    close = difflib.get_close_matches(name, CATALOG, n=3, cutoff=0.5)
    hint = f"did you mean {', '.join(close)}? " if close else ""
    return RobotNotFoundError(
        f"unknown robot '{name}': not a catalog name nor an existing URDF file ({hint}"
        "`multibody-sim models` lists the catalog)"
    )


def read_urdf(path: Path) -> bytes:
    """The URDF's bytes, refusing what is not a regular file and files over MAX_URDF_BYTES.

    Never blocks on a FIFO or reads more than MAX_URDF_BYTES + 1 bytes, whatever the size the file claims.
    """
    return read_xml_file(path, "URDF")


def read_xml_file(path: Path, kind: str) -> bytes:
    """A robot description file's bytes (kind: "URDF", "SRDF", "SDF", "MJCF"), refusing what is not a regular file
    and files over MAX_URDF_BYTES; never blocks on a FIFO or reads more than MAX_URDF_BYTES + 1 bytes."""
    try:
        # O_NONBLOCK: opening a FIFO for reading would otherwise wait for a writer forever.
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with os.fdopen(fd, "rb") as f:
            info = os.fstat(f.fileno())
            if not stat.S_ISREG(info.st_mode):
                raise ModelError(f"{path}: not a regular file")
            if info.st_size > MAX_URDF_BYTES:
                raise ModelError(
                    f"{path}: file is {info.st_size} bytes, larger than the {MAX_URDF_BYTES}-byte limit for a {kind}"
                )
            # Its stat size and one byte more (not the limit: a 32 MiB buffer per load); a file still growing (or
            # in /proc, whose size says 0) may exceed its stat size: then read on, up to the limit.
            xml = f.read(min(info.st_size, MAX_URDF_BYTES) + 1)
            if len(xml) > info.st_size:
                xml += f.read(MAX_URDF_BYTES + 1 - len(xml))
    except OSError as exc:
        raise ModelError(f"{path}: cannot read {kind} ({exc.strerror})") from None
    if len(xml) > MAX_URDF_BYTES:
        raise ModelError(f"{path}: file is larger than the {MAX_URDF_BYTES}-byte limit for a {kind}")
    return xml


def parse_xml(xml: bytes, path: Path, kind: str, largest: str) -> Any:
    """Parse untrusted XML bytes into an lxml element: no DTD, no entities, no network, at most MAX_XML_ELEMENTS
    elements (counted before parsing), comments and processing instructions dropped.

    Args:
        kind: what the file is ("URDF", "SRDF", ...), for messages.
        largest: what the element limit is compared with, for its message ("(the largest catalog robot has ...)").
    """
    # Before any parsing, anywhere in the file: entities never get a chance to expand (a DOCTYPE may follow a
    # long comment, so the whole file is searched; the prefix also catches lower-case spellings).
    if b"<!DOCTYPE" in xml or b"<!DOCTYPE" in xml[:65536].upper():
        raise ModelError(f"{path}: DOCTYPE declarations are not allowed in a {kind} (entities could expand)")
    tags = count_start_tags(xml)
    if tags > MAX_XML_ELEMENTS:
        raise ModelError(
            f"{path}: the file has {tags} XML elements, more than the {MAX_XML_ELEMENTS} a {kind} may have {largest}"
        )
    from lxml import etree

    parser = etree.XMLParser(
        resolve_entities=False, no_network=True, load_dtd=False, huge_tree=False, remove_comments=True, remove_pis=True
    )
    try:
        root = etree.fromstring(xml, parser=parser)
    except etree.XMLSyntaxError as exc:
        reason = str(exc.msg).replace("\n", "")  # libxml2 ends some messages with a newline: keep one line
        raise ModelError(f"{path}: malformed XML ({reason})") from None
    if root.getroottree().docinfo.doctype:
        raise ModelError(f"{path}: DOCTYPE declarations are not allowed in a {kind} (entities could expand)")
    return root


def count_start_tags(xml: bytes) -> int:
    """Number of element start tags in XML bytes (an upper bound: tags inside comments and CDATA count too).

    Counted without parsing, so that a file of millions of tiny elements is refused before libxml2 builds them.
    """
    opening = xml.count(b"<")
    if opening <= MAX_XML_ELEMENTS:  # the common case: one pass is enough to know it is small
        return opening
    return opening - xml.count(b"</") - xml.count(b"<!") - xml.count(b"<?")


def parse_urdf(xml: bytes, path: Path) -> Any:
    """Parse URDF bytes safely (no DTD, no entities, no network, bounded size) into yourdfpy's description."""
    root = parse_xml(xml, path, "URDF", "(the largest catalog robot has about 2000)")
    if root.tag != "robot":
        raise ModelError(f"{path}: not a URDF: the root element is <{root.tag}>, expected <robot>")
    if "name" not in root.attrib:
        raise ModelError(f"{path}: the <robot> element has no 'name' attribute")
    for kind, limit in (("link", MAX_LINKS), ("joint", MAX_JOINTS)):
        count = int(root.xpath(f"count({kind})"))  # counted in libxml2: no Python object per element
        if count > limit:
            raise ModelError(
                f"{path}: the robot has {count} {kind}s, more than the {limit} this simulator accepts "
                "(the largest catalog robot has 78)"
            )
    import yourdfpy  # lazily: it imports trimesh, a second of start-up that `--help` should not pay

    try:
        # NaN or infinite origins make trimesh warn while composing matrices; check_urdf reports them.
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            return yourdfpy.URDF(
                robot=yourdfpy.URDF._parse_robot(xml_element=root),
                build_scene_graph=False,
                load_meshes=False,
                load_collision_meshes=False,
            )
    except (ValueError, TypeError, KeyError, AttributeError, IndexError) as exc:
        raise ModelError(f"{path}: invalid URDF ({exc})") from None


def check_urdf(
    description: Any, path: Path, *, package_dirs: list[Path], allowed_roots: list[Path] | None = None
) -> None:
    """Refuse what Pinocchio would mis-read: unsupported joints, broken trees, bad numbers, escaping URIs.

    Args:
        description: yourdfpy's URDF, from parse_urdf.
        path: the URDF file (named in messages).
        package_dirs: the URDF's folder and the folders package:// URIs resolve against.
        allowed_roots: further folders mesh paths may resolve into.
    """
    robot = description.robot
    links = {link.name for link in robot.links}
    if not robot.links:
        raise ModelError(f"{path}: the robot has no <link>")
    if len(links) != len(robot.links):
        raise ModelError(f"{path}: duplicate link names")
    joint_names = [joint.name for joint in robot.joints]
    if len(set(joint_names)) != len(joint_names):
        repeated = sorted({str(n) for n in joint_names if joint_names.count(n) > 1})
        raise ModelError(f"{path}: duplicate joint names ({', '.join(repeated)})")
    children: dict[str, str] = {}
    for joint in robot.joints:
        if joint.type not in SUPPORTED_JOINT_TYPES:
            raise ModelError(
                f"{path}: joint '{joint.name}' has unsupported type '{joint.type}' "
                f"(supported: {', '.join(SUPPORTED_JOINT_TYPES)})"
            )
        for role, link in (("parent", joint.parent), ("child", joint.child)):
            if link not in links:
                raise ModelError(f"{path}: joint '{joint.name}' names {role} link '{link}', which does not exist")
        if joint.child in children:
            raise ModelError(
                f"{path}: link '{joint.child}' is the child of two joints "
                f"('{children[joint.child]}' and '{joint.name}')"
            )
        children[joint.child] = joint.name
        if (
            joint.type in ("revolute", "continuous", "prismatic")
            and joint.axis is not None
            and not (np.all(np.isfinite(joint.axis)) and np.linalg.norm(joint.axis) > 1e-9)
        ):
            raise ModelError(f"{path}: joint '{joint.name}' has a zero or non-finite axis")
        _check_joint_numbers(joint, path)
    roots = links - set(children)
    if not roots:
        raise ModelError(f"{path}: the joints form a cycle (every link has a parent joint)")
    if len(roots) != 1:
        raise ModelError(f"{path}: the links must form one tree, found {len(roots)} roots ({', '.join(sorted(roots))})")
    unreachable = links - _descendants(next(iter(roots)), robot.joints)
    if unreachable:  # one root, yet a loop elsewhere: those links each have a parent but never reach the root
        raise ModelError(
            f"{path}: the joints form a cycle (links {', '.join(sorted(unreachable))} are not connected to the root)"
        )
    welded = {joint.child for joint in robot.joints if joint.type == "fixed"}
    package_roots = [Path(os.path.realpath(p)) for p in package_dirs]
    mesh_roots = package_roots + [Path(os.path.realpath(p)) for p in allowed_roots or []]
    checked: set[tuple[str, str]] = set()  # visual and collision geometry often share files

    def check_uri(uri: str, kind: str) -> None:
        if (uri, kind) not in checked:
            _resolve_uri(uri, path, package_roots, mesh_roots, kind)
            checked.add((uri, kind))

    for link in robot.links:
        _check_inertial(link, path, welded=link.name in welded)
        for kind, elements in (("visual", link.visuals), ("collision", link.collisions)):
            for element in elements:
                _check_geometry(element, kind, link.name, path)
                mesh = getattr(element.geometry, "mesh", None) if element.geometry is not None else None
                if mesh is not None and mesh.filename:
                    check_uri(mesh.filename, "mesh")
    # Textures are files a viewer would read, like meshes: the same folders bound them.
    materials = [*robot.materials, *(v.material for link in robot.links for v in link.visuals)]
    for material in materials:
        texture = getattr(material, "texture", None) if material is not None else None
        if texture is not None and texture.filename:
            check_uri(texture.filename, "texture")


def _descendants(root: str, joints: list[Any]) -> set[str]:
    """The links reachable from root through the joints (root included), without recursion."""
    below: dict[str, list[str]] = {}
    for joint in joints:
        below.setdefault(joint.parent, []).append(joint.child)
    seen, stack = {root}, [root]
    while stack:
        for child in below.get(stack.pop(), []):
            if child not in seen:
                seen.add(child)
                stack.append(child)
    return seen


def _check_joint_numbers(joint: Any, path: Path) -> None:
    """Origins, limits and dynamics that Pinocchio would take as they are (NaN, inverted, negative)."""
    where = f"{path}: joint '{joint.name}'"
    if joint.origin is not None and not np.all(np.isfinite(joint.origin)):
        raise ModelError(f"{where} has a non-finite origin")
    limit = joint.limit
    if limit is not None:
        for attribute in ("lower", "upper", "effort", "velocity"):
            value = getattr(limit, attribute)
            if value is not None and not np.isfinite(value):
                raise ModelError(f"{where} has {attribute} limit {value}; it must be finite")
        for attribute in ("effort", "velocity"):
            value = getattr(limit, attribute)
            if value is not None and value < 0:
                raise ModelError(f"{where} has {attribute} limit {value}; it must be >= 0 (0 means none)")
        if limit.lower is not None and limit.upper is not None and limit.lower > limit.upper:
            raise ModelError(f"{where} has lower limit {limit.lower} above its upper limit {limit.upper}")
    if joint.dynamics is not None:
        for attribute in ("damping", "friction"):
            text = getattr(joint.dynamics, attribute)  # yourdfpy keeps these as the file's strings
            if text is None:
                continue
            try:
                value = float(text)
            except (TypeError, ValueError):
                raise ModelError(f"{where} has {attribute} '{text}', which is not a number") from None
            if not np.isfinite(value) or value < 0:  # negative damping or friction would feed energy in
                raise ModelError(f"{where} has {attribute} {value}; it must be finite and >= 0")


def _check_geometry(element: Any, kind: str, link: str, path: Path) -> None:
    """Visual and collision shapes: finite origins, sizes and mesh scales (the viewer builds them)."""
    sizes: list[Any] = []
    scale = None
    geometry = element.geometry
    if geometry is not None:
        if geometry.box is not None:
            sizes.append(geometry.box.size)
        if geometry.cylinder is not None:
            sizes += [geometry.cylinder.radius, geometry.cylinder.length]
        if geometry.sphere is not None:
            sizes.append(geometry.sphere.radius)
        if geometry.mesh is not None:
            scale = geometry.mesh.scale  # may be negative: talos mirrors its right arm with scale="1 -1 1"
    if element.origin is not None and not np.all(np.isfinite(element.origin)):
        raise ModelError(f"{path}: link '{link}' has a {kind} with a non-finite origin")
    numbers = np.concatenate([np.ravel(np.asarray(size, dtype=float)) for size in sizes] + [np.zeros(0)])
    if not (np.all(np.isfinite(numbers)) and np.all(numbers >= 0)):
        raise ModelError(f"{path}: link '{link}' has a {kind} with a non-finite or negative size")
    if scale is not None and not np.all(np.isfinite(np.asarray(scale, dtype=float))):
        raise ModelError(f"{path}: link '{link}' has a {kind} mesh with a non-finite scale")


def _inertia_tolerance(inertia: np.ndarray, mass: float) -> float:
    """How negative an inertia's eigenvalue may be and still be round-off [kg·m²]: 1e-9 of its trace, or of what a
    1 mm body of its mass would have when the file gives a point mass (icub's links hold zeros plus 1e-20s)."""
    return 1e-9 * max(float(np.trace(inertia)), mass * 1e-6, 1e-300)


def _check_inertial(link: Any, path: Path, *, welded: bool = False) -> None:
    """A link's mass and inertia: finite, mass >= 0 and (unless `welded`) a positive semi-definite inertia.

    A link welded to its parent by a fixed joint is never a body of its own: Pinocchio merges it into the body it
    is welded to, and _check_body_inertias judges that body. (tiago's 1 mg antennas carry inertias with a
    -3.5e-8 kg·m² eigenvalue, an error in the file that changes its base's merged inertia by less than 1e-7.)
    """
    inertial = link.inertial
    if inertial is None:
        return
    mass = inertial.mass if inertial.mass is not None else 0.0
    if not np.isfinite(mass) or mass < 0:
        raise ModelError(f"{path}: link '{link.name}' has mass {mass}; it must be finite and >= 0")
    if inertial.origin is not None and not np.all(np.isfinite(inertial.origin)):
        raise ModelError(f"{path}: link '{link.name}' has a non-finite inertial origin")
    if inertial.inertia is not None:
        inertia = np.asarray(inertial.inertia, dtype=float)
        if not np.all(np.isfinite(inertia)):
            raise ModelError(f"{path}: link '{link.name}' has a non-finite inertia")
        eig = np.linalg.eigvalsh(inertia)
        if not welded and eig[0] < -_inertia_tolerance(inertia, mass):
            raise ModelError(f"{path}: link '{link.name}' has an inertia with a negative eigenvalue ({eig[0]:.3g})")


def _check_body_inertias(model: pin.Model, path: Path) -> None:
    """Each rigid body (links welded together merged, as Pinocchio does) must have a positive semi-definite
    inertia whose principal moments satisfy the triangle inequality: a single massless dummy link may be thin,
    the body it is welded to may not."""
    for i in range(1, model.njoints):
        inertia = model.inertias[i].inertia
        a, b, c = np.linalg.eigvalsh(inertia)
        if a < -_inertia_tolerance(inertia, model.inertias[i].mass):
            raise ModelError(
                f"{path}: the body moved by joint '{model.names[i]}' has an inertia with a negative eigenvalue "
                f"({a:.3g})"
            )
        if a + b < c - 1e3 * _inertia_tolerance(inertia, model.inertias[i].mass):  # 1e-6 of the trace
            raise ModelError(
                f"{path}: the body moved by joint '{model.names[i]}' has principal inertias "
                f"{a:.3g}, {b:.3g}, {c:.3g} that violate the triangle inequality"
            )


def resolve_mesh_uri(
    uri: str,
    urdf_path: Path,
    package_dirs: list[Path],
    *,
    allowed_roots: list[Path] | None = None,
    kind: str = "mesh",
) -> Path | None:
    """The file a mesh URI names, which must lie inside the URDF's folder, a package directory or an allowed root.

    The check is lexical first (a `..` escape is refused without touching the file system), then on the real
    path (a symlink leading out is refused); no file is opened.

    Args:
        uri: the mesh filename as the URDF writes it: `package://NAME/...`, `file://...` or a path (relative
            to the URDF's folder).
        urdf_path: the URDF file.
        package_dirs: the URDF's folder and the folders package:// URIs resolve against.
        allowed_roots: further folders the mesh may resolve into.
        kind: what the URI names, for messages ("mesh" or "texture").

    Returns:
        The mesh file, or None when no candidate file exists (meshes only matter for viewing).

    Raises:
        ModelError: the URI resolves outside every allowed folder, or has a scheme other than package://.
    """
    package_roots = [Path(os.path.realpath(p)) for p in package_dirs]
    roots = package_roots + [Path(os.path.realpath(p)) for p in allowed_roots or []]
    return _resolve_uri(uri, urdf_path, package_roots, roots, kind)


def _resolve_uri(uri: str, urdf_path: Path, package_roots: list[Path], roots: list[Path], kind: str) -> Path | None:
    """resolve_mesh_uri with the roots already resolved (check_urdf resolves them once for all its meshes)."""
    if uri.startswith("package://"):
        package, _, rest = uri[len("package://") :].partition("/")
        candidates = [root / package / rest for root in package_roots]
        candidates += [root / rest for root in package_roots if root.name == package]
    elif uri.startswith("file://"):
        candidates = [Path(uri[len("file://") :])]
    elif "://" in uri:
        raise ModelError(f"{urdf_path}: {kind} URI '{uri}' has an unsupported scheme (use package:// or a file path)")
    else:
        candidates = [urdf_path.parent / uri]
    found = None
    for candidate in candidates:
        lexical = Path(os.path.normpath(candidate))
        resolved = lexical if not inside_roots(lexical, roots) else Path(os.path.realpath(lexical))
        if not inside_roots(resolved, roots):
            raise ModelError(
                f"{urdf_path}: {kind} '{uri}' resolves outside the allowed folders "
                f"({', '.join(str(r) for r in roots)}); add its folder to package_dirs"
            )
        if found is None and os.path.isfile(resolved):
            found = resolved
    return found


def inside_roots(path: Path, roots: list[Path]) -> bool:
    """Whether a normalized absolute path lies in (or is) one of the roots (compared as strings: 10x faster than
    Path.is_relative_to, which the catalog's 2000-odd meshes felt)."""
    text = str(path)
    return any(text == str(root) or text.startswith(str(root).rstrip(os.sep) + os.sep) for root in roots)


@contextlib.contextmanager
def _captured_stderr() -> Iterator[list[str]]:
    """Capture what C++ code writes to file descriptor 2 (urdfdom logs its parse errors there).

    Yields a list that holds the captured text once the block ends. The CLI promises one line on stderr for
    bad input; urdfdom's several lines would break that, and its first error is the useful part of the message.
    """
    captured: list[str] = []
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no usable fd 2 (embedded interpreters): do not capture
        yield captured
        return
    import tempfile

    try:
        with tempfile.TemporaryFile() as sink:
            os.dup2(sink.fileno(), 2)
            try:
                yield captured
            finally:
                os.dup2(saved, 2)
                sink.seek(0)
                captured.append(sink.read(1 << 20).decode("utf-8", "replace"))
    finally:
        os.close(saved)


def _build_model(xml: bytes, path: Path, floating: bool) -> pin.Model:
    try:
        text = xml.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ModelError(f"{path}: Pinocchio cannot build the model ({exc})") from None
    error: BaseException | None = None
    with _captured_stderr() as logged:
        try:
            model = pin.buildModelFromXML(text, pin.JointModelFreeFlyer()) if floating else pin.buildModelFromXML(text)
        except (RuntimeError, ValueError, TypeError, OverflowError) as exc:
            error = exc
    log = "".join(logged)
    # urdfdom's first "Error:" line says what is wrong; Pinocchio's own message only that something is.
    reasons = [line.removeprefix("Error:").strip() for line in log.splitlines() if line.startswith("Error:")]
    if error is None and reasons:
        # urdfdom skips what it cannot read and carries on: an <inertial> without <inertia> leaves its link
        # massless, though the file says otherwise. No example-robot-data URDF that builds logs an error.
        raise ModelError(f"{path}: Pinocchio's URDF parser skipped part of the file ({reasons[0]})")
    if error is None:
        if log:  # warnings of a model that did build: pass them on unchanged
            sys.stderr.write(log)
        return model
    lines = str(error).strip().splitlines()
    reason = reasons[0] if reasons else (lines[0] if lines else type(error).__name__)
    raise ModelError(f"{path}: Pinocchio cannot build the model ({reason})") from None


def _check_model_numbers(model: pin.Model, path: Path) -> None:
    """Whatever the URDF said, the model Pinocchio built must hold finite numbers (urdfdom reads some values
    yourdfpy does not, and vice versa)."""
    for i in range(model.njoints):
        inertia, placement = model.inertias[i], model.jointPlacements[i]
        numbers = [inertia.mass, *inertia.lever, *inertia.inertia.ravel(), *placement.homogeneous.ravel()]
        if not np.all(np.isfinite(numbers)):
            raise ModelError(f"{path}: the model Pinocchio built for joint '{model.names[i]}' has non-finite values")
    for name in ("damping", "friction"):
        if not np.all(np.isfinite(np.asarray(getattr(model, name), dtype=float))):
            raise ModelError(f"{path}: the model Pinocchio built has non-finite {name} values")
    for name in ("effortLimit", "velocityLimit", "lowerPositionLimit", "upperPositionLimit"):
        # ±inf means "no limit" (Pinocchio writes it for planar joints); NaN means nothing
        if np.any(np.isnan(np.asarray(getattr(model, name), dtype=float))):
            raise ModelError(f"{path}: the model Pinocchio built has NaN {name} values")


# A mass matrix whose smallest eigenvalue is below this fraction of its largest is singular for the purpose of
# simulating: its inverse amplifies round-off by as much (icub's point-mass head on the neck-yaw axis: -1.6e-17 of
# 29). The catalog's stiffest sound robots stay above 2e-7 (tiago_no_hand's wrist).
SINGULAR_MASS_RATIO = 1e-12


def _check_mass_matrix(robot: Robot, path: Path) -> None:
    """A moving subtree with no mass (or no inertia about its axis) makes M(q) singular: refuse it at load, not
    mid-run. Checked at the neutral configuration, the default pose and a random configuration."""
    if robot.nv == 0:
        raise ModelError(f"{path}: the robot has no movable joint (a fixed base with only fixed joints)")
    for q in (robot.neutral(), robot.default_pose(), robot.random_configuration(np.random.default_rng(0))):
        with np.errstate(all="ignore"):
            M = robot.mass_matrix(q)
        if not np.all(np.isfinite(M)):  # finite inputs can still overflow (masses and lengths near 1e300)
            raise ModelError(f"{path}: the mass matrix is not finite (masses, inertias or distances are too large)")
        eigenvalues = np.linalg.eigvalsh(M)
        if eigenvalues[0] <= SINGULAR_MASS_RATIO * eigenvalues[-1]:
            weak = int(np.argmax(np.abs(np.linalg.eigh(M)[1][:, 0])))  # the main dof of the null direction
            raise ModelError(
                f"{path}: the mass matrix is singular: the subtree moved by '{robot.dof_names[weak]}' has no mass "
                "or inertia"
            )


def catalog_table() -> list[dict[str, Any]]:
    """One row per catalog robot: name, nq, nv, base, poses (names), default_pose (name or None), description.

    Loads every model (a few seconds for the whole catalog).
    """
    rows = []
    for entry in CATALOG.values():
        robot = load_robot(entry.name)
        rows.append(
            {
                "name": entry.name,
                "nq": robot.nq,
                "nv": robot.nv,
                "base": "floating" if robot.floating_base else "fixed",
                "poses": list(robot.poses),
                "default_pose": robot.default_pose_name,
                "description": entry.description,
            }
        )
    return rows
