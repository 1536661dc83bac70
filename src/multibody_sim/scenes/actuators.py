"""Actuators of a scene: per joint, a torque source or a position or velocity servo, with gear ratio, rotor inertia,
effort and velocity limits and a torque–speed curve, evaluated inside the step (at every stage) from the held command.

The command u (the controller's output, ``Stepper.step``'s argument, a rollout's ``taus``, a gym action), shape (nv,),
is per actuated joint: a torque [N·m or N] for kind "torque", a position target [rad or m] for kind "position", a
velocity target [rad/s or m/s] for kind "velocity". Joints without an actuator keep today's ideal torque source (u
is their torque). Each actuator's joint torque at (q, v, u):

1. the command law: torque ``τ_c = u``; position servo ``τ_c = kp (u − q) − kv v``; velocity servo ``τ_c = kv (u − v)``;
2. the limits: ``τ = clip(τ_c, low, high)``, the interval of torques available at the joint's speed v. Without an
   overspeed brake (``overspeed = "none"``): in the direction of motion (τ_c v ≥ 0) the effort limit, the
   torque–speed curve ``stall_torque · max(0, 1 − |v| / no_load_speed)`` and, at or beyond the velocity limit
   (|v| ≥ velocity_limit), nothing; against it (braking) the effort limit only.
3. the overspeed brake (``overspeed = "brake"``, the default where the actuator has an effort and a velocity limit):
   the interval is further bounded by a velocity servo toward ± the velocity limit,
   ``−k (v_max + v) ≤ τ ≤ k (v_max − v)`` with ``k = effort_limit / (overspeed_band · v_max)``, and kept within
   ± the effort limit. Below the limit it caps the driving torque (which falls to 0 at the limit over the band,
   continuously); past it the drive brakes, whatever the command, with ``k (|v| − v_max)`` up to the full effort
   limit at ``(1 + overspeed_band) v_max``. It never cuts a braking torque (k v_max ≥ effort, as the band ≤ 1).
   A steady load τ_ext < effort_limit carrying the joint past its limit holds it at ``v_max + τ_ext / k``.

The rotor's inertia is reflected onto the joint as armature ``gear² · rotor_inertia`` (added to the model's
``armature``: ABA, CRBA and the kinetic energy include it).

Energy ledger, per actuator: ``actuator:<joint>`` (work), the command law's power ``τ_c v``; for an actuator with a
limit, ``actuator_limit:<joint>`` (dissipated), what the limits and the curve took out of it, ``(τ_c − τ₀) v`` with τ₀
the torque clipped without the brake (negative where they cut a braking torque); for an actuator with an overspeed
brake, ``actuator_overspeed:<joint>`` (dissipated), what the brake took out, ``(τ₀ − τ) v`` (never negative). The
lines net to the delivered power ``τ v``.

Implicit servo terms
--------------------
Semi-implicit Euler and the contact time-stepper take each unsaturated servo's linear terms implicitly, as MuJoCo's
implicitfast does with damping: over a step of h from (q, v), with c = 1 where the servo's torque at (q, v) is
within its limits (else 0, as its torque then does not depend on the state), the velocity update solves

    (M + h c kv + h² c kp) (v⁺ − v) = h (f(q, v) − h c kp v)

(f every force at (q, v), the servo's clipped torque included), which is the servo evaluated at the step's end,
τ(q + h v⁺, v⁺), linearised exactly. The extra ``h c kv + h² c kp`` goes onto the model's armature for the step's
ABA (and the contact problem's CRBA and Cholesky), and comes off again before the energies. An actuator on its
overspeed brake's bound at (q, v) is taken the same way, as a velocity servo of gain k toward ± its velocity limit:
armature + h k, torque held at the brake's line k (± v_max − v) at v (also where that is beyond the effort limit:
the step may bring the joint into the band). After the update each actuator's choice (free, braking, clipped) is
checked against its law and interval at v⁺ and revised where it fails (at most MAX_REVISIONS times; see revise()).
Explicit methods evaluate the actuators at every stage. With implicit terms, a stiff servo (kp 1e4 N·m/rad, kv 100
N·m·s/rad on ur5) is stable at any step semi-implicit Euler takes.
"""

