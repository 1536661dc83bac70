"""Randomised physics: scene parameters drawn from a scene's [randomize] distributions (per rollout row, per gym
reset), and the checked parameter values a Scene is built with (Scene.with_parameters).

A scene's parameter values are a dict: ``{name: value}`` for a quantity of the whole scene (``ground_friction``,
``body_restitution``) and ``{name: {target: value}}`` for the others (target: a body's or a joint's name, a payload's
index as a string). Every value is the quantity itself in its unit (a mass in kg, a damping coefficient, a servo's
kp), except ``inertia``'s, a factor on the body's rotational inertia. Such a dict is what a randomised rollout row
records (``Trajectory.metadata["parameters"]``) and what ``Scene.with_parameters`` takes: the row re-run alone on that
scene gives its samples bit for bit (the values are applied by one function, Scene's constructor, both times).

Draws: row b of a rollout draws from numpy's generator seeded with ``(seed, b)`` (a gym reset from the environment's
generator): the [[randomize.parameter]] tables in order, each table's targets in model order, one draw per target
(or one for all of them with ``shared = true``); a later table overrides an earlier one on the same target. A
``scale`` draw multiplies the declared (nominal) value, a ``value`` draw is the value; a normal draw outside the
quantity's range (a negative mass, a restitution above 1) is drawn again (a truncated normal).
"""

from __future__ import annotations

import dataclasses
import fnmatch
import math
import numbers
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pinocchio as pin

from ..exceptions import InvalidArgumentError, SceneError
from ..text import printable, safe_name
from .spec import ACTUATOR_QUANTITIES, QUANTITIES, ContactSpec, ParameterSpec, PayloadSpec, RandomizeSpec, SceneSpec

# What one target of each kind is called in messages.
_ONE = {"bodies": "body", "joints": "joint", "payloads": "payload"}
# A truncated normal gives up after this many draws outside the quantity's range (the mean lies inside it, so only
# a std far beyond the range makes this likely).
MAX_REDRAWS = 10_000


class Nominals:
    """The values a Scene is built with, and the declared (nominal) value of each parameter it could be given.

    The Scene's constructor asks `value(name, target, nominal)` wherever a parameter enters (a body's mass, a joint's
    damping, a servo's kp, the ground's friction ...): it gets the given value, or the nominal one, which is kept
    in `nominal` ({name: {target: value}} or {name: value}) for the Randomizer to draw around and to check names.
    """

    def __init__(self, given: Mapping[str, Any] | None):
        self.given: Mapping[str, Any] = given or {}
        self.nominal: dict[str, Any] = {}

    def value(self, name: str, target: str | None, nominal: float) -> float:
        """The value of parameter `name` on `target` (None: the whole scene), given or nominal."""
        given = self.given.get(name)
        if target is None:
            self.nominal[name] = nominal
            return float(given) if given is not None else nominal
        self.nominal.setdefault(name, {})[target] = nominal
        if given is not None and target in given:
            return float(given[target])
        return nominal


def matching(patterns: Sequence[str], candidates: Sequence[str]) -> list[str]:
    """The candidates any of the glob patterns matches, in the candidates' order."""
    return [c for c in candidates if any(fnmatch.fnmatchcase(c, p) for p in patterns)]


def randomized(randomize: RandomizeSpec | None, name: str, candidates: Sequence[str]) -> set[str]:
    """The candidates (joints) a [randomize] table may draw `name` on: what the scene must keep an element for even
    where the declared value is 0 (a joint's friction, its damping), so that every row has the same ledger."""
    if randomize is None:
        return set()
    found: set[str] = set()
    for table in randomize.parameters:
        if table.name == name:
            found.update(matching(table.targets, candidates))
    return found


