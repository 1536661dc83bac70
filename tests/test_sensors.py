"""Sensors (multibody_sim.sensors): each kind against an independent reference (closed forms, the URDF's masses,
finite differences of the recorded poses), and the readings' noise, bias, rate and latency against their
declarations; the tables, files, controllers, steppers and gym environments that carry them."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
from conftest import needs_native

import multibody_sim as ms
from multibody_sim.exceptions import InvalidArgumentError, SceneError
from multibody_sim.noise import NormalStream
from multibody_sim.readings import SensorStream

G = 9.81


@pytest.fixture(params=["native", "python"])
def kernel(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """The closed-form checks run on both kernels: "python" sets MULTIBODY_SIM_NATIVE=0, "native" needs the
    extension (on_kernel() checks that the run took it)."""
    from multibody_sim import native

    if request.param == "python":
        monkeypatch.setenv(native.ENV, "0")
    elif not native.available:
        pytest.skip(f"the native kernel is not available here: {native.why_unavailable}")
    return str(request.param)


def on_kernel(traj: Any, kernel: str) -> Any:
    """traj, after checking that it ran on `kernel` (its metadata says which, and why not native)."""
    ran = traj.metadata["kernel"]
    assert (ran == "native") == (kernel == "native"), (ran, traj.metadata.get("native"))
    return traj


def _box(**extra: object) -> ms.Scene:
    """A 1 kg box (20 cm cube) released 0.5 m above the ground, with an IMU at its centre and a touch sensor."""
    return ms.make_scene(
        object=[{"name": "box", "shape": "box", "size": [0.2, 0.2, 0.2], "mass": 1.0, "position": [0, 0, 0.5]}],
        ground={},
        sensor=[
            {"name": "imu", "kind": "imu", "frame": "box"},
            {"name": "touch", "kind": "contact_force", "body": "box"},
        ],
        **extra,
    )


def _urdf_masses(path: str) -> dict[str, float]:
    """Each link's mass as the URDF file writes it (read here with ElementTree, not through Pinocchio)."""
    root = ET.parse(path).getroot()
    masses = {}
    for link in root.iter("link"):
        mass = link.find("inertial/mass")
        masses[link.get("name", "")] = float(mass.get("value", "0")) if mass is not None else 0.0
    return masses


# ---- the IMU ------------------------------------------------------------------------------------------------------
def test_imu_in_free_fall_reads_zero_specific_force_and_on_the_ground_reads_g_upward(kernel: str) -> None:
    """The box falls for ~0.27 s, lands and rests: in the air the IMU reads no specific force (to round-off), at rest
    it reads g upward in the box's axes and the touch sensor the box's weight, m g."""
    scene = _box()
    traj = on_kernel(ms.simulate(scene, scene.q0, scene.v0, duration=0.6, dt=1e-3, integrator="timestepping"), kernel)
    imu, touch = traj.sensors["imu"], traj.sensors["touch"]
    falling = traj.t < 0.25  # it reaches the ground at sqrt(2 · 0.4 / g) = 0.286 s
    assert np.abs(imu[falling, :3]).max() < 1e-12
    assert np.abs(touch[falling]).max() == 0.0
    resting = traj.t > 0.5
    np.testing.assert_allclose(imu[resting, :3], np.tile([0.0, 0.0, G], (resting.sum(), 1)), atol=1e-6)
    np.testing.assert_allclose(touch[resting], np.tile([0.0, 0.0, 1.0 * G], (resting.sum(), 1)), atol=1e-6)
    assert np.abs(imu[:, 3:]).max() < 1e-9  # it never turns


def test_imu_on_a_tilted_resting_body_reads_g_in_its_own_axes() -> None:
    """A box resting on its side (turned 90° about x, then 0.7 rad about z) reads Rᵀ (0, 0, g), R its orientation
    (here from the frame_pose sensor's quaternion, compared with the declared rpy)."""
    rpy = [math.pi / 2, 0.0, 0.7]
    scene = ms.make_scene(
        object=[
            {"name": "box", "shape": "box", "size": [0.2, 0.2, 0.2], "mass": 2.0, "position": [0, 0, 0.1], "rpy": rpy}
        ],
        ground={},
        sensor=[{"name": "imu", "kind": "imu", "frame": "box"}, {"name": "pose", "kind": "frame_pose", "frame": "box"}],
    )
    traj = ms.simulate(scene, scene.q0, scene.v0, duration=0.2, dt=1e-3, integrator="timestepping")
    x, y, z, w = traj.sensors["pose"][-1, 3:]
    rotation = pin.Quaternion(w, x, y, z).matrix()
    np.testing.assert_allclose(rotation, pin.rpy.rpyToMatrix(*rpy), atol=1e-6)
    np.testing.assert_allclose(traj.sensors["imu"][-1, :3], rotation.T @ [0.0, 0.0, G], atol=1e-6)


def test_imu_of_a_spinning_falling_body_converges_to_zero_at_first_order() -> None:
    """A box spinning about a principal axis while it falls feels no specific force at its centre; the IMU reads
    the step's mean acceleration (v⁺ − v) / h at the end state, so its error falls linearly with dt. Its angular
    velocity reading is the spin exactly (a torque-free spin about a principal axis stays constant)."""
    errors = []
    for dt in (4e-3, 2e-3, 1e-3):
        scene = ms.make_scene(
            object=[
                {
                    "name": "box",
                    "shape": "box",
                    "size": [0.2, 0.3, 0.4],
                    "mass": 1.0,
                    "velocity": [1.0, 0.0, 0.0, 0.0, 0.0, 3.0],
                }
            ],
            sensor=[{"name": "imu", "kind": "imu", "frame": "box"}],
        )
        traj = ms.simulate(scene, scene.q0, scene.v0, duration=0.4, dt=dt, integrator="timestepping")
        imu = traj.sensors["imu"][1:]
        np.testing.assert_allclose(imu[:, 3:], np.tile([0.0, 0.0, 3.0], (len(imu), 1)), atol=1e-12)
        errors.append(np.abs(imu[:, :3]).max())
    slopes = np.diff(np.log(errors)) / np.log(0.5)
    assert errors[-1] < 1e-2
    np.testing.assert_allclose(slopes, 1.0, atol=0.05)


def test_imu_on_a_moving_arm_matches_finite_differences_of_its_recorded_pose() -> None:
    """ur5 swinging under gravity: the IMU at tool0, turned into world axes and with g added back, is the second
    derivative of the frame's recorded position (central differences of the frame_pose sensor), and its angular
    velocity the rotation's derivative; both agree to O(dt)."""
    scene = ms.make_scene(
        robot={"source": "ur5", "damping": False},
        sensor=[
            {"name": "imu", "kind": "imu", "frame": "tool0"},
            {"name": "pose", "kind": "frame_pose", "frame": "tool0"},
        ],
    )
    dt = 2e-4
    traj = ms.simulate(scene, scene.q0, np.full(scene.nv, 0.5), duration=0.2, dt=dt)
    pose, imu = traj.sensors["pose"], traj.sensors["imu"]
    rotations = np.array([pin.Quaternion(p[6], *p[3:6]).matrix() for p in pose])
    position = pose[:, :3]
    acceleration = (position[2:] - 2 * position[1:-1] + position[:-2]) / dt**2
    measured = np.einsum("nij,nj->ni", rotations[1:-1], imu[1:-1, :3]) + [0.0, 0.0, -G]
    scale = np.abs(acceleration).max()
    assert np.abs(measured - acceleration).max() < 1e-3 * scale  # 4.7e-4 measured: first order in dt
    spin = np.array([pin.log3(a.T @ b) for a, b in zip(rotations[:-2], rotations[2:], strict=True)]) / (2 * dt)
    assert np.abs(spin - imu[1:-1, 3:]).max() < 1e-6 * np.abs(spin).max()  # 4.7e-8 measured