from __future__ import annotations

import fnmatch
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin

from ..exceptions import SceneError
from ..text import safe_name
from .spec import ACTUATOR_GAINS, ACTUATOR_KEYS, ActuatorSpec

_UNBOUNDED = 1e300  # Pinocchio writes ±DBL_MAX for "no limit"
# The default overspeed band: the brake reaches the full effort limit 10 % past the velocity limit.
OVERSPEED_BAND = 0.1
# The table keys merged one by one (the curve's two merge together).
_MERGED_ONE_BY_ONE = tuple(key for key in ACTUATOR_KEYS[1:] if key not in ("stall_torque", "no_load_speed"))
KINDS = {"torque": 0, "position": 1, "velocity": 2}  # as the native kernel numbers them
# How many times a step's velocity update is made again for servos that change between free and clipped in it.
MAX_REVISIONS = 4


@dataclass(frozen=True)
class Actuator:
    """One joint's actuator, its tables merged and defaults filled in.

    Attributes:
        joint: the joint's name.
        dof: its velocity index; iq: its configuration index.
        kind: "torque", "position" or "velocity".
        kp, kv: servo gains [N·m/rad, N·m·s/rad] (0 where the kind takes none).
        gear: gear ratio; rotor_inertia: [kg·m²] at the motor.
        effort_limit, velocity_limit: [N·m, rad/s] (inf: none).
        stall_torque, no_load_speed: the torque–speed curve (inf and inf: none).
        overspeed: "brake" or "none" (module docstring); overspeed_band: the brake's band, a fraction of the
            velocity limit in (0, 1].
        sources: which tables set it ("actuator[i]" or "catalog:<robot>[i]").
    """

    joint: str
    dof: int
    iq: int
    kind: str
    kp: float
    kv: float
    gear: float
    rotor_inertia: float
    effort_limit: float
    velocity_limit: float
    stall_torque: float
    no_load_speed: float
    overspeed: str
    overspeed_band: float
    sources: tuple[str, ...]

    @property
    def armature(self) -> float:
        """The rotor's inertia reflected onto the joint, gear² · rotor_inertia [kg·m² or kg]."""
        return self.gear * self.gear * self.rotor_inertia

    @property
    def limited(self) -> bool:
        """Whether a limit or the curve can cut its torque (it then has an actuator_limit ledger line)."""
        return math.isfinite(self.effort_limit) or math.isfinite(self.velocity_limit) or self.curve

    @property
    def brake_gain(self) -> float:
        """The overspeed brake's gain k = effort_limit / (overspeed_band · velocity_limit) [N·m·s/rad or N·s/m]; 0
        without a brake."""
        if self.overspeed != "brake":
            return 0.0
        return self.effort_limit / (self.overspeed_band * self.velocity_limit)

    @property
    def curve(self) -> bool:
        return math.isfinite(self.stall_torque)

    def describe(self) -> str:
        """One line: kind, gains, gear, armature, limits, curve."""
        parts = [self.kind]
        if self.kind == "position":
            parts.append(f"kp {self.kp:g} kv {self.kv:g}")
        elif self.kind == "velocity":
            parts.append(f"kv {self.kv:g}")
        if self.gear != 1.0 or self.rotor_inertia:
            parts.append(f"gear {self.gear:g}, armature {self.armature:.4g}")
        if math.isfinite(self.effort_limit):
            parts.append(f"effort {self.effort_limit:g}")
        if math.isfinite(self.velocity_limit):
            parts.append(f"speed {self.velocity_limit:g}")
        if self.curve:
            parts.append(f"curve {self.stall_torque:g} at rest to 0 at {self.no_load_speed:g}")
        if self.overspeed == "brake":
            parts.append(f"overspeed brake {self.brake_gain:.4g} (full {100 * self.overspeed_band:g} % past the limit)")
        return ", ".join(parts)