class Randomizer:
    """A scene's [randomize] table resolved on its nominal values: per [[randomize.parameter]], its targets.

    Args:
        spec: the [randomize] table.
        nominal: the nominal Scene's Nominals.nominal (what each parameter applies to, and its declared value).
        where: the scene's source, for messages.

    Raises:
        SceneError: a parameter the scene does not have (ground_friction without [ground]), a name or pattern that
            matches no target (the message lists the valid ones), a scale whose range takes a value out of its
            quantity's range.
    """

    def __init__(self, spec: RandomizeSpec, nominal: Mapping[str, Any], where: str):
        self.seed = spec.seed
        self.tables: list[tuple[ParameterSpec, list[str | None], list[float]]] = []
        for i, table in enumerate(spec.parameters):
            path = f"{where}: randomize.parameter[{i}]"
            quantity = QUANTITIES[table.name]
            if table.name not in nominal:
                raise SceneError(f"{path}.name: the scene has no {table.name} ({_needs(table.name)})")
            if quantity.target is None:
                targets: list[str | None] = [None]
                bases = [float(nominal[table.name])]
            else:
                valid = list(nominal[table.name])
                for pattern in table.targets:
                    if not matching([pattern], valid):
                        raise SceneError(
                            printable(
                                f"{path}.{quantity.target}: '{pattern}' matches none of the {quantity.target} "
                                f"{table.name} applies to ({', '.join(valid) or 'none'})"
                            )
                        )
                names = matching(table.targets, valid)
                targets = list(names)
                bases = [float(nominal[table.name][n]) for n in names]
            if table.scale:
                self._check_scaled(table, bases, targets, path)
            self.tables.append((table, targets, bases))

    @staticmethod
    def _check_scaled(table: ParameterSpec, bases: list[float], targets: list[str | None], path: str) -> None:
        """A scale's range must keep every nominal × factor inside the quantity's range (normal: its mean)."""
        quantity = QUANTITIES[table.name]
        a, b = table.arguments
        highest = a if table.distribution == "normal" else b
        for base, target in zip(bases, targets, strict=True):
            if base * highest > quantity.high:
                on = f" of {target}" if target else ""
                raise SceneError(
                    f"{path}.scale: {table.distribution} [{a:g}, {b:g}] takes {table.name}{on} ({base:g}) to "
                    f"{base * highest:g}, beyond its range [{quantity.low:g}, {quantity.high:g}]"
                )
            if quantity.open_low and base <= 0.0:
                raise SceneError(
                    f"{path}.scale: {table.name} of {target} is {base:g}: a scale cannot make it > 0 (draw a value)"
                )

    def draw(self, rng: np.random.Generator) -> dict[str, Any]:
        """One set of parameter values from `rng` (module docstring: the order of the draws)."""
        values: dict[str, Any] = {}
        for table, targets, bases in self.tables:
            quantity = QUANTITIES[table.name]
            shared = _draw(table, rng) if table.shared else None
            for target, base in zip(targets, bases, strict=True):
                x = shared if shared is not None else _draw(table, rng)
                value = base * x if table.scale else x
                tries = 1
                while table.distribution == "normal" and not _inside(value, quantity):
                    if tries >= MAX_REDRAWS:
                        raise SceneError(
                            f"randomize: {table.name}: {MAX_REDRAWS} normal draws fell outside its range: give a "
                            "smaller std"
                        )
                    x = _draw(table, rng)
                    value = base * x if table.scale else x
                    tries += 1
                if target is None:
                    values[table.name] = float(value)
                else:
                    values.setdefault(table.name, {})[target] = float(value)
        return values

    def row(self, b: int) -> dict[str, Any]:
        """The parameter values of rollout row b: drawn from numpy's generator seeded with (seed, b)."""
        return self.draw(np.random.default_rng((self.seed, b)))

    def describe(self) -> list[str]:
        """The describe() lines: what is drawn, on how many targets, from which distribution."""
        lines = [f"  randomized per rollout row / gym reset (seed {self.seed}):"]
        for table, targets, bases in self.tables:
            quantity = QUANTITIES[table.name]
            a, b = table.arguments
            law = {"uniform": "uniform", "normal": "normal", "loguniform": "log-uniform"}[table.distribution]
            args = f"mean {a:g}, std {b:g}" if table.distribution == "normal" else f"[{a:g}, {b:g}]"
            how = f"× {law} {args}" if table.scale else f"{law} {args}" + (f" {quantity.unit}" if quantity.unit else "")
            if targets == [None]:
                lines.append(f"    {table.name} ({bases[0]:g}) {how}")
                continue
            shown = ", ".join(str(t) for t in targets[:4]) + (f", ... ({len(targets)})" if len(targets) > 4 else "")
            lines.append(f"    {table.name} of {shown} {how}" + (" (one draw for all)" if table.shared else ""))
        return lines