# ---- force–torque ---------------------------------------------------------------------------------------------------
def _hold(scene: ms.Scene, q: np.ndarray) -> ms.Trajectory:
    """The scene held at rest at q by its exact gravity torque."""
    gravity = pin.computeGeneralizedGravity(scene.model, scene.data, q).copy()
    return ms.simulate(scene, q, np.zeros(scene.nv), duration=0.05, dt=1e-3, controller=lambda t, q, v: gravity)


@pytest.mark.parametrize("mass", [0.0, 1.5])
def test_wrist_force_torque_sensor_reads_the_distal_weight_at_rest(mass: float, kernel: str) -> None:
    """panda held at rest, a payload of mass m at the hand's TCP (8 cm off the sensor's axis): a sensor at the
    hand's mounting (the URDF's fixed joint panda_hand_joint) carries the hand, both fingers and the payload, so it
    reads (m_hand + 2 m_finger + m) g upward (masses from the URDF file), and the payload's moment about it; a sensor
    at panda_joint7 adds link 7 and link 8."""
    payload = [{"frame": "panda_hand_tcp", "mass": mass, "com": [0.08, 0.0, 0.0]}] if mass else []
    scene = ms.make_scene(
        robot={"source": "panda"},
        payload=payload,
        sensor=[
            {"name": "wrist", "kind": "force_torque", "frame": "panda_hand_joint"},
            {"name": "joint7", "kind": "force_torque", "joint": "panda_joint7"},
            {"name": "mount", "kind": "frame_pose", "frame": "panda_hand_joint"},
        ],
    )
    masses = _urdf_masses(scene.full_robot.source["urdf_path"])
    distal = masses["panda_hand"] + masses["panda_leftfinger"] + masses["panda_rightfinger"]
    traj = on_kernel(_hold(scene, scene.q0), kernel)
    x, y, z, w = traj.sensors["mount"][-1, 3:]
    rotation = pin.Quaternion(w, x, y, z).matrix()
    wrist = traj.sensors["wrist"][-1]
    np.testing.assert_allclose(rotation @ wrist[:3], [0.0, 0.0, (distal + mass) * G], atol=1e-9)
    if mass:  # the payload's moment: its weight at its offset from the sensor (the tcp is 0.1034 m down the hand)
        bare = ms.make_scene(
            robot={"source": "panda"}, sensor=[{"name": "wrist", "kind": "force_torque", "frame": "panda_hand_joint"}]
        )
        without = on_kernel(_hold(bare, scene.q0), kernel).sensors["wrist"][-1]
        tcp = scene.model.frames[scene.model.getFrameId("panda_hand_tcp")].placement
        sensor = scene.model.frames[scene.model.getFrameId("panda_hand_joint")].placement
        offset = (sensor.inverse() * tcp).act(np.array([0.08, 0.0, 0.0]))  # the payload's centre, sensor axes
        weight = rotation.T @ [0.0, 0.0, -mass * G]  # its weight, in the sensor's axes
        np.testing.assert_allclose(wrist[:3] - without[:3], -weight, atol=1e-9)
        np.testing.assert_allclose(wrist[3:] - without[3:], -np.cross(offset, weight), atol=1e-9)
    joint7 = traj.sensors["joint7"][-1]
    link7 = masses["panda_link7"] + masses["panda_link8"]
    assert np.linalg.norm(joint7[:3]) == pytest.approx((distal + mass + link7) * G, rel=1e-12)


def test_force_torque_at_a_joint_carries_contact_forces_on_its_subtree(kernel: str) -> None:
    """go2 standing: at rest the wrench across each hip joint balances its leg's weight against the foot's ground
    force: Rᵀ(ground force) - leg weight, as the world sees it (sum of the four hips plus the trunk = 0)."""
    scene = ms.load_scene(_scene_file("go2_standing.toml"))
    feet = ["FL", "FR", "RL", "RR"]
    sensors = [{"name": f"{leg}_touch", "kind": "contact_force", "body": f"{leg}_foot"} for leg in feet]
    sensors += [{"name": f"{leg}_hip", "kind": "force_torque", "joint": f"{leg}_hip_joint"} for leg in feet]
    sensors += [{"name": f"{leg}_hip_pose", "kind": "frame_pose", "frame": f"{leg}_hip_joint"} for leg in feet]
    scene = _with_sensors(scene, sensors)
    traj = on_kernel(scene.run(duration=1.0), kernel)
    masses = _urdf_masses(scene.full_robot.source["urdf_path"])
    for leg in feet:
        leg_mass = sum(m for name, m in masses.items() if name.startswith(f"{leg}_"))
        x, y, z, w = traj.sensors[f"{leg}_hip_pose"][-1, 3:]
        rotation = pin.Quaternion(w, x, y, z).matrix()
        across = rotation @ traj.sensors[f"{leg}_hip"][-1, :3]  # the wrench on the leg, world axes
        ground = traj.sensors[f"{leg}_touch"][-1]
        np.testing.assert_allclose(across + ground, [0.0, 0.0, leg_mass * G], atol=0.05 * leg_mass * G)


def test_joint_torque_reads_what_the_actuators_deliver_not_their_command(kernel: str) -> None:
    """ur5 with stiff position servos holding a target: the joint_torque sensor reads the servos' output, which at
    rest balances gravity (Pinocchio's g(q), computed apart), while the commands are the targets; between control
    instants it is the trajectory's tau (the delivered torque at each sample under the same held command)."""
    scene = ms.make_scene(
        robot={"source": "ur5", "damping": False},
        actuator=[{"joints": "*", "kind": "position", "kp": 1e4, "kv": 100.0}],
        sensor=[{"name": "tq", "kind": "joint_torque", "rate": 500.0}],  # every step
    )
    target = scene.q0 + 0.05
    traj = scene.run(
        duration=3.0, dt=2e-3, integrator="semi_implicit_euler", control_dt=2e-2, controller=lambda t, q, v: target
    )
    on_kernel(traj, kernel)
    tq = traj.sensors["tq"]
    gravity = pin.computeGeneralizedGravity(scene.model, scene.model.createData(), traj.q[-1])
    np.testing.assert_allclose(tq[-1], gravity, atol=1e-9 * np.abs(gravity).max())
    assert np.abs(tq[-1] - traj.ctrl[-1]).max() > 1.0  # not the command (a target in rad)
    between = np.arange(len(traj)) % 10 != 0
    np.testing.assert_array_equal(tq[between], traj.tau[between])


# ---- contact forces -----------------------------------------------------------------------------------------------
def _scene_file(name: str) -> Path:
    return Path(__file__).parents[1] / "models" / "scenes" / name


def _with_sensors(scene: ms.Scene, sensors: list[dict[str, object]]) -> ms.Scene:
    import dataclasses

    from multibody_sim.scenes.parse import parse_scene

    parsed = parse_scene({"robot": {"source": "go2"}, "sensor": sensors}, "<test>", base_dir=None)
    return ms.Scene(dataclasses.replace(scene.spec, sensors=parsed.sensors))