# ---- declarations -> per-joint actuators ---------------------------------------------------------------------
def catalog_actuators(robot: str, where: str) -> tuple[ActuatorSpec, ...]:
    """The [[actuator]] tables of a catalog robot's published motor data (models/actuators/<robot>.toml).

    Raises:
        SceneError: the catalog has no motor data for that robot (the message lists those that have).
    """
    from ..catalog import shipped_models_dir
    from .parse import parse_actuator_file

    folder = shipped_models_dir() / "actuators"
    files = {path.stem: path for path in sorted(folder.glob("*.toml"))}
    if robot not in files:
        raise SceneError(
            f"{where}: actuators: the catalog has no published motor data for '{robot}' (it has: "
            f"{', '.join(files) or 'none'}); declare [[actuator]] tables instead"
        )
    return parse_actuator_file(files[robot])


def resolve_actuators(
    model: pin.Model,
    specs: Sequence[tuple[str, ActuatorSpec]],
    *,
    candidates: Sequence[str],
    locked: Sequence[str],
    where: str,
) -> list[Actuator]:
    """Merge the tables joint by joint (later tables override earlier ones key by key) and fill in the defaults.

    Args:
        model: the scene's model (locked joints removed); its URDF effort and velocity limits are the defaults.
        specs: (table name for messages, table), in order.
        candidates: the joints an actuator may drive (the robot's 1-dof joints, in model order); "*" means all.
        locked: the locked joints (named explicitly: an error).
        where: the scene's source, for messages.

    Raises:
        SceneError: a name or pattern that matches no joint, a locked joint, a gain the joint's kind does not take,
            a position servo without kp or on a continuous joint, a velocity servo without kv > 0, only one of
            stall_torque and no_load_speed, or overspeed = "brake" without an effort and a velocity limit.
    """
    merged: dict[str, dict[str, Any]] = {}
    origins: dict[str, list[str]] = {}
    for name, spec in specs:
        for pattern in spec.joints:
            if pattern in locked:
                raise SceneError(f"{where}: {name}.joints: '{pattern}' is locked: a locked joint takes no actuator")
            matched = [j for j in candidates if fnmatch.fnmatchcase(j, pattern)]
            if not matched:
                raise SceneError(
                    f"{where}: {name}.joints: '{pattern}' matches no actuated joint (valid: {', '.join(candidates)})"
                )
            for joint in matched:
                values = merged.setdefault(joint, {})
                origins.setdefault(joint, [])
                if name not in origins[joint]:
                    origins[joint].append(name)
                for key in _MERGED_ONE_BY_ONE:
                    if getattr(spec, key) is not None:
                        values[key] = getattr(spec, key)
                if spec.stall_torque is not None or spec.no_load_speed is not None:
                    values["curve"] = (spec.stall_torque, spec.no_load_speed, name)
                if spec.kind is not None:  # a new kind drops the gains another kind took
                    for gain in ("kp", "kv"):
                        if gain not in ACTUATOR_GAINS[spec.kind] and getattr(spec, gain) is None:
                            values.pop(gain, None)
    actuators = []
    for joint in candidates:  # model order
        if joint not in merged:
            continue
        values = merged[joint]
        name = origins[joint][-1]
        jmodel = model.joints[model.getJointId(joint)]
        kind = values.get("kind", "torque")
        for gain in ("kp", "kv"):
            if gain in values and gain not in ACTUATOR_GAINS[kind]:
                users = [k for k, gains in ACTUATOR_GAINS.items() if gain in gains]
                raise SceneError(
                    f"{where}: {name}: joint '{joint}': {gain} is only for kind {' or '.join(users)}, and its "
                    f"kind is {kind}"
                )
        if kind == "position":
            if "kp" not in values:
                raise SceneError(f"{where}: {name}: joint '{joint}': a position servo needs kp (and kv)")
            if jmodel.nq != 1:
                raise SceneError(
                    f"{where}: {name}: joint '{joint}' is continuous: a position servo needs a revolute or prismatic "
                    "joint (continuous joints take kind torque or velocity)"
                )
        if kind == "velocity" and not values.get("kv", 0.0) > 0.0:
            raise SceneError(f"{where}: {name}: joint '{joint}': a velocity servo needs kv > 0")
        stall, no_load = math.inf, math.inf
        if "curve" in values:
            stall_given, no_load_given, curve_table = values["curve"]
            if (stall_given is None) != (no_load_given is None):
                missing = "no_load_speed" if no_load_given is None else "stall_torque"
                raise SceneError(
                    f"{where}: {curve_table}.{missing}: missing (the torque–speed curve needs stall_torque and "
                    "no_load_speed)"
                )
            stall, no_load = stall_given, no_load_given
        effort = float(values.get("effort_limit", _urdf_limit(model.effortLimit[jmodel.idx_v])))
        speed = float(values.get("velocity_limit", _urdf_limit(model.velocityLimit[jmodel.idx_v])))
        bounded = math.isfinite(effort) and math.isfinite(speed)
        overspeed = values.get("overspeed", "brake" if bounded else "none")
        if overspeed == "brake" and not bounded:
            missing = " and ".join(n for n, x in (("an effort", effort), ("a velocity", speed)) if not math.isfinite(x))
            raise SceneError(
                f"{where}: {name}: joint '{joint}': overspeed = \"brake\" needs {missing} limit (declare "
                'effort_limit and velocity_limit, or overspeed = "none")'
            )
        actuators.append(
            Actuator(
                joint=joint,
                dof=jmodel.idx_v,
                iq=jmodel.idx_q,
                kind=kind,
                kp=float(values.get("kp", 0.0)),
                kv=float(values.get("kv", 0.0)),
                gear=float(values.get("gear", 1.0)),
                rotor_inertia=float(values.get("rotor_inertia", 0.0)),
                effort_limit=effort,
                velocity_limit=speed,
                stall_torque=float(stall),
                no_load_speed=float(no_load),
                overspeed=overspeed,
                overspeed_band=float(values.get("overspeed_band", OVERSPEED_BAND)),
                sources=tuple(origins[joint]),
            )
        )
    return actuators