def _draw(table: ParameterSpec, rng: np.random.Generator) -> float:
    a, b = table.arguments
    if table.distribution == "uniform":
        return float(rng.uniform(a, b))
    if table.distribution == "normal":
        return float(rng.normal(a, b))
    return float(math.exp(rng.uniform(math.log(a), math.log(b))))


def _inside(value: float, quantity: Any) -> bool:
    if quantity.open_low:
        return quantity.low < value <= quantity.high
    return quantity.low <= value <= quantity.high


def _needs(name: str) -> str:
    """What a scene needs for parameter `name` to exist."""
    if name.startswith("ground_"):
        return "it needs a [ground] table"
    if name.startswith("body_"):
        return "it needs contact: [ground], [contact] or [[object]]"
    if name == "payload_mass":
        return "it needs [[payload]] tables"
    if name in ("mass", "inertia"):
        return "it has no moving body"
    if name in ("damping", "friction", "armature"):
        return "it has no 1-dof joint"
    return "it needs [[actuator]] tables"


def check_parameters(parameters: Any, nominal: Mapping[str, Any]) -> dict[str, Any]:
    """Parameter values as Scene.with_parameters takes them, checked against what the scene has (`nominal`), as
    plain floats: InvalidArgumentError naming the first problem and the valid names otherwise."""
    if not isinstance(parameters, Mapping):
        raise InvalidArgumentError(
            f"parameters must be a dict {{name: value or {{target: value}}}} (a trajectory's "
            f"metadata['parameters']), got {type(parameters).__name__}"
        )
    checked: dict[str, Any] = {}
    for name, given in parameters.items():
        if name not in QUANTITIES:
            valid = ", ".join(QUANTITIES)
            raise InvalidArgumentError(printable(f"parameters: unknown parameter {name!r} (valid: {valid})"))
        if name not in nominal:
            raise InvalidArgumentError(f"parameters: the scene has no {name} ({_needs(name)})")
        quantity = QUANTITIES[name]
        if quantity.target is None:
            checked[name] = _checked_value(name, None, given, quantity)
            continue
        if not isinstance(given, Mapping):
            raise InvalidArgumentError(
                f"parameters: {name} must be a dict {{{_ONE[quantity.target]}: value}}, got {type(given).__name__}"
            )
        values = {}
        for target, value in given.items():
            if target not in nominal[name]:
                valid = ", ".join(map(str, nominal[name]))
                raise InvalidArgumentError(
                    printable(f"parameters: {name}: unknown {_ONE[quantity.target]} {target!r} (valid: {valid})")
                )
            values[target] = _checked_value(name, target, value, quantity)
        checked[name] = values
    return checked


def _checked_value(name: str, target: Any, value: Any, quantity: Any) -> float:
    on = f"[{target!r}]" if target is not None else ""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise InvalidArgumentError(printable(f"parameters: {name}{on} must be a real number, got {value!r:.80}"))
    x = float(value)
    if not math.isfinite(x) or not _inside(x, quantity):
        bracket = "(" if quantity.open_low else "["
        raise InvalidArgumentError(
            printable(
                f"parameters: {name}{on} must lie in {bracket}{quantity.low:g}, {quantity.high:g}], got {value!r:.80}"
            )
        )
    return x


# ---- where the Scene applies the values (its constructor calls these) ---------------------------------------------
BodyLinks = tuple[dict[int, str], dict[int, list[int]]]


def body_links(model: pin.Model) -> BodyLinks:
    """The robot's bodies as body_masses scales them: each joint's body name (the first body frame on it, its link;
    else the joint's name where it has none) and each joint's frames with a mass. The joints' and frames' structure
    only: a model with other masses has the same."""
    names: dict[int, str] = {}
    links: dict[int, list[int]] = {}
    for fid, frame in enumerate(model.frames):
        jid = int(frame.parentJoint)
        if frame.type == pin.FrameType.BODY and jid > 0:
            names.setdefault(jid, frame.name)
        if frame.inertia.mass > 0.0:
            links.setdefault(jid, []).append(fid)
    return names, links


