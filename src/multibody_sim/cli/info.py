"""The commands that describe: `models` (the catalog and the shipped scenes), `inspect` (one robot or scene) and
`integrators` (the registry)."""

from __future__ import annotations

import argparse
import math
from typing import Any

import multibody_sim as ms

from ..text import safe_name, text_table
from .common import EXIT_OK, PROG, load_system, print_note, print_text, savings_line

_FLOATING_NOTE = (
    "floating base: q = [x y z qx qy qz qw, joints...] (unit quaternion, scalar last) and "
    "v = [linear, angular (both in the base frame), joints...], so nq = nv + 1 and dq/dt != v"
)


def cmd_models(args: argparse.Namespace) -> int:
    rows = ms.catalog_table()
    print_text(
        table(
            ["name", "nq", "nv", "base", "poses", "description"],
            [[r["name"], r["nq"], r["nv"], r["base"], _poses_cell(r), r["description"]] for r in rows],
        )
    )
    print_text(
        "\nposes: the SRDF's named poses (run ROBOT --q0 NAME); * marks the default pose, where runs start; "
        "- none: runs start from the neutral configuration"
    )
    from ..scenes import shipped_scenes
    from ..scenes.parse import read_scene_file

    scenes = shipped_scenes()
    if scenes:
        print_text(f"\nscenes (run one with `{PROG} run NAME`; the files are in {next(iter(scenes.values())).parent}):")
        scene_rows = [[name, read_scene_file(path).description] for name, path in scenes.items()]
        print_text(table(["name", "description"], scene_rows, indent=2))
    both = sorted(set(scenes) & set(ms.CATALOG))
    if both:
        print_text(
            f"\n{', '.join(both)}: both a robot and a scene; run, inspect and bench take the scene "
            f"(robot:{both[0]} for the robot alone)"
        )
    return EXIT_OK


def _poses_cell(row: dict[str, Any]) -> str:
    """A robot's poses for `models`: the default first, starred."""
    poses = sorted(row["poses"], key=lambda name: name != row["default_pose"])
    return ",".join(f"{name}*" if name == row["default_pose"] else name for name in poses) or "-"