def _urdf_limit(value: float) -> float:
    """A URDF limit: 0 or absent (±DBL_MAX) means none (inf)."""
    return math.inf if value <= 0.0 or value >= _UNBOUNDED else float(value)


# ---- the element ---------------------------------------------------------------------------------------------
class Actuators:
    """The actuators of one scene: their joint torques, ledger powers, implicit step terms and derivatives.

    Attributes:
        items: the actuators, in model order.
        dofs: their velocity indices, shape (n,).
        ledger: (name, kind) of their ledger lines: ``actuator:<joint>`` (work) for each, then
            ``actuator_limit:<joint>`` (dissipated) for each limited one.
        servos: whether any is a servo (then semi-implicit Euler and the time-stepper take its terms implicitly).
    """

    def __init__(self, model: pin.Model, actuators: Sequence[Actuator]):
        """Build the element on the scene's model (the armature is the Scene's to add; this only reads)."""
        self.items = list(actuators)
        self._model = model
        self.nv = model.nv
        n = len(self.items)
        self.dofs = np.array([a.dof for a in self.items], dtype=int)
        self._iq = np.array([a.iq for a in self.items], dtype=int)
        self._kind = np.array([KINDS[a.kind] for a in self.items], dtype=int)
        self._kp = np.array([a.kp for a in self.items])
        self._kv = np.array([a.kv for a in self.items])
        self._effort = np.array([a.effort_limit for a in self.items])
        self._vlim = np.array([a.velocity_limit for a in self.items])
        self._stall = np.array([a.stall_torque for a in self.items])
        self._no_load = np.array([a.no_load_speed for a in self.items])
        self._torque = np.flatnonzero(self._kind == 0)
        self._position = np.flatnonzero(self._kind == 1)
        self._velocity = np.flatnonzero(self._kind == 2)
        self._curved = np.flatnonzero(np.isfinite(self._stall))
        self._speed_limited = np.flatnonzero(np.isfinite(self._vlim))
        self._limited = np.array([a.limited for a in self.items], dtype=bool)
        # The overspeed brakes: their actuators' indices, gains k and velocity limits (module docstring).
        self._braked = np.flatnonzero([a.overspeed == "brake" for a in self.items])
        self._brake_gain = np.array([a.brake_gain for a in self.items])
        self._brake_limit = np.array([a.velocity_limit if a.overspeed == "brake" else 0.0 for a in self.items])
        self.ledger: list[tuple[str, str]] = (
            [(f"actuator:{a.joint}", "work") for a in self.items]
            + [(f"actuator_limit:{a.joint}", "dissipated") for a in self.items if a.limited]
            + [(f"actuator_overspeed:{self.items[k].joint}", "dissipated") for k in self._braked]
        )
        self._is_servo = self._kind != 0
        self.servos = bool(self._is_servo.any())
        # Whether semi-implicit Euler and the time-stepper take terms inside the step (a servo's, a brake's).
        self.implicit = self.servos or bool(self._braked.size)
        # While a step takes the servos implicitly (begin_implicit .. end_implicit): the actuators' torques held
        # for it, which servos are free, the clipped ones' torques, the step's (law, speeds, h), the armature before.
        self._held: np.ndarray | None = None
        self._free = np.zeros(n, dtype=bool)
        self._braking = np.zeros(n, dtype=bool)
        self._clipped = np.zeros(n)
        self._side = np.ones(n, dtype=int)
        self._step: tuple[np.ndarray, np.ndarray, float] = (np.zeros(n), np.zeros(n), 0.0)
        self._saved_armature = np.zeros(n)
        self._iterations = 0
        if not n:
            raise SceneError("an actuator element needs at least one actuator")

    # ---- the hot path ---------------------------------------------------------------------------------------
    def evaluate(self, q: np.ndarray, v: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(τ_c, τ): each actuator's command-law torque and its torque after the limits, the curve and the overspeed
        brake, shape (n,) each [N·m or N], at (q, v) under the command u (nv,)."""
        c = self._law(q, v, u)
        low, high = self._interval(v[self.dofs])
        return c, np.minimum(np.maximum(c, low), high)

    def _law(self, q: np.ndarray, v: np.ndarray, u: np.ndarray) -> np.ndarray:
        """τ_c, each actuator's command-law torque at (q, v) under u, shape (n,)."""
        dofs = self.dofs
        w = v[dofs]
        c = u[dofs].copy()  # torque actuators: the command itself
        p = self._position
        if p.size:
            c[p] = self._kp[p] * (u[dofs[p]] - q[self._iq[p]]) - self._kv[p] * w[p]
        s = self._velocity
        if s.size:
            c[s] = self._kv[s] * (u[dofs[s]] - w[s])
        return c

    def _limits(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The torques each actuator can deliver at speeds w (n,) without its overspeed brake: (low, high), each (n,).
        In the direction of motion up to its drive limit (the effort limit and the curve; nothing at or past the
        velocity limit), against it up to the effort limit; at rest ± the drive limit."""
        effort = self._effort
        drive = effort
        if self._curved.size or self._speed_limited.size:
            drive = effort.copy()
            speed = np.abs(w)
            k = self._curved
            if k.size:
                curve = self._stall[k] * np.maximum(0.0, 1.0 - speed[k] / self._no_load[k])
                drive[k] = np.minimum(drive[k], curve)
            k = self._speed_limited
            if k.size:
                drive[k] = np.where(speed[k] >= self._vlim[k], 0.0, drive[k])
        return np.where(w > 0.0, -effort, -drive), np.where(w < 0.0, effort, drive)

    def _brakes(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The overspeed brakes' bounds at speeds w (n,): (k (v_max − w), −k (v_max + w)), each (n,): the velocity
        servo toward + and − the limit (0 and 0 where there is no brake)."""
        k, limit = self._brake_gain, self._brake_limit
        return k * (limit - w), -(k * (limit + w))

    def _interval(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The torques each actuator can deliver at speeds w (n,): (low, high), each (n,): _limits, within the
        overspeed brakes' bounds where there are brakes (kept within ± the effort limit)."""
        low, high = self._limits(w)
        if self._braked.size:
            self._within_brakes(low, high, *self._brakes(w))
        return low, high

    def _within_brakes(self, low: np.ndarray, high: np.ndarray, upper: np.ndarray, lower: np.ndarray) -> None:
        """_interval's second half: the limits low, high (n,) bounded, in place, by the brakes' bounds upper, lower
        (n,) where there are brakes, within ± the effort limit."""
        k = self._braked
        effort = self._effort[k]
        high[k] = np.maximum(-effort, np.minimum(high[k], upper[k]))
        low[k] = np.minimum(effort, np.maximum(low[k], lower[k]))

    def _select(
        self, law: np.ndarray, w: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Which bound each actuator's torque takes under the law's torques `law` (n,) at speeds w (n,): (within: the
        law within the interval; brake: clipped at its brake's bound, within ± the effort limit; saturated: clipped
        where its brake's bound is beyond the effort limit (the torque is ∓ the effort limit); side: 1 above the
        interval, −1 below; the interval's low, high), each (n,). The limits and the brakes' bounds are evaluated
        once."""
        limit_low, limit_high = self._limits(w)
        low, high = limit_low.copy(), limit_high.copy()
        upper, lower = self._brakes(w)
        k = self._braked
        if k.size:
            self._within_brakes(low, high, upper, lower)
        within = (law >= low) & (law <= high)
        side = np.where(law > high, 1, -1)
        brake = np.zeros(len(law), dtype=bool)
        saturated = np.zeros(len(law), dtype=bool)
        if k.size:
            effort = self._effort[k]
            beyond = np.where(side[k] > 0, upper[k] < limit_high[k], lower[k] > limit_low[k]) & ~within[k]
            inside = np.where(side[k] > 0, upper[k] > -effort, lower[k] < effort)
            brake[k] = beyond & inside
            saturated[k] = beyond & ~inside
        return within, brake, saturated, side, low, high

    def joint_torques(self, q: np.ndarray, v: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The generalized torque the command u (nv,) applies at (q, v), shape (nv,): the actuators' torques on their
        dofs (those held for the step while a step takes the servos implicitly: begin_implicit), u elsewhere."""
        tau = u.copy()
        tau[self.dofs] = self.evaluate(q, v, u)[1] if self._held is None else self._held
        return tau

    def powers(self, q: np.ndarray, v: np.ndarray, u: np.ndarray, out: np.ndarray) -> None:
        """Power [W] of each ledger line at (q, v) under u, in ledger order, into out: τ_c v, then (τ_c − τ₀) v, then
        (τ₀ − τ) v (τ₀: clipped without the overspeed brake)."""
        c = self._law(q, v, u)
        w = v[self.dofs]
        low, high = self._limits(w)
        limited = np.minimum(np.maximum(c, low), high)
        n, m = len(self.items), len(self.items) + int(self._limited.sum())
        out[:n] = c * w
        out[n:m] = ((c - limited) * w)[self._limited]
        k = self._braked
        if k.size:  # the interval: the same limits within the brakes' bounds
            self._within_brakes(low, high, *self._brakes(w))
            tau = np.minimum(np.maximum(c, low), high)
            out[m:] = ((limited - tau) * w)[k]

    # ---- implicit terms (semi-implicit Euler, the time-stepper) ---------------------------------------------
    def begin_implicit(self, q: np.ndarray, v: np.ndarray, u: np.ndarray, h: float) -> bool:
        """Hold the actuators' torques for a step of h from (q, v) under u, the servos and brakes taken implicitly
        (module docstring): the servos within their limits at (q, v) are free (armature raised by h kv + h² kp,
        torque τ_c(q, v) − h kp v), those on their overspeed brake's bound brake (armature raised by h k, torque the
        brake's line k (± v_max − v) at v, even where it is beyond the effort limit), the others are clipped (their
        torque held); until end_implicit(). Returns whether the scene
        takes any such terms (False: nothing changed)."""
        if not self.implicit:
            return False
        dofs = self.dofs
        w = v[dofs]
        law = self._law(q, v, u)
        within, brake, saturated, side, low, high = self._select(law, w)
        self._step = (law, w, h)
        self._saved_armature = self._model.armature[dofs].copy()
        self._iterations = 0
        # A brake beyond the effort limit at the start is taken on its line too: it may reach its band in the step.
        self._hold(self._is_servo & within, brake | saturated, np.minimum(np.maximum(law, low), high), side)
        return True

    def _hold(self, free: np.ndarray, braking: np.ndarray, clipped: np.ndarray, side: np.ndarray) -> None:
        """Take the servos `free` (n,) and the brakes `braking` (n,) implicitly and hold the other actuators at the
        torques `clipped` (n,); side: each one's bound, upper (1) or lower (−1)."""
        law, w, h = self._step
        hkp = h * self._kp
        self._free, self._braking, self._clipped, self._side = free, braking, clipped, side
        gain = self._brake_gain
        raised = np.where(free, h * self._kv + h * hkp, np.where(braking, h * gain, 0.0))
        self._model.armature[self.dofs] = self._saved_armature + raised
        upper, lower = self._brakes(w)
        self._held = np.where(free, law - hkp * w, np.where(braking, np.where(side > 0, upper, lower), clipped))

    def revise(self, v_next: np.ndarray) -> bool:
        """After the step's velocity update to v_next (nv,): whether each actuator's choice was consistent with its
        law and interval there (a free servo's law within the interval at v_next; a braking actuator's law still
        beyond its brake's bound on the same side, that bound within ± the effort limit; a clipped servo's law still
        at or beyond the bound it is held at, that bound not a brake's; a clipped torque actuator not on a brake's
        bound). If not (and fewer than MAX_REVISIONS revisions were made), change the choice and return True: the
        update is to be made again. Else False. The changes: a clipped servo whose law came back inside is freed; a
        brake beyond the effort limit at the step's start is held at the effort limit; any other takes its choice at
        v_next (held at its interval's bound there if clipped)."""
        law, w, h = self._step
        w_next = v_next[self.dofs]
        law_next = law - (h * self._kp) * w - (h * self._kp + self._kv) * (w_next - w)  # the law at the step's end
        within, brake, _, side, low, high = self._select(law_next, w_next)
        servo, was_held = self._is_servo, ~self._free & ~self._braking
        beyond = np.where(self._side > 0, law_next >= high, law_next <= low)  # a clipped servo's law past its bound
        consistent = np.where(
            self._free,
            within,
            np.where(self._braking, brake & (side == self._side), ~brake & (~servo | beyond)),
        )
        if consistent.all() or self._iterations >= MAX_REVISIONS:
            return False
        self._iterations += 1
        changed = ~consistent
        upper, lower = self._brakes(w)
        effort = self._effort
        # a brake beyond the effort limit at the start that did not land on its line: held at the effort limit
        stays = changed & self._braking & np.where(self._side > 0, upper <= -effort, lower >= effort)
        freed = changed & servo & was_held & ~beyond
        free = np.where(changed, ~stays & (freed | (servo & within)), self._free)
        braking = np.where(changed, ~stays & brake & ~freed, self._braking)
        side = np.where(changed & ~stays, side, self._side)
        newly = changed & ~free & ~braking  # clipped at the step's end: held at its interval's bound there
        clipped = np.where(newly, np.minimum(np.maximum(law_next, low), high), self._clipped)
        clipped = np.where(stays, -side * effort, clipped)
        self._hold(free, braking, clipped, side)
        return True

    def raised_armature(self) -> np.ndarray:
        """While a step takes the servos implicitly: what begin_implicit added to each dof's armature, shape (nv,)
        (the model's armature now less its own; 0 elsewhere)."""
        raised = np.zeros(self.nv)
        raised[self.dofs] = self._model.armature[self.dofs] - self._saved_armature
        return raised

    def end_implicit(self) -> None:
        """Undo begin_implicit(): the model's armature as it was, the torques following the state again."""
        if self._held is not None:
            self._model.armature[self.dofs] = self._saved_armature
            self._held = None

    # ---- commands, derivatives ------------------------------------------------------------------------------
    def command_bounds(self, low: np.ndarray, high: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> None:
        """Write each actuator's command range into low, high (nv,): ± its effort limit (torque), its joint's
        position limits lower, upper (nq,) (position), ± its velocity limit (velocity); inf where there is none."""
        for a in self.items:
            if a.kind == "torque":
                low[a.dof], high[a.dof] = -a.effort_limit, a.effort_limit
            elif a.kind == "position":
                low[a.dof], high[a.dof] = lower[a.iq], upper[a.iq]
            else:
                low[a.dof], high[a.dof] = -a.velocity_limit, a.velocity_limit

    def jacobians(self, q: np.ndarray, v: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Partial derivatives of joint_torques(q, v, u) (no implicit shift), exact away from the limits' kinks:
        (dτ/dq in the tangent space, dτ/dv, dτ/du), each (nv, nv)."""
        nv, dofs = self.nv, self.dofs
        dq, dv, du = np.zeros((nv, nv)), np.zeros((nv, nv)), np.eye(nv)
        c = self._law(q, v, u)
        w = v[dofs]
        free, brake, _, _, low, high = self._select(c, w)
        tau = np.minimum(np.maximum(c, low), high)
        # d(τ_c)/du, dq, dv of each law, kept where the torque is within its limits
        law_u = np.where(self._kind == 0, 1.0, np.where(self._kind == 1, self._kp, self._kv))
        law_q = np.where(self._kind == 1, -self._kp, 0.0)
        law_v = np.where(self._kind == 0, 0.0, -self._kv)
        du[dofs, dofs] = np.where(free, law_u, 0.0)
        dq[dofs, dofs] = np.where(free, law_q, 0.0)
        # Clipped at its drive limit (the side of the motion), the torque follows that limit's slope in the speed:
        # the curve's -stall / no_load where the curve is the limit; on an overspeed brake's bound, -k.
        speed = np.abs(w)
        slope = np.zeros(len(dofs))
        k = self._curved
        if k.size:
            curve = self._stall[k] * (1.0 - speed[k] / self._no_load[k])
            on_curve = (curve > 0.0) & (curve < self._effort[k]) & (speed[k] < self._vlim[k])
            slope[k] = np.where(on_curve, -self._stall[k] / self._no_load[k], 0.0)
        at_drive_limit = ~free & (((w > 0.0) & (tau == high)) | ((w < 0.0) & (tau == low)))
        slope = np.where(brake, -self._brake_gain, np.where(at_drive_limit, slope, 0.0))
        dv[dofs, dofs] = np.where(free, law_v, slope)
        return dq, dv, du

    def braking(self, q: np.ndarray, v: np.ndarray, u: np.ndarray) -> list[str]:
        """The joints whose overspeed brake's bound holds their torque at (q, v) under u."""
        brake = self._select(self._law(q, v, u), v[self.dofs])[1]  # (on the line; saturated: a constant torque)
        return [a.joint for a, b in zip(self.items, brake, strict=True) if b]

    def native_data(self) -> dict[str, object]:
        """The actuators as _native.SceneActuators takes them: each ActuatorTerm's fields (inf: no such limit or
        curve; brake_gain 0: no overspeed brake) and MAX_REVISIONS."""
        terms = [
            {
                "dof": a.dof,
                "iq": a.iq,
                "kind": a.kind,
                "kp": a.kp,
                "kv": a.kv,
                "effort": a.effort_limit,
                "velocity_limit": a.velocity_limit,
                "stall": a.stall_torque,
                "no_load": a.no_load_speed,
                "limited": a.limited,
                "brake_gain": a.brake_gain,
            }
            for a in self.items
        ]
        return {"terms": terms, "max_revisions": MAX_REVISIONS}


def describe_actuators(actuators: Actuators) -> list[str]:
    """The describe() lines: one per actuator."""
    return [f"  actuator {safe_name(a.joint)}: {a.describe()}" for a in actuators.items]