def body_masses(model: pin.Model, values: Nominals, bodies: BodyLinks) -> None:
    """Each moving body's mass (its rotational inertia in proportion) and a factor on its rotational inertia, as
    `values` gives them, on the robot's model before payloads and locking. A body is the rigid body a joint moves,
    named by its link (the links welded to it are part of it); the links' own inertias (their frames', which a
    force-torque sensor inside the body sums) scale alike: each link's mass by the body's ratio, its rotational
    inertia about its own centre by the same factor. `bodies`: body_links() of that model."""
    names, links = bodies
    for jid in range(1, model.njoints):
        body = model.inertias[jid]
        if body.mass <= 0.0:  # nothing to scale
            continue
        name = names.get(jid, model.names[jid])
        mass = values.value("mass", name, float(body.mass))
        factor = values.value("inertia", name, 1.0)
        if mass != body.mass or factor != 1.0:
            ratio = mass / body.mass
            model.inertias[jid] = pin.Inertia(mass, body.lever, body.inertia * (ratio * factor))
            for fid in links.get(jid, ()):
                frame = model.frames[fid]
                link = frame.inertia
                frame.inertia = pin.Inertia(link.mass * ratio, link.lever, link.inertia * (ratio * factor))
                model.frames[fid] = frame


def payload_mass(payload: PayloadSpec, mass: float) -> PayloadSpec:
    """The payload with another mass, its inertia in proportion."""
    if mass == payload.mass:
        return payload
    ratio = mass / payload.mass
    return dataclasses.replace(payload, mass=mass, inertia=tuple(x * ratio for x in payload.inertia))  # type: ignore[arg-type]


def actuator_constants(actuator: Any, values: Nominals) -> Any:
    """An actuator with the constants `values` gives it. Each constant is a parameter only where the actuator
    has it: kp on position servos, kv on servos, the limits where finite, the curve where declared."""
    changed = {}
    for name in ACTUATOR_QUANTITIES:
        nominal = float(getattr(actuator, name))
        if name == "kp" and actuator.kind != "position" or name == "kv" and actuator.kind == "torque":
            continue
        if not math.isfinite(nominal):  # no limit, no curve: a value would add one, and a line to the ledger
            continue
        value = values.value(name, actuator.joint, nominal)
        if value != nominal:
            changed[name] = value
    return dataclasses.replace(actuator, **changed) if changed else actuator


def contact_values(spec: SceneSpec, values: Nominals | None) -> SceneSpec:
    """The scene with the ground's and the bodies' contact coefficients `values` gives."""
    if values is None:
        return spec
    if spec.ground is not None:
        ground = spec.ground
        friction = values.value("ground_friction", None, ground.friction)
        restitution = values.value("ground_restitution", None, ground.restitution)
        spec = dataclasses.replace(spec, ground=dataclasses.replace(ground, friction=friction, restitution=restitution))
    contact = spec.contact if spec.contact is not None else ContactSpec()
    friction = values.value("body_friction", None, contact.body_friction)
    restitution = values.value("body_restitution", None, contact.body_restitution)
    if (friction, restitution) != (contact.body_friction, contact.body_restitution):
        contact = dataclasses.replace(contact, body_friction=friction, body_restitution=restitution)
        spec = dataclasses.replace(spec, contact=contact)
    return spec


def shown(parameters: dict[str, Any]) -> str:
    """Parameter values in one line, a few per name."""
    parts = []
    for name, value in parameters.items():
        if isinstance(value, dict):
            items = list(value.items())
            shown = ", ".join(f"{safe_name(str(k))} {v:.4g}" for k, v in items[:3])
            parts.append(f"{name} {shown}" + (f", ... ({len(items)})" if len(items) > 3 else ""))
        else:
            parts.append(f"{name} {value:.4g}")
    return "; ".join(parts)
