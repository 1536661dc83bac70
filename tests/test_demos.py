"""The shipped scenes as demos: each stays within its joint limits when run as declared, panda_push does what its
description says, and a limit report tells a held joint's round-off from a violation."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

import multibody_sim as ms
from multibody_sim.scenes import shipped_scenes
from multibody_sim.scenes.scene import HELD_DRIFT_RATE


@pytest.mark.parametrize("name", sorted(shipped_scenes()))
def test_a_shipped_scene_stays_within_its_limits(name: str) -> None:
    run = ms.load_scene(name).run()
    assert run.status == "completed"
    assert run.limit_violations.count == 0, run.limit_violations.describe()


def test_panda_push_does_what_its_description_says() -> None:
    """ "pushes a 0.5 kg box 30 cm ... tracking a computed-torque trajectory to within 0.02 rad and inside its joint
    limits": the box's displacement and the controller's own log, against the numbers the description gives."""
    scene = ms.load_scene("panda_push")
    description = scene.spec.description
    assert "0.5 kg box 30 cm" in description and "within 0.02 rad" in description
    controller = scene.make_controller()
    settings = scene.simulation_settings(controller=False)
    q0, v0 = settings.pop("q0"), settings.pop("v0")
    run = ms.simulate(scene, q0, v0, controller=controller, **settings)
    box = scene.model.joints[scene.model.getJointId("box")].idx_q
    pushed = run.q[-1, box] - run.q[0, box]
    assert 0.29 < pushed < 0.31, pushed
    log = controller.tracking_error()
    assert log.position_error.shape[1] == scene.actuated.stop  # the box's coordinates are not tracked
    assert log.max_position_error < 0.02
    assert run.limit_violations.count == 0
    # The sphere between the fingers is at mid-height of the box (z = 0.05 m) during the push: a reference that dips
    # into the ground (as the 4-waypoint spline did, to z = -0.017 m) would stall the arm against it.
    frame = scene.model.getFrameId("panda_hand")
    data = scene.model.createData()
    heights = []
    for t in np.arange(2.0, 4.0, 0.01):
        pin.framesForwardKinematics(scene.model, data, controller.reference(t)[0])
        heights.append(data.oMf[frame].act(np.array([0.0, 0.0, 0.1]))[2])
    assert min(heights) > 0.04 and max(heights) < 0.06


def test_talos_standing_reports_no_violation_for_its_grippers_round_off() -> None:
    """Its grippers rest on their stops, held by exact dry friction: the contact solve moves them by its own
    accuracy (the right one 1.1e-12 rad past its stop at 8 ms), which 8 machine epsilons (1.9e-15 rad) alone would
    call a violation; the allowance grows at HELD_DRIFT_RATE, the solver's tolerance."""
    scene = ms.load_scene("talos_standing")
    run = scene.run()
    assert run.limit_violations.count == 0, run.limit_violations.describe()
    grippers = [scene.model.joints[scene.model.getJointId(f"gripper_{side}_joint")].idx_q for side in ("left", "right")]
    excess = np.maximum(run.q[:, grippers] - scene.upper_limit[grippers], 0.0)
    assert excess.max() > scene.limit_tolerance[grippers].max()  # beyond the round-off of one evaluation...
    assert np.all(excess <= HELD_DRIFT_RATE * run.t[:, None])  # ...and within what the solve's accuracy allows by then


def test_a_held_joint_past_its_drift_is_a_violation() -> None:
    """The allowance grows with time at HELD_DRIFT_RATE on held coordinates only: a held gripper 10 times the
    allowance past its stop after 1 s is reported, and so is any coordinate of a robot past 8 epsilons."""
    scene = ms.load_scene("talos_standing")
    gripper = scene.model.joints[scene.model.getJointId("gripper_left_joint")].idx_q
    assert scene.limit_drift[gripper] == HELD_DRIFT_RATE
    q = scene.q0.copy()
    q[gripper] = scene.upper_limit[gripper] + 10 * HELD_DRIFT_RATE
    assert scene.limit_excess(q[None], t=np.array([1.0]))[0, gripper] == pytest.approx(10 * HELD_DRIFT_RATE)
    q[gripper] = scene.upper_limit[gripper] + 0.5 * HELD_DRIFT_RATE
    assert scene.limit_excess(q[None], t=np.array([1.0]))[0, gripper] == 0.0  # within 1 s of drift
    assert scene.limit_excess(q[None], t=np.array([0.1]))[0, gripper] > 0.0  # beyond 0.1 s of it
    assert not ms.load_robot("talos").limit_drift.any()  # a robot without a scene holds nothing