def test_contact_forces_on_a_standing_robot_sum_to_its_weight(kernel: str) -> None:
    """go2 dropped 0.6 mm onto its four feet and held at its stance: once settled, the four contact_force sensors
    sum to (0, 0, M g), M the sum of the URDF's link masses. At every step, with the robot still moving, they are
    the rate of change of its linear momentum less gravity (Newton–Euler on the whole robot: Pinocchio's centroidal
    momentum rate at the step's start with the step's acceleration), to round-off."""
    scene = ms.load_scene(_scene_file("go2_standing.toml"))
    feet = ["FL", "FR", "RL", "RR"]
    scene = _with_sensors(scene, [{"name": leg, "kind": "contact_force", "body": f"{leg}_foot"} for leg in feet])
    traj = on_kernel(scene.run(duration=1.5), kernel)
    total = sum(traj.sensors[leg] for leg in feet)
    mass = sum(_urdf_masses(scene.full_robot.source["urdf_path"]).values())
    settled = traj.t > 1.0
    np.testing.assert_allclose(total[settled].mean(axis=0), [0.0, 0.0, mass * G], atol=5e-4 * mass * G)
    for leg in feet:  # every foot carries its share
        assert (traj.sensors[leg][settled, 2] > 0.15 * mass * G).all()
    model, data = scene.model, scene.model.createData()
    h = 1e-3
    for k in range(1, len(traj), 7):
        a = (traj.v[k] - traj.v[k - 1]) / h
        rate = pin.computeCentroidalMomentumTimeVariation(model, data, traj.q[k - 1], traj.v[k - 1], a).linear
        np.testing.assert_allclose(rate, mass * np.array([0.0, 0.0, -G]) + total[k], atol=1e-8 * mass * G)


# ---- readings: noise, bias, rate, latency ---------------------------------------------------------------------------
def _stream(
    noise: float, bias: float, latency: int = 0, stride: int = 1, seed: int = 7
) -> tuple[SensorStream, ms.Scene]:
    scene = ms.make_scene(
        robot={"source": "double_pendulum"},
        sensor=[
            {
                "name": "enc",
                "kind": "joint_position",
                "joints": ["joint1"],
                "noise": noise,
                "bias": bias,
                "latency": latency,
                "seed": seed,
            }
        ],
    )
    return SensorStream(scene.sensors, [stride], np.array([0])), scene


def test_noise_mean_and_std_match_the_declaration_over_1e5_readings() -> None:
    """1e5 readings of a constant measurement: their mean is measurement + bias within 3 σ/√n, their standard
    deviation the declared noise within 3 σ/√(2n)."""
    n, std, bias = 100_000, 0.05, 0.3
    stream, _ = _stream(std, bias)
    zeros = np.zeros(1, dtype=np.int64)
    readings = stream.push(np.zeros(1), zeros, np.full((1, 1), 1.25))  # the first, then many more
    more = stream.push(np.arange(1, n) * 1e-3, np.zeros(n - 1, dtype=np.int64), np.full((n - 1, 1), 1.25))
    values = np.concatenate([readings[0][0][1][:, 0], more[0][0][1][:, 0]])
    assert len(values) == n
    assert abs(values.mean() - (1.25 + bias)) < 3 * std / math.sqrt(n)
    assert abs(values.std(ddof=1) - std) < 3 * std / math.sqrt(2 * n)


def test_readings_in_one_call_or_many_are_the_same() -> None:
    """The noise is drawn reading after reading from the sensor's generator: a run cut into pieces (a Stepper,
    chunks) reads the same numbers as one call."""
    z = np.linspace(0.0, 1.0, 50)[:, None]
    one, _ = _stream(0.1, 0.0, latency=3, stride=2)
    whole = one.push(np.arange(50.0), np.zeros(50, dtype=np.int64), z)
    many, _ = _stream(0.1, 0.0, latency=3, stride=2)
    parts = [
        many.push(np.arange(a, b, dtype=float), np.zeros(b - a, dtype=np.int64), z[a:b])
        for a, b in ((0, 7), (7, 8), (8, 50))
    ]
    times = np.concatenate([p[0][0][0] for p in parts])
    values = np.concatenate([p[0][0][1] for p in parts])
    np.testing.assert_array_equal(times, whole[0][0][0])
    np.testing.assert_array_equal(values, whole[0][0][1])


def _spoiled_ur5() -> ms.Scene:
    """ur5 with sensors of every reading feature: bias (one or per component), latency 1 to 4, noise (some
    components without), and a wide one (frame_pose)."""
    return ms.make_scene(
        robot={"source": "ur5"},
        sensor=[
            {
                "name": "imu",
                "kind": "imu",
                "frame": "tool0",
                "noise": 0.01,
                "bias": [0.1, 0, 0, 0, 0, -0.2],
                "latency": 2,
            },
            {"name": "enc", "kind": "joint_position", "bias": 0.001, "latency": 1},
            {"name": "gyro", "kind": "joint_velocity", "noise": [1e-3, 2e-3, 0, 0, 1e-3, 1.0]},
            {"name": "tq", "kind": "joint_torque", "noise": 0.5, "latency": 3, "seed": 11},
            {"name": "pose", "kind": "frame_pose", "frame": "tool0", "noise": 0.2, "bias": -3.0, "latency": 4},
        ],
    )


def test_readings_written_into_a_given_array_equal_those_made_apart() -> None:
    """SensorStream.push with `into` (a run's samples at its ticks: the every-tick sensors' readings go straight into
    the store's rows) makes the same numbers, bit for bit, as without (new arrays): bias, latency, per-component
    noise, a sensor at a rate, two rows, a run cut into pieces; and the same latest readings (with the extension:
    made natively into the given array, and by the specification apart)."""
    sensors = _spoiled_ur5().sensors
    rng = np.random.default_rng(3)
    Z = rng.normal(size=(60, sensors.width))
    strides = [1, 1, 1, 3, 1]  # tq every 3rd tick
    direct = SensorStream(sensors, strides, np.array([4, 9]))
    apart = SensorStream(sensors, strides, np.array([4, 9]), native=False)  # (the specification, in Python)
    store = np.full((2, 60, sensors.width), np.nan)
    every = [c for k in (0, 1, 2, 4) for c in range(sensors.width)[sensors.columns(k)]]
    for a, b in ((0, 1), (1, 17), (17, 60)):
        times = np.repeat(np.arange(a, b) * 1e-3, 2)
        rows = np.tile([0, 1], b - a)
        values = np.repeat(Z[a:b], 2, axis=0)
        values[1::2] *= 2.0
        got = direct.push(times, rows, values, into=lambda row, t, a=a, b=b: store[row, a:b])
        expected = apart.push(times, rows, values)
        assert got.keys() == expected.keys() == {0, 1}
        for row in (0, 1):
            for k, ((t1, r1), (t2, r2)) in enumerate(zip(got[row], expected[row], strict=True)):
                np.testing.assert_array_equal(t1, t2)
                np.testing.assert_array_equal(r1, r2)
                if strides[k] == 1:
                    np.testing.assert_array_equal(store[row, a:b, sensors.columns(k)], r2)
        np.testing.assert_array_equal(direct.latest, apart.latest)
    assert not np.isnan(store[:, :, every]).any()
    assert np.abs(direct.latest[0] - Z[-1]).max() > 0.0  # spoiled: not the measurement


