"""Randomised physics ([randomize], Scene.with_parameters, rollout(randomize=...)): the declarations and their one-line
errors, the draws against their declared distributions, drawn values against closed forms and against the same
values declared in a scene, and each row re-run alone bit for bit on both kernels."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from conftest import assert_same_run, both, ctrl_c_at, needs_native, on_kernel, shipped
from scipy import stats

import multibody_sim as ms
from multibody_sim.exceptions import InvalidArgumentError, SceneError
from multibody_sim.trajectory import Trajectory


def uniform(name: str, low: float, high: float, *, scale: bool = False, **targets: Any) -> dict[str, Any]:
    return {"name": name, "distribution": "uniform", ("scale" if scale else "value"): [low, high], **targets}


# A free box floating without ground (timestepping: semi-implicit Euler) pushed by a constant force.
PUSHED_BOX = {
    "object": [{"name": "box", "shape": "box", "size": [0.2, 0.1, 0.1], "mass": 2.0, "position": [0, 0, 1]}],
    "gravity": [0.0, 0.0, 0.0],
    "force": [{"name": "push", "frame": "box", "force": [3.0, 0.0, 0.0]}],
}


# ---- declarations --------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("table", "message"),
    [
        (
            {"sed": 1, "parameter": []},
            "<scene>: randomize: unknown key 'sed' (did you mean 'seed'? valid: parameter, seed)",
        ),
        ({"seed": -1, "parameter": []}, "<scene>: randomize.seed: must be a whole number >= 0, got -1"),
        ({"parameter": []}, "<scene>: randomize.parameter: must hold at least one [[randomize.parameter]] table"),
        (
            {"parameter": [uniform("mas", 1, 2)]},
            "<scene>: randomize.parameter[0].name: must be one of armature, body_friction, body_restitution, damping, "
            "effort_limit, friction, gear, ground_friction, ground_restitution, inertia, kp, kv, mass, no_load_speed, "
            "payload_mass, rotor_inertia, stall_torque, velocity_limit, got 'mas' (did you mean 'mass'?)",
        ),
        (
            {"parameter": [uniform("mass", 1, 2, joints="*")]},
            "<scene>: randomize.parameter[0].joints: 'mass' takes bodies = ..., not joints",
        ),
        (
            {"parameter": [uniform("ground_friction", 0.1, 0.2, bodies="*")]},
            "<scene>: randomize.parameter[0].bodies: 'ground_friction' applies to the whole scene, not bodies",
        ),
        (
            {"parameter": [{"name": "mass", "distribution": "uniform"}]},
            "<scene>: randomize.parameter[0]: give scale = [a, b] (the draw multiplies the declared value) or "
            "value = [a, b] (the draw is the value)",
        ),
        (
            {"parameter": [{"name": "mass", "distribution": "uniform", "scale": [1, 2], "value": [1, 2]}]},
            "<scene>: randomize.parameter[0]: give scale = [a, b] (the draw multiplies the declared value) or "
            "value = [a, b] (the draw is the value), not both",
        ),
        (
            {"parameter": [uniform("mass", 2, 1, scale=True)]},
            "<scene>: randomize.parameter[0].scale: uniform takes [low, high] with low <= high, got [2, 1]",
        ),
        (
            {"parameter": [{"name": "damping", "distribution": "loguniform", "value": [0, 1]}]},
            "<scene>: randomize.parameter[0].value: loguniform takes [low, high] with low > 0, got low 0",
        ),
        (
            {"parameter": [{"name": "kp", "distribution": "normal", "value": [10, -1]}]},
            "<scene>: randomize.parameter[0].value: normal takes [mean, std] with std >= 0, got std -1",
        ),
        (
            {"parameter": [uniform("ground_restitution", 0.5, 1.5)]},
            "<scene>: randomize.parameter[0].value: uniform [low, high] = [0.5, 1.5] leaves the range of "
            "ground_restitution, [0, 1]",
        ),
        (
            {"parameter": [uniform("mass", 0, 1)]},
            "<scene>: randomize.parameter[0].value: uniform [low, high] = [0, 1] leaves the range of mass [kg], "
            "(0, inf)",
        ),
        (
            {"parameter": [uniform("inertia", 1, 2)]},
            "<scene>: randomize.parameter[0].value: 'inertia' is a factor on the declared value: give scale = [a, b]",
        ),
        (
            {"parameter": [{"name": "mass", "distribution": "gauss", "scale": [1, 0.1]}]},
            "<scene>: randomize.parameter[0].distribution: must be one of loguniform, normal, uniform, got 'gauss'",
        ),
        (
            {"parameter": [{**uniform("mass", 1, 2), "shard": True}]},
            "<scene>: randomize.parameter[0]: unknown key 'shard' (did you mean 'shared'? valid: bodies, distribution, "
            "joints, name, payloads, scale, shared, value)",
        ),
        (
            {"parameter": [uniform("payload_mass", 1, 2, payloads=[-1])]},
            "<scene>: randomize.parameter[0].payloads[0]: must be a payload's index (0 is the first [[payload]]), "
            "got -1",
        ),
    ],
)
def test_a_bad_table_is_refused_in_one_line(table: dict[str, Any], message: str) -> None:
    with pytest.raises(SceneError) as caught:
        ms.make_scene(robot={"source": "double_pendulum"}, randomize=table)
    assert str(caught.value) == message


@pytest.mark.parametrize(
    ("tables", "message"),
    [
        (
            {"robot": {"source": "double_pendulum"}, "randomize": {"parameter": [uniform("mass", 1, 2, bodies="arm")]}},
            "<scene>: randomize.parameter[0].bodies: 'arm' matches none of the bodies mass applies to (link1, link2)",
        ),
        (
            {"robot": {"source": "double_pendulum"}, "randomize": {"parameter": [uniform("ground_friction", 0.1, 1)]}},
            "<scene>: randomize.parameter[0].name: the scene has no ground_friction (it needs a [ground] table)",
        ),
        (
            {"robot": {"source": "double_pendulum"}, "randomize": {"parameter": [uniform("kp", 1, 2)]}},
            "<scene>: randomize.parameter[0].name: the scene has no kp (it needs [[actuator]] tables)",
        ),
        (
            {
                "robot": {"source": "double_pendulum"},
                "actuator": [{"joints": "joint1", "kind": "position", "kp": 10.0, "kv": 1.0}, {"joints": "joint2"}],
                "randomize": {"parameter": [uniform("kp", 1, 2, joints="joint2")]},
            },
            "<scene>: randomize.parameter[0].joints: 'joint2' matches none of the joints kp applies to (joint1)",
        ),
    ],
)
def test_what_the_scene_does_not_have_is_refused_in_one_line(tables: dict[str, Any], message: str) -> None:
    with pytest.raises(SceneError) as caught:
        ms.make_scene(**tables)
    assert str(caught.value) == message


def test_a_scale_that_leaves_the_quantity_s_range_is_refused() -> None:
    tables = shipped("sliding_box")
    tables["ground"]["restitution"] = 0.6
    tables["randomize"] = {"parameter": [uniform("ground_restitution", 0.5, 2.0, scale=True)]}
    with pytest.raises(SceneError) as caught:
        ms.make_scene(**tables)
    assert str(caught.value) == (
        "<scene>: randomize.parameter[0].scale: uniform [0.5, 2] takes ground_restitution (0.6) to 1.2, beyond its "
        "range [0, 1]"
    )


def test_with_parameters_names_what_is_wrong() -> None:
    scene = ms.make_scene(robot={"source": "double_pendulum"})
    with pytest.raises(InvalidArgumentError) as caught:
        scene.with_parameters({"mas": {"link1": 1.0}})
    assert str(caught.value).startswith("parameters: unknown parameter 'mas' (valid: mass, inertia, payload_mass")
    with pytest.raises(InvalidArgumentError) as caught:
        scene.with_parameters({"mass": {"link3": 1.0}})
    assert str(caught.value) == "parameters: mass: unknown body 'link3' (valid: link1, link2)"
    with pytest.raises(InvalidArgumentError) as caught:
        scene.with_parameters({"damping": {"joint1": -1.0}})
    assert str(caught.value) == "parameters: damping['joint1'] must lie in [0, inf], got -1.0"
    with pytest.raises(InvalidArgumentError) as caught:
        scene.with_parameters({"ground_friction": 0.5})
    assert str(caught.value) == "parameters: the scene has no ground_friction (it needs a [ground] table)"


def test_describe_says_what_is_randomised() -> None:
    tables = {
        **shipped("sliding_box"),
        "randomize": {
            "seed": 7,
            "parameter": [
                uniform("mass", 0.5, 2.0, scale=True),
                {"name": "ground_friction", "distribution": "normal", "value": [0.8, 0.1]},
            ],
        },
    }
    scene = ms.make_scene(**tables)
    lines = scene.describe().splitlines()
    assert lines[-3:] == [
        "  randomized per rollout row / gym reset (seed 7):",
        "    mass of box × uniform [0.5, 2]",
        "    ground_friction (0.8) normal mean 0.8, std 0.1",
    ]
    variant = scene.with_parameters({"mass": {"box": 1.5}, "ground_friction": 0.7})
    assert variant.describe().splitlines()[-1] == "  parameters drawn: mass box 1.5; ground_friction 0.7"


# ---- draws ---------------------------------------------------------------------------------------------------
def draws(distribution: str, arguments: list[float], n: int, *, scale: bool = False) -> np.ndarray:
    """n rows' draws of the ground's friction (declared 0.8) from one [randomize] table."""
    tables = {
        **shipped("sliding_box"),
        "randomize": {
            "seed": 11,
            "parameter": [
                {"name": "ground_friction", "distribution": distribution, ("scale" if scale else "value"): arguments}
            ],
        },
    }
    scene = ms.make_scene(**tables)
    return np.array([scene.draw_parameters(b)["ground_friction"] for b in range(n)])


@pytest.mark.parametrize(
    ("distribution", "arguments", "scale", "law"),
    [
        ("uniform", [0.3, 1.1], False, stats.uniform(0.3, 0.8)),
        ("normal", [0.7, 0.05], False, stats.norm(0.7, 0.05)),
        ("loguniform", [0.05, 2.0], False, stats.loguniform(0.05, 2.0)),
        ("uniform", [0.5, 1.5], True, stats.uniform(0.4, 0.8)),  # × the declared 0.8
    ],
)
def test_draws_follow_the_declared_distribution(
    distribution: str, arguments: list[float], scale: bool, law: Any
) -> None:
    x = draws(distribution, arguments, 4000, scale=scale)
    # Kolmogorov–Smirnov against the declared law, and the mean within 4 standard errors of its own.
    assert stats.kstest(x, law.cdf).pvalue > 1e-3
    assert abs(x.mean() - law.mean()) < 4 * law.std() / math.sqrt(len(x))


def test_a_normal_is_truncated_to_the_quantity_s_range() -> None:
    x = draws("normal", [0.05, 0.1], 3000)  # half its mass below 0, where friction cannot be
    assert x.min() >= 0.0
    truncated = stats.truncnorm(-0.5, np.inf, loc=0.05, scale=0.1)
    assert stats.kstest(x, truncated.cdf).pvalue > 1e-3


def test_rows_draw_independently_and_reproducibly() -> None:
    tables = {
        "robot": {"source": "double_pendulum"},
        "randomize": {
            "seed": 5,
            "parameter": [
                uniform("mass", 0.8, 1.2, scale=True),
                {**uniform("damping", 0.0, 0.2, joints="*"), "shared": True},
            ],
        },
    }
    scene = ms.make_scene(**tables)
    first, again, other = scene.draw_parameters(0), ms.make_scene(**tables).draw_parameters(0), scene.draw_parameters(1)
    assert first == again and first != other
    assert first["mass"]["link1"] != first["mass"]["link2"]  # one draw per body
    assert first["damping"]["joint1"] == first["damping"]["joint2"]  # shared: one for both


# ---- drawn values act as physics says ----------------------------------------------------------------------------
def test_a_drawn_mass_gives_the_acceleration_newton_says() -> None:
    """A box pushed by F from rest: semi-implicit Euler's positions are exactly x_N = (F/m) h² N (N + 1) / 2."""
    scene = ms.make_scene(**PUSHED_BOX, randomize={"seed": 2, "parameter": [uniform("mass", 0.5, 4.0, bodies="box")]})
    B, h, N = 6, 1e-3, 200
    batch = ms.rollout(
        scene, np.tile(scene.q0, (B, 1)), np.zeros((B, 6)), duration=N * h, dt=h, integrator="timestepping"
    )
    masses = [p["mass"]["box"] for p in batch.metadata["parameters"]]
    assert len(set(masses)) == B and all(0.5 <= m <= 4.0 for m in masses)
    for b, m in enumerate(masses):
        x = batch.q[b, -1, 0] - scene.q0[0]
        assert x == pytest.approx(3.0 / m * h * h * N * (N + 1) / 2, rel=1e-9)


