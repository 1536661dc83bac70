"""The Scene: a robot with exactly the physics a scene declares, and nothing else built or computed.

A scene modifies the robot's Pinocchio model once, before any step (base pose, gravity, payloads, armature,
joint damping and friction, locked joints removed with ``pin.buildReducedModel``), and adds at run time only the
elements it declares: springs, Coulomb friction, external wrenches (ForceElements) and holonomic constraints
(Constraints). A scene with none of them steps exactly like its robot.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from ..catalog import CATALOG, MAX_DOFS, ROBOT_PREFIX, load_robot, read_urdf, reduce_configuration
from ..catalog.checks import check_body_inertias, check_mass_matrix, check_model_numbers
from ..exceptions import InvalidArgumentError, ModelError, SceneError
from ..integrators.cone_solver import TOLERANCE
from ..robot import Robot
from ..text import safe_name
from ..trajectory import Trajectory
from . import mimic
from .frames import frame_id
from .randomize import (
    Nominals,
    Randomizer,
    actuator_constants,
    body_links,
    body_masses,
    check_parameters,
    contact_values,
    payload_mass,
    randomized,
    shown,
)
from .spec import CONTACT_INTEGRATOR, PayloadSpec, RobotSpec, SceneSpec

# How fast a coordinate held by the contact solve may drift [rad/s or m/s]: its velocity is solved to within the
# solver's tolerance, TOLERANCE times the step's velocity scale (cone_solver.py); ten times TOLERANCE bounds it for
# velocity scales up to 10 m/s (talos_standing's held grippers pass their stops by 1.1e-12 rad at t = 8 ms).
HELD_DRIFT_RATE = 10 * TOLERANCE

# The time-stepper's ledger elements, last in a contact scene's ledger (see integrators/timestepping.py).
CONTACT_LEDGER = (
    ("contact", "dissipated"),
    ("penetration_correction", "work"),
    ("restitution", "work"),
    ("timestep_error", "work"),
)

_WORLD = pin.Convention.WORLD


class Scene(Robot):
    """A robot with the physics a scene declares: a Robot wherever one is accepted (simulate, Stepper, ...).

    Equations of motion: ``M(q) v' + C(q, v) v + g(q) = tau - D v + f(q, v, t) (+ Jᵀλ)`` on the scene's model
    (locked joints removed: q and v are the reduced model's), with f the springs, friction and external
    wrenches and λ the constraint forces.

    Build one with :func:`load_scene` (a TOML file) or :func:`make_scene` (the same tables in Python).

    Attributes:
        spec: the parsed scene.
        full_nq, full_nv: sizes of the robot before locking joints.
        locked: locked joint names and their positions.
        elements: the force elements (None when the scene declares none).
        constraints: the holonomic constraints (None when there are none).
        mimic: whether URDF <mimic> joints are honoured (forward dynamics by CRBA, as ABA does not support them).
        has_derivatives: whether the dynamics' analytic derivatives exist (implicit methods and linearize need
            them); `no_derivatives_reason` says why not ("" when they do).
        q0, v0: the scene's initial state ([initial], else the robot's default_pose() at rest: its SRDF's
            reference pose where it has one, else the neutral configuration).
    """

    def __init__(self, spec: SceneSpec, *, robot: Robot | None = None, variant_of: Scene | None = None):
        """Build the scene `spec` declares (with spec.parameters' values where it gives them: with_parameters).

        Args:
            spec: the parsed scene.
            robot: its robot, already loaded from spec.robot (a randomised rollout's rows share the nominal scene's
                `full_robot`); None: loaded here (variant_of's, with variant_of).
            variant_of: a scene built from the same declaration with other parameter values (with_parameters: a
                randomised row): what parameter values cannot change is taken from it instead of being made and
                checked again (the robot, the configuration space, the named poses, the bodies' links, the model's
                checks, the [randomize] table). Values within their quantities' ranges keep masses and inertias
                physical. Every value the parameters enter is computed by this very code, so the scene is the one
                `Scene(spec)` builds.

        Raises:
            InvalidArgumentError: variant_of's declaration differs from spec's in more than its parameters.
        """
        from .elements import ForceElements

        if variant_of is not None and not _same_declaration(variant_of.spec, spec):
            raise InvalidArgumentError("variant_of must be built from the same declaration (other parameters only)")
        self.spec = spec
        where = spec.source
        # The parameters [randomize] may draw: their nominal values are noted wherever they enter (values.value).
        values = None if spec.randomize is None and spec.parameters is None else Nominals(spec.parameters)
        if robot is None:
            robot = variant_of.full_robot if variant_of is not None else _load_robot(spec)
        robot_spec = spec.robot if spec.robot is not None else RobotSpec(source="", damping=False)
        if values is not None and robot_spec.mimic:
            raise SceneError(f"{where}: randomize: randomised parameters and mimic joints cannot be combined yet")
        model = _build_model(robot, spec)
        self.full_nq, self.full_nv = robot.nq, robot.nv
        self.full_robot = robot
        self._body_links = None  # the robot's bodies and their links (structure only: a variant's are its scene's)
        if values is not None:
            known = variant_of._body_links if variant_of is not None else None
            self._body_links = known if known is not None else body_links(model)
            body_masses(model, values, self._body_links)
        _apply_base_pose(model, spec)
        if spec.gravity is not None:
            model.gravity.linear = np.array(spec.gravity, dtype=float)
        payloads = list(spec.payloads)  # with their drawn masses
        for i, payload in enumerate(payloads):
            if values is not None:
                payloads[i] = payload = payload_mass(payload, values.value("payload_mass", str(i), payload.mass))
            _add_payload(model, payload, f"{where}: payload[{i}]")
        friction = np.array(model.friction, dtype=float) if robot_spec.damping else np.zeros(model.nv)
        damping = np.array(model.damping, dtype=float) if robot_spec.damping else np.zeros(model.nv)
        stiffness, rest_values = np.zeros(model.nv), {}
        for joint, settings in spec.joints.items():
            key = f"{where}: joints.{joint}"
            jid = _joint_id(model, joint, key, robot.floating_base)
            if joint in spec.lock:
                raise SceneError(
                    f"{key}: joint '{joint}' is locked, so it takes no damping, friction, spring or armature"
                )
            i = model.joints[jid].idx_v
            if settings.damping is not None:
                damping[i] = settings.damping
            if settings.friction is not None:
                friction[i] = settings.friction
            if settings.armature is not None:
                model.armature[i] += settings.armature
            if settings.stiffness is not None:
                stiffness[i] = settings.stiffness
            if settings.rest is not None:
                if not settings.stiffness:
                    raise SceneError(f"{key}.rest: a rest position needs a spring: give stiffness > 0")
                rest_values[joint] = settings.rest
        if values is not None:  # every unlocked 1-dof joint's damping, friction and armature
            for joint in _one_dof_joints(model):
                if joint not in spec.lock:
                    i = model.joints[model.getJointId(joint)].idx_v
                    damping[i] = values.value("damping", joint, float(damping[i]))
                    friction[i] = values.value("friction", joint, float(friction[i]))
                    model.armature[i] = values.value("armature", joint, float(model.armature[i]))
        if robot_spec.mimic:
            if spec.lock:
                raise SceneError(
                    f"{where}: lock.{next(iter(spec.lock))}: locked joints and mimic joints cannot be combined yet "
                    "(drop the lock or robot.mimic)"
                )
            if robot_spec.damping:  # the URDF's <dynamics> of the followers act on their leaders
                mimic.fold_dissipation(model, robot.model, damping, friction)
        model.damping = damping
        model.friction = friction
        built = model  # before locking: the dof indices the per-joint arrays above use
        model, lock_config = _lock_joints(model, spec, robot.floating_base)
        actuators = _actuators(model, spec)
        if values is not None:
            actuators = [actuator_constants(actuator, values) for actuator in actuators]
        for actuator in actuators:  # the rotors' inertia, reflected onto the joints
            model.armature[actuator.dof] += actuator.armature
        self.locked = dict(spec.lock)
        robot_nv, robot_nq = model.nv, model.nq
        object_joints = _add_objects(model, spec, values)  # free-flyers after the robot's joints
        if variant_of is not None:  # the joints' structure only
            poses = variant_of._poses
        else:
            poses = {name: reduce_configuration(robot.model, model, robot.pose(name)) for name in robot.poses}
            for q_pose in poses.values():
                _place_objects(model, spec, q_pose)
        # The Robot part: argument checks, limits, energies, damping (tau - D v) on the scene's model.
        super().__init__(
            model,
            name=_scene_name(spec, robot),
            floating_base=robot.floating_base,
            damping=True,
            # every row the same ledger: the damping line where [randomize] draws damping, D = 0 or not
            always_damped=bool(randomized(spec.randomize, "damping", _one_dof_joints(model))),
            source={**robot.source, "scene": _scene_source(spec)},
            # The robot's named poses on the scene's model (locked joints and mimic followers dropped; objects
            # where the scene puts them).
            poses=poses,
            default_pose=robot.default_pose_name,
            space=variant_of.space if variant_of is not None else None,
        )
        if variant_of is None:
            _check_scene_model(self, where, robot_nv, len(object_joints))
        self.actuated = slice(self.actuated.start, robot_nv)  # free objects are unactuated
        self.actuators = None
        if actuators:
            from .actuators import Actuators

            self.actuators = Actuators(model, actuators)
            for actuator in actuators:
                self.effort_limit[actuator.dof] = actuator.effort_limit
        self.robot_nq, self.robot_nv = robot_nq, robot_nv
        self.object_joints = object_joints
        self.mimic = robot_spec.mimic
        self._clear_crba = self.mimic and mimic.has_children(model)
        # Per-dof element parameters on the reduced model, read back by joint name (locking renumbers dofs).
        kept_stiffness, kept_friction = np.zeros(self.nv), np.array(model.friction, dtype=float)
        rest = pin.neutral(model)
        for joint in spec.joints:
            jid = model.getJointId(joint)
            kept_stiffness[model.joints[jid].idx_v] = stiffness[built.joints[built.getJointId(joint)].idx_v]
            if joint in rest_values:
                _set_joint_position(model, jid, rest_values[joint], rest)
        if self.floating_base:
            kept_friction[:6] = 0.0
        # Joints whose friction [randomize] draws keep their element at 0 too: every row has the same ledger.
        rough = np.zeros(self.nv, dtype=bool)
        for joint in randomized(spec.randomize, "friction", _one_dof_joints(model)):
            rough[model.joints[model.getJointId(joint)].idx_v] = True
        exact_friction: list[tuple[int, float]] = []
        if spec.contact is not None and spec.contact.friction == "exact":
            # Joint dry friction becomes a constraint of the time-stepper (exact stiction), not a tanh element.
            for jid in range(1, model.njoints):
                joint = model.joints[jid]
                if joint.nv == 1 and (kept_friction[joint.idx_v] > 0.0 or rough[joint.idx_v]):
                    exact_friction.append((jid, float(kept_friction[joint.idx_v])))
                    kept_friction[joint.idx_v] = 0.0
        held = np.zeros(self.nv, dtype=bool)  # the joints whose friction the contact solve holds
        for jid, _ in exact_friction:
            held[model.joints[jid].idx_v] = True
        self.q0, self.v0 = _initial_state(self, spec)
        wrenches = [_wrench(model, force, f"{where}: force[{i}]") for i, force in enumerate(spec.forces)]
        elements = ForceElements(
            model,
            dof_names=self.dof_names,
            damping=np.zeros(self.nv),  # viscous damping stays in the Robot part (D), which implicit methods use
            friction=kept_friction,
            friction_velocity=spec.friction_velocity,
            stiffness=kept_stiffness,
            rest=rest,
            wrenches=wrenches,
            keep=rough & ~held,
        )
        self.elements = None if elements.empty else elements
        self.constraints = None
        if spec.constraints:
            if self.mimic:
                raise SceneError(f"{where}: constraint: constraints and mimic joints cannot be combined yet")
            for i, constraint in enumerate(spec.constraints):
                for frame in constraint.frames:
                    frame_id(model, frame, f"{where}: constraint[{i}].frames")
            from .constraints import Constraints

            self.constraints = Constraints(model, list(spec.constraints), self.q0)
        self.lock_configuration = lock_config
        self.contact = None
        if spec.has_contact:
            if self.mimic:
                raise SceneError(
                    f"{where}: contact: contact and mimic joints cannot be combined: Pinocchio 4.1's constraint "
                    "Cholesky (the contact solver's Delassus operator) does not support mimic joints (drop "
                    "robot.mimic, making the followers independent joints, or drop [ground], [contact] and [[object]])"
                )
            from .contact import PENETRATION_SLOP, build_contact

            lines = len(super().ledger_elements)  # the robot's: the actuators' ledger lines follow them
            self.contact = build_contact(self, contact_values(spec, values), exact_friction, lines)
            # An enforced limit holds to the penetration slop, by design: only an excursion beyond it is a violation.
            for jid in self.contact.limited_joints:
                iq = model.joints[jid].idx_q
                self.limit_tolerance[iq] = max(self.limit_tolerance[iq], PENETRATION_SLOP)
            # A coordinate whose velocity the contact solve holds (an enforced limit, exact dry friction) has it to
            # within the solver's accuracy, and no position term pulls it back: it may drift by HELD_DRIFT_RATE per
            # second (talos_standing's grippers, held at their stops: 7.5e-15 rad after 1 s), which is no violation.
            for jid in {*self.contact.limited_joints, *(jid for jid, _ in exact_friction)}:
                self.limit_drift[model.joints[jid].idx_q] = HELD_DRIFT_RATE
        self.sensors = _sensors(self, spec, payloads)
        self._flow_elements = list(super().ledger_elements)
        self._n_robot_flows = len(self._flow_elements)
        if self.actuators is not None:
            self._flow_elements += self.actuators.ledger
        if self.elements is not None:
            self._flow_elements += self.elements.ledger
        if self.constraints is not None:
            self._flow_elements += self.constraints.ledger
        if self.contact is not None:  # last, as the time-stepper writes them
            self._flow_elements += list(CONTACT_LEDGER)
        fields: list[tuple[str, str, int]] = []
        if self.elements is not None:
            fields += [("potential", name, 1) for name in self.elements.potentials]
        if self.constraints is not None:
            fields += [
                ("constraint", name, rows + 2)
                for name, rows in zip(self.constraints.names, self.constraints.rows, strict=True)
            ]
        if self.actuators is not None:  # the joint torques the actuators deliver (the trajectory's tau)
            fields.append(("torque", "tau", self.nv))
        self.record_fields = tuple(fields)
        self._last: tuple[Any, Any, float] | None = None  # (q, v, t) of the latest element/constraint evaluation
        self.no_derivatives_reason = ""
        if self.contact is not None:
            self.no_derivatives_reason = "it has contact, which only the timestepping integrator steps"
        elif self.constraints is not None:
            self.no_derivatives_reason = f"it has constraints: {', '.join(self.constraints.names)}"
        elif self.mimic:
            self.no_derivatives_reason = "it honours mimic joints, which Pinocchio's ABA derivatives do not support"
        self.has_derivatives = not self.no_derivatives_reason
        if variant_of is None:
            _check_scene_mass_matrix(self, where)
        # The values of the parameters [randomize] may draw as declared, and the table resolved on them.
        self.nominal_parameters: dict[str, Any] = values.nominal if values is not None else {}
        self.randomizer = None
        if variant_of is not None:
            self.randomizer = variant_of.randomizer
        elif spec.randomize is not None:
            self.randomizer = Randomizer(spec.randomize, self.nominal_parameters, where)

    def __repr__(self) -> str:
        return f"Scene({self.name!r}, nq={self.nq}, nv={self.nv}, elements={len(self._flow_elements) - 1})"

    # ---- what was modelled ---------------------------------------------------------------------------
    @property
    def element_names(self) -> list[str]:
        """The force elements in play (ledger names, springs included; constraints and joint torques not)."""
        time_stepper = {name for name, _ in CONTACT_LEDGER} if self.contact is not None else set()
        names = [
            name
            for name, _ in self._flow_elements[1:]
            if not name.startswith("constraint:") and name not in time_stepper
        ]
        return names + (self.elements.potentials if self.elements is not None else [])

    @property
    def parameters(self) -> dict[str, Any] | None:
        """The parameter values this scene was built with (with_parameters), None for the declared ones."""
        return self.spec.parameters

    def with_parameters(self, parameters: dict[str, Any] | None) -> Scene:
        """This scene with the given parameter values in place of the declared ones (scenes/randomize.py: the form
        a randomised row records in ``metadata["parameters"]``; None: the declared values). The same robot, built
        again with them: a randomised row re-run alone on it gives the row's samples bit for bit.

        Raises:
            InvalidArgumentError: an unknown parameter or target (the message lists the valid ones), a value
                outside its quantity's range.
        """
        if parameters is not None:
            nominal = self.nominal_parameters
            if not nominal:  # none noted (nothing randomised or given): this scene's variant notes them as it builds
                nominal = Scene(dataclasses.replace(self.spec, parameters={}), variant_of=self).nominal_parameters
            parameters = check_parameters(parameters, nominal)
        return Scene(dataclasses.replace(self.spec, parameters=parameters), robot=self.full_robot, variant_of=self)

    def draw_parameters(self, b: int) -> dict[str, Any]:
        """The parameter values of randomised rollout row b (the [randomize] table's draw seeded with (seed, b)).

        Raises:
            InvalidArgumentError: the scene has no [randomize] table.
        """
        if self.randomizer is None:
            raise InvalidArgumentError(f"scene '{self.name}' has no [randomize] table: nothing to draw")
        return self.randomizer.row(b)

    def __reduce__(self) -> tuple[Any, tuple[SceneSpec]]:
        """Pickled as its declaration and built again where it is unpickled (a Ray worker): Pinocchio's collision
        data and joint-friction constraints do not pickle; the same declaration builds the same scene, which steps
        to the same bytes. Its robot's files must be at the same paths there."""
        return (Scene, (self.spec,))

    def describe(self) -> str:
        """What the scene modelled, a few lines for the run summary."""
        spec = self.spec
        base = "floating" if self.floating_base else "fixed"
        if spec.robot is not None and (spec.robot.position is not None or spec.robot.rpy is not None):
            base += f" at position {list(spec.robot.position or (0, 0, 0))} rpy {list(spec.robot.rpy or (0, 0, 0))}"
        if spec.robot is None:
            lines = [f"scene '{safe_name(self.name)}': no robot, {len(spec.objects)} object(s)"]
        else:
            lines = [f"scene '{safe_name(self.name)}': robot {safe_name(self.full_robot.name)}, {base} base"]
        for item in spec.objects:
            lines.append(
                f"  object '{item.name}': {item.shape.shape}, {item.mass:g} kg, free-flyer (dofs {item.name}.vx..wz)"
            )
        if self.locked:
            locked = ", ".join(f"{safe_name(name)} = {value:g}" for name, value in self.locked.items())
            lines.append(f"  locked: {locked}; model nq/nv {self.full_nq}/{self.full_nv} -> {self.nq}/{self.nv}")
        else:
            lines.append(f"  model nq/nv {self.nq}/{self.nv} (nothing locked)")
        lines.append(f"  gravity {np.round(self.model.gravity.linear, 6).tolist()} m/s²")
        if spec.payloads:
            lines.append("  payloads: " + ", ".join(f"{p.mass:g} kg on {safe_name(p.frame)}" for p in spec.payloads))
        armature = [f"{safe_name(self.dof_names[i])} {a:g}" for i, a in enumerate(self.model.armature) if a]
        if armature:
            lines.append("  armature [kg·m²]: " + ", ".join(armature))
        if self.mimic:
            lines.append("  mimic joints honoured (forward dynamics by CRBA: ABA does not support them)")
        if self.actuators is not None:
            from .actuators import describe_actuators

            lines += describe_actuators(self.actuators)
        elements = [name for name in self.element_names if not name.startswith(("actuator:", "actuator_limit:"))]
        lines.append("  force elements: " + (", ".join(map(safe_name, elements)) if elements else "none"))
        friction = np.array(self.model.friction, dtype=float)
        if self.elements is not None and friction.any():
            # The regularized friction's slope F/v_s over the joint's inertia: the rate of a stiff mode.
            inverse_mass = np.diag(np.linalg.inv(self.mass_matrix(self.q0)))
            rates = friction / self.spec.friction_velocity * inverse_mass
            i = int(np.argmax(rates))
            lines.append(
                f"  friction stiffness: a mode of rate ~{rates[i]:.3g} 1/s in '{safe_name(self.dof_names[i])}' at the "
                f"initial state: explicit methods need dt < ~{2.8 / rates[i]:.2g} s (RK4); implicit_euler takes any "
                "step"
            )
        if self.constraints is not None:
            rows = ", ".join(
                f"{safe_name(n)} ({r} rows)" for n, r in zip(self.constraints.names, self.constraints.rows, strict=True)
            )
            lines.append(f"  constraints: {rows}")
        else:
            lines.append("  constraints: none")
        if self.contact is None:
            lines.append("  not modelled: collision geometry, contact (visual meshes are loaded only to view)")
        else:
            lines += self.contact.describe()
        if self.sensors is not None:
            lines.append("  sensors:\n" + self.sensors.describe())
        if self.randomizer is not None:
            lines += self.randomizer.describe()
        if self.spec.parameters is not None:
            lines.append("  parameters drawn: " + shown(self.spec.parameters))
        return "\n".join(lines)

    def default_pose(self) -> np.ndarray:
        """The robot's default pose (its SRDF's everyday pose, else neutral), with the scene's objects where it puts
        them, shape (nq,)."""
        q = super().default_pose()
        _place_objects(self.model, self.spec, q)
        return q

    # ---- dynamics (the hot path) ---------------------------------------------------------------------
    def _applied(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, t: float) -> np.ndarray:
        """The actuators' torques under the command tau (tau itself without actuators), plus the force elements and
        minus damping: everything but the constraints."""
        if self.actuators is not None:
            tau = self.actuators.joint_torques(q, v, tau)
        if self.elements is not None:
            tau = tau + self.elements.evaluate(q, v, t)
        if self.damped:
            tau = tau - self.damping * v
        return tau

    def unchecked_forward_dynamics(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, t: float = 0.0) -> np.ndarray:
        """Accelerations at time t [s] with every declared element and constraint, no argument checks."""
        applied = self._applied(q, v, tau, t)
        self._last = (q, v, t)
        if self.constraints is not None:
            return self.constraints.forward_dynamics(q, v, applied)
        if self.mimic:
            return mimic.crba_forward_dynamics(self.model, self.data, q, v, applied, self._clear_crba)
        return pin.aba(self.model, self.data, q, v, applied, _WORLD)

    def unchecked_dynamics_derivatives(
        self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, t: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Partial derivatives of the forward dynamics with the force elements (see Robot); no constraints."""
        if not self.has_derivatives:
            raise InvalidArgumentError(
                f"scene '{self.name}' has no analytic dynamics derivatives ({self.no_derivatives_reason})"
            )
        applied = self._applied(q, v, tau, t)
        da_dq, da_dv, da_dtau = pin.computeABADerivatives(self.model, self.data, q, v, applied)
        da_dq, da_dv, da_dtau = da_dq.copy(), da_dv.copy(), da_dtau.copy()
        if self.damped:
            da_dv -= da_dtau * self.damping
        if self.elements is not None:
            df_dq, df_dv = self.elements.jacobians(q, v, t)
            da_dq += da_dtau @ df_dq
            da_dv += da_dtau @ df_dv
        if self.actuators is not None:  # the command u enters through the actuators' torques
            dtau_dq, dtau_dv, dtau_du = self.actuators.jacobians(q, v, tau)
            da_dq += da_dtau @ dtau_dq
            da_dv += da_dtau @ dtau_dv
            da_dtau = da_dtau @ dtau_du
        return da_dq, da_dv, da_dtau

    # ---- energy ledger -------------------------------------------------------------------------------
    @property
    def ledger_elements(self) -> list[tuple[str, str]]:
        """(name, kind) of every flow element: joint torques, damping, friction, external forces, constraints."""
        return self._flow_elements

    def ledger_power(
        self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, out: np.ndarray | None = None, t: float = 0.0
    ) -> np.ndarray:
        """Power [W] of each flow element at (q, v, tau, t), in ledger_elements order."""
        if out is None:
            out = np.empty(len(self._flow_elements))
        n = self._n_robot_flows
        actuators = self.actuators
        if actuators is None:
            super().ledger_power(q, v, tau, out[:n])
        else:  # joint_torques: the ideal torque sources only (joints without an actuator)
            sources = tau.copy()
            sources[actuators.dofs] = 0.0
            super().ledger_power(q, v, sources, out[:n])
            m = n + len(actuators.ledger)
            actuators.powers(q, v, tau, out[n:m])
            n = m
        if len(out) == n:
            return out
        last = self._last
        if last is None or last[0] is not q or last[1] is not v or last[2] != t:
            self.unchecked_forward_dynamics(q, v, tau, t)  # the elements' parts at this very point
        if self.elements is not None:
            m = n + len(self.elements.ledger)
            self.elements.powers(v, out[n:m])
            n = m
        if self.constraints is not None:
            self.constraints.powers(v, out[n : n + len(self.constraints.ledger)])
        if self.contact is not None:  # impulses, not powers: the time-stepper books them
            out[-len(CONTACT_LEDGER) :] = 0.0
        return out

    def mass_matrix(self, q: Any) -> np.ndarray:
        """Joint-space inertia matrix M(q) of the scene's model (armature and payloads included), (nv, nv)."""
        if self.mimic:
            return mimic.mass_matrix(self.model, self.data, self.check_q(q), self._clear_crba)
        return super().mass_matrix(q)

    def kinetic_energy(self, q: Any, v: Any) -> float:
        """T = ½ vᵀ M(q) v [J]."""
        return self.unchecked_energies(self.check_q(q), self.check_v(v))[0]

    def potential_energy(self, q: Any) -> float:
        """V(q) [J]: gravity's and the springs'."""
        q = self.check_q(q)
        return self.unchecked_energies(q, np.zeros(self.nv))[1]

    def unchecked_energies(self, q: np.ndarray, v: np.ndarray) -> tuple[float, float]:
        """(T, V) [J]: V includes the springs' stored energy."""
        if self.mimic:
            kinetic, potential = mimic.energies(self.model, self.data, q, v, self._clear_crba)
        else:
            kinetic, potential = super().unchecked_energies(q, v)
        if self.elements is not None and self.elements.potentials:
            potential += float(self.elements.potential_energy(q))  # in order, as the native kernel sums
        return kinetic, potential

    def unchecked_record(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, t: float, out: np.ndarray) -> None:
        """Springs' stored energies, then each constraint's forces, drift and velocity drift, into `out`."""
        i = 0
        if self.elements is not None and self.elements.potentials:
            n = len(self.elements.potentials)
            out[:n] = self.elements.potential_energies(q)
            i = n
        if self.constraints is not None:
            i += self._record_constraints(q, v, tau, t, out[i:])
        if self.actuators is not None:
            out[i : i + self.nv] = self.actuators.joint_torques(q, v, tau)

    def _record_constraints(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, t: float, out: np.ndarray) -> int:
        """Each constraint's forces, drift and velocity drift at (q, v, tau, t), into `out`; returns the width."""
        i = 0
        if self.constraints is not None:
            self.unchecked_forward_dynamics(q, v, tau, t)  # the multipliers in force at this sample
            forces = self.constraints.multipliers()
            drift, velocity_drift = self.constraints.drift(q, v)
            row = 0
            for k, rows in enumerate(self.constraints.rows):
                out[i : i + rows] = forces[row : row + rows]
                out[i + rows], out[i + rows + 1] = drift[k], velocity_drift[k]
                i += rows + 2
                row += rows
        return i

    # ---- running -------------------------------------------------------------------------------------
    def run(self, **overrides: Any) -> Trajectory:
        """Simulate the scene as it declares: its initial state, [simulation] settings and [controller].

        Args:
            **overrides: anything simulate() takes (q0, v0, duration, dt, integrator, controller, out, chunk,
                on_sample, progress, output_dt, control_dt, rtol, atol, max_step); given values win over the
                scene's. Defaults where the scene is silent too: duration 1 s, dt 1 ms, rk4.

        Returns:
            The trajectory (see simulate for the errors raised).
        """
        from ..simulation import simulate

        settings = self.simulation_settings()
        settings.update(overrides)
        q0, v0 = settings.pop("q0"), settings.pop("v0")
        return simulate(self, q0, v0, **settings)

    def simulation_settings(self, *, controller: bool = True) -> dict[str, Any]:
        """simulate()'s keyword arguments as the scene declares them (with q0 and v0), defaults filled in; without
        the scene's controller when `controller` is False (the gym environments take torques as actions)."""
        sim = self.spec.simulation
        integrator = CONTACT_INTEGRATOR if self.contact is not None else "rk4"
        settings: dict[str, Any] = {"q0": self.q0, "v0": self.v0, "duration": 1.0, "dt": 1e-3, "integrator": integrator}
        if sim is not None:
            for name in ("duration", "dt", "integrator"):
                if getattr(sim, name) is not None:
                    settings[name] = getattr(sim, name)
            settings.update(sim.options)
        policy = self.make_controller() if controller else None
        if policy is not None:
            settings["controller"] = policy
        return settings

    def make_controller(self) -> Any:
        """The scene's [controller], built for this scene's model, or None."""
        if self.spec.controller is None:
            return None
        from ..controllers import make_controller

        try:
            return make_controller(self.spec.controller.name, self, self.spec.controller.as_param_strings())
        except InvalidArgumentError as exc:
            raise SceneError(f"{self.spec.source}: controller: {exc}") from None

    def full_configuration(self, q: np.ndarray) -> np.ndarray:
        """The full robot's configuration for a scene configuration q: locked joints at their lock positions,
        mimic followers at scaling · leader + offset."""
        full, model = self.full_robot.model, self.model
        out = pin.neutral(full)  # a scene's objects are not the robot's: left out
        for jid in range(1, full.njoints):
            name, joint = full.names[jid], full.joints[jid]
            i, n = joint.idx_q, joint.nq
            if not model.existJointName(name):  # locked: the pre-lock model has the full robot's layout
                out[i : i + n] = self.lock_configuration[i : i + n]
                continue
            kept = model.joints[model.getJointId(name)]
            if kept.shortname() == "JointModelMimic":  # shares its leader's coordinate
                follower = kept.extract()
                out[i] = follower.scaling * q[kept.idx_q] + follower.offset
            else:
                out[i : i + n] = q[kept.idx_q : kept.idx_q + n]
        return out


# ---- building ----------------------------------------------------------------------------------------
def _same_declaration(a: SceneSpec, b: SceneSpec) -> bool:
    """Whether two scenes declare the same thing but for their parameter values (Scene's variant_of)."""
    return all(
        getattr(a, f.name) is getattr(b, f.name) or getattr(a, f.name) == getattr(b, f.name)
        for f in dataclasses.fields(a)
        if f.name != "parameters"
    )


def _actuators(model: pin.Model, spec: SceneSpec) -> list[Any]:
    """The scene's actuators on its model (locked joints removed): the catalog's defaults when it asks for them,
    then its [[actuator]] tables, merged joint by joint (scenes/actuators.py)."""
    if not spec.actuators and spec.actuator_defaults is None:
        return []
    from .actuators import catalog_actuators, resolve_actuators

    where = spec.source
    assert spec.robot is not None, "the parser refuses actuators without a robot"
    if spec.robot.mimic:
        raise SceneError(f"{where}: actuator: actuators and mimic joints cannot be combined yet (drop robot.mimic)")
    tables: list[tuple[str, Any]] = []
    if spec.actuator_defaults == "catalog":
        name = spec.robot.source.removeprefix(ROBOT_PREFIX)
        if name not in CATALOG:
            raise SceneError(
                f'{where}: actuators: "catalog" needs a catalog robot, and robot.source is a file; declare '
                "[[actuator]] tables instead"
            )
        tables += [(f"catalog {name}: actuator[{i}]", t) for i, t in enumerate(catalog_actuators(name, where))]
    tables += [(f"actuator[{i}]", t) for i, t in enumerate(spec.actuators)]
    return resolve_actuators(model, tables, candidates=_one_dof_joints(model), locked=list(spec.lock), where=where)


def _load_robot(spec: SceneSpec) -> Robot:
    r = spec.robot
    if r is None:  # objects only: an empty world to add them to
        return Robot(pin.Model(), name="objects", floating_base=False, damping=False, source={"source": None})
    floating = None if r.base is None else r.base == "floating"
    try:
        return load_robot(
            r.source,
            floating_base=floating,
            damping=r.damping,
            package_dirs=list(r.package_dirs) or None,
            allowed_roots=list(spec.allowed_roots) or None,
        )
    except InvalidArgumentError as exc:
        raise SceneError(f"{spec.source}: robot.source: {exc}") from None


def _build_model(robot: Robot, spec: SceneSpec) -> pin.Model:
    """A copy of the robot's model to modify; rebuilt from its (already checked) URDF to honour mimic joints."""
    if spec.robot is None or not spec.robot.mimic:
        return robot.model.copy()
    path = Path(robot.source["urdf_path"])
    text = read_urdf(path).decode("utf-8")
    model = (
        pin.buildModelFromXML(text, pin.JointModelFreeFlyer(), True)
        if robot.floating_base
        else pin.buildModelFromXML(text, True)
    )
    mimics = [model.names[j] for j in range(1, model.njoints) if model.joints[j].shortname() == "JointModelMimic"]
    if not mimics:
        raise SceneError(f"{spec.source}: robot.mimic: the URDF of '{robot.name}' declares no <mimic> joint")
    return model


def _apply_base_pose(model: pin.Model, spec: SceneSpec) -> None:
    """Weld the root at the scene's pose: every joint and frame attached to the world moves with it."""
    if spec.robot is None:
        return
    position, rpy = spec.robot.position, spec.robot.rpy
    if position is None and rpy is None:
        return
    pose = pin.SE3(pin.rpy.rpyToMatrix(*(rpy or (0.0, 0.0, 0.0))), np.array(position or (0.0, 0.0, 0.0), dtype=float))
    for jid in range(1, model.njoints):
        if model.parents[jid] == 0:
            model.jointPlacements[jid] = pose * model.jointPlacements[jid]
    for fid in range(len(model.frames)):
        frame = model.frames[fid]
        if frame.parentJoint == 0 and frame.name != "universe":
            frame.placement = pose * frame.placement
            model.frames[fid] = frame


def _add_payload(model: pin.Model, payload: Any, key: str) -> None:
    fid = frame_id(model, payload.frame, f"{key}.frame", moving=True)
    frame = model.frames[fid]
    model.inertias[frame.parentJoint] = model.inertias[frame.parentJoint] + frame.placement.act(
        _payload_inertia(payload)
    )


def _payload_inertia(payload: Any) -> pin.Inertia:
    """A payload's spatial inertia in its frame."""
    ixx, iyy, izz, ixy, ixz, iyz = payload.inertia
    inertia = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]], dtype=float)
    return pin.Inertia(float(payload.mass), np.array(payload.com, dtype=float), inertia)


def _lock_joints(model: pin.Model, spec: SceneSpec, floating: bool) -> tuple[pin.Model, np.ndarray]:
    """The reduced model without the locked joints, and the full configuration they are locked in."""
    reference = pin.neutral(model)
    if not spec.lock:
        return model, reference
    ids = []
    for joint, value in spec.lock.items():
        key = f"{spec.source}: lock.{joint}"
        jid = _joint_id(model, joint, key, floating)
        _set_joint_position(model, jid, value, reference, key)
        ids.append(jid)
    if len(ids) == len(_movable_joints(model)):
        raise SceneError(f"{spec.source}: lock: every joint is locked: nothing is left to simulate")
    return pin.buildReducedModel(model, ids, reference), reference


def _set_joint_position(model: pin.Model, jid: int, value: float, q: np.ndarray, key: str = "") -> None:
    joint = model.joints[jid]
    i = joint.idx_q
    if joint.nq == 1:
        lo, hi = model.lowerPositionLimit[i], model.upperPositionLimit[i]
        if key and -1e300 < lo < hi < 1e300 and not lo <= value <= hi:
            raise SceneError(f"{key}: {value:g} is outside the joint's limits [{lo:g}, {hi:g}]")
        q[i] = value
    else:  # a continuous joint: (cos, sin)
        q[i], q[i + 1] = math.cos(value), math.sin(value)


def _movable_joints(model: pin.Model) -> list[str]:
    return [model.names[j] for j in range(1, model.njoints) if model.joints[j].nv > 0]


def _one_dof_joints(model: pin.Model) -> list[str]:
    return [model.names[j] for j in range(1, model.njoints) if model.joints[j].nv == 1]


def _joint_id(model: pin.Model, name: str, key: str, floating: bool) -> int:
    """The id of a 1-dof joint by name, or SceneError naming the valid ones."""
    if model.existJointName(name) and model.joints[model.getJointId(name)].nv == 1:
        return model.getJointId(name)
    if floating and model.existJointName(name) and model.joints[model.getJointId(name)].nv == 6:
        raise SceneError(f"{key}: '{name}' is the floating base: it cannot be locked or given joint settings")
    raise SceneError(f"{key}: unknown joint '{name}' (valid: {', '.join(_one_dof_joints(model))})")


def _sensors(scene: Scene, spec: SceneSpec, declared: list[PayloadSpec]) -> Any:
    """The scene's sensors placed on its model (sensors.build_sensors, with this module's name checks), or None."""
    if not spec.sensors:
        return None
    from ..sensors import build_sensors

    where = spec.source
    payloads = [
        (frame_id(scene.model, p.frame, f"{where}: payload[{i}].frame", moving=True), _payload_inertia(p))
        for i, p in enumerate(declared)
    ]
    return build_sensors(scene, spec, frame_id=frame_id, joint_id=_joint_id, payloads=payloads)


def _wrench(model: pin.Model, force: Any, key: str) -> Any:
    from .elements import Wrench

    fid = frame_id(model, force.frame, f"{key}.frame", moving=True)
    return Wrench(
        name=force.name,
        frame_id=fid,
        force=np.array(force.force, dtype=float),
        torque=np.array(force.torque, dtype=float),
        reference=force.reference,
        scale=force.scale,
    )


def _initial_state(scene: Scene, spec: SceneSpec) -> tuple[np.ndarray, np.ndarray]:
    where = spec.source
    q, v = scene.default_pose(), np.zeros(scene.nv)  # the robot's SRDF pose where it has one, else neutral
    _place_objects(scene.model, spec, q, v)
    for key, given, size, target in (
        ("initial.q", spec.initial_q, scene.nq, q),
        ("initial.v", spec.initial_v, scene.nv, v),
    ):
        if given is None:
            continue
        if isinstance(given, dict):
            for joint, value in given.items():
                jid = _joint_id(scene.model, joint, f"{where}: {key}.{joint}", scene.floating_base)
                if key == "initial.q":
                    _set_joint_position(scene.model, jid, value, target)
                else:
                    target[scene.model.joints[jid].idx_v] = value
        else:
            if len(given) != size:
                locked = f" after locking {len(spec.lock)} joint(s)" if spec.lock else ""
                raise SceneError(f"{where}: {key}: has {len(given)} entries, the scene's model needs {size}{locked}")
            target[:] = given
    try:
        scene.check_q(q, "initial.q")
    except InvalidArgumentError as exc:
        raise SceneError(f"{where}: {exc}") from None
    return q, v


def _check_scene_model(scene: Robot, source: str, robot_nv: int, objects: int) -> None:
    """The checks a URDF's model passes, on the scene's (objects, payloads, locked joints): its size, finite numbers
    and physical inertias (an object whose size makes its inertia overflow is refused as a URDF body would be, not
    run into divergence; one whose inertia underflows, by _check_scene_mass_matrix)."""
    if scene.nv > MAX_DOFS:
        raise SceneError(
            f"{source}: the scene has {scene.nv} degrees of freedom ({robot_nv} of its robot, 6 for each of its "
            f"{objects} objects), more than the {MAX_DOFS} this simulator accepts"
        )
    try:
        check_model_numbers(scene.model, Path(source))
        check_body_inertias(scene.model, Path(source))
    except ModelError as exc:
        raise SceneError(str(exc)) from None


def _check_scene_mass_matrix(scene: Scene, source: str) -> None:
    """The scene's mass matrix at a few configurations: finite and not singular (catalog.check_mass_matrix)."""
    if not scene.nv:
        return
    try:
        check_mass_matrix(scene, Path(source))
    except ModelError as exc:
        raise SceneError(str(exc)) from None


def _add_objects(model: pin.Model, spec: SceneSpec, values: Nominals | None = None) -> dict[str, int]:
    """Append each [[object]] as a free-flyer joint of the world carrying its body (uniform density) and a body
    frame of its name, of the mass `values` gives it; returns {name: joint id}."""
    from .contact import shape_inertia

    joints = {}
    for i, item in enumerate(spec.objects):
        if values is not None:
            item = dataclasses.replace(item, mass=values.value("mass", item.name, item.mass))
        if model.existJointName(item.name) or model.existFrame(item.name):
            raise SceneError(
                f"{spec.source}: object[{i}].name: '{item.name}' is already a joint or frame of the robot; "
                "choose another name"
            )
        with np.errstate(over="ignore", under="ignore"):
            inertia = shape_inertia(item.shape.shape, item.shape.dimensions, item.mass)
        moments = np.diag(inertia.inertia)
        if not (np.all(np.isfinite(moments)) and np.all(moments > 0)):
            what = "overflow" if not np.all(np.isfinite(moments)) else "underflow to 0"
            raise SceneError(
                f"{spec.source}: object[{i}] ('{safe_name(item.name)}'): a {item.shape.shape} of "
                f"{' x '.join(f'{d:g}' for d in item.shape.dimensions)} m and {item.mass:g} kg has principal "
                f"inertias {', '.join(f'{m:.3g}' for m in moments)} kg·m²: they {what} (sizes in m, masses in kg)"
            )
        jid = model.addJoint(0, pin.JointModelFreeFlyer(), pin.SE3.Identity(), item.name)
        model.appendBodyToJoint(jid, inertia, pin.SE3.Identity())
        model.addBodyFrame(item.name, jid, pin.SE3.Identity(), 0)
        joints[item.name] = jid
    return joints


def _place_objects(model: pin.Model, spec: SceneSpec, q: np.ndarray, v: np.ndarray | None = None) -> None:
    """Write each object's declared pose into q (position, scalar-last quaternion) and, when v is given, its
    declared world-frame velocity as Pinocchio's body-frame (linear, angular) velocity."""
    for item in spec.objects:
        joint = model.joints[model.getJointId(item.name)]
        rotation = pin.rpy.rpyToMatrix(*item.rpy)
        q[joint.idx_q : joint.idx_q + 3] = item.position
        q[joint.idx_q + 3 : joint.idx_q + 7] = pin.Quaternion(rotation).coeffs()
        if v is not None:
            linear, angular = np.array(item.velocity[:3]), np.array(item.velocity[3:])
            v[joint.idx_v : joint.idx_v + 3] = rotation.T @ linear
            v[joint.idx_v + 3 : joint.idx_v + 6] = rotation.T @ angular


def _scene_name(spec: SceneSpec, robot: Robot) -> str:
    """The scene file's stem, or '<robot>-scene' for a scene built in Python."""
    return Path(spec.source).stem if spec.text is not None else f"{robot.name}-scene"


def _scene_source(spec: SceneSpec) -> dict[str, Any]:
    """How the scene was given, for trajectory metadata: its TOML text, or a description of the dict."""
    source: dict[str, Any] = {"source": spec.source}
    if spec.text is not None:
        source["toml"] = spec.text
    else:  # built in Python: its tables as text (a callable shape shows as its repr), so caches keyed on it differ
        source["spec"] = repr(dataclasses.replace(spec, text=None))
    if spec.base_dir is not None:
        source["base_dir"] = os.fspath(spec.base_dir)
    if spec.allowed_roots:  # recorded only when given (a replay needs them)
        source["allowed_roots"] = list(spec.allowed_roots)
    return source
