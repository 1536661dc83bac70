"""Scene files: read, parse and validate a scene's TOML (or the same dict built in Python) into frozen dataclasses.

This module checks structure and types only: unknown keys, wrong types, ranges, enumerations, counts. Names that
need the model (joints, frames) are checked later, when the Scene is built. Every problem is a
:class:`~multibody_sim.exceptions.SceneError` with one line, ``{source}: {key path}: {problem} (valid: ...)``,
where the key path reads like ``joints.panda_joint2.damping`` or ``force[1].shape``.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import numbers
import os
import re
import sys
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from ..catalog import CATALOG, MAX_DOFS
from ..controllers import CONTROLLERS
from ..exceptions import SceneError
from ..integrators import INTEGRATORS
from ..safety import MAX_TOML_DEPTH, toml_depth
from ..text import printable
from .spec import (
    ACTUATOR_GAINS,
    ACTUATOR_KEYS,
    ACTUATOR_KINDS,
    ACTUATOR_NUMBERS,
    ACTUATOR_OVERSPEED,
    ACTUATOR_SOURCES,
    BASES,
    CONSTRAINT_FRAMES,
    CONSTRAINT_KEYS,
    CONTACT_FRICTION,
    CONTACT_INTEGRATOR,
    CONTACT_KEYS,
    CONTACT_LIMITS,
    CONTACT_PAIRS,
    CONTACT_SOLVERS,
    DEFAULT_FRICTION_VELOCITY,
    DEFAULT_GROUND_FRICTION,
    DISTRIBUTIONS,
    FORCE_KEYS,
    GEOMETRY_KEYS,
    GROUND_KEYS,
    INITIAL_KEYS,
    JOINT_KEYS,
    OBJECT_KEYS,
    OBJECT_SHAPES,
    PARAMETER_KEYS,
    PAYLOAD_KEYS,
    QUANTITIES,
    RANDOMIZE_KEYS,
    REFERENCES,
    ROBOT_GEOMETRY,
    ROBOT_KEYS,
    SENSOR_KEYS,
    SENSOR_KINDS,
    SENSOR_PLACES,
    SHAPE_DIMENSIONS,
    SHAPE_KEYS,
    SHAPES,
    SIMULATION_KEYS,
    SIMULATION_OPTIONS,
    SPEED_CAPS,
    TARGET_KEYS,
    TOP_LEVEL_KEYS,
    ActuatorSpec,
    ConstraintSpec,
    ContactSpec,
    ControllerSpec,
    ForceSpec,
    GeometrySpec,
    GroundSpec,
    JointSpec,
    ObjectSpec,
    ParameterSpec,
    PayloadSpec,
    RandomizeSpec,
    RobotSpec,
    SceneSpec,
    SensorSpec,
    ShapeSpec,
    SimulationSpec,
)

OBJECT_DOFS = 6  # a free object's degrees of freedom (a free-flyer joint)
MAX_SCENE_BYTES = 1024 * 1024  # a scene is a few hundred bytes; a megabyte of TOML is not a scene
# Ledger names become keys of trajectory files ("ledger/force:<name>"): keep them short and plain.
_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")
_NAME_RULE = "1-64 letters, digits, '_', '.' or '-' (not starting with '.' or '-')"
_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")
_TOML_POSITION = re.compile(r"^(.*) \(at line (\d+), column (\d+)\)$", re.DOTALL)


# ---- reading -------------------------------------------------------------------------------------------
def read_scene_file(path: str | os.PathLike[str]) -> SceneSpec:
    """Read and validate a scene file (TOML).

    Scene files may come from strangers: files over MAX_SCENE_BYTES, binary files and text that is not UTF-8
    are refused before parsing. Relative paths in the file are relative to its folder.

    Args:
        path: the scene file; messages name it as given.

    Raises:
        SceneError: the file is missing, too large, not UTF-8 text, not valid TOML (the message gives TOML's
            line and column) or not a valid scene.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise SceneError(f"a scene file must be a path, got {type(path).__name__}")
    source = printable(os.fspath(path))
    file = Path(path).expanduser()
    if file.is_dir():
        raise SceneError(f"{source}: is a folder, not a scene file")
    if file.exists() and not file.is_file():  # a FIFO or a device would block or never end
        raise SceneError(f"{source}: not a regular file")
    try:
        with open(file, "rb") as stream:
            raw = stream.read(MAX_SCENE_BYTES + 1)  # never more than the limit, whatever the file claims
    except FileNotFoundError:
        raise SceneError(f"{source}: no such file") from None
    except OSError as exc:
        raise SceneError(printable(f"{source}: cannot read the file ({exc.strerror or exc})")) from None
    if len(raw) > MAX_SCENE_BYTES:
        raise SceneError(f"{source}: the file is larger than {MAX_SCENE_BYTES} bytes (1 MiB), too large for a scene")
    nul = raw.find(b"\0")
    if nul >= 0:  # TOML forbids it anyway; say plainly that this is a binary file
        raise SceneError(f"{source}: not a text file (NUL byte at offset {nul})")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SceneError(
            f"{source}: not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset {exc.start}); save it as UTF-8"
        ) from None
    spec = parse_scene(parse_toml(text, source), source, base_dir=file.absolute().parent)
    return dataclasses.replace(spec, text=text)


def parse_toml(text: str, source: str) -> dict[str, Any]:
    """A scene's TOML text as tables (a scene file's, or the text a trajectory stored), its nesting bounded first.

    Raises:
        SceneError: the text nests arrays and inline tables deeper than MAX_TOML_DEPTH (counted before parsing:
            tomllib recurses per level), or is not valid TOML (the message gives TOML's line and column).
    """
    depth = toml_depth(text)
    if depth > MAX_TOML_DEPTH:
        raise SceneError(
            f"{source}: refused: it nests arrays and inline tables {depth} levels deep, more than the "
            f"{MAX_TOML_DEPTH} a scene may (the shipped scenes nest 2 deep)"
        )
    if sys.version_info >= (3, 11):  # here, not at the top: its regular expressions slow `import multibody_sim`
        import tomllib
    else:  # pragma: no cover - exercised on Python 3.10 only
        import tomli as tomllib
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(printable(f"{source}: {_toml_problem(exc)}")) from None
    except RecursionError:  # what the count above missed (it should miss nothing)
        raise SceneError(f"{source}: TOML syntax error: values nested too deeply") from None