def test_a_drawn_ground_friction_stops_a_sliding_box_where_coulomb_says() -> None:
    """The shipped sliding box (2 m/s): it stops after v0² / (2 μ g), to within a step's travel v0 h."""
    tables = {**shipped("sliding_box"), "randomize": {"seed": 4, "parameter": [uniform("ground_friction", 0.3, 1.2)]}}
    scene = ms.make_scene(**tables)
    B, h = 5, 1e-3
    batch = ms.rollout(
        scene, np.tile(scene.q0, (B, 1)), np.tile(scene.v0, (B, 1)), duration=1.0, dt=h, integrator="timestepping"
    )
    for b in range(B):
        mu = batch.element(b).metadata["parameters"]["ground_friction"]
        travelled = batch.q[b, -1, 0] - scene.q0[0]
        assert abs(travelled - 2.0**2 / (2 * mu * 9.81)) < 2.0 * h
        assert abs(batch.v[b, -1, 0]) < 1e-9  # at rest by the end


def test_a_drawn_mass_scales_a_spring_pendulum_s_period_as_its_square_root() -> None:
    """A body on a spring without gravity: T = 2π √(I/k); every body's mass and inertia × s (one draw) makes T × √s."""
    tables = {
        "robot": {"source": "double_pendulum", "damping": False},
        "gravity": [0.0, 0.0, 0.0],
        "lock": {"joint2": 0.0},
        "joints": {"joint1": {"stiffness": 40.0}},
        "randomize": {"seed": 1, "parameter": [{**uniform("mass", 0.5, 2.0, scale=True), "shared": True}]},
    }
    scene = ms.make_scene(**tables)

    def period(system: ms.Robot) -> float:
        traj = ms.simulate(system, [0.1], [0.0], duration=3.0, dt=1e-4, integrator="rk4")
        q, t = traj.q[:, 0], traj.t
        up = np.flatnonzero((q[:-1] < 0) & (q[1:] >= 0))
        crossings = t[up] - q[up] * (t[up + 1] - t[up]) / (q[up + 1] - q[up])
        return float(np.mean(np.diff(crossings)))

    nominal = period(scene.with_parameters(None))
    for b in range(3):
        parameters = scene.draw_parameters(b)
        s = parameters["mass"]["link1"] / scene.nominal_parameters["mass"]["link1"]
        assert period(scene.with_parameters(parameters)) == pytest.approx(nominal * math.sqrt(s), rel=1e-6)