def cmd_inspect(args: argparse.Namespace) -> int:
    from ..text import safe_name

    robot = load_system(args)
    print_note(args)
    if isinstance(robot, ms.Scene):
        print_text(robot.describe())
        print_text(savings_line(robot))
        print_text()
    model = robot.model
    entry = ms.CATALOG.get(args.robot)
    lines = [safe_name(robot.name) + (f": {entry.description}" if entry is not None else "")]
    source = robot.source
    derived = {"sdf": " (SDF, converted to URDF)"}.get(source.get("derivation", ""), "")
    if source.get("derivation", "").startswith("prune:"):
        derived = f" (without the subtree below {safe_name(source['derivation'].removeprefix('prune:'))})"
    lines += [f"URDF: {safe_name(source.get('urdf_path'))}{derived}", f"sha256: {source.get('urdf_sha256')}"]
    base = "floating (free-flyer root joint)" if robot.floating_base else "fixed (root link welded to the world)"
    lines += [f"base: {base}", f"nq: {robot.nq}  nv: {robot.nv}"]
    if robot.poses:
        named = ", ".join(safe_name(p) + (" (default)" if p == robot.default_pose_name else "") for p in robot.poses)
        lines.append(f"poses: {named} (from {safe_name(source.get('srdf_path'))})")
    elif not isinstance(robot, ms.Scene):
        lines.append("poses: none (runs start from the neutral configuration)")
    if isinstance(robot, ms.Scene):
        lines.append("start: the scene's initial state ([initial], else the robot's default pose; objects as declared)")
    welded = float(model.inertias[0].mass)
    lines.append(
        f"total mass: {robot.total_mass:.6g} kg"
        + (f" (moving bodies; {welded:.6g} kg welded to the world not counted)" if welded > 0 else "")
    )
    if robot.floating_base:
        lines.append(_FLOATING_NOTE)

    joint_rows = []
    for jid in range(1, model.njoints):
        joint = model.joints[jid]
        if joint.nv == 0:
            continue
        iq, iv = joint.idx_q, joint.idx_v
        kind = _joint_kind(joint.shortname())
        unit = "m" if kind == "prismatic" else "rad"
        if joint.nq == 1 and math.isfinite(robot.lower_limit[iq]):
            limits = f"[{robot.lower_limit[iq]:.6g}, {robot.upper_limit[iq]:.6g}] {unit}"
        else:
            limits = "none"
        if robot.floating_base and iv < 6:
            effort = velocity = "unactuated"
        else:
            velocity = _limit(robot.velocity_limit, joint, "m/s" if kind == "prismatic" else "rad/s")
            effort = _limit(robot.effort_limit, joint, "N" if kind == "prismatic" else "N·m")
        damping = ", ".join(f"{d:.6g}" for d in robot.damping[iv : iv + joint.nv])
        joint_rows.append([model.names[jid], kind, limits, velocity, effort, damping])
    headers = ["name", "type", "position limits", "velocity limit", "effort limit", "damping"]
    lines += ["", "joints (Pinocchio order; velocity limits act through a scene's [[actuator]]s):"]
    lines.append(table(headers, joint_rows, indent=2))

    # Pinocchio merges links joined by fixed joints into one body per joint; list the links in each.
    links: dict[int, list[str]] = {}
    for frame in model.frames:
        if frame.type.name == "BODY":
            links.setdefault(frame.parentJoint, []).append(frame.name)
    body_rows = []
    for jid in range(model.njoints):
        mass = float(model.inertias[jid].mass)
        if jid == 0 and mass == 0.0:
            continue
        moved_by = "(welded to the world)" if jid == 0 else model.names[jid]
        body_rows.append([moved_by, f"{mass:.6g}", ", ".join(links.get(jid, []))])
    lines += [
        "",
        "bodies (links joined by fixed joints are merged):",
        table(["moved by joint", "mass [kg]", "links"], body_rows, indent=2),
    ]
    print_text("\n".join(lines))
    return EXIT_OK


def _limit(limits: Any, joint: Any, unit: str) -> str:
    """A one-dof joint's velocity or effort limit with its unit, or "none"."""
    value = limits[joint.idx_v]
    return f"{value:.6g} {unit}" if joint.nv == 1 and math.isfinite(value) else "none"


def cmd_integrators(args: argparse.Namespace) -> int:
    rows, notes = [], []
    for name, method in ms.INTEGRATORS.items():
        properties = {"adaptive": method.adaptive, "implicit": method.implicit, "symplectic": method.symplectic}
        flags = [flag for flag, on in {**properties, "A-stable": method.a_stable}.items() if on]
        # Newton's iterations vary, so an implicit method's count is typical, not exact.
        evaluations = f"~{method.evaluations_per_step}" if method.implicit else method.evaluations_per_step
        rows.append([name, method.order, evaluations, ", ".join(flags) or "-", method.description])
        if method.notes:
            notes.append(f"  {name}: {method.notes}")
    print_text(table(["name", "order", "evaluations/step", "flags", "description"], rows))
    if notes:
        print_text("\nnotes:\n" + "\n".join(notes))
    return EXIT_OK


def _joint_kind(shortname: str) -> str:
    """The URDF word for a Pinocchio joint model (JointModelRZ -> revolute, JointModelRUBX -> continuous)."""
    short = shortname.removeprefix("JointModel")
    if short.startswith("RUB") or short.startswith("RevoluteUnbounded"):
        return "continuous"
    if short in ("RX", "RY", "RZ") or short.startswith("Revolute"):
        return "revolute"
    if short in ("PX", "PY", "PZ") or short.startswith("Prismatic"):
        return "prismatic"
    return {"FreeFlyer": "floating", "Planar": "planar", "Spherical": "spherical"}.get(short, short)


def table(headers: list[str], rows: list[list[Any]], indent: int = 0) -> str:
    """A listing's columns, names from files escaped (safe_name: one line each)."""
    return text_table(headers, rows, indent, cell=safe_name)