def _toml_problem(exc: Exception) -> str:
    """TOML's complaint as "TOML syntax error at line L, column C: what" (tomllib appends the position)."""
    message = str(exc)
    lineno, colno = getattr(exc, "lineno", None), getattr(exc, "colno", None)
    what = getattr(exc, "msg", None)
    if isinstance(lineno, int) and isinstance(colno, int) and isinstance(what, str):  # Python >= 3.14
        return f"TOML syntax error at line {lineno}, column {colno}: {what}"
    match = _TOML_POSITION.match(message)
    if match:
        return f"TOML syntax error at line {match[2]}, column {match[3]}: {match[1]}"
    return f"TOML syntax error: {message}"


def parse_actuator_file(path: Path) -> tuple[ActuatorSpec, ...]:
    """A catalog robot's published motor data (models/actuators/<robot>.toml): its [[actuator]] tables, checked as
    a scene's are (besides them the file holds only `description` and `sources`, the citations)."""
    source = printable(str(path))
    data = parse_toml(path.read_text(encoding="utf-8"), source)
    parser = _Parser(source, None)
    parser.table(data, "", ("description", "sources", "actuator"))
    tables = parser.array_of_tables(data.get("actuator", []), "actuator")
    return tuple(parser.actuator(value, f"actuator[{i}]") for i, value in enumerate(tables))


def parse_scene(data: Mapping[str, Any], source: str, *, base_dir: Path | None) -> SceneSpec:
    """Validate a scene's tables (from TOML or built in Python) into a SceneSpec.

    Args:
        data: the top-level table: description, gravity, friction_velocity, robot, lock, joints, force,
            payload, constraint, initial, simulation, controller.
        source: the name messages use (the file path as given, or "<scene>").
        base_dir: the folder relative robot paths resolve against (the scene file's); None: left as given
            (relative to the working directory).

    Raises:
        SceneError: one line naming source, the key path, the problem and the valid options.
    """
    return _Parser(printable(str(source)), base_dir).scene(data)


def parse_randomize(data: Any, source: str) -> RandomizeSpec:
    """A [randomize] table given apart from its scene (rollout's and the gym environments' `randomize`), checked
    as a scene's is.

    Raises:
        SceneError: one line naming the key path, the problem and the valid options.
    """
    return _Parser(printable(str(source)), None).randomize(data)


# ---- validation ----------------------------------------------------------------------------------------
def _describe(value: Any) -> str:
    """A value as a message shows it: TOML words for TOML types, bounded in length."""
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, str):
        return repr(value if len(value) <= 80 else value[:80] + "...")
    if isinstance(value, Mapping):
        return "a table"
    if isinstance(value, np.ndarray):
        return f"an array of shape {value.shape}"
    if isinstance(value, (list, tuple)):
        return f"an array of {len(value)}"
    if isinstance(value, numbers.Integral) and abs(int(value)) >= 10**20:
        return f"an integer of {len(str(abs(int(value))))} digits"
    if isinstance(value, numbers.Real):
        return repr(float(value)) if isinstance(value, float) else str(value)
    if value is None:
        return "None"
    return f"a {type(value).__name__}"


def _key(name: str) -> str:
    """A key as a path shows it: bare when TOML allows, quoted otherwise ("a.b" must not read as a path)."""
    return name if _BARE_KEY.fullmatch(name) else '"' + name.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _join(path: str, key: str) -> str:
    return f"{path}.{_key(key)}" if path else _key(key)


def _hint(word: str, options: Iterable[str]) -> str:
    close = difflib.get_close_matches(word, list(options), n=1, cutoff=0.6)
    return f"did you mean '{close[0]}'? " if close else ""