def test_drawn_values_are_the_values_declared() -> None:
    """A row's drawn values give the dynamics of the scene that declares them (payload, joint damping, friction
    and armature, object mass, ground friction): the two paths agree bit for bit."""
    base = {
        "robot": {"source": "ur5"},
        "payload": [{"frame": "tool0", "mass": 1.0, "com": [0, 0, 0.05], "inertia": [1e-3, 1e-3, 2e-3, 0, 0, 0]}],
        "joints": {"shoulder_lift_joint": {"damping": 0.5}},
    }
    randomized = ms.make_scene(
        **base,
        randomize={
            "parameter": [
                uniform("payload_mass", 0.5, 3.0),
                uniform("damping", 0.1, 1.0, joints="elbow_joint"),
                uniform("friction", 0.1, 1.0, joints="wrist_1_joint"),
                uniform("armature", 0.01, 0.1, joints="wrist_2_joint"),
            ]
        },
    )
    p = randomized.draw_parameters(3)
    m = p["payload_mass"]["0"]
    declared = ms.make_scene(
        robot={"source": "ur5"},
        payload=[
            {"frame": "tool0", "mass": m, "com": [0, 0, 0.05], "inertia": [1e-3 * m, 1e-3 * m, 2e-3 * m, 0, 0, 0]}
        ],
        joints={
            "shoulder_lift_joint": {"damping": 0.5},
            "elbow_joint": {"damping": p["damping"]["elbow_joint"]},
            "wrist_1_joint": {"friction": p["friction"]["wrist_1_joint"]},
            "wrist_2_joint": {"armature": p["armature"]["wrist_2_joint"]},
        },
    )
    variant = randomized.with_parameters(p)
    q0, v0 = variant.q0, np.linspace(-0.5, 0.5, 6)
    a = ms.simulate(variant, q0, v0, duration=0.05, dt=1e-3)
    b = ms.simulate(declared, q0, v0, duration=0.05, dt=1e-3)
    np.testing.assert_array_equal(a.q, b.q)
    np.testing.assert_array_equal(a.v, b.v)


def test_drawn_contact_and_motor_constants_are_the_values_declared() -> None:
    """The coefficients of contacts between bodies (a box sliding on a box) and an actuator's velocity limit and
    torque-speed curve (ur5's motors), drawn and declared: the same dynamics bit for bit."""
    boxes = {
        "ground": {"friction": 0.8},
        "contact": {"pairs": "all"},
        "object": [
            {"name": "base", "shape": "box", "size": [0.6, 0.6, 0.1], "mass": 5.0, "position": [0, 0, 0.05]},
            {
                "name": "top",
                "shape": "box",
                "size": [0.2, 0.2, 0.1],
                "mass": 1.0,
                "position": [0, 0, 0.15],
                "velocity": [1.0, 0.0, -0.2, 0.0, 0.0, 0.0],
            },
        ],
    }
    drawn_boxes = ms.make_scene(
        **boxes,
        randomize={"parameter": [uniform("body_friction", 0.2, 0.8), uniform("body_restitution", 0.0, 0.5)]},
    )
    p = drawn_boxes.draw_parameters(1)
    coefficients = {"body_friction": p["body_friction"], "body_restitution": p["body_restitution"]}
    declared_boxes = ms.make_scene(**{**boxes, "contact": {"pairs": "all", **coefficients}})
    motors = {
        "robot": {"source": "ur5"},
        "actuator": [{"joints": "*", "velocity_limit": 2.0, "stall_torque": 40.0, "no_load_speed": 3.0}],
    }
    drawn_motors = ms.make_scene(
        **motors,
        randomize={
            "parameter": [
                uniform("velocity_limit", 0.5, 1.5, scale=True),
                uniform("stall_torque", 0.5, 1.5, scale=True),
                uniform("no_load_speed", 0.5, 1.5, scale=True),
            ]
        },
    )
    m = drawn_motors.draw_parameters(2)
    names = [item.joint for item in drawn_motors.actuators.items]
    declared_motors = ms.make_scene(
        robot=motors["robot"],
        actuator=motors["actuator"]
        + [
            {"joints": n, **{key: m[key][n] for key in ("velocity_limit", "stall_torque", "no_load_speed")}}
            for n in names
        ],
    )
    command = np.array([30.0, -30.0, 20.0, 10.0, 10.0, 5.0])
    for drawn, declared, values, settings in [
        (drawn_boxes, declared_boxes, p, {"integrator": "timestepping"}),
        (drawn_motors, declared_motors, m, {"integrator": "rk4", "controller": lambda t, q, v: command}),
    ]:
        variant = drawn.with_parameters(values)
        a = ms.simulate(variant, variant.q0, variant.v0, duration=0.1, dt=1e-3, **settings)
        b = ms.simulate(declared, declared.q0, declared.v0, duration=0.1, dt=1e-3, **settings)
        assert_same_run(a, b)
        # the draw matters: the declared values give another run
        c = ms.simulate(drawn, drawn.q0, drawn.v0, duration=0.1, dt=1e-3, **settings)
        assert not np.array_equal(a.v, c.v)