@needs_native
@pytest.mark.parametrize("strides", [[1, 1, 1, 1, 1], [1, 2, 1, 3, 5], [4, 2, 2, 3, 1]])
def test_native_readings_are_the_specifications_bit_for_bit(strides: list[int]) -> None:
    """The extension's make_readings (one call per row and push) against _read_python, the specification: three
    rows at random, chunks of 1 to 12 ticks, sensors at rates and late, a reset with entropy and one without, a
    snapshot restored: the same readings, times, latest readings, histories and stream states, bit for bit. Both
    are also checked against the readings written out from the module docstring's definition, sensor by sensor
    (measurement `latency` readings before, the first before that, + bias + noise · the stream's next draws)."""
    sensors = _spoiled_ur5().sensors
    seeds = np.array([0, 3, 8])
    native = SensorStream(sensors, strides, seeds)
    python = SensorStream(sensors, strides, seeds, native=False)
    assert native._native is not None and python._native is None
    rng = np.random.default_rng(5)
    got: dict[int, list[list[np.ndarray]]] = {b: [[] for _ in strides] for b in range(3)}
    measured: dict[int, list[np.ndarray]] = {b: [] for b in range(3)}  # each row's measurements since its start
    calls: list[tuple[np.ndarray, np.ndarray, np.ndarray, dict]] = []  # calls 40 to 44: inputs and readings
    snapshots = None
    t = 0
    for call in range(60):
        m = int(rng.integers(1, 13))
        rows = rng.integers(0, 3, m)
        times, t = np.arange(t, t + m) * 1e-3, t + m
        Z = rng.normal(size=(m, sensors.width))
        if call == 40:
            snapshots = (native.snapshot(), python.snapshot())
        a, b = native.push(times, rows, Z.copy()), python.push(times, rows, Z.copy())
        assert a.keys() == b.keys() == set(rows.tolist())
        for row in a:
            for k, ((t1, r1), (t2, r2)) in enumerate(zip(a[row], b[row], strict=True)):
                np.testing.assert_array_equal(t1, t2)
                np.testing.assert_array_equal(r1, r2)
                got[row][k].append(r1.copy())
            measured[row].append(Z[rows == row])
        for name in ("latest", "count", "history", "states"):
            np.testing.assert_array_equal(getattr(native, name), getattr(python, name), err_msg=name)
        if 40 <= call < 45:
            calls.append((times, rows, Z, {row: [r.copy() for _, r in a[row]] for row in a}))
        if call == 20:  # no row has reset yet: each one's readings so far by the definition
            for row in range(3):
                reference = _readings_by_definition(sensors, strides, np.concatenate(measured[row]), int(seeds[row]))
                for k in range(len(strides)):
                    np.testing.assert_array_equal(np.concatenate(got[row][k]), reference[k])
        if call == 30:  # row 1 resets with new streams, row 2 with the streams it has
            for stream in (native, python):
                stream.restart(np.array([1]), 99)
                stream.restart(np.array([2]))
    assert snapshots is not None and len(calls) == 5
    for stream, snapshot in zip((native, python), snapshots, strict=True):
        stream.restore(snapshot)
        for times, rows, Z, readings in calls:  # calls 40 to 44 again: the same readings (draws, histories)
            again = stream.push(times, rows, Z.copy())
            for row, values in readings.items():
                for (_, r1), r2 in zip(again[row], values, strict=True):
                    np.testing.assert_array_equal(r1, r2)


@needs_native
@pytest.mark.parametrize("shift", [-1, 0, 1])
def test_native_readings_written_over_their_own_measurements_are_the_specifications(shift: int) -> None:
    """The native engine may leave its measurements in the rows of the store where the readings then go, or a row
    off (Sensing.update's spare and into): readings written over them, from the same row or a row before or after,
    are those made from a copy, bit for bit."""
    sensors = _spoiled_ur5().sensors
    strides = [1, 1, 1, 2, 1]
    native = SensorStream(sensors, strides, np.array([2]))
    python = SensorStream(sensors, strides, np.array([2]), native=False)
    rng = np.random.default_rng(8)
    buffer = np.empty((40, sensors.width))
    t = 0
    for m in (1, 7, 12, 3):
        times, t = np.arange(t, t + m) * 1e-3, t + m
        Z = rng.normal(size=(m, sensors.width))
        buffer[5 : 5 + m] = Z
        rows = np.zeros(m, dtype=np.int64)
        got = native.push(times, rows, buffer[5 : 5 + m], into=lambda b, t, m=m: buffer[5 + shift : 5 + shift + m])
        expected = python.push(times, rows, Z)
        for (t1, r1), (t2, r2) in zip(got[0], expected[0], strict=True):
            np.testing.assert_array_equal(t1, t2)
            np.testing.assert_array_equal(r1, r2)
        np.testing.assert_array_equal(native.latest, python.latest)


def _readings_by_definition(sensors: Any, strides: list[int], Z: np.ndarray, seed: int) -> list[np.ndarray]:
    """Each sensor's readings from a row's measurements Z (n, width) since its start (its streams never reset), by
    the definition: at every `stride`-th tick from the first, reading r is measurement r − latency (the first one
    before that) + bias + noise · draws of NormalStream(the sensor's seed + the row's `seed`), in reading and
    component order."""
    out = []
    for k, p in enumerate(sensors.placed):
        z = Z[:: strides[k], sensors.columns(k)]
        late = z[np.maximum(np.arange(len(z)) - p.spec.latency, 0)]
        draws = np.empty(late.shape)
        NormalStream(p.spec.seed + seed).fill(draws)
        out.append((late + p.bias) + p.noise * draws if np.any(p.noise) else late + p.bias)
    return out