class _Parser:
    """The checks, with the source name every message starts with."""

    def __init__(self, source: str, base_dir: Path | None):
        self.source = source
        self.base_dir = base_dir

    def fail(self, path: str, problem: str) -> NoReturn:
        prefix = f"{self.source}: {path}: " if path else f"{self.source}: "
        raise SceneError(printable(prefix + problem))

    # -- generic shapes --
    def table(self, value: Any, path: str, valid: Sequence[str] | None = None) -> Mapping[str, Any]:
        """value as a table whose keys are strings (and among `valid` when given)."""
        if not isinstance(value, Mapping):
            self.fail(path, f"must be a table, got {_describe(value)}")
        for key in value:
            if not isinstance(key, str):
                self.fail(path, f"keys must be strings, got {_describe(key)}")
            if valid is not None and key not in valid:
                listing = ", ".join(sorted(valid))
                self.fail(path, f"unknown key '{key}' ({_hint(key, valid)}valid: {listing})")
        return value

    def array_of_tables(self, value: Any, path: str) -> list[Mapping[str, Any]]:
        if isinstance(value, Mapping):
            self.fail(path, f"must be an array of tables ([[{path}]] in TOML, a list of dicts in Python), got a table")
        if not isinstance(value, (list, tuple)):
            self.fail(path, f"must be an array of tables, got {_describe(value)}")
        return list(value)

    def number(self, value: Any, path: str) -> float:
        """A finite real number (not a boolean, not a string)."""
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
            self.fail(path, f"must be a real number, got {_describe(value)}")
        try:
            result = float(value)
        except OverflowError:  # a huge integer
            result = math.inf
        if not math.isfinite(result):
            self.fail(path, f"must be a finite number, got {_describe(value)}")
        return result

    def positive(self, value: Any, path: str, *, allow_zero: bool = False) -> float:
        result = self.number(value, path)
        if result < 0 or (result == 0 and not allow_zero):
            self.fail(path, f"must be {'>= 0' if allow_zero else '> 0'}, got {_describe(value)}")
        return result

    def vector(self, value: Any, path: str, size: int | None = None) -> tuple[float, ...]:
        """A list of finite real numbers, of exactly `size` entries when given."""
        wanted = f"an array of {size} numbers" if size is not None else "an array of numbers"
        if isinstance(value, np.ndarray) and value.ndim != 1:
            self.fail(path, f"must be {wanted}, got an array of shape {value.shape}")
        if not isinstance(value, (list, tuple, np.ndarray)):
            self.fail(path, f"must be {wanted}, got {_describe(value)}")
        if size is not None and len(value) != size:
            self.fail(path, f"must be {wanted}, got {len(value)}")
        return tuple(self.number(item, f"{path}[{i}]") for i, item in enumerate(value))

    def vec3(self, value: Any, path: str) -> tuple[float, float, float]:
        x, y, z = self.vector(value, path, 3)
        return (x, y, z)

    def string(self, value: Any, path: str) -> str:
        if not isinstance(value, str):
            self.fail(path, f"must be a string, got {_describe(value)}")
        if not value:
            self.fail(path, "must not be empty")
        return value

    def flag(self, value: Any, path: str) -> bool:
        if not isinstance(value, (bool, np.bool_)):
            self.fail(path, f"must be true or false, got {_describe(value)}")
        return bool(value)

    def choice(self, value: Any, path: str, options: Sequence[str]) -> str:
        listing = ", ".join(sorted(options))
        if not isinstance(value, str) or value not in options:
            hint = f" ({_hint(value, options).rstrip()})" if isinstance(value, str) and _hint(value, options) else ""
            self.fail(path, f"must be one of {listing}, got {_describe(value)}{hint}")
        return value

    def name(self, value: Any, path: str) -> str:
        text = self.string(value, path)
        if not _NAME.fullmatch(text):
            self.fail(path, f"must be {_NAME_RULE}, got {_describe(text)}")
        return text

    def required(self, table: Mapping[str, Any], key: str, path: str, what: str) -> Any:
        if key not in table:
            self.fail(_join(path, key), f"missing ({what})")
        return table[key]

    def path_value(self, text: str) -> str:
        """A path from the scene, relative ones made relative to the scene file's folder."""
        path = Path(text).expanduser()
        if self.base_dir is not None and not path.is_absolute():
            path = self.base_dir / path
        return str(path)

    # -- the tables --
    def scene(self, data: Any) -> SceneSpec:
        if not isinstance(data, Mapping):
            self.fail("", f"a scene must be a table of keys, got {_describe(data)}")
        self.table(data, "", TOP_LEVEL_KEYS)
        tables = self.array_of_tables(data.get("object", []), "object")
        if OBJECT_DOFS * len(tables) > MAX_DOFS:  # before building any: 10 000 objects ran 23 s into a MemoryError
            self.fail(
                "object",
                f"{len(tables)} objects have {OBJECT_DOFS * len(tables)} degrees of freedom, more than the "
                f"{MAX_DOFS} this simulator accepts ({MAX_DOFS // OBJECT_DOFS} objects at most, fewer beside a robot)",
            )
        objects = tuple(self.object(value, f"object[{i}]", i) for i, value in enumerate(tables))
        self.unique([o.name for o in objects], "object")
        if "robot" not in data and not objects:
            self.fail(
                "robot",
                "missing (a scene needs a [robot] table with source = a catalog name or URDF path, or [[object]]s)",
            )
        robot = self.robot(data["robot"]) if "robot" in data else None
        if robot is None:
            for key in ("lock", "joints", "payload", "constraint", "controller", "actuator", "actuators"):
                if key in data:
                    self.fail(key, "needs a robot: this scene has objects only (add a [robot] table)")
        ground = self.ground(data["ground"]) if "ground" in data else None
        contact = self.contact(data["contact"]) if "contact" in data else None
        if robot is None and contact is not None:
            if contact.geometry:
                self.fail("contact.geometry", "needs a robot: this scene has objects only")
            if contact.robot_geometry is not None:
                self.fail("contact.robot_geometry", "needs a robot: this scene has objects only")
            if contact.limits == "enforce" or contact.friction == "exact":
                key = "limits" if contact.limits == "enforce" else "friction"
                self.fail(f"contact.{key}", "needs a robot: this scene has objects only")
        lock = {
            key: self.number(value, _join("lock", key))
            for key, value in self.table(data.get("lock", {}), "lock").items()
        }
        joints = {}
        for key, value in self.table(data.get("joints", {}), "joints").items():
            path = _join("joints", key)
            if key in lock:
                self.fail(path, f"the joint is locked ({_join('lock', key)}); a locked joint takes no overrides")
            joints[key] = self.joint(value, path)
        forces = tuple(
            self.force(value, f"force[{i}]", i)
            for i, value in enumerate(self.array_of_tables(data.get("force", []), "force"))
        )
        self.unique([f.name for f in forces], "force")
        payloads = tuple(
            self.payload(value, f"payload[{i}]")
            for i, value in enumerate(self.array_of_tables(data.get("payload", []), "payload"))
        )
        constraints = tuple(
            self.constraint(value, f"constraint[{i}]", i)
            for i, value in enumerate(self.array_of_tables(data.get("constraint", []), "constraint"))
        )
        self.unique([c.name for c in constraints], "constraint")
        initial = self.table(data.get("initial", {}), "initial", INITIAL_KEYS)
        has_contact = ground is not None or contact is not None or bool(objects)
        if has_contact and constraints:
            self.fail(
                "constraint",
                "holonomic constraints and contact cannot be combined yet: the contact time-stepper does not solve "
                "[[constraint]] rows with its cones (drop [[constraint]], or [ground], [contact] and [[object]])",
            )
        actuators = tuple(
            self.actuator(value, f"actuator[{i}]")
            for i, value in enumerate(self.array_of_tables(data.get("actuator", []), "actuator"))
        )
        sensors = tuple(
            self.sensor(value, f"sensor[{i}]", i)
            for i, value in enumerate(self.array_of_tables(data.get("sensor", []), "sensor"))
        )
        self.unique([s.name for s in sensors], "sensor")
        if robot is None:
            for i, sensor in enumerate(sensors):
                if sensor.kind.startswith("joint_"):
                    self.fail(f"sensor[{i}].kind", f"{sensor.kind} needs a robot: this scene has objects only")
        simulation = self.simulation(data["simulation"]) if "simulation" in data else None
        declared = simulation.integrator if simulation is not None else None
        if has_contact and declared is not None and declared != CONTACT_INTEGRATOR:
            self.fail(
                "simulation.integrator",
                f"a scene with contact ([ground], [contact] or [[object]]) steps with {CONTACT_INTEGRATOR}, "
                f"got '{declared}'",
            )
        return SceneSpec(
            robot=robot,
            description=self.text(data.get("description", ""), "description"),
            gravity=self.vec3(data["gravity"], "gravity") if "gravity" in data else None,
            friction_velocity=self.positive(
                data.get("friction_velocity", DEFAULT_FRICTION_VELOCITY), "friction_velocity"
            ),
            lock=lock,
            joints=joints,
            forces=forces,
            payloads=payloads,
            constraints=constraints,
            initial_q=self.state(initial["q"], "initial.q") if "q" in initial else None,
            initial_v=self.state(initial["v"], "initial.v") if "v" in initial else None,
            simulation=simulation,
            controller=self.controller(data["controller"]) if "controller" in data else None,
            ground=ground,
            contact=contact,
            objects=objects,
            actuators=actuators,
            actuator_defaults=(
                self.choice(data["actuators"], "actuators", ACTUATOR_SOURCES) if "actuators" in data else None
            ),
            sensors=sensors,
            randomize=self.randomize(data["randomize"]) if "randomize" in data else None,
            source=self.source,
            text=None,
            base_dir=self.base_dir,
        )

    def text(self, value: Any, path: str) -> str:
        if not isinstance(value, str):
            self.fail(path, f"must be a string, got {_describe(value)}")
        return value

    def unique(self, names: list[str], path: str) -> None:
        seen: dict[str, int] = {}
        for i, name in enumerate(names):
            if name in seen:
                self.fail(f"{path}[{i}].name", f"'{name}' is already the name of {path}[{seen[name]}]")
            seen[name] = i

    def robot(self, value: Any) -> RobotSpec:
        table = self.table(value, "robot", ROBOT_KEYS)
        source = self.string(self.required(table, "source", "robot", "a catalog name or a URDF path"), "robot.source")
        base = self.choice(table["base"], "robot.base", BASES) if "base" in table else None
        if source not in CATALOG:  # a catalog name stays a name, as load_robot reads it
            source = self.path_value(source)
        natural_floating = CATALOG[source].floating_base if source in CATALOG else False
        for key in ("position", "rpy"):
            if key not in table:
                continue
            if base == "floating":
                self.fail(f"robot.{key}", 'only for a fixed base, not with base = "floating"')
            if base is None and natural_floating:
                self.fail(
                    f"robot.{key}",
                    f"only for a fixed base, and '{source}' is floating by default (add base = \"fixed\")",
                )
        dirs = table.get("package_dirs", [])
        if not isinstance(dirs, (list, tuple)):
            self.fail("robot.package_dirs", f"must be an array of folder paths, got {_describe(dirs)}")
        return RobotSpec(
            source=source,
            base=base,
            position=self.vec3(table["position"], "robot.position") if "position" in table else None,
            rpy=self.vec3(table["rpy"], "robot.rpy") if "rpy" in table else None,
            damping=self.flag(table.get("damping", True), "robot.damping"),
            mimic=self.flag(table.get("mimic", False), "robot.mimic"),
            package_dirs=tuple(self.path_value(self.string(d, f"robot.package_dirs[{i}]")) for i, d in enumerate(dirs)),
        )

    def joint(self, value: Any, path: str) -> JointSpec:
        table = self.table(value, path, JOINT_KEYS)
        values: dict[str, float] = {}
        for key in JOINT_KEYS:
            if key in table:
                sub = _join(path, key)
                values[key] = (
                    self.number(table[key], sub) if key == "rest" else self.positive(table[key], sub, allow_zero=True)
                )
        return JointSpec(**values)

    def actuator(self, value: Any, path: str) -> ActuatorSpec:
        table = self.table(value, path, ACTUATOR_KEYS)
        joints_value = self.required(
            table, "joints", path, 'a joint name, a list of names or a glob pattern ("*": every actuated joint)'
        )
        if isinstance(joints_value, str):
            joints: tuple[str, ...] = (self.string(joints_value, f"{path}.joints"),)
        elif isinstance(joints_value, (list, tuple)):
            joints = tuple(self.string(j, f"{path}.joints[{i}]") for i, j in enumerate(joints_value))
            if not joints:
                self.fail(f"{path}.joints", "must not be empty")
        else:
            self.fail(f"{path}.joints", f"must be a joint name or a list of names, got {_describe(joints_value)}")
        kind = self.choice(table["kind"], f"{path}.kind", ACTUATOR_KINDS) if "kind" in table else None
        if kind is not None:
            for gain in ("kp", "kv"):
                if gain in table and gain not in ACTUATOR_GAINS[kind]:
                    users = [k for k in ACTUATOR_KINDS if gain in ACTUATOR_GAINS[k]]
                    self.fail(f"{path}.{gain}", f"only for kind {' or '.join(users)}, not {kind}")
        overspeed = None
        if "overspeed" in table:
            overspeed = self.choice(table["overspeed"], f"{path}.overspeed", ACTUATOR_OVERSPEED)
        values: dict[str, float] = {}
        for key in ACTUATOR_NUMBERS:
            if key in table:
                values[key] = self.positive(
                    table[key], f"{path}.{key}", allow_zero=key in ("kp", "kv", "rotor_inertia")
                )
        if values.get("overspeed_band", 0.0) > 1.0:
            band = values["overspeed_band"]
            self.fail(f"{path}.overspeed_band", f"must be <= 1 (a fraction of the velocity limit), got {band:g}")
        return ActuatorSpec(joints=joints, kind=kind, overspeed=overspeed, **values)

    def force(self, value: Any, path: str, index: int) -> ForceSpec:
        table = self.table(value, path, FORCE_KEYS)
        name = self.name(table.get("name", f"force{index}"), f"{path}.name")
        frame = self.string(self.required(table, "frame", path, "the frame the force acts on"), f"{path}.frame")
        shape = table.get("shape", "constant")
        if callable(shape) and not isinstance(shape, str):
            kind = "callable"
        else:
            kind = shape = self.choice(shape, f"{path}.shape", SHAPES)
        for key in ("start", "ramp_time", "frequency", "phase"):
            if key in table and key not in SHAPE_KEYS[kind]:
                users = [s for s in SHAPES if key in SHAPE_KEYS[s]]
                listing = users[0] if len(users) == 1 else f"{', '.join(users[:-1])} or {users[-1]}"
                self.fail(f"{path}.{key}", f"only for shape {listing}, not {kind}")
        return ForceSpec(
            name=name,
            frame=frame,
            force=self.vec3(table.get("force", (0.0, 0.0, 0.0)), f"{path}.force"),
            torque=self.vec3(table.get("torque", (0.0, 0.0, 0.0)), f"{path}.torque"),
            reference=self.choice(table.get("reference", "world"), f"{path}.reference", REFERENCES),
            shape=shape,
            start=self.number(table.get("start", 0.0), f"{path}.start"),
            ramp_time=self.positive(table.get("ramp_time", 1.0), f"{path}.ramp_time"),
            frequency=self.positive(table.get("frequency", 1.0), f"{path}.frequency"),
            phase=self.number(table.get("phase", 0.0), f"{path}.phase"),
        )

    def payload(self, value: Any, path: str) -> PayloadSpec:
        table = self.table(value, path, PAYLOAD_KEYS)
        frame = self.string(
            self.required(table, "frame", path, "the frame the payload is attached to"), f"{path}.frame"
        )
        mass = self.positive(self.required(table, "mass", path, "kg, > 0"), f"{path}.mass")
        com = self.vec3(table.get("com", (0.0, 0.0, 0.0)), f"{path}.com")
        ixx, iyy, izz, ixy, ixz, iyz = self.vector(table.get("inertia", (0.0,) * 6), f"{path}.inertia", 6)
        inertia = (ixx, iyy, izz, ixy, ixz, iyz)
        self.check_inertia(inertia, f"{path}.inertia")
        return PayloadSpec(frame=frame, mass=mass, com=com, inertia=inertia)

    def check_inertia(self, inertia: tuple[float, ...], path: str) -> None:
        """A physical rotational inertia: positive semi-definite, each principal moment <= the sum of the others.

        Round-off allowance: 1e-12 of the trace (a diagonal written with 1e-3 entries passes exactly).
        """
        ixx, iyy, izz, ixy, ixz, iyz = inertia
        matrix = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
        moments = np.linalg.eigvalsh(matrix)
        tol = 1e-12 * max(abs(ixx) + abs(iyy) + abs(izz), np.abs(matrix).max())
        shown = ", ".join(f"{m:.6g}" for m in moments)
        if moments[0] < -tol:
            self.fail(path, f"not positive semi-definite (principal moments {shown} kg·m²)")
        if moments[2] > moments[0] + moments[1] + tol:
            self.fail(
                path,
                f"principal moments {shown} kg·m² break the triangle inequality (each at most the sum of the others)",
            )

    def constraint(self, value: Any, path: str, index: int) -> ConstraintSpec:
        table = self.table(value, path, CONSTRAINT_KEYS)
        name = self.name(table.get("name", f"constraint{index}"), f"{path}.name")
        kind = self.choice(
            self.required(table, "type", path, "loop, point or weld"), f"{path}.type", tuple(CONSTRAINT_FRAMES)
        )
        count = CONSTRAINT_FRAMES[kind]
        wanted = "two distinct frames" if count == 2 else "one frame"
        frames_value = self.required(table, "frames", path, f"{kind} needs {wanted}")
        if not isinstance(frames_value, (list, tuple)):
            self.fail(f"{path}.frames", f"must be an array of frame names, got {_describe(frames_value)}")
        frames = tuple(self.string(f, f"{path}.frames[{i}]") for i, f in enumerate(frames_value))
        if len(frames) != count:
            self.fail(f"{path}.frames", f"a {kind} constraint needs {wanted}, got {len(frames)}")
        if count == 2 and frames[0] == frames[1]:
            self.fail(f"{path}.frames", f"a {kind} constraint needs {wanted}, got '{frames[0]}' twice")
        if "position" in table and kind != "point":
            self.fail(f"{path}.position", f"only for type point, not {kind}")
        gains = None
        if "stabilization" in table:
            kp, kd = self.vector(table["stabilization"], f"{path}.stabilization", 2)
            for i, gain in enumerate((kp, kd)):
                if gain < 0:
                    self.fail(f"{path}.stabilization[{i}]", f"must be >= 0, got {_describe(table['stabilization'][i])}")
            gains = (kp, kd)
        return ConstraintSpec(
            name=name,
            type=kind,
            frames=frames,
            position=self.vec3(table["position"], f"{path}.position") if "position" in table else None,
            stabilization=gains,
        )

    def ground(self, value: Any) -> GroundSpec:
        table = self.table(value, "ground", GROUND_KEYS)
        restitution = self.positive(table.get("restitution", 0.0), "ground.restitution", allow_zero=True)
        if restitution > 1.0:
            self.fail("ground.restitution", f"must be within 0..1, got {_describe(table['restitution'])}")
        return GroundSpec(
            height=self.number(table.get("height", 0.0), "ground.height"),
            friction=self.positive(table.get("friction", DEFAULT_GROUND_FRICTION), "ground.friction", allow_zero=True),
            restitution=restitution,
        )

    def contact(self, value: Any) -> ContactSpec:
        table = self.table(value, "contact", CONTACT_KEYS)
        pairs_value = table.get("pairs", "ground")
        pairs: str | tuple[tuple[str, str], ...]
        if isinstance(pairs_value, str):
            pairs = self.choice(pairs_value, "contact.pairs", CONTACT_PAIRS)
        elif isinstance(pairs_value, (list, tuple)):
            found = []
            for i, pair in enumerate(pairs_value):
                path = f"contact.pairs[{i}]"
                if not isinstance(pair, (list, tuple)) or len(pair) != 2:
                    self.fail(path, f"must be a pair of body names [body, body], got {_describe(pair)}")
                first, second = (self.string(name, f"{path}[{k}]") for k, name in enumerate(pair))
                if first == second:
                    self.fail(path, f"must name two different bodies, got '{first}' twice")
                found.append((first, second))
            if not found:
                self.fail("contact.pairs", "must not be empty (valid: ground, all, or a list of [body, body] pairs)")
            pairs = tuple(found)
        else:
            self.fail(
                "contact.pairs",
                f"must be one of all, ground, or a list of [body, body] pairs, got {_describe(pairs_value)}",
            )
        restitution = self.positive(table.get("body_restitution", 0.0), "contact.body_restitution", allow_zero=True)
        if restitution > 1.0:
            self.fail("contact.body_restitution", f"must be within 0..1, got {_describe(table['body_restitution'])}")
        geometry = tuple(
            self.geometry(item, f"contact.geometry[{i}]")
            for i, item in enumerate(self.array_of_tables(table.get("geometry", []), "contact.geometry"))
        )
        return ContactSpec(
            pairs=pairs,
            limits=self.choice(table.get("limits", "report"), "contact.limits", CONTACT_LIMITS),
            velocity_limits=self.choice(table.get("velocity_limits", "enforce"), "contact.velocity_limits", SPEED_CAPS),
            friction=self.choice(table.get("friction", "regularized"), "contact.friction", CONTACT_FRICTION),
            solver=self.choice(table.get("solver", "admm"), "contact.solver", CONTACT_SOLVERS),
            body_friction=self.positive(
                table.get("body_friction", DEFAULT_GROUND_FRICTION), "contact.body_friction", allow_zero=True
            ),
            body_restitution=restitution,
            robot_geometry=(
                self.choice(table["robot_geometry"], "contact.robot_geometry", ROBOT_GEOMETRY)
                if "robot_geometry" in table
                else None
            ),
            geometry=geometry,
        )

    def shape(self, table: Mapping[str, Any], path: str) -> ShapeSpec:
        """The shape and exactly the dimensions it takes, each > 0."""
        kind = self.choice(
            self.required(table, "shape", path, "box, cylinder or sphere"), f"{path}.shape", OBJECT_SHAPES
        )
        for key in ("size", "radius", "length"):
            if key in table and key not in SHAPE_DIMENSIONS[kind]:
                users = [s for s in OBJECT_SHAPES if key in SHAPE_DIMENSIONS[s]]
                self.fail(f"{path}.{key}", f"only for shape {' or '.join(users)}, not {kind}")
        for key in SHAPE_DIMENSIONS[kind]:
            what = "[x, y, z] full extents in m" if key == "size" else "m, > 0"
            self.required(table, key, path, f"a {kind} needs {key}: {what}")
        size = None
        if "size" in table:
            size = self.vec3(table["size"], f"{path}.size")
            for i, extent in enumerate(size):
                if extent <= 0:
                    self.fail(f"{path}.size[{i}]", f"must be > 0, got {_describe(table['size'][i])}")
        return ShapeSpec(
            shape=kind,
            size=size,
            radius=self.positive(table["radius"], f"{path}.radius") if "radius" in table else None,
            length=self.positive(table["length"], f"{path}.length") if "length" in table else None,
        )

    def geometry(self, value: Any, path: str) -> GeometrySpec:
        table = self.table(value, path, GEOMETRY_KEYS)
        frame = self.string(self.required(table, "frame", path, "the frame the shape is attached to"), f"{path}.frame")
        return GeometrySpec(
            frame=frame,
            shape=self.shape(table, path),
            position=self.vec3(table.get("position", (0.0, 0.0, 0.0)), f"{path}.position"),
            rpy=self.vec3(table.get("rpy", (0.0, 0.0, 0.0)), f"{path}.rpy"),
        )

    def object(self, value: Any, path: str, index: int) -> ObjectSpec:
        table = self.table(value, path, OBJECT_KEYS)
        name = self.name(table.get("name", f"object{index}"), f"{path}.name")
        if name == "ground":
            self.fail(f"{path}.name", "'ground' names the ground plane; choose another name")
        x, y, z, wx, wy, wz = self.vector(table.get("velocity", (0.0,) * 6), f"{path}.velocity", 6)
        return ObjectSpec(
            name=name,
            shape=self.shape(table, path),
            mass=self.positive(self.required(table, "mass", path, "kg, > 0"), f"{path}.mass"),
            position=self.vec3(table.get("position", (0.0, 0.0, 0.0)), f"{path}.position"),
            rpy=self.vec3(table.get("rpy", (0.0, 0.0, 0.0)), f"{path}.rpy"),
            velocity=(x, y, z, wx, wy, wz),
        )

    def sensor(self, value: Any, path: str, index: int) -> SensorSpec:
        table = self.table(value, path, SENSOR_KEYS)
        kind = self.choice(self.required(table, "kind", path, ", ".join(SENSOR_KINDS)), f"{path}.kind", SENSOR_KINDS)
        name = self.name(table.get("name", f"{kind}{index}"), f"{path}.name")
        if "." in name:  # the dataframe's columns are <name>.<component>
            self.fail(f"{path}.name", f"must not contain '.' (columns are <name>.<component>), got {_describe(name)}")
        places = SENSOR_PLACES[kind]
        for key in ("frame", "joint", "body", "joints"):
            if key in table and key not in places:
                users = [k for k, keys in SENSOR_PLACES.items() if key in keys]
                self.fail(f"{path}.{key}", f"only for kind {', '.join(users)}, not {kind}")
        given = [key for key in places if key in table]
        if len(given) > 1:
            self.fail(f"{path}.{given[1]}", f"give one of {' or '.join(places)}, not both")
        if not given and places != ("joints",):
            self.fail(f"{path}.{places[0]}", f"missing (a {kind} sensor needs {' or '.join(places)})")
        joints = None
        if "joints" in table:
            value = table["joints"]
            if isinstance(value, str):
                value = [value]
            if not isinstance(value, (list, tuple)) or not value:
                self.fail(
                    f"{path}.joints", f"must be a joint name or a non-empty array of them, got {_describe(value)}"
                )
            joints = tuple(self.string(j, f"{path}.joints[{i}]") for i, j in enumerate(value))
            if len(set(joints)) != len(joints):
                self.fail(f"{path}.joints", "names a joint twice")
        rate = None
        if "rate" in table:
            rate = self.positive(table["rate"], f"{path}.rate")
        latency = self.whole(table.get("latency", 0), f"{path}.latency", 10**6, "readings ")
        seed = self.whole(table.get("seed", 0), f"{path}.seed", 2**63 - 1)
        return SensorSpec(
            name=name,
            kind=kind,
            frame=self.string(table["frame"], f"{path}.frame") if "frame" in table else None,
            joint=self.string(table["joint"], f"{path}.joint") if "joint" in table else None,
            body=self.string(table["body"], f"{path}.body") if "body" in table else None,
            joints=joints,
            noise=self.spoiler(table.get("noise", 0.0), f"{path}.noise", allow_negative=False),
            bias=self.spoiler(table.get("bias", 0.0), f"{path}.bias", allow_negative=True),
            rate=rate,
            latency=latency,
            seed=seed,
        )

    def whole(self, value: Any, path: str, high: int, unit: str = "") -> int:
        """A whole number within 0..high (not a boolean, not a float)."""
        if (
            isinstance(value, (bool, np.bool_))
            or not isinstance(value, numbers.Integral)
            or not 0 <= int(value) <= high
        ):
            self.fail(path, f"must be a whole number of {unit}within 0..{high}, got {_describe(value)}")
        return int(value)

    def spoiler(self, value: Any, path: str, *, allow_negative: bool) -> float | tuple[float, ...]:
        """A sensor's noise or bias: one number, or one per component (their count is checked with the model)."""
        if isinstance(value, (list, tuple, np.ndarray)):
            values = self.vector(value, path)
            if not values:
                self.fail(path, "must not be empty")
        else:
            values = (self.number(value, path),)
        if not allow_negative:
            for i, x in enumerate(values):
                if x < 0:
                    self.fail(
                        path
                        if len(values) == 1 and not isinstance(value, (list, tuple, np.ndarray))
                        else f"{path}[{i}]",
                        f"must be >= 0, got {x!r}",
                    )
        return values if isinstance(value, (list, tuple, np.ndarray)) else values[0]

    def state(self, value: Any, path: str) -> tuple[float, ...] | dict[str, float]:
        if isinstance(value, Mapping):
            return {key: self.number(item, _join(path, key)) for key, item in self.table(value, path).items()}
        if not isinstance(value, (list, tuple, np.ndarray)):
            self.fail(path, f"must be an array of numbers or a table {{joint = value}}, got {_describe(value)}")
        return self.vector(value, path)

    def simulation(self, value: Any) -> SimulationSpec:
        table = self.table(value, "simulation", SIMULATION_KEYS)
        integrator = None
        if "integrator" in table:
            integrator = self.choice(table["integrator"], "simulation.integrator", tuple(INTEGRATORS))
        return SimulationSpec(
            duration=self.positive(table["duration"], "simulation.duration") if "duration" in table else None,
            dt=self.positive(table["dt"], "simulation.dt") if "dt" in table else None,
            integrator=integrator,
            options={key: self.positive(table[key], f"simulation.{key}") for key in SIMULATION_OPTIONS if key in table},
        )

    def controller(self, value: Any) -> ControllerSpec:
        table = self.table(value, "controller")
        name = self.choice(
            self.required(table, "name", "controller", f"valid: {', '.join(sorted(CONTROLLERS))}"),
            "controller.name",
            tuple(CONTROLLERS),
        )
        parameters = {p.name: p for p in CONTROLLERS[name].parameters}
        self.table(table, "controller", ("name", *parameters))
        params: dict[str, Any] = {}
        for key, item in table.items():
            if key != "name":
                params[key] = self.parameter(item, f"controller.{key}", parameters[key].kind)
        for parameter in CONTROLLERS[name].parameters:
            if parameter.required and parameter.name not in params:
                self.fail(f"controller.{parameter.name}", f"missing (required by controller {name})")
        return ControllerSpec(name=name, params=params)

    def parameter(self, value: Any, path: str, kind: str) -> Any:
        """A controller parameter of make_controller's `kind`, with numbers kept int or float as written."""
        if kind == "flag":
            return self.flag(value, path)
        if kind == "text":
            return self.string(value, path)
        if kind == "integer":
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
                self.fail(path, f"must be a whole number, got {_describe(value)}")
            return int(value)
        if kind == "number" or (kind == "gain" and not isinstance(value, (list, tuple, np.ndarray))):
            return self.plain_number(value, path)
        if kind == "rows" and isinstance(value, np.ndarray) and value.ndim == 2:
            value = list(value)
        if (
            kind == "rows"
            and isinstance(value, (list, tuple))
            and value
            and isinstance(value[0], (list, tuple, np.ndarray))
        ):
            return tuple(self.plain_vector(row, f"{path}[{i}]") for i, row in enumerate(value))
        if kind == "vector" and not isinstance(value, (list, tuple, np.ndarray)):
            return (self.plain_number(value, path),)
        return self.plain_vector(value, path)

    def randomize(self, value: Any) -> RandomizeSpec:
        table = self.table(value, "randomize", RANDOMIZE_KEYS)
        seed = table.get("seed", 0)
        if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, numbers.Integral) or seed < 0:
            self.fail("randomize.seed", f"must be a whole number >= 0, got {_describe(seed)}")
        tables = self.array_of_tables(
            self.required(table, "parameter", "randomize", "[[randomize.parameter]] tables: what to draw"),
            "randomize.parameter",
        )
        if not tables:
            self.fail("randomize.parameter", "must hold at least one [[randomize.parameter]] table")
        parameters = tuple(self.random_parameter(item, f"randomize.parameter[{i}]") for i, item in enumerate(tables))
        return RandomizeSpec(seed=int(seed), parameters=parameters)

    def random_parameter(self, value: Any, path: str) -> ParameterSpec:
        """One [[randomize.parameter]]: its name, targets, distribution and range (checked against the quantity's
        range where the draw is the value itself; a scale's range is checked when the Scene knows the nominal)."""
        table = self.table(value, path, PARAMETER_KEYS)
        names = ", ".join(QUANTITIES)
        name = self.choice(self.required(table, "name", path, f"valid: {names}"), f"{path}.name", tuple(QUANTITIES))
        quantity = QUANTITIES[name]
        for key in TARGET_KEYS:
            if key in table and key != quantity.target:
                takes = f"takes {quantity.target} = ..." if quantity.target else "applies to the whole scene"
                self.fail(f"{path}.{key}", f"'{name}' {takes}, not {key}")
        target = quantity.target
        targets = self.targets(table.get(target, "*"), f"{path}.{target}", target) if target is not None else ()
        distribution = self.choice(
            self.required(
                table, "distribution", path, "uniform [low, high], normal [mean, std] or loguniform [low, high]"
            ),
            f"{path}.distribution",
            DISTRIBUTIONS,
        )
        if ("scale" in table) == ("value" in table):
            self.fail(
                path,
                "give scale = [a, b] (the draw multiplies the declared value) or value = [a, b] (the draw is the "
                "value)" + (", not both" if "scale" in table else ""),
            )
        scale = "scale" in table
        if quantity.scale_only and not scale:
            self.fail(f"{path}.value", f"'{name}' is a factor on the declared value: give scale = [a, b]")
        key = f"{path}.{'scale' if scale else 'value'}"
        a, b = self.vector(table["scale" if scale else "value"], key, 2)
        args = "[mean, std]" if distribution == "normal" else "[low, high]"
        if distribution == "normal":
            if b < 0:
                self.fail(key, f"normal takes {args} with std >= 0, got std {b:g}")
        elif a > b:
            self.fail(key, f"{distribution} takes {args} with low <= high, got [{a:g}, {b:g}]")
        if distribution == "loguniform" and a <= 0:
            self.fail(key, f"loguniform takes {args} with low > 0, got low {a:g}")
        if scale:
            low, high, open_low, unit = 0.0, math.inf, quantity.open_low, ""
        else:
            low, high, open_low, unit = quantity.low, quantity.high, quantity.open_low, quantity.unit
        inside = f"{'(' if open_low else '['}{low:g}, {high:g}{']' if math.isfinite(high) else ')'}"
        lowest = a  # normal: its mean must lie inside (draws outside are drawn again)
        highest = a if distribution == "normal" else b
        if lowest < low or (open_low and lowest <= low) or highest > high:
            what = "a factor" if scale else f"{name}{f' [{unit}]' if unit else ''}"
            self.fail(key, f"{distribution} {args} = [{a:g}, {b:g}] leaves the range of {what}, {inside}")
        return ParameterSpec(
            name=name,
            targets=targets,
            distribution=distribution,
            arguments=(a, b),
            scale=scale,
            shared=self.flag(table.get("shared", False), f"{path}.shared"),
        )

    def targets(self, value: Any, path: str, kind: str) -> tuple[str, ...]:
        """What a parameter applies to: names or glob patterns (bodies, joints) or indices (payloads, kept as
        strings); "*" is everything."""
        if kind == "payloads" and isinstance(value, numbers.Integral) and not isinstance(value, bool):
            value = [value]
        if isinstance(value, str):
            return (self.string(value, path),)
        if not isinstance(value, (list, tuple)) or not value:
            self.fail(path, f"must be a name, a glob pattern or a non-empty list of them, got {_describe(value)}")
        if kind == "payloads":
            indices = []
            for i, item in enumerate(value):
                if isinstance(item, (bool, np.bool_)) or not isinstance(item, numbers.Integral) or item < 0:
                    self.fail(
                        f"{path}[{i}]", f"must be a payload's index (0 is the first [[payload]]), got {_describe(item)}"
                    )
                indices.append(str(int(item)))
            return tuple(indices)
        return tuple(self.string(item, f"{path}[{i}]") for i, item in enumerate(value))

    def plain_number(self, value: Any, path: str) -> int | float:
        self.number(value, path)
        return int(value) if isinstance(value, numbers.Integral) else float(value)

    def plain_vector(self, value: Any, path: str) -> tuple[int | float, ...]:
        self.vector(value, path)
        if len(value) == 0:
            self.fail(path, "must not be empty")
        return tuple(self.plain_number(item, f"{path}[{i}]") for i, item in enumerate(value))