# ---- a row re-run alone: bit for bit -------------------------------------------------------------------------
RANDOM_ARM = {
    "robot": {"source": "ur5"},
    "randomize": {
        "seed": 3,
        "parameter": [
            uniform("mass", 0.8, 1.25, scale=True),
            uniform("inertia", 0.9, 1.1, scale=True),
            uniform("damping", 0.0, 0.5),
            uniform("friction", 0.0, 0.3, joints=["shoulder_*", "elbow_joint"]),
            uniform("armature", 0.0, 0.02),
        ],
    },
}


def rerun(batch: Any, scene: ms.Scene, b: int, **settings: Any) -> Trajectory:
    """Element b run alone on the scene with its drawn values."""
    element = batch.element(b)
    variant = scene.with_parameters(element.metadata["parameters"])
    return ms.simulate(variant, element.q[0], element.v[0], **settings)


@pytest.mark.parametrize("kernel", ["python", pytest.param("native", marks=needs_native)])
def test_a_randomised_arm_row_re_run_alone_is_bit_for_bit(kernel: str, monkeypatch: pytest.MonkeyPatch) -> None:
    scene = ms.make_scene(**RANDOM_ARM)
    rng = np.random.default_rng(0)
    B = 5
    Q = np.array([scene.random_configuration(rng) for _ in range(B)])
    settings = {"duration": 0.1, "dt": 1e-3, "integrator": "rk4"}
    controller = ms.PD(scene, q_ref=scene.q0, kp=50.0)

    def run() -> tuple[Any, list[Trajectory]]:
        batch = ms.rollout(scene, Q, np.zeros((B, 6)), controller=controller, num_threads=2, **settings)
        return batch, [rerun(batch, scene, b, controller=controller, **settings) for b in range(B)]

    batch, alone = on_kernel(kernel == "native", run, monkeypatch)
    assert batch.metadata["kernel"] == ("native" if kernel == "native" else "python (row)")
    for b in range(B):
        assert_same_run(batch.element(b), alone[b])
    assert len({p["mass"]["shoulder_link"] for p in batch.metadata["parameters"]}) == B


@needs_native
def test_randomised_rows_are_the_same_on_both_kernels(monkeypatch: pytest.MonkeyPatch) -> None:
    scene = ms.make_scene(**RANDOM_ARM)
    B = 4
    Q = np.tile(scene.q0, (B, 1)) + 0.1
    nat, py = both(lambda: ms.rollout(scene, Q, np.zeros((B, 6)), duration=0.05, dt=1e-3), monkeypatch)
    assert nat.metadata["kernel"] == "native" and py.metadata["kernel"] == "python (row)"
    for b in range(B):
        assert_same_run(nat.element(b), py.element(b))