def test_ticks_keep_what_the_engines_buffer_held_before_it_is_reused() -> None:
    """The native engine hands its ticks' measurements over in a buffer its next call reuses: ticks still held when
    it is called again (a tick measured in Python in between) keep their own numbers."""
    from multibody_sim.sensors import Ticks

    buffer = np.zeros((4, 1))
    calls: list[int] = []

    def source(into: Any = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = len(calls) + 1
        calls.append(n)
        buffer[:n] = n
        return np.arange(n, dtype=float), np.zeros(n, dtype=np.int64), buffer[:n]

    ticks = Ticks(1, 1)
    ticks.source = source
    ticks._keep(5.0, np.array([0]), np.array([[9.0]]))  # the source's first tick (1), then this one (9)
    times, rows, values = ticks.take()  # the source's next two (2, 2), in its buffer again
    assert values[:, 0].tolist() == [1.0, 9.0, 2.0, 2.0]
    assert times.tolist() == [0.0, 5.0, 0.0, 1.0]


def test_latency_is_exact_in_readings_and_rate_holds_them_between(kernel: str) -> None:
    """The double pendulum swinging: a sensor 3 readings late at 250 Hz (every 4 steps of 1 ms) reads exactly what
    its on-time twin read 3 readings (12 ms) before (its first reading before that), and holds each reading for 4
    samples."""
    scene = ms.make_scene(
        robot={"source": "double_pendulum"},
        sensor=[
            {"name": "now", "kind": "joint_velocity", "rate": 250.0},
            {"name": "late", "kind": "joint_velocity", "rate": 250.0, "latency": 3},
            {"name": "every", "kind": "joint_velocity"},
        ],
    )
    traj = on_kernel(ms.simulate(scene, [2.5, 0.3], [0.0, 0.0], duration=0.2, dt=1e-3), kernel)
    now, late, every = traj.sensors["now"], traj.sensors["late"], traj.sensors["every"]
    np.testing.assert_array_equal(every, traj.v)  # every step: the velocity itself
    ticks = np.arange(0, len(traj), 4)
    np.testing.assert_array_equal(now[ticks], traj.v[ticks])
    for i in range(len(traj)):  # held between its readings
        np.testing.assert_array_equal(now[i], traj.v[(i // 4) * 4])
    np.testing.assert_array_equal(late[12:], now[:-12])
    np.testing.assert_array_equal(late[:12], np.tile(traj.v[0], (12, 1)))


def test_readings_are_late_biased_noisy_measurements_on_every_path(kernel: str, tmp_path: Path) -> None:
    """A joint_velocity sensor's readings, rebuilt from the velocity itself and the declared generator: reading j
    (at its j-th tick) is v at tick j − latency (the first tick's before that) + bias + noise · d_j, with d the
    draws of noise.NormalStream(seed + row) (its own draws: tests/test_noise.py), (readings, components) in order;
    each sample holds the latest reading at or before it. Sensors at every step and at 250 Hz (with others, and
    alone: the run's ticks are then its readings), sampled every step, every 2 and every 3 steps, in one piece and
    in chunks (simulate), in rows (rollout), and step by step (Stepper)."""
    spoil = {"kind": "joint_velocity", "noise": [0.01, 0.5], "bias": [0.25, -1.0], "latency": 3}
    declared = {
        "fast": {**spoil, "seed": 11},
        "slow": {**spoil, "seed": 40, "rate": 250.0},
        "late": {"kind": "joint_velocity", "latency": 5, "seed": 7},  # no noise
    }
    for names in (("fast", "slow", "late"), ("slow",)):
        scene = ms.make_scene(
            robot={"source": "double_pendulum"}, sensor=[{"name": name, **declared[name]} for name in names]
        )
        _check_readings_on_every_path(scene, kernel, tmp_path)


def _check_readings_on_every_path(scene: ms.Scene, kernel: str, tmp_path: Path) -> None:
    """test_readings_are_late_biased_noisy_measurements_on_every_path's runs and checks on one scene."""
    spoil = {"noise": [0.01, 0.5], "bias": [0.25, -1.0]}
    q0, dt, steps = np.array([2.5, 0.3]), 1e-3, 60
    truth = on_kernel(ms.simulate(scene, q0, np.zeros(2), duration=steps * dt, dt=dt), kernel)
    V = truth.v  # the velocity at every step (tick)
    assert len(V) == steps + 1

    def expected(seed: int, stride: int, noise: Any, bias: Any, latency: int) -> np.ndarray:
        """Per step: the reading held there."""
        ticks = np.arange(0, steps + 1, stride)
        late = np.maximum(np.arange(len(ticks)) - latency, 0)
        draws = np.empty((len(ticks), 2))
        NormalStream(seed).fill(draws)
        readings = V[ticks[late]] + np.asarray(bias, dtype=float) + np.asarray(noise, dtype=float) * draws
        return readings[np.arange(steps + 1) // stride]

    def check(sensors: dict[str, np.ndarray], every: int, row: int = 0) -> None:
        picked = np.arange(0, steps + 1, every)
        for name, seed, stride, noise, bias, latency in (
            ("fast", 11, 1, spoil["noise"], spoil["bias"], 3),
            ("slow", 40, 4, spoil["noise"], spoil["bias"], 3),
            ("late", 7, 1, 0.0, 0.0, 5),
        ):
            if name not in sensors:
                continue
            want = expected(seed + row, stride, noise, bias, latency)[picked]
            np.testing.assert_array_equal(sensors[name], want, err_msg=f"{name}, every {every} steps, row {row}")

    check(truth.sensors, 1)
    for every in (2, 3):
        traj = ms.simulate(scene, q0, np.zeros(2), duration=steps * dt, dt=dt, output_dt=every * dt)
        check(on_kernel(traj, kernel).sensors, every)
    out = tmp_path / f"{'-'.join(scene.sensors.names)}.npz"
    chunked = ms.simulate(scene, q0, np.zeros(2), duration=steps * dt, dt=dt, out=out, chunk=7)
    check(on_kernel(chunked, kernel).sensors, 1)
    for every in (1, 3):
        Q0, V0 = np.array([q0, q0]), np.zeros((2, 2))
        batch = ms.rollout(scene, Q0, V0, duration=steps * dt, dt=dt, output_dt=every * dt)
        on_kernel(batch, kernel)
        for row in (0, 1):  # row 1's velocity is row 0's (the same start), its noise seed + 1's
            check({name: r[row] for name, r in batch.sensors.items()}, every, row)
    stepper = ms.Stepper(scene, dt=dt, q0=q0)
    seen = [stepper.readings]
    for _ in range(steps):
        stepper.step(np.zeros(2))
        seen.append(stepper.readings)
    check({name: np.array([r[name] for r in seen]) for name in seen[0]}, 1)


def test_noise_is_seeded_per_sensor_and_per_rollout_row() -> None:
    """The same seed, the same noise; a rollout's row b draws from seed + b (its element equals a simulate() of the
    scene declared with seed + b)."""

    def scene(seed: int) -> ms.Scene:
        return ms.make_scene(
            robot={"source": "double_pendulum"},
            sensor=[{"name": "enc", "kind": "joint_position", "noise": 0.1, "bias": [0.0, 1.0], "seed": seed}],
        )

    q0, v0 = np.array([0.4, 0.1]), np.zeros(2)
    a = ms.simulate(scene(5), q0, v0, duration=0.02, dt=1e-3)
    b = ms.simulate(scene(5), q0, v0, duration=0.02, dt=1e-3)
    np.testing.assert_array_equal(a.sensors["enc"], b.sensors["enc"])
    batch = ms.rollout(scene(5), np.array([q0, q0]), np.array([v0, v0]), duration=0.02, dt=1e-3)
    assert batch.sensors["enc"].shape == (2, len(a), 2)
    np.testing.assert_array_equal(batch.sensors["enc"][0], a.sensors["enc"])
    other = ms.simulate(scene(6), q0, v0, duration=0.02, dt=1e-3)
    np.testing.assert_array_equal(batch.sensors["enc"][1], other.sensors["enc"])
    np.testing.assert_array_equal(batch.element(1).sensors["enc"], other.sensors["enc"])
    assert np.abs(a.sensors["enc"] - a.q - [0.0, 1.0]).max() < 0.5  # noise about the biased truth
    assert not np.array_equal(a.sensors["enc"], other.sensors["enc"])


# ---- where readings go ----------------------------------------------------------------------------------------------
def test_readings_go_to_files_tables_and_chunks(tmp_path: Path) -> None:
    """.npz round trip (chunked too), dataframe columns <name>.<component>, CSV and Parquet."""
    scene = _box()
    traj = ms.simulate(scene, scene.q0, scene.v0, duration=0.05, dt=1e-3, integrator="timestepping")
    loaded = ms.Trajectory.load(traj.save(tmp_path / "box.npz"))
    for name in ("imu", "touch"):
        np.testing.assert_array_equal(loaded.sensors[name], traj.sensors[name])
    chunked = ms.simulate(
        scene,
        scene.q0,
        scene.v0,
        duration=0.05,
        dt=1e-3,
        integrator="timestepping",
        out=tmp_path / "chunked.npz",
        chunk=7,
    )
    np.testing.assert_array_equal(chunked.sensors["imu"], traj.sensors["imu"])
    pytest.importorskip("pandas")
    frame = traj.to_dataframe()
    assert [c for c in frame.columns if c.startswith(("imu.", "touch."))] == [
        "imu.ax",
        "imu.ay",
        "imu.az",
        "imu.wx",
        "imu.wy",
        "imu.wz",
        "touch.fx",
        "touch.fy",
        "touch.fz",
    ]
    np.testing.assert_array_equal(frame["touch.fz"].to_numpy(), traj.sensors["touch"][:, 2])
    import pandas

    from multibody_sim.tables import write_table

    write_table(traj, tmp_path / "box.csv")
    table = pandas.read_csv(tmp_path / "box.csv")
    np.testing.assert_array_equal(table["imu.az"].to_numpy(), traj.sensors["imu"][:, 2])
    pytest.importorskip("pyarrow")
    write_table(traj, tmp_path / "box.parquet")
    np.testing.assert_array_equal(pandas.read_parquet(tmp_path / "box.parquet")["imu.az"], traj.sensors["imu"][:, 2])


def test_a_controller_that_asks_reads_what_the_trajectory_records() -> None:
    """A controller with `sensors = True` is called with the readings (by name); they are the trajectory's
    readings at the control instants, and the run's samples equal a Stepper driven by the same controller."""
    scene = ms.make_scene(
        robot={"source": "double_pendulum"},
        sensor=[
            {"name": "enc", "kind": "joint_position", "noise": 0.01, "latency": 1},
            {"name": "gyro", "kind": "joint_velocity", "noise": 0.01},
        ],
    )
    seen: list[tuple[float, np.ndarray]] = []

    def pd(t: float, q: np.ndarray, v: np.ndarray, readings: dict[str, np.ndarray]) -> np.ndarray:
        seen.append((t, readings["enc"].copy()))
        return -5.0 * (readings["enc"] - [math.pi, 0.0]) - 0.5 * readings["gyro"]

    pd.sensors = True  # type: ignore[attr-defined]
    q0, v0 = np.array([2.8, 0.2]), np.zeros(2)
    traj = ms.simulate(scene, q0, v0, duration=0.05, dt=1e-3, control_dt=5e-3, controller=pd)
    assert len(seen) == 10
    for t, enc in seen:
        i = int(round(t / 1e-3))
        np.testing.assert_array_equal(enc, traj.sensors["enc"][i])
    stepper = ms.Stepper(scene, dt=1e-3, control_dt=5e-3, q0=q0, v0=v0)
    stepper.advance_to(0.05, pd)
    np.testing.assert_array_equal(stepper.q, traj.q[-1])
    np.testing.assert_array_equal(stepper.readings["enc"], traj.sensors["enc"][-1])


def test_steppers_read_what_simulate_records() -> None:
    """Stepper.readings and BatchStepper.readings after each interval are simulate()'s readings at that sample."""
    scene = _box()
    traj = ms.simulate(scene, scene.q0, scene.v0, duration=0.4, dt=1e-3, integrator="timestepping")
    stepper = ms.Stepper(scene, dt=1e-3, control_dt=1e-2, integrator="timestepping", q0=scene.q0, v0=scene.v0)
    batch = ms.BatchStepper(
        scene, np.array([scene.q0] * 2), np.array([scene.v0] * 2), dt=1e-3, control_dt=1e-2, integrator="timestepping"
    )
    np.testing.assert_array_equal(stepper.readings["imu"], traj.sensors["imu"][0])
    for k in range(1, 41):
        stepper.step()
        batch.step(np.zeros((2, scene.nv)))
        np.testing.assert_array_equal(stepper.readings["touch"], traj.sensors["touch"][10 * k])
        np.testing.assert_array_equal(batch.readings["imu"][0], traj.sensors["imu"][10 * k])


def test_gym_observations_are_the_sensors_readings() -> None:
    """observation="sensors": the Box has the sensors' components, and each observation is the readings; a seeded
    reset reproduces the noise; the vector env's row i equals the single env seeded with seed + i."""
    pytest.importorskip("gymnasium")
    from multibody_sim.gym import MultibodyEnv, MultibodyVectorEnv

    scene = ms.make_scene(
        robot={"source": "double_pendulum"},
        sensor=[
            {"name": "enc", "kind": "joint_position", "noise": 0.01},
            {"name": "tip", "kind": "frame_pose", "frame": "link2"},
        ],
    )
    env = MultibodyEnv(scene, reward=lambda q, v, tau: 0.0, observation="sensors", control_dt=2e-3)
    assert env.observation_space.shape == (9,)
    obs, _ = env.reset(seed=3)
    readings = env.stepper.readings
    np.testing.assert_array_equal(obs, np.concatenate([readings["enc"], readings["tip"]]))
    first = [env.step(np.zeros(2))[0] for _ in range(5)]
    again, _ = env.reset(seed=3)
    np.testing.assert_array_equal(again, obs)
    np.testing.assert_array_equal([env.step(np.zeros(2))[0] for _ in range(5)], first)
    only = MultibodyEnv(scene, reward=lambda q, v, tau: 0.0, observation=["tip"])
    assert only.observation_space.shape == (7,)
    vector = MultibodyVectorEnv(scene, 2, reward=lambda q, v, tau: 0.0, observation="sensors", control_dt=2e-3)
    observations, _ = vector.reset(seed=2)
    np.testing.assert_array_equal(observations[1], obs)  # row 1: seed 2 + 1
    for expected in first:
        observations = vector.step(np.zeros((2, 2)))[0]
        np.testing.assert_array_equal(observations[1], expected)


def test_describe_lists_the_sensors() -> None:
    scene = ms.make_scene(
        robot={"source": "ur5"},
        sensor=[
            {"name": "imu", "kind": "imu", "frame": "tool0", "noise": 0.01, "rate": 500.0, "latency": 2},
            {"name": "enc", "kind": "joint_position", "joints": "*_joint"},
        ],
    )
    text = scene.describe()
    assert "  sensors:\n    imu: imu at tool0, 500 Hz, noise 0.01, latency 2 (ax ay az wx wy wz)" in text
    assert "    enc: joint_position of 6 joints, every control instant (shoulder_pan_joint" in text


# ---- mistakes -------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("sensor", "message"),
    [
        ({"kind": "imu"}, "<scene>: sensor[0].frame: missing (a imu sensor needs frame)"),
        (
            {"kind": "lidar"},
            "<scene>: sensor[0].kind: must be one of contact_force, force_torque, frame_pose, imu, "
            "joint_position, joint_torque, joint_velocity, got 'lidar'",
        ),
        (
            {"kind": "imu", "frame": "tool0", "body": "x"},
            "<scene>: sensor[0].body: only for kind contact_force, not imu",
        ),
        ({"kind": "imu", "frame": "tool0", "noise": -1.0}, "<scene>: sensor[0].noise: must be >= 0, got -1.0"),
        (
            {"kind": "imu", "frame": "tool0", "noise": [0.1, 0.2]},
            "<scene>: sensor[0].noise: must be one number or 6 (one per component: ax ay az wx wy wz), got 2",
        ),
        ({"kind": "imu", "frame": "tool9"}, "<scene>: sensor[0].frame: unknown frame 'tool9' (did you mean 'tool0'?)"),
        (
            {"kind": "contact_force", "body": "wrist_3_link"},
            "<scene>: sensor[0].body: a contact_force sensor needs contact ([ground], [contact] or [[object]])",
        ),
        ({"kind": "joint_position", "joints": ["nope_*"]}, "<scene>: sensor[0].joints: 'nope_*' matches no actuated"),
        ({"kind": "imu", "frame": "tool0", "name": "a.b"}, "<scene>: sensor[0].name: must not contain '.'"),
        ({"kind": "imu", "frame": "tool0", "latency": 1.5}, "<scene>: sensor[0].latency: must be a whole number"),
    ],
)
def test_sensor_mistakes_are_one_line(sensor: dict[str, object], message: str) -> None:
    with pytest.raises(SceneError) as info:
        ms.make_scene(robot={"source": "ur5"}, sensor=[sensor])
    assert str(info.value).startswith(message), str(info.value)
    assert "\n" not in str(info.value)


def test_run_mistakes_are_one_line() -> None:
    scene = ms.make_scene(robot={"source": "double_pendulum"}, sensor=[{"kind": "joint_position", "rate": 300.0}])
    with pytest.raises(InvalidArgumentError, match=r"^sensor 'joint_position0': rate 300 Hz must read every whole "):
        ms.simulate(scene, [0.1, 0.0], [0.0, 0.0], duration=0.01, dt=1e-3)
    with pytest.raises(InvalidArgumentError, match=r"^sensors tick every so many fixed steps: integrator 'dp54'"):
        ms.simulate(scene, [0.1, 0.0], [0.0, 0.0], duration=0.01, dt=1e-3, integrator="dp54", rtol=1e-6, atol=1e-8)
    reads = lambda t, q, v, readings: np.zeros(2)  # noqa: E731
    reads.sensors = True  # type: ignore[attr-defined]
    with pytest.raises(InvalidArgumentError, match=r"^the controller reads sensors \(sensors = True\) but the system"):
        ms.simulate(
            ms.make_scene(robot={"source": "double_pendulum"}),
            [0.1, 0.0],
            [0.0, 0.0],
            duration=0.01,
            dt=1e-3,
            controller=reads,
        )
    pytest.importorskip("gymnasium")
    from multibody_sim.gym import MultibodyEnv

    with pytest.raises(InvalidArgumentError, match=r"^observation: unknown sensor 'imu' \(the system's sensors: "):
        MultibodyEnv(scene, reward=lambda q, v, tau: 0.0, observation=["imu"])


# ---- the native kernel: the same readings, bit for bit --------------------------------------------------------------
def _native_or_skip() -> None:
    from multibody_sim import native

    if not native.available:
        pytest.skip(f"the native kernel is not available here: {native.why_unavailable}")


def _both(monkeypatch: pytest.MonkeyPatch, run: Any) -> tuple[Any, Any]:
    """run() on the native kernel, then on the Python kernel."""
    from multibody_sim import native

    on_native = run()
    with monkeypatch.context() as m:
        m.setenv(native.ENV, "0")
        on_python = run()
    return on_native, on_python


def _ur5_sensors() -> ms.Scene:
    return ms.make_scene(
        robot={"source": "ur5"},
        payload=[{"frame": "ee_link", "mass": 0.7, "com": [0.0, 0.02, 0.05]}],  # beyond the wrist sensor
        sensor=[
            {"name": "imu", "kind": "imu", "frame": "tool0", "noise": 0.01, "latency": 2},
            {"name": "pose", "kind": "frame_pose", "frame": "wrist_3_link"},
            {"name": "wrist", "kind": "force_torque", "frame": "ee_fixed_joint", "rate": 500.0},
            {"name": "elbow", "kind": "force_torque", "joint": "elbow_joint"},
            {"name": "enc", "kind": "joint_position", "bias": 0.001},
            {"name": "gyro", "kind": "joint_velocity"},
            {"name": "tq", "kind": "joint_torque"},
        ],
    )


def test_native_readings_equal_the_python_kernels(monkeypatch: pytest.MonkeyPatch) -> None:
    """ur5 (every kind but contact, a built-in controller inside the engine and a Python one that reads the sensors)
    and go2 standing (contact forces, an IMU and force-torque sensors whose subtrees touch the ground, on two
    threads of a rollout): the native kernel's readings are the Python kernel's, bit for bit."""
    _native_or_skip()
    scene = _ur5_sensors()
    q0, v0 = scene.q0 + 0.2, np.full(scene.nv, 0.3)
    pd = ms.PD(scene, q_ref=scene.q0, kp=50.0, kd=5.0)

    def reads(t: float, q: np.ndarray, v: np.ndarray, readings: dict[str, np.ndarray]) -> np.ndarray:
        return -20.0 * (readings["enc"] - scene.q0) - 2.0 * readings["gyro"]

    reads.sensors = True  # type: ignore[attr-defined]
    for controller in (pd, reads):
        native, python = _both(
            monkeypatch,
            lambda c=controller: ms.simulate(scene, q0, v0, duration=0.05, dt=1e-3, control_dt=2e-3, controller=c),
        )
        assert native.metadata["kernel"] == "native" and python.metadata["kernel"] != "native"
        np.testing.assert_array_equal(native.q, python.q)
        for name in python.sensors:
            np.testing.assert_array_equal(native.sensors[name], python.sensors[name], err_msg=name)
    go2 = ms.load_scene(_scene_file("go2_standing.toml"))
    sensors = [{"name": f"{leg}", "kind": "contact_force", "body": f"{leg}_foot"} for leg in ("FL", "RR")]
    sensors += [
        {"name": "imu", "kind": "imu", "frame": "base", "noise": 0.05},
        {"name": "hip", "kind": "force_torque", "joint": "FL_hip_joint"},
        {"name": "calf", "kind": "force_torque", "frame": "FL_calf"},
    ]
    go2 = _with_sensors(go2, sensors)
    native = _go2_rollouts_read_alike(monkeypatch, go2, rows=3, duration=0.1)
    assert np.abs(native.sensors["FL"][:, -1, 2]).min() > 10.0  # the feet carry the robot


def _go2_rollouts_read_alike(monkeypatch: pytest.MonkeyPatch, go2: ms.Scene, rows: int, duration: float) -> Any:
    """go2 standing under its controller on two threads of a rollout (row 1 with its joints moving): the native
    kernel's readings are the Python kernel's bit for bit; returns the native run."""
    V0 = np.zeros((rows, go2.nv))
    V0[1, 6:] = 0.1
    native, python = _both(
        monkeypatch,
        lambda: ms.rollout(
            go2,
            np.tile(go2.q0, (rows, 1)),
            V0,
            duration=duration,
            dt=1e-3,
            integrator="timestepping",
            controller=go2.make_controller(),
            num_threads=2,
        ),
    )
    assert native.metadata["kernel"] == "native" and python.metadata["kernel"] != "native"
    for name in python.sensors:
        np.testing.assert_array_equal(native.sensors[name], python.sensors[name], err_msg=f"go2 {name}")
    return native


def test_native_steppers_read_what_the_python_kernel_reads(monkeypatch: pytest.MonkeyPatch) -> None:
    """Stepper and BatchStepper (rows reset apart, so their ticks' phases differ) read the same on both kernels."""
    _native_or_skip()
    scene = ms.make_scene(
        robot={"source": "ur5"},
        sensor=[
            {"name": "imu", "kind": "imu", "frame": "tool0", "rate": 250.0, "noise": 0.01},
            {"name": "enc", "kind": "joint_position", "latency": 1},
        ],
    )

    def run() -> list[dict[str, np.ndarray]]:
        seen = []
        stepper = ms.Stepper(scene, dt=1e-3, control_dt=2e-3, q0=scene.q0)
        batch = ms.BatchStepper(scene, np.array([scene.q0] * 2), np.zeros((2, scene.nv)), dt=1e-3, control_dt=2e-3)
        for k in range(12):
            stepper.step(np.full(scene.nv, 0.5))
            batch.step(np.full((2, scene.nv), 0.5))
            if k == 4:
                batch.reset(np.array([1]), np.array([scene.q0 + 0.1]))
            seen += [stepper.readings, batch.readings]
        return seen

    native, python = _both(monkeypatch, run)
    for a, b in zip(native, python, strict=True):
        for name in b:
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_native_joint_torque_sensors_read_the_actuators_delivered_torque(monkeypatch: pytest.MonkeyPatch) -> None:
    """With actuators the joint_torque sensors read what the actuators deliver at the tick (their law, curve and
    limits at the tick's state under the held command), on the native kernel as on the Python kernel, bit for bit:
    ur5's stiff position servos near their effort limits (rk4, and semi-implicit Euler's implicit step with its
    revisions), and go2's catalog motors standing on the ground under torque commands (the time-stepper)."""
    _native_or_skip()
    ur5 = ms.make_scene(
        robot={"source": "ur5"},
        actuator=[{"joints": "*", "kind": "position", "kp": 1e4, "kv": 100.0, "effort_limit": 40.0}],
        sensor=[{"name": "tq", "kind": "joint_torque"}, {"name": "enc", "kind": "joint_position", "noise": 1e-3}],
    )
    target = ur5.q0 + 0.3
    for integrator in ("rk4", "semi_implicit_euler"):
        native, python = _both(
            monkeypatch,
            lambda i=integrator: ms.simulate(
                ur5,
                ur5.q0,
                np.zeros(ur5.nv),
                duration=0.05,
                dt=1e-3,
                control_dt=2e-3,
                integrator=i,
                controller=lambda t, q, v: target,
            ),
        )
        assert native.metadata["kernel"] == "native" and python.metadata["kernel"] != "native"
        for name in python.sensors:
            np.testing.assert_array_equal(native.sensors[name], python.sensors[name], err_msg=f"{integrator} {name}")
        tq = native.sensors["tq"]
        assert np.abs(tq).max() == 40.0  # the servos saturate: the sensor reads the limited torque
        assert np.abs(tq[1:] - native.ctrl[1:]).max() > 1.0  # not the command (a target in rad)
    import dataclasses

    go2 = _with_sensors(
        ms.load_scene(_scene_file("go2_standing.toml")),
        [{"name": "tq", "kind": "joint_torque"}, {"name": "FL", "kind": "contact_force", "body": "FL_foot"}],
    )
    go2 = ms.Scene(dataclasses.replace(go2.spec, actuator_defaults="catalog"))
    gains = ms.PDGravity(go2, q_ref=go2.q0, kp=100.0, kd=5.0)
    native, python = _both(
        monkeypatch,
        lambda: ms.simulate(
            go2, go2.q0, np.zeros(go2.nv), duration=0.05, dt=1e-3, integrator="timestepping", controller=gains
        ),
    )
    assert native.metadata["kernel"] == "native" and python.metadata["kernel"] != "native"
    for name in python.sensors:
        np.testing.assert_array_equal(native.sensors[name], python.sensors[name], err_msg=f"go2 {name}")
    assert np.abs(native.sensors["FL"][-1, 2]) > 10.0  # standing on its feet


def test_native_kinematic_sensors_taken_from_the_next_steps_aba_equal_the_python_kernels(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Without force-torque sensors the engine takes a tick's IMU and frame pose from the next step's first ABA at
    the tick's state (measure.hpp, kinematics_after_aba), and the last tick of each engine call from a pass of its
    own: the readings are still the Python kernel's bit for bit. ur5 under servos with rk4 and semi-implicit Euler
    (a built-in controller: many steps per engine call; sensors at 500 Hz: ticks every other step), a one-row
    rollout of torques sampled at every tick or every fourth (the IMU 1 reading late), and go2 standing on two
    threads under the time-stepper with its catalog motors."""
    _native_or_skip()
    import dataclasses

    sensors: list[dict[str, object]] = [
        {"name": "imu", "kind": "imu", "frame": "tool0", "noise": 0.01, "latency": 1},
        {"name": "pose", "kind": "frame_pose", "frame": "wrist_3_link"},
        {"name": "enc", "kind": "joint_position"},
        {"name": "tq", "kind": "joint_torque"},
    ]
    servos = [{"joints": "*", "kind": "position", "kp": 1e3, "kv": 30.0}]
    for rate in (None, 500.0):
        chosen = [{**s, "rate": rate} for s in sensors] if rate else sensors
        ur5 = ms.make_scene(robot={"source": "ur5"}, actuator=servos, sensor=chosen)
        pd = ms.PD(ur5, q_ref=ur5.q0 + 0.3, kp=50.0, kd=5.0)
        for integrator in ("rk4", "semi_implicit_euler"):
            native, python = _both(
                monkeypatch,
                lambda s=ur5, i=integrator, c=pd: ms.simulate(
                    s, s.q0, np.full(s.nv, 0.2), duration=0.03, dt=1e-3, control_dt=2e-3, integrator=i, controller=c
                ),
            )
            assert native.metadata["kernel"] == "native" and python.metadata["kernel"] != "native"
            np.testing.assert_array_equal(native.q, python.q)
            for name in python.sensors:
                np.testing.assert_array_equal(
                    native.sensors[name], python.sensors[name], err_msg=f"{integrator} {name}"
                )
            assert np.abs(np.diff(native.sensors["imu"][:, :3], axis=0)).max() > 1e-3  # the arm moves
    bare = ms.make_scene(robot={"source": "ur5"}, sensor=sensors[:2])
    taus = np.tile(np.linspace(-2.0, 2.0, bare.nv), (1, 40, 1))
    for output_dt in (None, 4e-3):  # a sample at every tick (velocities shared with its energies), or every 4th
        native, python = _both(
            monkeypatch,
            lambda o=output_dt: ms.rollout(
                bare, bare.q0[None], np.zeros((1, bare.nv)), duration=0.04, dt=1e-3, taus=taus, output_dt=o
            ),
        )
        assert native.metadata["kernel"] == "native" and python.metadata["kernel"] != "native"
        for name in python.sensors:
            np.testing.assert_array_equal(native.sensors[name], python.sensors[name], err_msg=f"rollout {name}")
    go2 = _with_sensors(
        ms.load_scene(_scene_file("go2_standing.toml")),
        [
            {"name": "imu", "kind": "imu", "frame": "base"},
            {"name": "foot", "kind": "frame_pose", "frame": "FL_foot"},
            {"name": "FL", "kind": "contact_force", "body": "FL_foot"},
        ],
    )
    go2 = ms.Scene(dataclasses.replace(go2.spec, actuator_defaults="catalog"))
    _go2_rollouts_read_alike(monkeypatch, go2, rows=2, duration=0.05)
