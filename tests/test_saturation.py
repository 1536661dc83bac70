"""Actuators saturate at the URDF's effort limits: the applied torque is clipped, counted and reported."""

from __future__ import annotations

import numpy as np

import multibody_sim as ms


def test_torques_are_clipped_at_the_effort_limits_and_counted(robot) -> None:
    ur5 = robot("ur5")
    limits = ur5.effort_limit
    assert np.all(np.isfinite(limits)) and np.all(limits > 0)
    requested: list[np.ndarray] = []

    def stiff_pd(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        tau = 2000.0 * (0.5 - q) - 50.0 * v  # asks for far more than the motors give at first
        requested.append(tau)
        return tau

    traj = ms.simulate(ur5, ur5.neutral(), np.zeros(6), duration=0.3, dt=1e-3, controller=stiff_pd)
    raw = np.array(requested)
    over = np.abs(raw) > limits
    assert over.any() and not over.all()  # some calls saturate, others do not
    # The applied torque is the requested one clipped to the limits (the last row repeats the last applied).
    np.testing.assert_array_equal(traj.tau[:-1], np.clip(raw, -limits, limits))
    assert np.all(np.abs(traj.tau) <= limits)
    assert traj.stats["saturated_controls"] == int(over.any(axis=1).sum())
    expected = {name: int(n) for name, n in zip(ur5.dof_names, over.sum(axis=0), strict=True) if n}
    assert traj.stats["saturated_dofs"] == expected
    assert "torque saturated at the effort limits in" in traj.summary()
    # The ledger books the work of the applied torque: it still balances.
    assert traj.max_abs_energy_error < 1e-6 * np.abs(traj.work).max()


def test_no_effort_limit_means_no_clipping(robot) -> None:
    dp = robot("double_pendulum")  # declares effort 0: no limit
    assert np.all(np.isinf(dp.effort_limit))
    big = np.array([50.0, -50.0])  # hundreds of times the links' weight torques
    traj = ms.simulate(dp, [3.0, 0.0], [0.0, 0.0], duration=0.01, dt=1e-4, controller=lambda t, q, v: big)
    np.testing.assert_array_equal(traj.tau, np.tile(big, (len(traj.t), 1)))
    assert traj.stats["saturated_controls"] == 0 and traj.stats["saturated_dofs"] == {}
    assert "saturated" not in traj.summary()