@pytest.mark.parametrize("kernel", ["python", pytest.param("native", marks=needs_native)])
def test_a_randomised_contact_row_re_run_alone_is_bit_for_bit(kernel: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """go2 standing, its bodies' masses and the ground's friction and restitution drawn per row."""
    tables = shipped("go2_standing")
    tables["randomize"] = {
        "seed": 9,
        "parameter": [
            uniform("mass", 0.85, 1.15, scale=True),
            uniform("ground_friction", 0.4, 1.0),
            uniform("ground_restitution", 0.0, 0.3),
        ],
    }
    scene = ms.make_scene(**tables)
    B = 3
    settings = {"duration": 0.06, "dt": 1e-3, "integrator": "timestepping"}
    controller = scene.make_controller()

    def run() -> tuple[Any, list[Trajectory]]:
        batch = ms.rollout(
            scene, np.tile(scene.q0, (B, 1)), np.zeros((B, scene.nv)), controller=controller, num_threads=2, **settings
        )
        return batch, [rerun(batch, scene, b, controller=controller, **settings) for b in range(B)]

    batch, alone = on_kernel(kernel == "native", run, monkeypatch)
    assert batch.metadata["kernel"] == ("native" if kernel == "native" else "python (row)")
    for b in range(B):
        assert_same_run(batch.element(b), alone[b])
        mine, its = batch.element(b).contacts, alone[b].contacts
        assert mine is not None and its is not None and mine.bodies == its.bodies
        for part in ("sample", "pair", "point", "normal", "impulse"):
            np.testing.assert_array_equal(getattr(mine, part), getattr(its, part), err_msg=part)
    # the rows differ: their own masses carry them
    assert not np.array_equal(batch.q[0], batch.q[1])


# ur5: position servos on the shoulder and elbow, torque motors on the wrists; their constants drawn per row.
RANDOM_ACTUATORS = {
    "robot": {"source": "ur5"},
    "gravity": [0.0, 0.0, 0.0],
    "actuator": [
        {"joints": "*", "kind": "torque", "gear": 50.0, "rotor_inertia": 2e-5},
        {"joints": ["shoulder_*", "elbow_joint"], "kind": "position", "kp": 400.0, "kv": 20.0},
    ],
    "randomize": {
        "seed": 2,
        "parameter": [
            uniform("kp", 0.5, 2.0, scale=True, joints=["shoulder_*", "elbow_joint"]),
            uniform("kv", 0.5, 2.0, scale=True, joints=["shoulder_*", "elbow_joint"]),
            uniform("gear", 30.0, 80.0),
            uniform("rotor_inertia", 1e-5, 4e-5),
            uniform("effort_limit", 2.0, 5.0, joints="wrist_*"),
        ],
    },
}


@pytest.mark.parametrize("integrator", ["semi_implicit_euler", "rk4"])
@pytest.mark.parametrize("kernel", ["python", pytest.param("native", marks=needs_native)])
def test_randomised_actuator_constants_reach_each_row(
    kernel: str, integrator: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Servo gains, gears, rotor inertias and effort limits drawn per row: at rest at q0 a position servo delivers
    -kp q0 (its target 0), a wrist motor commanded 100 N·m its drawn effort limit; each row re-run alone is bit for
    bit (semi-implicit Euler takes the servos inside the step on the row's own armature gear² I)."""
    scene = ms.make_scene(**RANDOM_ACTUATORS)
    B, q0 = 4, np.array([0.1, -0.15, 0.2, 0.3, -0.2, 0.1])
    command = np.array([0.0, 0.0, 0.0, 100.0, 100.0, 100.0])
    settings = {"duration": 0.02, "dt": 1e-3, "integrator": integrator, "controller": lambda t, q, v: command}

    def run() -> tuple[Any, list[Trajectory]]:
        batch = ms.rollout(scene, np.tile(q0, (B, 1)), np.zeros((B, 6)), num_threads=2, **settings)
        return batch, [rerun(batch, scene, b, **settings) for b in range(B)]

    batch, alone = on_kernel(kernel == "native", run, monkeypatch)
    assert batch.metadata["kernel"] == ("native" if kernel == "native" else "python (row)")
    names = [item.joint for item in scene.actuators.items]
    for b in range(B):
        element, p = batch.element(b), batch.metadata["parameters"][b]
        assert_same_run(element, alone[b])
        kp = np.array([p["kp"][name] for name in names[:3]])
        np.testing.assert_allclose(element.tau[0, :3], -kp * q0[:3], rtol=1e-14)
        np.testing.assert_array_equal(element.tau[0, 3:], [p["effort_limit"][name] for name in names[3:]])
        armature = np.array([p["gear"][name] ** 2 * p["rotor_inertia"][name] for name in names])
        np.testing.assert_allclose(scene.with_parameters(p).model.armature, armature, rtol=1e-14)
    assert len({p["kp"]["shoulder_pan_joint"] for p in batch.metadata["parameters"]}) == B


@needs_native
def test_randomised_actuator_rows_are_the_same_on_both_kernels(monkeypatch: pytest.MonkeyPatch) -> None:
    """Wrist commands of 3.5 N·m: inside the declared effort limits, outside some rows' drawn ones (2 to 5 N·m), so
    rows saturate differently (counted per row on both kernels)."""
    scene = ms.make_scene(**RANDOM_ACTUATORS)
    B = 4
    taus = np.tile([0.2, -0.1, 0.3, 3.5, -3.5, 3.5], (B, 30, 1))
    settings = {"duration": 0.03, "dt": 1e-3, "integrator": "semi_implicit_euler"}
    nat, py = both(lambda: ms.rollout(scene, np.zeros((B, 6)), np.zeros((B, 6)), taus=taus, **settings), monkeypatch)
    assert nat.metadata["kernel"] == "native" and py.metadata["kernel"] == "python (row)"
    for b in range(B):
        assert_same_run(nat.element(b), py.element(b))
    assert not np.array_equal(nat.q[0], nat.q[1])
    assert 0 < np.count_nonzero(nat.stats["saturated_controls"]) < B


def test_a_saved_row_keeps_its_parameters(tmp_path: Any) -> None:
    scene = ms.make_scene(**PUSHED_BOX, randomize={"parameter": [uniform("mass", 0.5, 4.0)]})
    settings = {"duration": 0.02, "dt": 1e-3, "integrator": "timestepping"}
    batch = ms.rollout(scene, np.tile(scene.q0, (2, 1)), np.zeros((2, 6)), **settings)
    element = batch.element(1)
    element.save(tmp_path / "row.npz")
    loaded = Trajectory.load(tmp_path / "row.npz")
    assert loaded.metadata["parameters"] == element.metadata["parameters"] == batch.metadata["parameters"][1]
    again = ms.simulate(scene.with_parameters(loaded.metadata["parameters"]), scene.q0, np.zeros(6), **settings)
    assert again.metadata["parameters"] == loaded.metadata["parameters"]
    assert_same_run(again, element)


def test_rollout_takes_a_table_or_none() -> None:
    scene = ms.make_scene(**PUSHED_BOX, randomize={"seed": 1, "parameter": [uniform("mass", 0.5, 4.0)]})
    Q, V = np.tile(scene.q0, (2, 1)), np.zeros((2, 6))
    settings = {"duration": 0.01, "dt": 1e-3, "integrator": "timestepping"}
    plain = ms.rollout(scene, Q, V, randomize=False, **settings)
    assert "parameters" not in plain.metadata and "parameters" not in plain.element(0).metadata
    other = ms.rollout(scene, Q, V, randomize={"seed": 2, "parameter": [uniform("mass", 5.0, 6.0)]}, **settings)
    assert all(5.0 <= p["mass"]["box"] <= 6.0 for p in other.metadata["parameters"])
    with pytest.raises(InvalidArgumentError) as caught:
        ms.rollout(scene, Q, V, randomize={"parameter": [uniform("mas", 1, 2)]}, **settings)
    assert str(caught.value).startswith("rollout: randomize.parameter[0].name: must be one of armature,")
    with pytest.raises(InvalidArgumentError) as caught:
        ms.rollout(scene, Q, V, randomize=[1], **settings)
    assert str(caught.value).startswith("randomize must be None (the scene's own [randomize]), False (none) or a dict")
    robot = ms.load_robot("double_pendulum")
    with pytest.raises(InvalidArgumentError) as caught:
        ms.rollout(robot, np.zeros((1, 2)), np.zeros((1, 2)), randomize={"parameter": []}, **settings)
    assert str(caught.value) == (
        "randomize draws a scene's parameters: the system must be a Scene (load_scene, make_scene), got a Robot"
    )


def test_an_adaptive_randomised_rollout_runs_each_row_on_its_own_values() -> None:
    scene = ms.make_scene(
        robot={"source": "double_pendulum"}, randomize={"parameter": [uniform("mass", 0.5, 2.0, scale=True)]}
    )
    Q = np.tile([0.3, -0.2], (3, 1))
    settings = {"duration": 0.2, "dt": 1e-3, "integrator": "dp54", "rtol": 1e-8, "atol": 1e-10}
    batch = ms.rollout(scene, Q, np.zeros((3, 2)), **settings)
    assert len(batch.metadata["parameters"]) == 3
    for b in range(3):
        assert_same_run(batch.element(b), rerun(batch, scene, b, **settings))


@pytest.mark.parametrize(
    "method",
    [{"integrator": "rk4"}, {"integrator": "dp54", "rtol": 1e-8, "atol": 1e-10}],  # one run over all rows; one per row
)
def test_an_interrupted_randomised_rollout_keeps_every_row_s_parameters(method: dict[str, Any]) -> None:
    # A Ctrl-C keeps each element's drawn values, as a finished rollout does: element b's are its own, not row 0's.
    scene = ms.make_scene(
        robot={"source": "double_pendulum"}, randomize={"parameter": [uniform("mass", 0.5, 2.0, scale=True)]}
    )
    Q, V = np.tile([0.3, -0.2], (3, 1)), np.zeros((3, 2))
    settings = {"duration": 0.05, "dt": 1e-3, **method}
    drawn = ms.rollout(scene, Q, V, **settings).metadata["parameters"]
    assert drawn == [scene.draw_parameters(b) for b in range(3)] and drawn[0] != drawn[1] != drawn[2]

    with pytest.raises(ms.SimulationInterrupted) as caught:
        ms.rollout(scene, Q, V, controller=ctrl_c_at(0.0095, 2), **settings)
    batch = caught.value.trajectory
    assert batch.metadata["parameters"] == drawn
    for b in range(3):
        assert batch.element(b).metadata["parameters"] == drawn[b]


# ---- per gym reset -----------------------------------------------------------------------------------------------
def test_each_gym_episode_draws_its_own_scene() -> None:
    gym = pytest.importorskip("multibody_sim.gym")
    tables = {**shipped("sliding_box"), "randomize": {"seed": 0, "parameter": [uniform("ground_friction", 0.5, 1.0)]}}
    scene = ms.make_scene(**tables)
    settings = {
        "reward": lambda q, v, tau: 0.0,
        "dt": 1e-3,
        "control_dt": 0.01,
        "reset_noise_q": 0.0,
        "reset_noise_v": 0.0,
    }
    env = gym.MultibodyEnv(scene, **settings)
    _, first = env.reset(seed=4)
    _, second = env.reset()
    _, again = env.reset(seed=4)
    assert first["parameters"] == again["parameters"] != second["parameters"]
    for _ in range(50):  # 0.5 s: the box stops where its episode's friction says
        observation, *_ = env.step(np.zeros(6))
    mu = again["parameters"]["ground_friction"]
    assert abs(observation[0] - 2.0**2 / (2 * mu * 9.81)) < 2e-3
    # The vector environment: each row draws from its own generator, as the single environment seeded seed + i.
    vector = gym.MultibodyVectorEnv(scene, 3, **settings)
    _, infos = vector.reset(seed=4)
    drawn = infos["parameters"]["ground_friction"]
    assert drawn[0] == first["parameters"]["ground_friction"]
    for i in range(1, 3):
        _, info = env.reset(seed=4 + i)
        assert drawn[i] == info["parameters"]["ground_friction"]
    for _ in range(50):
        observations, *_ = vector.step(np.zeros((3, 6)))
    np.testing.assert_allclose(observations[:, 0], 2.0**2 / (2 * drawn * 9.81), atol=2e-3)
    plain = gym.MultibodyEnv(scene, randomize=False, **settings)
    assert "parameters" not in plain.reset(seed=4)[1]


def test_a_wrist_force_torque_sensor_weighs_the_drawn_masses() -> None:
    """panda held at rest by its own gravity torque, every body's mass x s (one draw) and a drawn payload m at the
    hand: a force-torque sensor at the hand's mounting (inside link 7's body, welded to it: it sums the links after
    it, the finger joints' bodies and the payloads there) reads (s (m_hand + 2 m_finger) + m) g, the link masses
    read from the URDF file."""
    import pinocchio as pin

    scene = ms.make_scene(
        robot={"source": "panda"},
        payload=[{"frame": "panda_hand_tcp", "mass": 1.0, "com": [0.08, 0.0, 0.0]}],
        sensor=[
            {"name": "wrist", "kind": "force_torque", "frame": "panda_hand_joint"},
            {"name": "mount", "kind": "frame_pose", "frame": "panda_hand_joint"},
        ],
        randomize={
            "parameter": [
                {**uniform("mass", 0.7, 1.4, scale=True), "shared": True},
                uniform("payload_mass", 0.5, 3.0),
            ]
        },
    )
    import xml.etree.ElementTree as ET

    links = ET.parse(scene.full_robot.source["urdf_path"]).getroot().iter("link")
    masses = {link.get("name"): float(link.find("inertial/mass").get("value")) for link in links}  # type: ignore[union-attr]
    distal = masses["panda_hand"] + masses["panda_leftfinger"] + masses["panda_rightfinger"]
    nominal = scene.nominal_parameters["mass"]
    for b in range(2):
        drawn = scene.draw_parameters(b)
        s = drawn["mass"]["panda_leftfinger"] / nominal["panda_leftfinger"]
        variant = scene.with_parameters(drawn)
        q = variant.q0
        gravity = pin.computeGeneralizedGravity(variant.model, variant.data, q).copy()
        traj = ms.simulate(
            variant, q, np.zeros(variant.nv), duration=0.02, dt=1e-3, controller=lambda t, q, v, g=gravity: g
        )
        x, y, z, w = traj.sensors["mount"][-1, 3:]
        force = pin.Quaternion(w, x, y, z).matrix() @ traj.sensors["wrist"][-1, :3]
        expected = (s * distal + drawn["payload_mass"]["0"]) * 9.81
        np.testing.assert_allclose(force, [0.0, 0.0, expected], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("kernel", ["python", pytest.param("native", marks=needs_native)])
def test_randomised_rows_with_sensors_read_their_own_masses(kernel: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A rollout's rows measure with their own scenes' sensors (a force-torque sensor's cut masses are drawn):
    each row's readings equal its re-run alone, bit for bit, and the rows' readings differ, on either kernel (the
    engine measures each row with its own sensors: RowPhysics.sensors)."""
    scene = ms.make_scene(
        robot={"source": "ur5"},
        payload=[{"frame": "tool0", "mass": 1.0, "com": [0, 0, 0.05], "inertia": [1e-3, 1e-3, 2e-3, 0, 0, 0]}],
        sensor=[{"name": "wrist", "kind": "force_torque", "frame": "tool0"}],
        randomize={"parameter": [uniform("payload_mass", 0.5, 3.0), uniform("mass", 0.9, 1.1, scale=True)]},
    )
    B = 3
    settings = {"duration": 0.02, "dt": 1e-3, "integrator": "rk4", "controller": ms.PD(scene, q_ref=scene.q0, kp=50.0)}

    def run() -> tuple[Any, list[Trajectory]]:
        batch = ms.rollout(scene, np.tile(scene.q0, (B, 1)), np.zeros((B, 6)), **settings)
        return batch, [rerun(batch, scene, b, **settings) for b in range(B)]

    batch, alone = on_kernel(kernel == "native", run, monkeypatch)
    assert batch.metadata["kernel"] == ("native" if kernel == "native" else "python (row)")
    for b in range(B):
        assert_same_run(batch.element(b), alone[b])
        np.testing.assert_array_equal(batch.element(b).sensors["wrist"], alone[b].sensors["wrist"])
    assert not np.array_equal(batch.element(0).sensors["wrist"][0], batch.element(1).sensors["wrist"][0])


# ---- a row built as a variant of its scene is the scene built alone ---------------------------------------------
VARIANT_SCENES = {
    "arm": (RANDOM_ARM, {"integrator": "rk4"}),
    "actuators": (RANDOM_ACTUATORS, {"integrator": "semi_implicit_euler"}),
    "go2": (
        {
            **shipped("go2_standing"),
            "randomize": {
                "seed": 4,
                "parameter": [
                    uniform("mass", 0.85, 1.15, scale=True),
                    uniform("inertia", 0.9, 1.1, scale=True),
                    uniform("ground_friction", 0.4, 1.0),
                    uniform("ground_restitution", 0.0, 0.3),
                ],
            },
        },
        {"integrator": "timestepping"},
    ),
    # the catalog's motors, their velocity limits drawn: the time-stepper's velocity-limit rows take the row's
    "go2_motors": (
        {
            **shipped("go2_standing"),
            "actuators": "catalog",
            "randomize": {
                "seed": 8,
                "parameter": [
                    uniform("mass", 0.9, 1.1, scale=True),
                    uniform("velocity_limit", 0.05, 0.2, scale=True),
                    uniform("effort_limit", 0.8, 1.0, scale=True),
                ],
            },
        },
        {"integrator": "timestepping"},
    ),
    # a locked joint, a payload, a sensor, a free object on the ground, exact joint friction, body coefficients
    "locked": (
        {
            "robot": {"source": "ur5"},
            "lock": {"wrist_3_joint": 0.3},
            "payload": [{"frame": "wrist_2_link", "mass": 1.0, "com": [0, 0, 0.05]}],
            "sensor": [{"name": "wrist", "kind": "force_torque", "frame": "wrist_2_link"}],
            "ground": {"friction": 0.8},
            "contact": {"friction": "exact", "robot_geometry": "declared", "pairs": "all"},
            "object": [{"name": "box", "shape": "box", "size": [0.2, 0.2, 0.2], "mass": 2.0, "position": [0.6, 0, 0.1]}],
            "randomize": {
                "seed": 5,
                "parameter": [
                    uniform("mass", 0.8, 1.2, scale=True),
                    uniform("payload_mass", 0.5, 3.0),
                    uniform("friction", 0.1, 0.4, joints=["shoulder_*"]),
                    uniform("damping", 0.0, 0.5),
                    uniform("armature", 0.0, 0.02),
                    uniform("body_friction", 0.2, 0.9),
                    uniform("body_restitution", 0.0, 0.5),
                ],
            },
        },
        {"integrator": "timestepping"},
    ),
}


@pytest.mark.parametrize("case", sorted(VARIANT_SCENES))
def test_a_variant_row_is_its_scene_built_alone(case: str) -> None:
    """with_parameters builds a row from its scene (taking the joints' structure from it, checking nothing again):
    the same model (Pinocchio's archive, byte for byte), arrays, elements, contact and actuators (their native data)
    and the same run, bit for bit, as the row's declaration built alone by the constructor (robot loaded again)."""
    import dataclasses

    from multibody_sim.native import model_bytes

    tables, settings = VARIANT_SCENES[case]
    scene = ms.make_scene(**tables)
    for b in range(2):
        drawn = scene.draw_parameters(b)
        variant = scene.with_parameters(drawn)
        alone = ms.Scene(dataclasses.replace(scene.spec, parameters=drawn))
        assert variant.full_robot is scene.full_robot and alone.full_robot is not scene.full_robot
        assert model_bytes(variant.model) == model_bytes(alone.model)
        for name in ("damping", "effort_limit", "velocity_limit", "limit_tolerance", "limit_drift", "q0", "v0"):
            np.testing.assert_array_equal(getattr(variant, name), getattr(alone, name), err_msg=name)
        assert variant.total_mass == alone.total_mass and variant.energy_scale == alone.energy_scale
        assert variant.ledger_elements == alone.ledger_elements and variant.record_fields == alone.record_fields
        assert variant.nominal_parameters == alone.nominal_parameters == scene.nominal_parameters
        assert variant.parameters == alone.parameters == drawn
        for part in ("elements", "contact", "actuators"):
            mine, its = getattr(variant, part), getattr(alone, part)
            assert (mine is None) == (its is None), part
            if mine is not None:
                data = (mine.native_data(model_bytes), its.native_data(model_bytes)) if part == "elements" else (
                    mine.native_data(), its.native_data())
                assert repr(data[0]) == repr(data[1]), part
        if variant.contact is not None:
            assert variant.contact.friction_joints == alone.contact.friction_joints
        run = {"duration": 0.03, "dt": 1e-3, **settings}
        q0 = variant.q0
        a, c = ms.simulate(variant, q0, variant.v0, **run), ms.simulate(alone, q0, alone.v0, **run)
        assert a.metadata["kernel"] == c.metadata["kernel"]
        assert_same_run(a, c)
        for name in a.sensors or {}:
            np.testing.assert_array_equal(a.sensors[name], c.sensors[name], err_msg=name)
    # the rows differ from the declared scene
    assert model_bytes(scene.with_parameters(scene.draw_parameters(0)).model) != model_bytes(scene.model)
    # a variant is of the same declaration, other parameter values only
    other = dataclasses.replace(scene.spec, gravity=(0.0, 0.0, -1.0), parameters=scene.draw_parameters(0))
    with pytest.raises(InvalidArgumentError, match=r"^variant_of must be built from the same declaration"):
        ms.Scene(other, variant_of=scene)


# ur5 whose joints' dry friction is exact (a constraint of the time-stepper: stiction), drawn per row, and its masses.
RANDOM_STICTION = {
    "robot": {"source": "ur5"},
    "ground": {},
    "contact": {"friction": "exact", "robot_geometry": "declared"},
    "randomize": {
        "seed": 6,
        "parameter": [uniform("friction", 0.0, 12.0), uniform("mass", 0.9, 1.1, scale=True)],
    },
}


@needs_native
def test_randomised_exact_joint_friction_runs_natively_bit_for_bit(monkeypatch: pytest.MonkeyPatch) -> None:
    """Rows whose exact joint friction forces are drawn run on the native kernel (each step reads its row's forces),
    bit for bit with the Python kernel and with each row re-run alone; the rows hold or slip as their forces say."""
    scene = ms.make_scene(**RANDOM_STICTION)
    assert scene.contact is not None and len(scene.contact.friction_joints) == 6
    B = 4
    Q = np.tile(scene.q0, (B, 1)) + np.array([0.0, -0.6, 0.9, -0.4, 0.3, 0.0])
    settings = {"duration": 0.05, "dt": 1e-3, "integrator": "timestepping"}

    def run() -> tuple[Any, list[Trajectory]]:
        batch = ms.rollout(scene, Q, np.zeros((B, 6)), num_threads=2, **settings)
        return batch, [rerun(batch, scene, b, **settings) for b in range(B)]

    (nat, nat_alone), (py, _) = both(run, monkeypatch)
    assert nat.metadata["kernel"] == "native" and py.metadata["kernel"] == "python (row)"
    for b in range(B):
        assert_same_run(nat.element(b), py.element(b))
        assert_same_run(nat.element(b), nat_alone[b])
    forces = [[f for _, f in scene.with_parameters(p).contact.friction_joints] for p in nat.metadata["parameters"]]
    assert len({tuple(f) for f in forces}) == B
    moved = np.abs(nat.q[:, -1] - nat.q[:, 0])  # (B, 6): some joints held (to the solver's accuracy), some slipping
    held = moved < 1e-12
    assert held[:, 2].any() and (moved[:, 2] > 1e-4).any()  # the elbow: held in one row, slipping in another


@needs_native
def test_randomised_rows_with_sensors_are_the_same_on_both_kernels(monkeypatch: pytest.MonkeyPatch) -> None:
    """go2 on the ground with an IMU, foot contact forces and a force-torque sensor at its foot (cutting the foot from
    its calf: the cut mass is drawn), its masses and the ground's friction drawn per row, under its own PD controller,
    sensors ticking at 500 Hz with noise: every row's samples and readings on the native kernel equal the Python
    kernel's, bit for bit."""
    tables = shipped("go2_standing")
    tables["sensor"] = [
        {"name": "imu", "kind": "imu", "frame": "base", "noise": 0.01, "seed": 1},
        {"name": "foot", "kind": "contact_force", "body": "FL_foot"},
        {"name": "ankle", "kind": "force_torque", "frame": "FL_foot", "rate": 500.0},
    ]
    tables["randomize"] = {
        "seed": 7,
        "parameter": [uniform("mass", 0.8, 1.2, scale=True), uniform("ground_friction", 0.4, 1.0)],
    }
    scene = ms.make_scene(**tables)
    B = 3
    settings = {"duration": 0.03, "dt": 1e-3, "integrator": "timestepping", "controller": scene.make_controller()}

    def run() -> Any:
        Q = np.tile(scene.q0, (B, 1))
        return ms.rollout(scene, Q, np.zeros((B, scene.nv)), num_threads=2, **settings)

    nat, py = both(run, monkeypatch)
    assert nat.metadata["kernel"] == "native" and py.metadata["kernel"] == "python (row)"
    for b in range(B):
        assert_same_run(nat.element(b), py.element(b))
        for name in ("imu", "foot", "ankle"):
            np.testing.assert_array_equal(nat.element(b).sensors[name], py.element(b).sensors[name], err_msg=name)
    ankles = [nat.element(b).sensors["ankle"][-1] for b in range(B)]
    assert not np.array_equal(ankles[0], ankles[1])  # each row's own cut masses


@needs_native
def test_the_engine_refuses_rows_whose_sensors_measure_other_things() -> None:
    """A row's own sensors must measure what the engine's do, at the same places (only their cuts' masses may
    differ): the engine refuses others in one line, whichever of set_rows and set_sensors comes first."""
    from multibody_sim.integrators import INTEGRATORS
    from multibody_sim.kernels.native import NativeKernel
    from multibody_sim.step_control import ConstantStep

    def arm(frame: str) -> ms.Scene:
        return ms.make_scene(robot={"source": "ur5"}, sensor=[{"name": "s", "kind": "force_torque", "frame": frame}])

    scene, other = arm("tool0"), arm("wrist_1_link")
    Q, V = np.tile(scene.q0, (2, 1)), np.zeros((2, 6))
    for rows, fails in (([scene, scene], False), ([scene, other], True)):
        kernel = NativeKernel(scene, INTEGRATORS["rk4"], Q, V, systems=rows)
        kernel.bind(ConstantStep(1e-3))
        if fails:
            with pytest.raises(ValueError, match="a row's sensors disagree with the engine's"):
                kernel.set_sensors(scene.sensors, 1, np.zeros(2, dtype=int))
        else:
            kernel.set_sensors(scene.sensors, 1, np.zeros(2, dtype=int))
            with pytest.raises(ValueError, match="a row's sensors disagree with the engine's"):
                kernel.engine.set_rows([kernel._row_physics(row) for row in (scene, other)])


@needs_native
def test_a_vector_env_s_rows_keep_their_physics_through_other_rows_resets() -> None:
    """A randomised vector environment makes its engine again at every reset, reusing the rows' rendered physics
    (kernels/native._RENDERED): rows not reset keep stepping on their own drawn physics, a reset row on its new
    draw, each bit for bit as a single environment seeded as that row."""
    gym = pytest.importorskip("multibody_sim.gym")
    scene = ms.make_scene(**RANDOM_ARM)
    settings = {"reward": lambda q, v, tau: 0.0, "dt": 1e-3, "control_dt": 5e-3}
    vector = gym.MultibodyVectorEnv(scene, 3, **settings)
    singles = [gym.MultibodyEnv(scene, **settings) for _ in range(3)]
    observed, _ = vector.reset(seed=11)
    for i, env in enumerate(singles):
        np.testing.assert_array_equal(env.reset(seed=11 + i)[0], observed[i])
    rng = np.random.default_rng(1)
    for k in range(12):
        if k == 4:  # row 1 alone starts a new episode, on a new draw
            observed, infos = vector.reset(options={"reset_mask": np.array([False, True, False])})
            single, info = singles[1].reset()
            assert info["parameters"]["mass"]["shoulder_link"] == infos["parameters"]["mass"]["shoulder_link"][1]
            np.testing.assert_array_equal(single, observed[1])
        actions = rng.uniform(-5.0, 5.0, (3, 6))
        observed, *_ = vector.step(actions)
        assert vector.stepper._core.kernel.__class__.__name__ == "NativeKernel"
        for i, env in enumerate(singles):
            np.testing.assert_array_equal(env.step(actions[i])[0], observed[i], err_msg=f"step {k}, row {i}")


@needs_native
def test_randomised_velocity_limits_are_the_same_on_both_kernels(monkeypatch: pytest.MonkeyPatch) -> None:
    """go2 with the catalog's motors under random torques, their velocity limits (rows of the time-stepper's contact
    problem) and effort limits drawn per row far below the declared ones: the native rows equal the Python kernel's
    bit for bit, and the joints keep to each row's own limits."""
    tables, _ = VARIANT_SCENES["go2_motors"]
    scene = ms.make_scene(**tables)
    B, n = 3, 40
    taus = np.zeros((B, n, scene.nv))
    taus[:, :, 6:] = np.random.default_rng(3).uniform(-20.0, 20.0, (B, n, scene.nv - 6))
    settings = {"duration": n * 1e-3, "dt": 1e-3, "integrator": "timestepping", "taus": taus}

    def run() -> Any:
        return ms.rollout(scene, np.tile(scene.q0, (B, 1)), np.zeros((B, scene.nv)), num_threads=2, **settings)

    nat, py = both(run, monkeypatch)
    assert nat.metadata["kernel"] == "native" and py.metadata["kernel"] == "python (row)"
    for b in range(B):
        assert_same_run(nat.element(b), py.element(b))
        row = scene.with_parameters(nat.metadata["parameters"][b])
        assert row.contact is not None and row.contact.speed_limits
        for jid, vmax, _ in row.contact.speed_limits:
            v = nat.element(b).v[:, row.model.joints[jid].idx_v]
            assert np.abs(v).max() <= vmax * (1 + 1e-6) + 1e-9, row.model.names[jid]
        assert any(np.abs(nat.element(b).v[:, row.model.joints[jid].idx_v]).max() > 0.5 * vmax
                   for jid, vmax, _ in row.contact.speed_limits)  # the limits bind
