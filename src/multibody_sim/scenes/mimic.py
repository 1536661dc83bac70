"""Models with mimic joints (Pinocchio 4.1's JointModelMimic): M(q), forward dynamics and energies where ABA and the
energy algorithms refuse them, and a follower's damping and friction folded onto its leader."""

from __future__ import annotations

import numpy as np
import pinocchio as pin


def has_children(model: pin.Model) -> bool:
    """Whether a mimic joint of the model has joints below it (where Pinocchio 4.1's CRBA accumulates)."""
    return any(
        model.joints[j].shortname() == "JointModelMimic" and len(model.subtrees[j]) > 1 for j in range(1, model.njoints)
    )


def mass_matrix(model: pin.Model, data: pin.Data, q: np.ndarray, clear: bool = True) -> np.ndarray:
    """M(q) by CRBA on a model with mimic joints, symmetric.

    Pinocchio 4.1's CRBA accumulates into data.Fcrb on such models (a mimic joint with children gets its coupling
    added again at every call), so the workspace is cleared first when `clear` (has_children(model)).
    """
    M = _crba(model, data, q, clear)
    return np.triu(M) + np.triu(M, 1).T


def _crba(model: pin.Model, data: pin.Data, q: np.ndarray, clear: bool) -> np.ndarray:
    """CRBA's upper triangle of M(q), its workspace cleared first when `clear` (see mass_matrix)."""
    if clear:
        zero = np.zeros((6, model.nv))
        for i in range(len(data.Fcrb)):
            data.Fcrb[i] = zero
    return pin.crba(model, data, q)


def crba_forward_dynamics(
    model: pin.Model, data: pin.Data, q: np.ndarray, v: np.ndarray, tau: np.ndarray, clear: bool = True
) -> np.ndarray:
    """v' = M⁻¹ (tau - C v - g) by CRBA and RNEA (for models ABA does not support: mimic joints).

    A Cholesky solve on the upper triangle CRBA fills (LAPACK dposv), with no symmetrized copy.
    """
    from scipy.linalg.lapack import dposv

    M = _crba(model, data, q, clear)
    _, a, info = dposv(M, tau - pin.nonLinearEffects(model, data, q, v), lower=0)
    if info != 0:  # not positive definite: a NaN state, which the stepping loop reports as divergence
        return np.full(model.nv, np.nan)
    return a


def fold_dissipation(model: pin.Model, plain: pin.Model, damping: np.ndarray, friction: np.ndarray) -> None:
    """A follower's damper and friction act on its leader's dof: damping s² D_f (exact, GᵀDG), friction |s| F_f
    (exact where |v| ≫ friction_velocity)."""
    for jid in range(1, model.njoints):
        joint = model.joints[jid]
        if joint.shortname() != "JointModelMimic":
            continue
        scaling = joint.extract().scaling
        follower = plain.joints[plain.getJointId(model.names[jid])].idx_v
        damping[joint.idx_v] += scaling**2 * plain.damping[follower]
        friction[joint.idx_v] += abs(scaling) * plain.friction[follower]


def energies(
    model: pin.Model, data: pin.Data, q: np.ndarray, v: np.ndarray, clear: bool = True
) -> tuple[float, float]:
    """(T, V) [J] for a model with mimic joints, which Pinocchio's energy algorithms refuse: T = ½ vᵀ M v by CRBA,
    V = -Σ m_i gᵀ c_i over the moving bodies (what computePotentialEnergy sums)."""
    kinetic = 0.5 * float(v @ mass_matrix(model, data, q, clear) @ v)
    pin.forwardKinematics(model, data, q)
    gravity = model.gravity.linear
    potential = 0.0
    for jid in range(1, model.njoints):
        body = model.inertias[jid]
        potential -= body.mass * float(gravity @ data.oMi[jid].act(body.lever))
    return kinetic, potential
