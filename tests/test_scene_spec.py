"""Scene files: every accepted field round-trips, every kind of mistake gives its exact one-line message."""

from __future__ import annotations

import dataclasses
import math
import os
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import joint, link, urdf

import multibody_sim as ms
from multibody_sim.exceptions import InvalidArgumentError, SceneError
from multibody_sim.scenes.parse import MAX_SCENE_BYTES, parse_scene, read_scene_file
from multibody_sim.scenes.spec import (
    ConstraintSpec,
    ControllerSpec,
    ForceSpec,
    JointSpec,
    PayloadSpec,
    RobotSpec,
    SceneSpec,
    SimulationSpec,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

FULL_SCENE = """\
description = "panda holding a 1 kg payload, fingers locked"
gravity = [0.0, 1.5, -9.81]
friction_velocity = 2e-3

[robot]
source = "panda"
base = "fixed"
position = [0.1, -0.2, 0.5]
rpy = [0.0, 0.25, 3.0]
damping = false
mimic = true
package_dirs = ["pkgs", "/abs/pkgs"]

[lock]
panda_finger_joint1 = 0.02
panda_finger_joint2 = -0.01

[joints.panda_joint2]
damping = 0.5
friction = 0.3
stiffness = 20.0
rest = -0.4
armature = 0.01

[joints.panda_joint4]
stiffness = 5

[[force]]
name = "push"
frame = "panda_hand"
force = [0.0, 0.0, -10.0]
torque = [1.0, 2.0, 3.0]
reference = "local"
shape = "ramp"
start = 0.5
ramp_time = 2.0

[[force]]
frame = "panda_link3"
force = [1, 0, 0]
shape = "sine"
start = 0.25
frequency = 3.0
phase = 0.5

[[force]]
name = "kick"
frame = "panda_link5"
torque = [0.0, 0.0, 1.0]
shape = "step"
start = 1.0

[[payload]]
frame = "panda_hand"
mass = 1.0
com = [0.0, 0.0, 0.1]
inertia = [1e-3, 2e-3, 2.5e-3, 1e-4, 0.0, 0.0]

[[payload]]
frame = "panda_link7"
mass = 0.25

[[constraint]]
name = "closure"
type = "loop"
frames = ["coupler_tip", "rocker_tip"]
stabilization = [100.0, 20.0]

[[constraint]]
type = "point"
frames = ["panda_hand"]
position = [0.3, 0.0, 0.4]

[[constraint]]
type = "weld"
frames = ["panda_leftfinger", "panda_rightfinger"]

[initial]
q = [0.0, 0.1, 0, -1.5, 0, 1.6, 0.7]
v = {panda_joint1 = 0.5, panda_joint3 = -1}

[simulation]
duration = 2.0
dt = 1e-3
integrator = "dp54"
output_dt = 0.01
control_dt = 0.002
rtol = 1e-8
atol = 1e-9
max_step = 0.05

[controller]
name = "pd"
kp = 100.0
kd = [1, 2, 3, 4, 5, 6, 7, 8, 9]
q_ref = [0, -1, 1, -2, 0, 1.5, 0.5, 0.01, 0.01]
"""


def expected_full_scene(base_dir: Path, source: str, text: str | None) -> SceneSpec:
    """FULL_SCENE written out by hand as dataclasses: the values the file holds, defaults where it is silent."""
    return SceneSpec(
        robot=RobotSpec(
            source="panda",
            base="fixed",
            position=(0.1, -0.2, 0.5),
            rpy=(0.0, 0.25, 3.0),
            damping=False,
            mimic=True,
            package_dirs=(str(base_dir / "pkgs"), "/abs/pkgs"),
        ),
        description="panda holding a 1 kg payload, fingers locked",
        gravity=(0.0, 1.5, -9.81),
        friction_velocity=2e-3,
        lock={"panda_finger_joint1": 0.02, "panda_finger_joint2": -0.01},
        joints={
            "panda_joint2": JointSpec(damping=0.5, friction=0.3, stiffness=20.0, rest=-0.4, armature=0.01),
            "panda_joint4": JointSpec(damping=None, friction=None, stiffness=5.0, rest=None, armature=None),
        },
        forces=(
            ForceSpec("push", "panda_hand", (0.0, 0.0, -10.0), (1.0, 2.0, 3.0), "local", "ramp", 0.5, 2.0, 1.0, 0.0),
            ForceSpec("force1", "panda_link3", (1.0, 0.0, 0.0), (0.0, 0.0, 0.0), "world", "sine", 0.25, 1.0, 3.0, 0.5),
            ForceSpec("kick", "panda_link5", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "world", "step", 1.0, 1.0, 1.0, 0.0),
        ),
        payloads=(
            PayloadSpec("panda_hand", 1.0, (0.0, 0.0, 0.1), (1e-3, 2e-3, 2.5e-3, 1e-4, 0.0, 0.0)),
            PayloadSpec("panda_link7", 0.25, (0.0, 0.0, 0.0), (0.0,) * 6),
        ),
        constraints=(
            ConstraintSpec("closure", "loop", ("coupler_tip", "rocker_tip"), None, (100.0, 20.0)),
            ConstraintSpec("constraint1", "point", ("panda_hand",), (0.3, 0.0, 0.4), None),
            ConstraintSpec("constraint2", "weld", ("panda_leftfinger", "panda_rightfinger"), None, None),
        ),
        initial_q=(0.0, 0.1, 0.0, -1.5, 0.0, 1.6, 0.7),
        initial_v={"panda_joint1": 0.5, "panda_joint3": -1.0},
        simulation=SimulationSpec(
            2.0, 1e-3, "dp54", {"output_dt": 0.01, "control_dt": 0.002, "rtol": 1e-8, "atol": 1e-9, "max_step": 0.05}
        ),
        controller=ControllerSpec(
            "pd", {"kp": 100.0, "kd": (1, 2, 3, 4, 5, 6, 7, 8, 9), "q_ref": (0, -1, 1, -2, 0, 1.5, 0.5, 0.01, 0.01)}
        ),
        source=source,
        text=text,
        base_dir=base_dir,
    )


def write(folder: Path, text: str | bytes, name: str = "scene.toml") -> Path:
    path = folder / name
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8")
    return path


def scene(**tables: Any) -> dict[str, Any]:
    """A minimal valid scene (panda) with the given top-level keys added or replaced."""
    return {"robot": {"source": "panda"}, **tables}


def parse(data: Any) -> SceneSpec:
    return parse_scene(data, "scene.toml", base_dir=None)


# ---- accepted scenes -----------------------------------------------------------------------------------
def test_every_field_of_a_scene_file_round_trips(tmp_path, monkeypatch):
    """Each value written in the file comes back in its dataclass field, unit for unit; the text is kept."""
    folder = tmp_path / "scenes"
    folder.mkdir()
    write(folder, FULL_SCENE)
    monkeypatch.chdir(tmp_path)
    spec = read_scene_file("scenes/scene.toml")
    assert spec == expected_full_scene(folder, "scenes/scene.toml", FULL_SCENE)
    # Integers written for floats come back as floats (the Scene builder does arithmetic with them).
    assert isinstance(spec.joints["panda_joint4"].stiffness, float)
    assert all(isinstance(x, float) for x in spec.forces[1].force)


def test_a_dict_built_in_python_gives_the_same_spec(tmp_path):
    """parse_scene on the same tables (as make_scene passes them) equals reading the file, less the text."""
    spec = parse_scene(tomllib.loads(FULL_SCENE), "<scene>", base_dir=tmp_path)
    assert spec == expected_full_scene(tmp_path, "<scene>", None)


def test_numpy_values_are_accepted_from_python():
    """Arrays and numpy scalars (what Python callers have at hand) are plain numbers in the spec."""
    spec = parse(
        scene(
            gravity=np.array([0.0, 0.0, -1.62]),
            lock={"panda_finger_joint1": np.float64(0.03)},
            initial={"q": np.zeros(7), "v": np.arange(7)},
            payload=[{"frame": "panda_hand", "mass": np.float32(0.5), "com": np.array([0, 0, 0.1])}],
        )
    )
    assert spec.gravity == (0.0, 0.0, -1.62)
    assert spec.lock == {"panda_finger_joint1": 0.03}
    assert spec.initial_q == (0.0,) * 7
    assert spec.initial_v == (0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0)
    assert spec.payloads[0].mass == 0.5 and spec.payloads[0].com == (0.0, 0.0, 0.1)


def test_defaults_of_a_minimal_scene():
    """Only robot.source is required; everything else takes the documented default."""
    spec = parse(scene())
    assert spec == SceneSpec(
        robot=RobotSpec("panda", None, None, None, True, False, ()),
        description="",
        gravity=None,
        friction_velocity=1e-3,
        lock={},
        joints={},
        forces=(),
        payloads=(),
        constraints=(),
        initial_q=None,
        initial_v=None,
        simulation=None,
        controller=None,
        source="scene.toml",
        text=None,
        base_dir=None,
    )
    # An empty [simulation] table is a SimulationSpec that leaves everything to the caller.
    assert parse(scene(simulation={})).simulation == SimulationSpec(None, None, None, {})
    # A force with only a frame is a constant, world-aligned zero wrench named after its index.
    assert parse(scene(force=[{"frame": "panda_hand"}])).forces == (
        ForceSpec("force0", "panda_hand", (0.0,) * 3, (0.0,) * 3, "world", "constant", 0.0, 1.0, 1.0, 0.0),
    )


def test_specs_are_frozen():
    spec = parse(scene(force=[{"frame": "panda_hand"}]))
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.forces[0].frame = "panda_link1"  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.robot = RobotSpec("ur5")  # type: ignore[misc]


def test_base_pose_is_accepted_with_a_natural_fixed_base():
    """position/rpy need a fixed base: a fixed catalog entry, base = "fixed", or a URDF path (fixed by default)."""
    assert parse(scene(robot={"source": "ur5", "position": [0, 0, 1]})).robot.position == (0.0, 0.0, 1.0)
    spec = parse(scene(robot={"source": "solo12", "base": "fixed", "rpy": [0.1, 0, 0]}))
    assert spec.robot.rpy == (0.1, 0.0, 0.0)
    assert parse(scene(robot={"source": "/robots/arm.urdf", "position": [1, 2, 3]})).robot.position == (1.0, 2.0, 3.0)


@pytest.mark.parametrize(
    "inertia",
    [
        pytest.param((0.0,) * 6, id="point mass"),
        # A thin rod of m L²/12 = 1 along (1, 1, 0)/√2: I = 1 − u uᵀ, principal moments (0, 1, 1), the
        # triangle inequality holding with equality; rotated, so round-off must be tolerated.
        pytest.param((0.5, 0.5, 1.0, -0.5, 0.0, 0.0), id="rotated thin rod"),
        # A flat plate: izz = ixx + iyy exactly (the perpendicular axis theorem).
        pytest.param((2e-3, 3e-3, 5e-3, 0.0, 0.0, 0.0), id="flat plate"),
        pytest.param((1e-3, 1e-3, 1e-3, 0.0, 0.0, 0.0), id="sphere"),
    ],
)
def test_physical_inertias_are_accepted(inertia):
    """Limiting cases of physical inertias (point, rod, plate) pass the semi-definiteness and triangle checks."""
    spec = parse(scene(payload=[{"frame": "panda_hand", "mass": 1.0, "inertia": list(inertia)}]))
    assert spec.payloads[0].inertia == tuple(float(x) for x in inertia)


# ---- paths ---------------------------------------------------------------------------------------------
def test_relative_urdf_path_resolves_against_the_scene_folder(tmp_path, monkeypatch):
    """A relative robot.source is found from the scene file's folder whatever the working directory."""
    folder = tmp_path / "project" / "scenes"
    (folder / "urdf").mkdir(parents=True)
    (folder / "urdf" / "arm.urdf").write_text(
        urdf(link("base"), link("arm"), joint("shoulder", "base", "arm")), encoding="utf-8"
    )
    write(folder, '[robot]\nsource = "urdf/arm.urdf"\npackage_dirs = ["meshes"]\n')
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    spec = read_scene_file(folder / "scene.toml")
    assert spec.robot.source == str(folder / "urdf" / "arm.urdf")
    assert spec.robot.package_dirs == (str(folder / "meshes"),)
    assert spec.base_dir == folder
    # The resolved path is the file: load_robot (from another working directory) finds the one-joint arm.
    assert ms.load_robot(spec.robot.source).joint_names == ["shoulder"]


def test_catalog_names_and_absolute_paths_are_kept(tmp_path):
    """A catalog name stays a name even beside a file of that name; absolute paths are not touched."""
    write(tmp_path, "not a urdf", name="panda")
    write(tmp_path, '[robot]\nsource = "panda"\n')
    assert read_scene_file(tmp_path / "scene.toml").robot.source == "panda"
    absolute = str(tmp_path / "robots" / "arm.urdf")
    write(tmp_path, f"[robot]\nsource = '{absolute}'\n")
    assert read_scene_file(tmp_path / "scene.toml").robot.source == absolute


def test_relative_path_in_a_dict_without_base_dir_is_left_as_given():
    """make_scene's dicts have no file: relative paths stay relative to the working directory."""
    assert parse(scene(robot={"source": "urdf/arm.urdf"})).robot.source == "urdf/arm.urdf"


# ---- force shapes --------------------------------------------------------------------------------------
def force(**keys: Any) -> ForceSpec:
    return parse(scene(force=[{"frame": "panda_hand", **keys}])).forces[0]


def test_constant_shape_is_one_at_all_times():
    f = force()
    assert [f.scale(t) for t in (-1.0, 0.0, 3.7)] == [1.0, 1.0, 1.0]


def test_step_shape_switches_on_at_start():
    f = force(shape="step", start=0.5)
    assert [f.scale(t) for t in (0.0, 0.4999, 0.5, 2.0)] == [0.0, 0.0, 1.0, 1.0]


def test_ramp_shape_rises_linearly_over_ramp_time():
    """clip((t − 1) / 2, 0, 1): 0 until 1 s, 1/4 at 1.5 s, 1/2 at 2 s, 3/4 at 2.5 s, 1 from 3 s on."""
    f = force(shape="ramp", start=1.0, ramp_time=2.0)
    values = [f.scale(t) for t in (0.0, 1.0, 1.5, 2.0, 2.5, 3.0, 10.0)]
    assert values == pytest.approx([0.0, 0.0, 0.25, 0.5, 0.75, 1.0, 1.0], abs=1e-15)


def test_sine_shape_matches_its_closed_form():
    """sin(2π f (t − start) + φ): sin φ at start, cos φ a quarter period later, −sin φ at half a period, a full
    period repeats; 0 before start."""
    frequency, start, phase = 2.0, 0.5, 0.3
    f = force(shape="sine", start=start, frequency=frequency, phase=phase)
    period = 1.0 / frequency
    assert f.scale(start - 1e-9) == 0.0
    assert f.scale(start) == pytest.approx(math.sin(phase), abs=1e-15)
    assert f.scale(start + period / 4) == pytest.approx(math.cos(phase), abs=1e-14)
    assert f.scale(start + period / 2) == pytest.approx(-math.sin(phase), abs=1e-14)
    assert f.scale(start + 3 * period / 4) == pytest.approx(-math.cos(phase), abs=1e-14)
    assert f.scale(start + period) == pytest.approx(math.sin(phase), abs=1e-14)


def test_python_callable_shape():
    """From Python a shape may be t -> scale; its values are the factor, and it takes no timing keys."""
    f = force(shape=lambda t: 1.0 - t**2, force=[0, 0, 2])
    assert f.scale(0.0) == 1.0 and f.scale(3.0) == -8.0
    assert isinstance(f.scale(0.5), float)
    with pytest.raises(
        SceneError, match=re.escape("scene.toml: force[0].start: only for shape step, ramp or sine, not callable")
    ):
        force(shape=lambda t: 1.0, start=1.0)


@pytest.mark.parametrize(
    ("shape", "shown"), [(lambda t: math.nan, "nan"), (lambda t: "1", "'1'"), (lambda t: True, "True")]
)
def test_callable_shape_returning_a_non_number_is_refused(shape, shown):
    f = force(name="wind", shape=shape)
    with pytest.raises(
        InvalidArgumentError, match=re.escape(f"force 'wind': shape(0.5) returned {shown}, not a finite real number")
    ):
        f.scale(0.5)


def test_a_callable_cannot_come_from_toml(tmp_path):
    """TOML gives strings only: code in a scene file is a name like any other, refused."""
    write(tmp_path, '[robot]\nsource = "panda"\n[[force]]\nframe = "panda_hand"\nshape = "lambda t: 1"\n')
    with pytest.raises(
        SceneError, match=re.escape("force[0].shape: must be one of constant, ramp, sine, step, got 'lambda t: 1'")
    ):
        read_scene_file(tmp_path / "scene.toml")


# ---- controller parameters -----------------------------------------------------------------------------
def controller_of(data: dict[str, Any]) -> ControllerSpec:
    controller = parse(data).controller
    assert controller is not None
    return controller


def test_controller_params_become_make_controller_strings(robot):
    """The strings build the same PD as the numbers: tau = kp (q_ref − q) + kd (0 − v) on a revolute pair."""
    spec = controller_of(scene(controller={"name": "pd", "kp": 100.0, "kd": [1, 2.5], "q_ref": [3, -0.5]}))
    strings = spec.as_param_strings()
    assert strings == ["kp=100.0", "kd=1,2.5", "q_ref=3,-0.5"]
    pendulum = robot("double_pendulum")
    controller = ms.make_controller(spec.name, pendulum, strings)
    q, v = np.array([2.0, 0.25]), np.array([0.5, -1.0])
    expected = 100.0 * (np.array([3.0, -0.5]) - q) - np.array([1.0, 2.5]) * v
    np.testing.assert_allclose(controller(0.0, q, v), expected, rtol=1e-14)


def test_controller_rows_flags_and_exact_floats(robot):
    """Repeated ("rows") parameters give one string each; floats read back bit for bit; numpy scalars are numbers."""
    waypoints = [[3.0, 0.0], [2.5, 0.1 + 0.2], [3.5, -0.5]]
    spec = controller_of(
        scene(controller={"name": "computed_torque", "waypoint": waypoints, "kp": np.float64(0.1 + 0.2)})
    )
    strings = spec.as_param_strings()
    assert strings == [
        "waypoint=3.0,0.0",
        "waypoint=2.5,0.30000000000000004",
        "waypoint=3.5,-0.5",
        "kp=0.30000000000000004",
    ]
    controller = ms.make_controller("computed_torque", robot("double_pendulum"), strings)
    for t, point in enumerate(waypoints):  # the default times are 0, 1, 2 s
        np.testing.assert_array_equal(controller.reference(float(t))[0], point)
    # The same rows as a 2-D array, as Python callers hold them.
    as_array = controller_of(scene(controller={"name": "computed_torque", "waypoint": np.array(waypoints)}))
    assert as_array.as_param_strings() == strings[:3]
    flags = controller_of(scene(controller={"name": "potential_field", "goal": [1, 2], "escape": False, "seed": 7}))
    assert flags.as_param_strings() == ["goal=1,2", "escape=false", "seed=7"]


# ---- errors --------------------------------------------------------------------------------------------
TOP = (
    "valid: actuator, actuators, constraint, contact, controller, description, force, friction_velocity, gravity, "
    "ground, initial, joints, lock, object, payload, randomize, robot, sensor, simulation"
)
TRIANGLE = "break the triangle inequality (each at most the sum of the others)"
ROBOT_KEYS = "valid: base, damping, mimic, package_dirs, position, rpy, source"
CONTROLLER_NAMES = "computed_torque, gravity_compensation, pd, pd_gravity, potential_field"
PANDA_HAND = {"frame": "panda_hand"}

ERRORS = [
    # top level
    ("unknown key", scene(gravty=[0, 0, 0]), f"unknown key 'gravty' (did you mean 'gravity'? {TOP})"),
    ("unknown key, nothing close", scene(zzz=1), f"unknown key 'zzz' ({TOP})"),
    ("contact not a table", scene(contact=[{"frame": "foot"}]), "contact: must be a table, got an array of 1"),
    ("not a table", [1, 2], "a scene must be a table of keys, got an array of 2"),
    (
        "no robot",
        {"gravity": [0, 0, 0]},
        "robot: missing (a scene needs a [robot] table with source = a catalog name or URDF path, or [[object]]s)",
    ),
    ("description", scene(description=3), "description: must be a string, got 3"),
    ("gravity length", scene(gravity=[0, -9.81]), "gravity: must be an array of 3 numbers, got 2"),
    ("gravity string", scene(gravity="down"), "gravity: must be an array of 3 numbers, got 'down'"),
    ("gravity bool entry", scene(gravity=[0, True, 0]), "gravity[1]: must be a real number, got true"),
    ("gravity string entry", scene(gravity=[0, 0, "g"]), "gravity[2]: must be a real number, got 'g'"),
    ("gravity nan", scene(gravity=[0, 0, math.nan]), "gravity[2]: must be a finite number, got nan"),
    ("gravity inf", scene(gravity=[-math.inf, 0, 0]), "gravity[0]: must be a finite number, got -inf"),
    # Python ints have no bound: 10**400 overflows a float and is refused like inf.
    (
        "huge integer",
        scene(gravity=[0, 0, 10**400]),
        "gravity[2]: must be a finite number, got an integer of 401 digits",
    ),
    ("friction_velocity zero", scene(friction_velocity=0), "friction_velocity: must be > 0, got 0"),
    ("friction_velocity table", scene(friction_velocity={}), "friction_velocity: must be a real number, got a table"),
    # robot
    ("robot not a table", {"robot": "panda"}, "robot: must be a table, got 'panda'"),
    (
        "robot unknown key",
        scene(robot={"source": "panda", "bse": "fixed"}),
        f"robot: unknown key 'bse' (did you mean 'base'? {ROBOT_KEYS})",
    ),
    ("robot no source", {"robot": {"base": "fixed"}}, "robot.source: missing (a catalog name or a URDF path)"),
    ("robot empty source", {"robot": {"source": ""}}, "robot.source: must not be empty"),
    (
        "robot base",
        scene(robot={"source": "panda", "base": "fixd"}),
        "robot.base: must be one of fixed, floating, got 'fixd' (did you mean 'fixed'?)",
    ),
    (
        "robot base bool",
        scene(robot={"source": "panda", "base": True}),
        "robot.base: must be one of fixed, floating, got true",
    ),
    (
        "position with floating",
        scene(robot={"source": "panda", "base": "floating", "position": [0, 0, 1]}),
        'robot.position: only for a fixed base, not with base = "floating"',
    ),
    (
        "rpy on natural floating",
        scene(robot={"source": "solo12", "rpy": [0, 0, 1]}),
        "robot.rpy: only for a fixed base, and 'solo12' is floating by default (add base = \"fixed\")",
    ),
    (
        "position length",
        scene(robot={"source": "panda", "position": [0, 0]}),
        "robot.position: must be an array of 3 numbers, got 2",
    ),
    ("damping int", scene(robot={"source": "panda", "damping": 1}), "robot.damping: must be true or false, got 1"),
    ("mimic string", scene(robot={"source": "panda", "mimic": "yes"}), "robot.mimic: must be true or false, got 'yes'"),
    (
        "package_dirs string",
        scene(robot={"source": "panda", "package_dirs": "/x"}),
        "robot.package_dirs: must be an array of folder paths, got '/x'",
    ),
    (
        "package_dirs entry",
        scene(robot={"source": "panda", "package_dirs": ["/x", 3]}),
        "robot.package_dirs[1]: must be a string, got 3",
    ),
    # lock and joints
    ("lock not a table", scene(lock=["panda_joint1"]), "lock: must be a table, got an array of 1"),
    ("lock string", scene(lock={"panda_joint1": "0"}), "lock.panda_joint1: must be a real number, got '0'"),
    ("lock nan", scene(lock={"panda_joint1": math.nan}), "lock.panda_joint1: must be a finite number, got nan"),
    ("lock key type", scene(lock={1: 0.0}), "lock: keys must be strings, got 1"),
    ("joint not a table", scene(joints={"panda_joint2": 0.5}), "joints.panda_joint2: must be a table, got 0.5"),
    (
        "joint unknown key",
        scene(joints={"panda_joint2": {"dampng": 1}}),
        "joints.panda_joint2: unknown key 'dampng' "
        "(did you mean 'damping'? valid: armature, damping, friction, rest, stiffness)",
    ),
    (
        "joint damping negative",
        scene(joints={"panda_joint2": {"damping": -1}}),
        "joints.panda_joint2.damping: must be >= 0, got -1",
    ),
    (
        "joint friction negative",
        scene(joints={"panda_joint2": {"friction": -0.5}}),
        "joints.panda_joint2.friction: must be >= 0, got -0.5",
    ),
    (
        "joint stiffness negative",
        scene(joints={"panda_joint2": {"stiffness": -2.0}}),
        "joints.panda_joint2.stiffness: must be >= 0, got -2.0",
    ),
    (
        "joint armature negative",
        scene(joints={"panda_joint2": {"armature": -1e-3}}),
        "joints.panda_joint2.armature: must be >= 0, got -0.001",
    ),
    (
        "joint rest string",
        scene(joints={"panda_joint2": {"rest": "up"}}),
        "joints.panda_joint2.rest: must be a real number, got 'up'",
    ),
    (
        "dotted joint name is quoted",
        scene(joints={"arm.elbow": {"damping": -1}}),
        'joints."arm.elbow".damping: must be >= 0, got -1',
    ),
    (
        "locked and overridden",
        scene(lock={"panda_finger_joint1": 0.02}, joints={"panda_finger_joint1": {"damping": 1.0}}),
        "joints.panda_finger_joint1: the joint is locked (lock.panda_finger_joint1); a locked joint takes no overrides",
    ),
    # forces
    (
        "force as a table",
        scene(force=PANDA_HAND),
        "force: must be an array of tables ([[force]] in TOML, a list of dicts in Python), got a table",
    ),
    ("force entry not a table", scene(force=["panda_hand"]), "force[0]: must be a table, got 'panda_hand'"),
    (
        "force unknown key",
        scene(force=[{**PANDA_HAND, "frequncy": 2}]),
        "force[0]: unknown key 'frequncy' (did you mean 'frequency'? "
        "valid: force, frame, frequency, name, phase, ramp_time, reference, shape, start, torque)",
    ),
    ("force no frame", scene(force=[{"force": [0, 0, 1]}]), "force[0].frame: missing (the frame the force acts on)"),
    (
        "force shape",
        scene(force=[PANDA_HAND, {**PANDA_HAND, "shape": "square"}]),
        "force[1].shape: must be one of constant, ramp, sine, step, got 'square'",
    ),
    (
        "force shape close",
        scene(force=[{**PANDA_HAND, "shape": "sin"}]),
        "force[0].shape: must be one of constant, ramp, sine, step, got 'sin' (did you mean 'sine'?)",
    ),
    (
        "force reference",
        scene(force=[{**PANDA_HAND, "reference": "body"}]),
        "force[0].reference: must be one of local, world, got 'body'",
    ),
    (
        "force vector length",
        scene(force=[{**PANDA_HAND, "torque": [0, 0, 0, 1]}]),
        "force[0].torque: must be an array of 3 numbers, got 4",
    ),
    (
        "force ramp_time zero",
        scene(force=[{**PANDA_HAND, "shape": "ramp", "ramp_time": 0}]),
        "force[0].ramp_time: must be > 0, got 0",
    ),
    (
        "force frequency negative",
        scene(force=[{**PANDA_HAND, "shape": "sine", "frequency": -1.0}]),
        "force[0].frequency: must be > 0, got -1.0",
    ),
    (
        "force start string",
        scene(force=[{**PANDA_HAND, "shape": "step", "start": "now"}]),
        "force[0].start: must be a real number, got 'now'",
    ),
    (
        "frequency on a ramp",
        scene(force=[{**PANDA_HAND, "shape": "ramp", "frequency": 2.0}]),
        "force[0].frequency: only for shape sine, not ramp",
    ),
    (
        "ramp_time on a constant",
        scene(force=[{**PANDA_HAND, "ramp_time": 2.0}]),
        "force[0].ramp_time: only for shape ramp, not constant",
    ),
    (
        "start on a constant",
        scene(force=[{**PANDA_HAND, "start": 1.0}]),
        "force[0].start: only for shape step, ramp or sine, not constant",
    ),
    (
        "duplicate force names",
        scene(force=[{**PANDA_HAND, "name": "push"}, {**PANDA_HAND, "name": "push"}]),
        "force[1].name: 'push' is already the name of force[0]",
    ),
    (
        "default name taken",
        scene(force=[{**PANDA_HAND, "name": "force1"}, PANDA_HAND]),
        "force[1].name: 'force1' is already the name of force[0]",
    ),
    (
        "force name characters",
        scene(force=[{**PANDA_HAND, "name": "a/b"}]),
        "force[0].name: must be 1-64 letters, digits, '_', '.' or '-' (not starting with '.' or '-'), got 'a/b'",
    ),
    # payloads
    ("payload no mass", scene(payload=[PANDA_HAND]), "payload[0].mass: missing (kg, > 0)"),
    ("payload mass zero", scene(payload=[{**PANDA_HAND, "mass": 0.0}]), "payload[0].mass: must be > 0, got 0.0"),
    (
        "payload no frame",
        scene(payload=[{"mass": 1.0}]),
        "payload[0].frame: missing (the frame the payload is attached to)",
    ),
    (
        "payload com",
        scene(payload=[{**PANDA_HAND, "mass": 1.0, "com": 0.1}]),
        "payload[0].com: must be an array of 3 numbers, got 0.1",
    ),
    (
        "payload inertia length",
        scene(payload=[{**PANDA_HAND, "mass": 1.0, "inertia": [1, 1, 1]}]),
        "payload[0].inertia: must be an array of 6 numbers, got 3",
    ),
    # [[1, 2, 0], [2, 1, 0], [0, 0, 1]] has eigenvalues 1 − 2, 1, 1 + 2.
    (
        "inertia indefinite",
        scene(payload=[{**PANDA_HAND, "mass": 1.0, "inertia": [1, 1, 1, 2, 0, 0]}]),
        "payload[0].inertia: not positive semi-definite (principal moments -1, 1, 3 kg·m²)",
    ),
    (
        "inertia negative diagonal",
        scene(payload=[{**PANDA_HAND, "mass": 1.0, "inertia": [-1e-3, 1e-3, 1e-3, 0, 0, 0]}]),
        "payload[0].inertia: not positive semi-definite (principal moments -0.001, 0.001, 0.001 kg·m²)",
    ),
    # No body has izz > ixx + iyy: a plate is the limit.
    (
        "inertia triangle",
        scene(payload=[{**PANDA_HAND, "mass": 1.0, "inertia": [1e-3, 1e-3, 3e-3, 0, 0, 0]}]),
        f"payload[0].inertia: principal moments 0.001, 0.001, 0.003 kg·m² {TRIANGLE}",
    ),
    (
        "inertia just beyond a plate",
        scene(payload=[{**PANDA_HAND, "mass": 1.0, "inertia": [2e-3, 3e-3, 5.00001e-3, 0, 0, 0]}]),
        f"payload[0].inertia: principal moments 0.002, 0.003, 0.00500001 kg·m² {TRIANGLE}",
    ),
    # constraints
    (
        "constraint type",
        scene(constraint=[{"type": "hinge", "frames": ["a", "b"]}]),
        "constraint[0].type: must be one of loop, point, weld, got 'hinge'",
    ),
    (
        "constraint no type",
        scene(constraint=[{"frames": ["a", "b"]}]),
        "constraint[0].type: missing (loop, point or weld)",
    ),
    (
        "constraint no frames",
        scene(constraint=[{"type": "weld"}]),
        "constraint[0].frames: missing (weld needs two distinct frames)",
    ),
    (
        "loop with one frame",
        scene(constraint=[{"type": "loop", "frames": ["a"]}]),
        "constraint[0].frames: a loop constraint needs two distinct frames, got 1",
    ),
    (
        "weld with one frame twice",
        scene(constraint=[{"type": "weld", "frames": ["a", "a"]}]),
        "constraint[0].frames: a weld constraint needs two distinct frames, got 'a' twice",
    ),
    (
        "point with two frames",
        scene(constraint=[{"type": "point", "frames": ["a", "b"]}]),
        "constraint[0].frames: a point constraint needs one frame, got 2",
    ),
    (
        "frames a string",
        scene(constraint=[{"type": "point", "frames": "a"}]),
        "constraint[0].frames: must be an array of frame names, got 'a'",
    ),
    (
        "frame not a string",
        scene(constraint=[{"type": "point", "frames": [3]}]),
        "constraint[0].frames[0]: must be a string, got 3",
    ),
    (
        "position on a loop",
        scene(constraint=[{"type": "loop", "frames": ["a", "b"], "position": [0, 0, 0]}]),
        "constraint[0].position: only for type point, not loop",
    ),
    (
        "stabilization negative",
        scene(constraint=[{"type": "point", "frames": ["a"], "stabilization": [10.0, -1.0]}]),
        "constraint[0].stabilization[1]: must be >= 0, got -1.0",
    ),
    (
        "stabilization length",
        scene(constraint=[{"type": "point", "frames": ["a"], "stabilization": [10.0]}]),
        "constraint[0].stabilization: must be an array of 2 numbers, got 1",
    ),
    (
        "duplicate constraint names",
        scene(
            constraint=[
                {"name": "c", "type": "point", "frames": ["a"]},
                {"name": "c", "type": "point", "frames": ["b"]},
            ]
        ),
        "constraint[1].name: 'c' is already the name of constraint[0]",
    ),
    # initial state
    ("initial unknown key", scene(initial={"qd": [0.0]}), "initial: unknown key 'qd' (did you mean 'q'? valid: q, v)"),
    (
        "initial q string",
        scene(initial={"q": "zero"}),
        "initial.q: must be an array of numbers or a table {joint = value}, got 'zero'",
    ),
    ("initial q entry", scene(initial={"q": [0.0, None]}), "initial.q[1]: must be a real number, got None"),
    (
        "initial v table entry",
        scene(initial={"v": {"panda_joint1": "fast"}}),
        "initial.v.panda_joint1: must be a real number, got 'fast'",
    ),
    # simulation
    (
        "simulation unknown key",
        scene(simulation={"output_rate": 100}),
        "simulation: unknown key 'output_rate' (did you mean 'output_dt'? "
        "valid: atol, control_dt, dt, duration, integrator, max_step, output_dt, rtol)",
    ),
    ("duration zero", scene(simulation={"duration": 0}), "simulation.duration: must be > 0, got 0"),
    ("dt negative", scene(simulation={"dt": -1e-3}), "simulation.dt: must be > 0, got -0.001"),
    ("rtol zero", scene(simulation={"rtol": 0.0}), "simulation.rtol: must be > 0, got 0.0"),
    (
        "output_dt string",
        scene(simulation={"output_dt": "10ms"}),
        "simulation.output_dt: must be a real number, got '10ms'",
    ),
    (
        "integrator",
        scene(simulation={"integrator": "rk5"}),
        "simulation.integrator: must be one of bs32, dop853, dp54, euler, implicit_euler, implicit_midpoint, midpoint, "
        "rk4, semi_implicit_euler, timestepping, variational, got 'rk5' (did you mean 'rk4'?)",
    ),
    # controller
    ("controller no name", scene(controller={"kp": 1.0}), f"controller.name: missing (valid: {CONTROLLER_NAMES})"),
    (
        "controller name",
        scene(controller={"name": "pid"}),
        f"controller.name: must be one of {CONTROLLER_NAMES}, got 'pid' (did you mean 'pd'?)",
    ),
    (
        "controller unknown parameter",
        scene(controller={"name": "pd", "kpp": 1.0, "q_ref": [0]}),
        "controller: unknown key 'kpp' (did you mean 'kp'? valid: kd, kp, name, q_ref, v_ref)",
    ),
    (
        "controller missing parameter",
        scene(controller={"name": "pd", "kp": 100.0}),
        "controller.q_ref: missing (required by controller pd)",
    ),
    (
        "controller number",
        scene(controller={"name": "pd", "kp": "high", "q_ref": [0]}),
        "controller.kp: must be a real number, got 'high'",
    ),
    (
        "controller vector entry",
        scene(controller={"name": "pd", "kp": 1, "q_ref": [0, math.inf]}),
        "controller.q_ref[1]: must be a finite number, got inf",
    ),
    (
        "controller empty vector",
        scene(controller={"name": "pd", "kp": 1, "q_ref": []}),
        "controller.q_ref: must not be empty",
    ),
    (
        "controller integer",
        scene(controller={"name": "potential_field", "goal": [1], "seed": 1.5}),
        "controller.seed: must be a whole number, got 1.5",
    ),
    (
        "controller flag",
        scene(controller={"name": "potential_field", "goal": [1], "escape": "no"}),
        "controller.escape: must be true or false, got 'no'",
    ),
    (
        "controller text",
        scene(controller={"name": "computed_torque", "waypoint": [[0], [1]], "bc_type": 2}),
        "controller.bc_type: must be a string, got 2",
    ),
    (
        "controller row entry",
        scene(controller={"name": "computed_torque", "waypoint": [[0], [1, "x"]]}),
        "controller.waypoint[1][1]: must be a real number, got 'x'",
    ),
    # contact
    (
        "ground key",
        scene(ground={"hieght": 0}),
        "ground: unknown key 'hieght' (did you mean 'height'? valid: friction, height, restitution)",
    ),
    ("ground friction", scene(ground={"friction": -0.1}), "ground.friction: must be >= 0, got -0.1"),
    ("ground restitution", scene(ground={"restitution": 1.5}), "ground.restitution: must be within 0..1, got 1.5"),
    (
        "contact pairs word",
        scene(contact={"pairs": "everything"}),
        "contact.pairs: must be one of all, ground, got 'everything'",
    ),
    (
        "contact pairs type",
        scene(contact={"pairs": 3}),
        "contact.pairs: must be one of all, ground, or a list of [body, body] pairs, got 3",
    ),
    (
        "contact pair shape",
        scene(contact={"pairs": [["a", "b", "c"]]}),
        "contact.pairs[0]: must be a pair of body names [body, body], got an array of 3",
    ),
    (
        "contact pair twice",
        scene(contact={"pairs": [["a", "a"]]}),
        "contact.pairs[0]: must name two different bodies, got 'a' twice",
    ),
    (
        "contact limits",
        scene(contact={"limits": "enforced"}),
        "contact.limits: must be one of enforce, report, got 'enforced' (did you mean 'enforce'?)",
    ),
    (
        "contact friction",
        scene(contact={"friction": "coulomb"}),
        "contact.friction: must be one of exact, regularized, got 'coulomb'",
    ),
    ("contact solver", scene(contact={"solver": "lcp"}), "contact.solver: must be one of admm, pgs, got 'lcp'"),
    (
        "contact key",
        scene(contact={"pair": "all"}),
        "contact: unknown key 'pair' (did you mean 'pairs'? valid: body_friction, body_restitution, friction, "
        "geometry, limits, pairs, robot_geometry, solver, velocity_limits)",
    ),
    (
        "geometry frame",
        scene(contact={"geometry": [{"shape": "sphere", "radius": 0.1}]}),
        "contact.geometry[0].frame: missing (the frame the shape is attached to)",
    ),
    (
        "geometry shape",
        scene(contact={"geometry": [{"frame": "panda_hand", "shape": "cone"}]}),
        "contact.geometry[0].shape: must be one of box, cylinder, sphere, got 'cone'",
    ),
    (
        "geometry missing radius",
        scene(contact={"geometry": [{"frame": "panda_hand", "shape": "sphere"}]}),
        "contact.geometry[0].radius: missing (a sphere needs radius: m, > 0)",
    ),
    (
        "geometry size on sphere",
        scene(contact={"geometry": [{"frame": "panda_hand", "shape": "sphere", "radius": 0.1, "size": [1, 1, 1]}]}),
        "contact.geometry[0].size: only for shape box, not sphere",
    ),
    (
        "object no mass",
        scene(object=[{"name": "box", "shape": "box", "size": [0.1, 0.1, 0.1]}]),
        "object[0].mass: missing (kg, > 0)",
    ),
    (
        "object zero size",
        scene(object=[{"shape": "box", "size": [0.1, 0, 0.1], "mass": 1}]),
        "object[0].size[1]: must be > 0, got 0",
    ),
    (
        "object velocity",
        scene(object=[{"shape": "sphere", "radius": 0.1, "mass": 1, "velocity": [1, 0, 0]}]),
        "object[0].velocity: must be an array of 6 numbers, got 3",
    ),
    (
        "object named ground",
        scene(object=[{"name": "ground", "shape": "sphere", "radius": 0.1, "mass": 1}]),
        "object[0].name: 'ground' names the ground plane; choose another name",
    ),
    (
        "object names",
        scene(object=[{"name": "b", "shape": "sphere", "radius": 0.1, "mass": 1}] * 2),
        "object[1].name: 'b' is already the name of object[0]",
    ),
    (
        "object as table",
        scene(object={"shape": "sphere"}),
        "object: must be an array of tables ([[object]] in TOML, a list of dicts in Python), got a table",
    ),
    (
        "objects only with lock",
        {"object": [{"shape": "sphere", "radius": 0.1, "mass": 1}], "lock": {"j": 0.0}},
        "lock: needs a robot: this scene has objects only (add a [robot] table)",
    ),
    (
        "contact with rk4",
        scene(ground={}, simulation={"integrator": "rk4"}),
        "simulation.integrator: a scene with contact ([ground], [contact] or [[object]]) steps with timestepping, "
        "got 'rk4'",
    ),
    (
        "contact with constraints",
        scene(ground={}, constraint=[{"type": "point", "frames": ["panda_hand"]}]),
        "constraint: holonomic constraints and contact cannot be combined yet: the contact time-stepper does not "
        "solve [[constraint]] rows with its cones (drop [[constraint]], or [ground], [contact] and [[object]])",
    ),
]


@pytest.mark.parametrize(("data", "message"), [pytest.param(d, m, id=i) for i, d, m in ERRORS])
def test_scene_errors_name_the_key_and_the_valid_options(data, message):
    """Each mistake gives exactly one line: the source, the key path, the problem and what is valid."""
    with pytest.raises(SceneError, match=f"^{re.escape('scene.toml: ' + message)}$") as info:
        parse(data)
    assert "\n" not in str(info.value)


def test_messages_quoting_the_file_stay_on_one_line():
    """Keys come from strangers' files: line breaks and terminal escapes are shown escaped, never printed."""
    with pytest.raises(SceneError) as info:
        parse(scene(**{"evil\n\x1b[31mkey": 1}))
    message = str(info.value)
    assert message.startswith("scene.toml: unknown key 'evil\\x0a\\x1b[31mkey' (valid: actuator,")
    assert "\n" not in message and "\x1b" not in message


def test_errors_from_python_dicts_name_the_scene():
    with pytest.raises(SceneError, match=re.escape("<scene>: robot.source: must be a string, got 3")):
        parse_scene({"robot": {"source": 3}}, "<scene>", base_dir=None)


# ---- reading files -------------------------------------------------------------------------------------
def test_toml_syntax_error_gives_the_line_and_column(tmp_path, monkeypatch):
    """`base = fixed` (an unquoted word) is invalid at line 3, column 8: the value's first character."""
    write(tmp_path, '[robot]\nsource = "panda"\nbase = fixed\n')
    monkeypatch.chdir(tmp_path)
    with pytest.raises(
        SceneError, match="^" + re.escape("scene.toml: TOML syntax error at line 3, column 8: Invalid value") + "$"
    ):
        read_scene_file("scene.toml")


def test_toml_duplicate_table_is_a_syntax_error(tmp_path):
    """Declaring [robot] twice is TOML's error, reported at the second declaration (line 3)."""
    write(tmp_path, '[robot]\nsource = "panda"\n[robot]\nbase = "fixed"\n')
    with pytest.raises(SceneError, match=re.escape("scene.toml: TOML syntax error at line 3, column ")):
        read_scene_file(tmp_path / "scene.toml")


def test_deeply_nested_toml_is_refused(tmp_path):
    """A few kilobytes of brackets would overflow the parser's recursion: refused before parsing, in one line."""
    write(tmp_path, "a = " + "[" * 100_000)
    with pytest.raises(SceneError, match=re.escape("scene.toml: refused: it nests arrays and inline tables 100000 ")):
        read_scene_file(tmp_path / "scene.toml")


def test_file_size_limit_is_one_mebibyte(tmp_path):
    """A file of exactly 1 MiB is read; one byte more is refused before parsing."""
    head = '[robot]\nsource = "panda"\n'
    padding = MAX_SCENE_BYTES - len(head) - 1
    path = write(tmp_path, head + "#" * padding + "\n")
    assert path.stat().st_size == MAX_SCENE_BYTES == 1024 * 1024
    assert read_scene_file(path).robot.source == "panda"
    write(tmp_path, head + "#" * (padding + 1) + "\n")
    with pytest.raises(
        SceneError,
        match=re.escape(f"{path}: the file is larger than 1048576 bytes (1 MiB), too large for a scene"),
    ):
        read_scene_file(path)


def test_binary_and_non_utf8_files_are_refused(tmp_path):
    """A NUL byte marks a binary file; Latin-1 'é' (0xe9) is not UTF-8 (offset: len('description = "caf'))."""
    path = write(tmp_path, b"\x7fELF\x02\x01\x01\x00\x00")
    with pytest.raises(SceneError, match=re.escape(f"{path}: not a text file (NUL byte at offset 7)")):
        read_scene_file(path)
    path = write(tmp_path, b'description = "caf\xe9"\n[robot]\nsource = "panda"\n')
    with pytest.raises(
        SceneError, match=re.escape(f"{path}: not UTF-8 text (byte 0xe9 at offset 18); save it as UTF-8")
    ):
        read_scene_file(path)


def test_missing_file_and_folder_are_refused(tmp_path):
    with pytest.raises(SceneError, match=re.escape(f"{tmp_path / 'nope.toml'}: no such file")):
        read_scene_file(tmp_path / "nope.toml")
    with pytest.raises(SceneError, match=re.escape(f"{tmp_path}: is a folder, not a scene file")):
        read_scene_file(tmp_path)


def test_fifo_is_refused_without_blocking(tmp_path):
    """A named pipe would block the read forever: refused from its type alone."""
    fifo = tmp_path / "scene.toml"
    os.mkfifo(fifo)
    with pytest.raises(SceneError, match=re.escape(f"{fifo}: not a regular file")):
        read_scene_file(fifo)


def test_scene_errors_in_a_file_name_the_file_as_given(tmp_path, monkeypatch):
    (tmp_path / "scenes").mkdir()
    write(tmp_path / "scenes", '[robot]\nsource = "panda"\n[[force]]\nframe = "panda_hand"\nshape = "square"\n')
    monkeypatch.chdir(tmp_path)
    with pytest.raises(
        SceneError,
        match="^"
        + re.escape("scenes/scene.toml: force[0].shape: must be one of constant, ramp, sine, step, got 'square'")
        + "$",
    ):
        read_scene_file("scenes/scene.toml")


def test_scene_error_is_an_invalid_argument_error():
    """The CLI maps InvalidArgumentError to exit code 2 (bad input); a SceneError must be one."""
    with pytest.raises(InvalidArgumentError):
        parse({})
    assert issubclass(SceneError, ValueError)
