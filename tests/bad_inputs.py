"""The catalogue of bad inputs: what a user (or a stranger's file) may hand us, and the one error each gets.

Data, not tests: tests/test_security.py checks every entry (the exact message; exit code 2 and one line on
stderr for the command line) and scripts/bad_inputs_table.py renders the same entries as docs/bad_inputs.md.
Each entry builds its input in a fresh folder and returns a Trigger: the API call that must raise, the command
line that must exit 2, and the values its message template is filled with.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import importlib.metadata
import importlib.util
import io
import json
import os
import pickle
import shutil
import signal
import socket
import struct
import subprocess
import sys
import xml.etree.ElementTree as ET
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import joint, link, urdf
from lxml import etree

import multibody_sim as ms

ROOT = Path(__file__).resolve().parents[1]

# Documented limits (docs/bad_inputs.md, catalog.py, safety.py), written out rather than imported: a change of
# limit must show up here and in the table users read.
MAX_URDF_BYTES = 32 * 1024 * 1024
MAX_XML_ELEMENTS = 100_000
MAX_LINKS = 1000
MAX_DOFS = 128
MAX_NPZ_MEMBERS = 4096
MIN_BUDGET_BYTES = 256 * 1024 * 1024
MAX_EXPANSION = 100

# A unique marker in a file outside every allowed folder: it must never appear in any message or output.
MARKER = "MBS-SECRET-7f3c9a1e-do-not-leak"
SECRET_NAME = "secret/passwords.txt"

BASE = '<link name="base"/>'
ONE_JOINT = BASE + link("bob") + joint("j1", "base", "bob")


@dataclass(frozen=True)
class Trigger:
    """How to produce one bad input's error.

    Attributes:
        call: the Python API call that must raise the entry's error (None for command-line-only entries).
        argv: the command line (after `multibody-sim`) that must exit 2 with the message (None for API-only).
        fields: values for the message template's {placeholders}.
        during: a context in which both run (a full disk, a signal at a chosen moment), or None.
        process: for what only a fresh process shows (the installed package's state, read once at import): runs
            `multibody-sim --version` there; its output must hold the message as one line.
    """

    call: Callable[[], object] | None = None
    argv: list[str] | None = None
    fields: dict[str, str] = field(default_factory=dict)
    during: Callable[[], contextlib.AbstractContextManager[Any]] | None = None
    process: Callable[[], subprocess.CompletedProcess[str]] | None = None


@dataclass(frozen=True)
class BadInput:
    """One catalogue entry.

    Attributes:
        id: short name (the pytest id).
        kind: "URDF file", "trajectory file", "command line", "Python API", "installed package", ...
        what: what the user did, in words.
        message: the exact message, with {placeholders} (paths differ from run to run).
        advice: what to do about it.
        build: makes the input in a fresh folder and says how to trigger the error.
        error: the exception class the API raises.
        code: the command line's exit code: 2 (bad input), or for a run that ends early 1 (failed) and 130 / 143
            (SIGINT / SIGTERM), whose line starts "multibody-sim: SIGINT: " instead of "multibody-sim: error: ";
            0 for an installed package whose compiled kernel cannot run (the Python kernel runs instead).
    """

    id: str
    kind: str
    what: str
    message: str
    advice: str
    build: Callable[[Path], Trigger]
    error: type[Exception] = ms.ModelError
    code: int = 2


# ur5's movable joints and the frames on its moving bodies, as the scene errors list them.
UR5_JOINTS = "shoulder_pan_joint, shoulder_lift_joint, elbow_joint, wrist_1_joint, wrist_2_joint, wrist_3_joint"
UR5_MOVING_FRAMES = (
    "shoulder_pan_joint, shoulder_link, shoulder_lift_joint, upper_arm_link, elbow_joint, forearm_link, "
    "wrist_1_joint, wrist_1_link, wrist_2_joint, wrist_2_link, wrist_3_joint, wrist_3_link, ee_fixed_joint, ee_link, "
    "wrist_3_link-tool0_fixed_joint, tool0"
)


# What the table shows for the placeholders (the tests fill in real paths).
DISPLAY = {
    "out": "/home/me/run.npz",
    "target": "/home/me/pipe",
    "lock": "/home/me/run.npz.lock",
    "pid": "12345",
    "parts": "/home/me/run.npz.parts",
    "other": "9c41d7e2a0b3",
    "mine": "5f0e8b2c7d16",
    "urdf": "/home/me/robot/robot.urdf",
    "dir": "/home/me/robot",
    "secret": "/home/me/secret/passwords.txt",
    "npz": "/home/me/run.npz",
    "folder": "/home/me/meshes",
    "libxml2": "Excessive depth in document: 256, use XML_PARSE_HUGE option, line 1, column 3011",
    "zlib": "Error -3 while decompressing data: invalid block type",
    "file_size": "1092",
    "total": "536871040",
    "member_size": "152",
    "integrators": "bs32, dop853, dp54, euler, ...",
    "adaptive": "bs32, dop853, dp54",
    "numpy": "('EOF in multi-line statement', (2, 0))",
    "scene": "/home/me/scene.toml",
    "roots": "/home/me, <site-packages>/multibody_sim/models, <site-packages>/cmeel.prefix/share",
    "trusted": "<site-packages>/multibody_sim/models, <site-packages>/cmeel.prefix/share, /home/me/robot",
    "joints": UR5_JOINTS,
    "frames": UR5_MOVING_FRAMES,
    "table": "/home/me/study.json",
    "extension": "<site-packages>/multibody_sim/_native.cpython-311-x86_64-linux-gnu.so",
    "size": "666804",
    "built": "1333608",
    "sources": "/home/me/multibody-sim/src/native",
    "pinocchio": "4.1.0",
}


def render(template: str, fields: dict[str, str]) -> str:
    """The message with its placeholders filled in."""
    return template.format(**fields)


# ---- building files ------------------------------------------------------------------------------------
def secret_file(tmp: Path) -> Path:
    """A file outside the robot's folder holding MARKER."""
    secret = tmp / SECRET_NAME
    secret.parent.mkdir(parents=True, exist_ok=True)
    secret.write_text(f"{MARKER}\nroot:x:0:0:root:/root:/bin/bash\n")
    return secret


def urdf_trigger(
    tmp: Path, text: str | bytes, *, fields: dict[str, str] | None = None, name: str = "robot.urdf"
) -> Trigger:
    """Write robot/robot.urdf (or another name: robot.xml for MJCF) beside a secret/ folder and load it through the
    API and `inspect`."""
    folder = tmp / "robot"
    folder.mkdir(exist_ok=True)
    path = folder / name
    path.write_bytes(text.encode() if isinstance(text, str) else text)
    secret = secret_file(tmp)
    values = {"urdf": str(path.resolve()), "dir": str(folder.resolve()), "secret": str(secret.resolve())}
    values.update(fields or {})
    return Trigger(call=lambda: ms.load_robot(path), argv=["inspect", str(path)], fields=values)


def with_mesh(uri: str) -> str:
    """A one-joint robot whose moving link shows the mesh at uri."""
    bob = link("bob").replace("</link>", f'<visual><geometry><mesh filename="{uri}"/></geometry></visual></link>')
    return urdf(BASE, bob, joint("j1", "base", "bob"))


def lol_doctype(levels: int) -> str:
    """The billion-laughs DTD: each entity is ten of the previous one (10**levels 'lol's at the top)."""
    entities = ['<!ENTITY lol0 "lol">']
    entities += [f'<!ENTITY lol{i} "{f"&lol{i - 1};" * 10}">' for i in range(1, levels + 1)]
    return f'<?xml version="1.0"?><!DOCTYPE robot [{"".join(entities)}]>'


def element_count(text: str) -> int:
    """Elements of an XML text, counted by the standard library's parser (not the code under test)."""
    return sum(1 for _ in ET.fromstring(text).iter())


def libxml2_error(data: bytes) -> str:
    """libxml2's own account of why it refuses data (the message the loader passes on)."""
    parser = etree.XMLParser(resolve_entities=False, no_network=True, load_dtd=False, huge_tree=False)
    try:
        etree.fromstring(data, parser=parser)
    except etree.XMLSyntaxError as exc:
        return str(exc.msg).replace("\n", "")  # passed on as one line
    raise AssertionError("libxml2 accepted the data")


def star(n_links: int, kind: str = "revolute") -> str:
    """A base with n_links - 1 links hanging from it, each on its own joint."""
    parts = [BASE]
    for i in range(1, n_links):
        parts += [link(f"l{i}"), joint(f"j{i}", "base", f"l{i}", kind=kind)]
    return urdf(*parts)


def many_elements(tmp: Path) -> Trigger:
    extra = MAX_XML_ELEMENTS
    text = urdf(ONE_JOINT).replace("</robot>", "<foo/>" * extra + "</robot>")
    return urdf_trigger(tmp, text, fields={"count": str(element_count(urdf(ONE_JOINT)) + extra)})


def deep_nesting(tmp: Path, levels: int) -> Trigger:
    text = urdf(ONE_JOINT).replace("</robot>", "<a>" * levels + "</a>" * levels + "</robot>")
    count = element_count(urdf(ONE_JOINT)) + levels
    if count > MAX_XML_ELEMENTS:  # refused by the element count before libxml2 sees the nesting
        return urdf_trigger(tmp, text, fields={"count": str(count)})
    return urdf_trigger(tmp, text, fields={"libxml2": libxml2_error(text.encode())})


def long_name(tmp: Path) -> Trigger:
    """A NaN mass on a link named with 10**6 letters: the message is cut to its first 1500 and last 400
    characters around a note of how much was left out (the documented rule)."""
    name = "A" * 10**6
    trigger = urdf_trigger(tmp, urdf(BASE, link(name, mass="nan"), joint("j1", "base", name)))
    full = f"{trigger.fields['urdf']}: link '{name}' has mass nan; it must be finite and >= 0"
    fields = {"head": full[:1500], "tail": full[-400:], "omitted": str(len(full) - 1900)}
    return Trigger(trigger.call, trigger.argv, {**trigger.fields, **fields})


def too_large(tmp: Path) -> Trigger:
    trigger = urdf_trigger(tmp, urdf(ONE_JOINT))
    path = Path(trigger.fields["urdf"])
    with path.open("r+b") as f:  # sparse: the size check must refuse it without reading 32 MiB
        f.truncate(MAX_URDF_BYTES + 1)
    return trigger


def mesh_outside(tmp: Path, uri_of: Callable[[Path], str]) -> Trigger:
    secret = secret_file(tmp)
    uri = uri_of(secret)
    trigger = urdf_trigger(tmp, with_mesh(uri))
    return Trigger(trigger.call, trigger.argv, {**trigger.fields, "uri": uri})


def mesh_symlink(tmp: Path) -> Trigger:
    trigger = urdf_trigger(tmp, with_mesh("meshes/bob.stl"))
    meshes = Path(trigger.fields["dir"]) / "meshes"
    meshes.mkdir()
    os.symlink(trigger.fields["secret"], meshes / "bob.stl")
    return trigger


# ---- building trajectory files -------------------------------------------------------------------------
def npz_trigger(path: Path, fields: dict[str, str] | None = None) -> Trigger:
    return Trigger(call=lambda: ms.Trajectory.load(path), fields={"npz": str(path), **(fields or {})})


def npy_header(shape: tuple[int, ...], descr: str = "<f8") -> bytes:
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": descr, "fortran_order": False, "shape": shape})
    return buffer.getvalue()


def claimed_shape(tmp: Path) -> Trigger:
    """An .npz whose q.npy header claims 10**12 x 3 doubles (24 TB) while holding three."""
    path = tmp / "claims.npz"
    member = npy_header((10**12, 3)) + np.zeros(3).tobytes()
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("q.npy", member)
    return npz_trigger(
        path, {"member_size": str(len(member)), "described": str(len(npy_header((10**12, 3))) + 24 * 10**12)}
    )


def malformed_header(tmp: Path) -> Trigger:
    """An .npz whose t.npy header is an unclosed Python literal (numpy's tokenizer fails on it)."""
    text = "{'descr': '<f8', 'fortran_order': False, 'shape': (3, "
    text += " " * (63 - len(text)) + "\n"  # padded to 64 bytes with the 10-byte prefix, as numpy writes
    member = b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text.encode() + np.zeros(3).tobytes()
    path = tmp / "run.npz"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("t.npy", member)
    try:  # numpy's own account, read straight from the bytes
        np.lib.format.read_array_header_1_0(io.BytesIO(member[8:]))
    except Exception as exc:  # noqa: BLE001 (whatever numpy raises is what the message quotes)
        return npz_trigger(path, {"numpy": str(exc).splitlines()[0]})
    raise AssertionError("numpy should refuse the header")


def write_zip(path: Path, members: list[tuple[str, bytes, int, int]]) -> None:
    """A zip of deflated members given as (name, deflate stream, CRC-32, uncompressed size), written by hand.

    The standard library would have to inflate (or hold) the data to write it; a bomb is built from its stream.
    """
    local, central = io.BytesIO(), io.BytesIO()
    for name, stream, crc, size in members:
        offset = local.tell()
        encoded = name.encode()
        # Local file header: signature, version 2.0, no flags, deflate, a fixed DOS time and date.
        sizes = (crc, len(stream), size, len(encoded))
        local.write(struct.pack("<4s5H3L2H", b"PK\x03\x04", 20, 0, 8, 0, 0x21, *sizes, 0) + encoded + stream)
        # Central directory entry: made by and needs 2.0; then as the local header; no comment, disk 0, offset.
        central.write(struct.pack("<4s6H3L5H2L", b"PK\x01\x02", 20, 20, 0, 8, 0, 0x21, *sizes, 0, 0, 0, 0, 0, offset))
        central.write(encoded)
    directory = central.getvalue()
    end = struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, len(members), len(members), len(directory), local.tell(), 0)
    path.write_bytes(local.getvalue() + directory + end)


BOMB_BYTES = 2 * MIN_BUDGET_BYTES  # twice what a small file may expand to: 512 MiB of zeros


@functools.cache
def deflate_bomb_member() -> tuple[bytes, int, int]:
    """(deflate stream, CRC-32, size) of a q.npy holding BOMB_BYTES of zeros: ~0.5 MB for 512 MiB.

    Built by repeating one compressed block: after a full flush, deflate restarts from an empty window, so the
    same input gives the same bytes (checked below).
    """
    header = npy_header((BOMB_BYTES // 8,))
    block_input = bytes(1 << 20)
    compressor = zlib.compressobj(9, zlib.DEFLATED, -15)
    start = compressor.compress(header) + compressor.flush(zlib.Z_FULL_FLUSH)
    block = compressor.compress(block_input) + compressor.flush(zlib.Z_FULL_FLUSH)
    again = compressor.compress(block_input) + compressor.flush(zlib.Z_FULL_FLUSH)
    assert block == again, "deflate blocks after a full flush should repeat"
    blocks = BOMB_BYTES // len(block_input)
    stream = start + block * blocks + compressor.flush(zlib.Z_FINISH)
    crc = zlib.crc32(header)
    for _ in range(blocks):
        crc = zlib.crc32(block_input, crc)
    return stream, crc, len(header) + BOMB_BYTES


def deflate_bomb(tmp: Path) -> Trigger:
    path = tmp / "bomb.npz"
    stream, crc, size = deflate_bomb_member()
    write_zip(path, [("q.npy", stream, crc, size)])
    return npz_trigger(path, {"file_size": str(path.stat().st_size), "total": str(size)})


def plain_npz(path: Path, compression: int = zipfile.ZIP_STORED) -> Path:
    """A small valid .npz (two arrays) written with the given zip compression."""
    with zipfile.ZipFile(path, "w", compression=compression) as archive:
        for name, array in (("t", np.linspace(0.0, 1.0, 11)), ("q", np.zeros((11, 2)))):
            buffer = io.BytesIO()
            np.save(buffer, array)
            archive.writestr(f"{name}.npy", buffer.getvalue())
    return path


def escape_named_member(path: Path) -> Path:
    """A bzip2 member whose name holds ESC [31m (a terminal colour change)."""
    buffer = io.BytesIO()
    np.save(buffer, np.zeros(3))
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_BZIP2) as archive:
        archive.writestr("q\x1b[31m.npy", buffer.getvalue())
    return path


def patched(path: Path, edit: Callable[[bytearray], None]) -> Path:
    data = bytearray(path.read_bytes())
    edit(data)
    path.write_bytes(bytes(data))
    return path


def set_member_count(data: bytearray) -> None:
    """Claim 65535 members in the end-of-central-directory record (the last 22 bytes: no comment)."""
    data[-22 + 8 : -22 + 12] = struct.pack("<2H", 0xFFFF, 0xFFFF)


def set_encrypted(data: bytearray) -> None:
    """Set the 'encrypted' flag of the first member in the central directory (zipfile reads it from there)."""
    at = data.index(b"PK\x01\x02")
    data[at + 8] |= 0x1


def set_version_needed(data: bytearray) -> None:
    """Claim that the first member needs zip version 11.7 to extract (central directory, offset 6)."""
    at = data.index(b"PK\x01\x02")
    data[at + 6 : at + 8] = struct.pack("<H", 117)


def corrupt_deflate(tmp: Path) -> Trigger:
    """A deflated .npz whose q.npy stream has its block bytes overwritten: zlib's error is computed here too."""
    path = plain_npz(tmp / "corrupt.npz", zipfile.ZIP_DEFLATED)
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo("q.npy")
    data = bytearray(path.read_bytes())
    start = info.header_offset + 30 + len(info.filename) + len(info.extra)
    data[start : start + 8] = b"\xff" * 8  # 0b11 block type: reserved, never valid
    path.write_bytes(bytes(data))
    try:
        zlib.decompressobj(-15).decompress(bytes(data[start : start + info.compress_size]))
    except zlib.error as exc:
        return npz_trigger(path, {"zlib": str(exc)})
    raise AssertionError("the corruption should break the deflate stream")


def truncated(tmp: Path) -> Trigger:
    path = plain_npz(tmp / "run.npz")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return npz_trigger(path)


def pickle_file(tmp: Path) -> Trigger:
    path = tmp / "run.npz"
    path.write_bytes(pickle.dumps({"t": [0.0, 1.0]}))
    return npz_trigger(path)


def object_array(tmp: Path) -> Trigger:
    path = tmp / "run.npz"
    objects = np.empty(1, dtype=object)
    objects[0] = {"anything": "pickled"}
    np.savez(path, t=np.zeros(2), q=objects)
    return npz_trigger(path)


def foreign_npz(tmp: Path) -> Trigger:
    path = tmp / "other.npz"
    np.savez(path, t=np.linspace(0, 1, 5), q=np.zeros((5, 2)))
    return npz_trigger(path)


# ---- command line and API ------------------------------------------------------------------------------
def cli(*argv: str, **fields: str) -> Callable[[Path], Trigger]:
    return lambda tmp: Trigger(argv=list(argv), fields=dict(fields))


def missing_folder(option: str, argument: str) -> Callable[[Path], Trigger]:
    def build(tmp: Path) -> Trigger:
        folder = tmp / "meshes"  # never created
        call = lambda: ms.load_robot("pendulum", **{argument: [folder]})  # noqa: E731
        return Trigger(call=call, argv=["inspect", "pendulum", option, str(folder)], fields={"folder": str(folder)})

    return build


def scene_trigger(text: str) -> Callable[[Path], Trigger]:
    """Write scene.toml and load it through the API and `run`."""

    def build(tmp: Path) -> Trigger:
        path = tmp / "scene.toml"
        path.write_text(text)
        fields = {"scene": str(path), "joints": UR5_JOINTS, "frames": UR5_MOVING_FRAMES}
        return Trigger(call=lambda: ms.load_scene(path), argv=["run", str(path)], fields=fields)

    return build


def constrained_scene_on_implicit() -> object:
    scene = ms.load_scene("four_bar")
    return ms.simulate(scene, scene.q0, scene.v0, duration=0.1, dt=1e-3, integrator="implicit_euler")


def api(call: Callable[[], object], **fields: str) -> Callable[[Path], Trigger]:
    return lambda tmp: Trigger(call=call, fields=dict(fields))


def pendulum() -> ms.Robot:
    return ms.load_robot("pendulum")


def adaptive_names() -> str:
    return ", ".join(sorted(name for name, method in ms.INTEGRATORS.items() if method.adaptive))


def integrator_names() -> str:
    return ", ".join(sorted(ms.INTEGRATORS))


DOCTYPE = "{urdf}: DOCTYPE declarations are not allowed in a URDF (entities could expand)"
OUTSIDE = "{urdf}: mesh '{uri}' resolves outside the allowed folders ({dir}); add its folder to package_dirs"
ALLOW_ROOT = "Move the mesh under the URDF's folder, or allow its folder: `--allow-root DIR` (`allowed_roots=[DIR]`)."
FIX_NUMBERS = "Fix the number in the URDF (usually an export or unit error)."

CATALOGUE: list[BadInput] = [
    # ---- hostile XML -----------------------------------------------------------------------------------
    BadInput(
        "billion-laughs",
        "URDF file",
        "a URDF with an entity-expansion bomb (billion laughs: 10⁹ 'lol's, ~3 GB if expanded)",
        DOCTYPE,
        "Remove the DOCTYPE: a URDF needs no DTD or entities (run xacro first if the file uses macros).",
        lambda tmp: urdf_trigger(tmp, lol_doctype(9) + f'<robot name="&lol9;">{ONE_JOINT}</robot>'),
    ),
    BadInput(
        "xxe-local-file",
        "URDF file",
        "a URDF whose external entity (XXE) names a local file",
        DOCTYPE,
        "Remove the DOCTYPE; nothing outside the robot's folders is ever read.",
        lambda tmp: urdf_trigger(
            tmp,
            f'<?xml version="1.0"?><!DOCTYPE robot [<!ENTITY x SYSTEM "file://{(tmp / SECRET_NAME).resolve()}">]>'
            f'<robot name="r">{ONE_JOINT}<material name="&x;"/></robot>',
        ),
    ),
    BadInput(
        "xxe-url",
        "URDF file",
        "a URDF whose external DTD is a URL",
        DOCTYPE,
        "Remove the DOCTYPE; loading never touches the network.",
        lambda tmp: urdf_trigger(
            tmp,
            '<?xml version="1.0"?><!DOCTYPE robot SYSTEM "http://127.0.0.1:9/robot.dtd">'
            f'<robot name="r">{ONE_JOINT}</robot>',
        ),
    ),
    BadInput(
        "doctype-after-long-comment",
        "URDF file",
        "a DOCTYPE hidden after a 100 kB comment",
        DOCTYPE,
        "Remove the DOCTYPE.",
        lambda tmp: urdf_trigger(
            tmp,
            '<?xml version="1.0"?><!--'
            + "x" * 100_000
            + "-->"
            + lol_doctype(3)
            + f'<robot name="&lol3;">{ONE_JOINT}</robot>',
        ),
    ),
    BadInput(
        "file-too-large",
        "URDF file",
        "a URDF file larger than 32 MiB",
        "{urdf}: file is 33554433 bytes, larger than the 33554432-byte limit for a URDF",
        "This is not a robot description (the largest catalog URDF is ~200 kB); check the file.",
        too_large,
    ),
    BadInput(
        "too-many-elements",
        "URDF file",
        "a URDF with more than 100 000 XML elements",
        "{urdf}: the file has {count} XML elements, more than the 100000 a URDF may have "
        "(the largest catalog robot has about 2000)",
        "Check the file; a real robot has a few thousand elements at most.",
        many_elements,
        # placeholders shown in the table
    ),
    BadInput(
        "nested-100k-deep",
        "URDF file",
        "100 000 nested elements",
        "{urdf}: the file has {count} XML elements, more than the 100000 a URDF may have "
        "(the largest catalog robot has about 2000)",
        "Check the file.",
        lambda tmp: deep_nesting(tmp, MAX_XML_ELEMENTS),
    ),
    BadInput(
        "nested-300-deep",
        "URDF file",
        "elements nested 300 deep",
        "{urdf}: malformed XML ({libxml2})",
        "Check the file; URDF elements nest 4 to 6 deep.",
        lambda tmp: deep_nesting(tmp, 300),
    ),
    BadInput(
        "not-xml",
        "URDF file",
        "a binary file given as a URDF",
        "{urdf}: malformed XML ({libxml2})",
        "Pass the URDF itself (run xacro on .xacro files first).",
        lambda tmp: urdf_trigger(
            tmp, bytes(range(1, 256)) * 4, fields={"libxml2": libxml2_error(bytes(range(1, 256)) * 4)}
        ),
    ),
    BadInput(
        "root-not-robot",
        "URDF file",
        "an SDF (or any XML whose root is not `<robot>`)",
        "{urdf}: not a URDF: the root element is <sdf>, expected <robot>",
        "Convert the model to URDF.",
        lambda tmp: urdf_trigger(tmp, '<sdf version="1.6"><model name="m"/></sdf>'),
    ),
    # ---- size of the model -----------------------------------------------------------------------------
    BadInput(
        "too-many-links",
        "URDF file",
        "a robot with 1001 links",
        "{urdf}: the robot has 1001 links, more than the 1000 this simulator accepts "
        "(the largest catalog robot has 78)",
        "Split or simplify the model (Pinocchio's URDF parser crashes on chains of ~4000 links).",
        lambda tmp: urdf_trigger(tmp, star(MAX_LINKS + 1)),
    ),
    BadInput(
        "50k-links",
        "URDF file",
        "a robot with 50 000 links",
        "{urdf}: the robot has 50001 links, more than the 1000 this simulator accepts "
        "(the largest catalog robot has 78)",
        "Split or simplify the model.",
        # Two links of ONE_JOINT and 49 999 bare ones: 50 013 elements, under the element limit.
        lambda tmp: urdf_trigger(tmp, urdf(ONE_JOINT, *(f'<link name="x{i}"/>' for i in range(49_999)))),
    ),
    BadInput(
        "too-many-dofs",
        "URDF file",
        "a robot with 22 floating joints (132 degrees of freedom)",
        "{urdf}: the robot has 132 degrees of freedom, more than the 128 this simulator accepts",
        "Weld the joints you do not need (Pinocchio's workspace grows as the cube of the number of dof).",
        lambda tmp: urdf_trigger(tmp, star(23, kind="floating")),
    ),
    # ---- mesh paths ------------------------------------------------------------------------------------
    BadInput(
        "mesh-package-dotdot",
        "URDF file",
        "a mesh URI climbing out of its package (`package://x/../../…`)",
        OUTSIDE,
        ALLOW_ROOT,
        lambda tmp: mesh_outside(tmp, lambda secret: "package://x/../../" + SECRET_NAME),
    ),
    BadInput(
        "mesh-absolute-path",
        "URDF file",
        "an absolute mesh path outside the allowed folders",
        OUTSIDE,
        ALLOW_ROOT,
        lambda tmp: mesh_outside(tmp, lambda secret: str(secret.resolve())),
    ),
    BadInput(
        "mesh-file-uri",
        "URDF file",
        "a `file://` mesh URI outside the allowed folders",
        OUTSIDE,
        ALLOW_ROOT,
        lambda tmp: mesh_outside(tmp, lambda secret: f"file://{secret.resolve()}"),
    ),
    BadInput(
        "mesh-symlink-out",
        "URDF file",
        "a mesh inside the robot's folder that is a symlink to a file outside",
        "{urdf}: mesh 'meshes/bob.stl' resolves outside the allowed folders ({dir}); add its folder to package_dirs",
        "Copy the mesh instead of linking it, or allow the link's target folder with `--allow-root`.",
        mesh_symlink,
    ),
    BadInput(
        "texture-outside",
        "URDF file",
        "a material texture outside the allowed folders (viewers would read it)",
        "{urdf}: texture '{secret}' resolves outside the allowed folders ({dir}); add its folder to package_dirs",
        ALLOW_ROOT.replace("the mesh", "the texture"),
        lambda tmp: urdf_trigger(
            tmp,
            urdf(ONE_JOINT, f'<material name="m"><texture filename="{secret_file(tmp).resolve()}"/></material>'),
        ),
    ),
    BadInput(
        "mesh-url",
        "URDF file",
        "a mesh URI with a network scheme",
        "{urdf}: mesh URI 'http://example.com/bob.stl' has an unsupported scheme (use package:// or a file path)",
        "Download the mesh and refer to it by package:// or a relative path.",
        lambda tmp: urdf_trigger(tmp, with_mesh("http://example.com/bob.stl")),
    ),
    # ---- numbers ---------------------------------------------------------------------------------------
    BadInput(
        "mass-nan",
        "URDF file",
        "a NaN mass",
        "{urdf}: link 'bob' has mass nan; it must be finite and >= 0",
        FIX_NUMBERS,
        lambda tmp: urdf_trigger(tmp, urdf(BASE, link("bob", mass="nan"), joint("j1", "base", "bob"))),
    ),
    BadInput(
        "mass-negative",
        "URDF file",
        "a negative mass",
        "{urdf}: link 'bob' has mass -1.0; it must be finite and >= 0",
        FIX_NUMBERS,
        lambda tmp: urdf_trigger(tmp, urdf(BASE, link("bob", mass=-1.0), joint("j1", "base", "bob"))),
    ),
    BadInput(
        "inertia-negative-eigenvalue",
        "URDF file",
        "an inertia with a negative eigenvalue (ixx = 0.01, ixy = 0.02)",
        "{urdf}: link 'bob' has an inertia with a negative eigenvalue (-0.01)",
        "Recompute the inertia (an inertia matrix is positive semi-definite).",
        lambda tmp: urdf_trigger(
            tmp, urdf(BASE, link("bob"), joint("j1", "base", "bob")).replace('ixy="0"', 'ixy="0.02"')
        ),
    ),
    BadInput(
        "inertia-triangle",
        "URDF file",
        "principal inertias 0.01, 0.01, 0.05 (no body has them: 0.01 + 0.01 < 0.05)",
        "{urdf}: the body moved by joint 'j1' has principal inertias 0.01, 0.01, 0.05 that violate the "
        "triangle inequality",
        "Recompute the inertia (each principal moment is at most the sum of the other two).",
        lambda tmp: urdf_trigger(tmp, urdf(BASE, link("bob", inertia="0.01 0.01 0.05"), joint("j1", "base", "bob"))),
    ),
    BadInput(
        "massless-moving-subtree",
        "URDF file",
        "a moving link with no mass and no inertia at the end of a chain (singular mass matrix)",
        "{urdf}: the mass matrix is singular: the subtree moved by 'j2' has no mass or inertia",
        "Give the link a mass and inertia, or make its joint fixed (massless links fixed to a parent are fine).",
        lambda tmp: urdf_trigger(
            tmp,
            urdf(
                BASE,
                link("arm"),
                joint("j1", "base", "arm"),
                '<link name="tip"/>',
                joint("j2", "arm", "tip", xyz="0 0 -1"),
            ),
        ),
    ),
    BadInput(
        "mass-matrix-overflow",
        "URDF file",
        "a centre of mass 10²⁰⁰ m away (finite, but M(q) overflows)",
        "{urdf}: the model Pinocchio built for joint 'j1' has non-finite values",
        FIX_NUMBERS,
        lambda tmp: urdf_trigger(tmp, urdf(BASE, link("bob", com="0 0 -1e200"), joint("j1", "base", "bob"))),
    ),
    BadInput(
        "origin-nan",
        "URDF file",
        "a NaN in a joint origin",
        "{urdf}: joint 'j1' has a non-finite origin",
        FIX_NUMBERS,
        lambda tmp: urdf_trigger(tmp, urdf(BASE, link("bob"), joint("j1", "base", "bob", xyz="nan 0 0"))),
    ),
    BadInput(
        "limits-inverted",
        "URDF file",
        "a lower position limit above the upper one",
        "{urdf}: joint 'j1' has lower limit 2.0 above its upper limit 1.0",
        "Swap the limits (or set both to 0 for no limit).",
        lambda tmp: urdf_trigger(
            tmp,
            urdf(BASE, link("bob"), joint("j1", "base", "bob", limits='lower="2" upper="1" effort="1" velocity="1"')),
        ),
    ),
    BadInput(
        "damping-negative",
        "URDF file",
        "negative joint damping (it would feed energy in)",
        "{urdf}: joint 'j1' has damping -0.5; it must be finite and >= 0",
        FIX_NUMBERS,
        lambda tmp: urdf_trigger(tmp, urdf(BASE, link("bob"), joint("j1", "base", "bob", damping=-0.5))),
    ),
    # ---- structure -------------------------------------------------------------------------------------
    BadInput(
        "duplicate-joints",
        "URDF file",
        "two joints with the same name",
        "{urdf}: duplicate joint names (j1)",
        "Rename one of them.",
        lambda tmp: urdf_trigger(
            tmp, urdf(BASE, link("arm"), link("tip"), joint("j1", "base", "arm"), joint("j1", "arm", "tip"))
        ),
    ),
    BadInput(
        "detached-cycle",
        "URDF file",
        "two links that are each other's parent, apart from the tree",
        "{urdf}: the joints form a cycle (links a, b are not connected to the root)",
        "URDF describes trees: remove one of the joints (closed chains need constraints, not joints).",
        lambda tmp: urdf_trigger(
            tmp, urdf(ONE_JOINT, link("a"), link("b"), joint("ab", "a", "b"), joint("ba", "b", "a"))
        ),
    ),
    BadInput(
        "unsupported-joint",
        "URDF file",
        "a joint type URDF does not define (ball)",
        "{urdf}: joint 'j1' has unsupported type 'ball' (supported: continuous, fixed, floating, planar, "
        "prismatic, revolute)",
        "Use one of the supported types (a ball joint is three revolute joints).",
        lambda tmp: urdf_trigger(tmp, urdf(BASE, link("bob"), joint("j1", "base", "bob", kind="ball"))),
    ),
    BadInput(
        "urdfdom-skips-inertial",
        "URDF file",
        "an inertial origin with one number instead of three (Pinocchio's parser would drop the link's mass)",
        "{urdf}: Pinocchio's URDF parser skipped part of the file (Parser found 1 elements but 3 expected while "
        "parsing vector [0.0])",
        "Fix the element the message quotes; a model missing part of its file would simulate other dynamics.",
        lambda tmp: urdf_trigger(
            tmp,
            urdf(BASE, link("bob", com="0.0"), joint("j1", "base", "bob"), link("tip"), joint("j2", "bob", "tip")),
        ),
    ),
    BadInput(
        "urdfdom-duplicate-material",
        "URDF file",
        "two materials with the same name (refused by Pinocchio's URDF parser, whose log is not printed)",
        "{urdf}: Pinocchio cannot build the model (material 'm' is not unique.)",
        "Rename or remove the duplicate material.",
        lambda tmp: urdf_trigger(tmp, urdf(ONE_JOINT, *['<material name="m"><color rgba="1 0 0 1"/></material>'] * 2)),
    ),
    # ---- what messages quote from the file -------------------------------------------------------------
    BadInput(
        "name-with-line-break",
        "URDF file",
        "a joint name holding a line break (`&#10;`) in a file with an error",
        "{urdf}: joint 'j\\x0a1' has a non-finite origin",
        "Messages escape control characters: the error stays on one line.",
        lambda tmp: urdf_trigger(tmp, urdf(BASE, link("bob"), joint("j&#10;1", "base", "bob", xyz="nan 0 0"))),
    ),
    BadInput(
        "name-with-terminal-escape",
        "URDF file",
        "a link name holding a terminal control sequence (CSI, U+009B, legal in XML)",
        "{urdf}: link 'bob\\x9b2J' has mass nan; it must be finite and >= 0",
        "Messages escape control characters: nothing in a file can drive your terminal.",
        lambda tmp: urdf_trigger(tmp, urdf(BASE, link("bob&#x9b;2J", mass="nan"), joint("j1", "base", "bob&#x9b;2J"))),
    ),
    BadInput(
        "megabyte-name",
        "URDF file",
        "a link name one million characters long in a file with an error",
        "{head} [... {omitted} characters omitted ...] {tail}",
        "Messages are cut to 2000 characters (the start and the end kept).",
        lambda tmp: long_name(tmp),
    ),
    # ---- trajectory files ------------------------------------------------------------------------------
    BadInput(
        "npz-claimed-shape",
        "trajectory file",
        "a trajectory whose array header claims 10¹² × 3 doubles (24 TB) but holds three",
        "{npz}: not a readable trajectory file (member 'q.npy' holds {member_size} bytes but its header "
        "describes {described}: shape (1000000000000, 3), dtype float64)",
        "The file is corrupted or forged: regenerate it.",
        claimed_shape,
        ms.TrajectoryFileError,
    ),
    BadInput(
        "npz-deflate-bomb",
        "trajectory file",
        "a zip bomb: 512 MiB of zeros deflated to half a megabyte",
        "{npz}: refused: its arrays would take more than 268435456 bytes once read (at least {total}, from a "
        "{file_size}-byte file; the limit is 100 times the file's size or 268435456 bytes, whichever is larger)",
        "Do not load files from strangers that expand this much; files we write are never compressed.",
        deflate_bomb,
        ms.TrajectoryFileError,
    ),
    BadInput(
        "npz-bzip2",
        "trajectory file",
        "an .npz whose members are bzip2-compressed (bzip2 inflates far more per byte than deflate)",
        "{npz}: not a trajectory file (member 't.npy' uses zip compression method 12; only stored and deflated "
        "members are read)",
        "Re-save with numpy (np.savez or np.savez_compressed).",
        lambda tmp: npz_trigger(plain_npz(tmp / "run.npz", zipfile.ZIP_BZIP2)),
        ms.TrajectoryFileError,
    ),
    BadInput(
        "npz-member-name-escape",
        "trajectory file",
        "an archive member named with a terminal escape sequence (ESC [31m)",
        "{npz}: not a trajectory file (member 'q\\x1b[31m.npy' uses zip compression method 12; only stored and "
        "deflated members are read)",
        "Messages escape control characters: nothing in a file can drive your terminal.",
        lambda tmp: npz_trigger(escape_named_member(tmp / "run.npz")),
        ms.TrajectoryFileError,
    ),
    BadInput(
        "npz-encrypted",
        "trajectory file",
        "an .npz with an encrypted member",
        "{npz}: not a trajectory file (member 't.npy' is encrypted)",
        "Decrypt it first.",
        lambda tmp: npz_trigger(patched(plain_npz(tmp / "run.npz"), set_encrypted)),
        ms.TrajectoryFileError,
    ),
    BadInput(
        "npz-too-many-members",
        "trajectory file",
        "an archive claiming 65 535 members",
        "{npz}: not a trajectory file (65535 archive members, more than 4096)",
        "The file is not a trajectory.",
        lambda tmp: npz_trigger(patched(plain_npz(tmp / "run.npz"), set_member_count)),
        ms.TrajectoryFileError,
    ),
    BadInput(
        "npz-malformed-header",
        "trajectory file",
        "an array header that is not a valid Python literal (found by fuzzing)",
        "{npz}: not a readable trajectory file (member 't.npy' has a malformed .npy header: {numpy})",
        "The file is damaged or forged: regenerate it.",
        malformed_header,
        ms.TrajectoryFileError,
    ),
    BadInput(
        "npz-future-zip-version",
        "trajectory file",
        "an archive whose directory says a member needs zip version 11.7 (found by fuzzing)",
        "{npz}: not a readable trajectory file (zip file version 11.7)",
        "The file is damaged or not a trajectory.",
        lambda tmp: npz_trigger(patched(plain_npz(tmp / "run.npz"), set_version_needed)),
        ms.TrajectoryFileError,
    ),
    BadInput(
        "npz-corrupt-deflate",
        "trajectory file",
        "a compressed trajectory with corrupted bytes",
        "{npz}: not a readable trajectory file ({zlib})",
        "The file is damaged: copy it again.",
        corrupt_deflate,
        ms.TrajectoryFileError,
    ),
    BadInput(
        "npz-truncated",
        "trajectory file",
        "a trajectory file cut in half (an interrupted copy)",
        "{npz}: not a readable trajectory file (File is not a zip file)",
        "Copy it again; runs write their files atomically, so a file we wrote is whole or absent.",
        truncated,
        ms.TrajectoryFileError,
    ),
    BadInput(
        "npz-is-pickle",
        "trajectory file",
        "a pickle renamed to .npz",
        "{npz}: not a trajectory file (not an .npz archive)",
        "Never unpickle files from strangers; trajectories are plain arrays.",
        pickle_file,
        ms.TrajectoryFileError,
    ),
    BadInput(
        "npz-object-array",
        "trajectory file",
        "an .npz holding a pickled object array",
        "{npz}: not a readable trajectory file (Object arrays cannot be loaded when allow_pickle=False)",
        "Trajectories hold numbers only; the file was not written by multibody-sim.",
        object_array,
        ms.TrajectoryFileError,
    ),
    BadInput(
        "npz-not-ours",
        "trajectory file",
        "an .npz written by something else",
        "{npz}: not a multibody-sim trajectory (no valid header)",
        "Load it with numpy directly.",
        foreign_npz,
        ms.TrajectoryFileError,
    ),
    # ---- command line ----------------------------------------------------------------------------------
    BadInput(
        "allow-root-missing",
        "command line",
        "`--allow-root` naming a folder that does not exist",
        "allowed_roots: '{folder}' is not a folder",
        "Check the path.",
        missing_folder("--allow-root", "allowed_roots"),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "package-dir-missing",
        "command line",
        "`--package-dir` naming a folder that does not exist",
        "package_dirs: '{folder}' is not a folder",
        "Check the path.",
        missing_folder("--package-dir", "package_dirs"),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "dt-nan",
        "command line",
        "`run pendulum --dt nan`",
        "dt must be a positive number of seconds, got nan",
        "Give a positive step in seconds.",
        cli("run", "pendulum", "--dt", "nan"),
    ),
    BadInput(
        "duration-inf",
        "command line",
        "`run pendulum --duration inf`",
        "duration must be a positive number of seconds, got inf",
        "Give a finite duration; Ctrl-C stops a long run and keeps its samples.",
        cli("run", "pendulum", "--duration", "inf"),
    ),
    BadInput(
        "q0-nan",
        "command line",
        "`run pendulum --q0 nan`",
        "q0 must be finite, got non-finite entries at indices [0]",
        "Give nq finite numbers.",
        cli("run", "pendulum", "--q0", "nan"),
    ),
    BadInput(
        "unknown-integrator",
        "command line",
        "`run pendulum --integrator magic`",
        "unknown integrator 'magic' (valid: {integrators})",
        "Pick one of the listed names (`multibody-sim integrators` describes them).",
        lambda tmp: Trigger(
            argv=["run", "pendulum", "--integrator", "magic"], fields={"integrators": integrator_names()}
        ),
    ),
    # ---- Python API ------------------------------------------------------------------------------------
    BadInput(
        "source-not-a-path",
        "Python API",
        "`load_robot(42)`",
        "source must be a catalog name or a URDF path, got int",
        "Pass a catalog name or a path.",
        api(lambda: ms.load_robot(42)),  # type: ignore[arg-type]
        ms.InvalidArgumentError,
    ),
    BadInput(
        "floating-base-not-bool",
        "Python API",
        "`load_robot('pendulum', floating_base='yes')`",
        "floating_base must be True, False or None, got 'yes'",
        "Pass True, False or None (the catalog's natural base).",
        api(lambda: ms.load_robot("pendulum", floating_base="yes")),  # type: ignore[arg-type]
        ms.InvalidArgumentError,
    ),
    BadInput(
        "package-dirs-a-string",
        "Python API",
        "`load_robot(path, package_dirs='/opt/share')` (one string, not a list)",
        "package_dirs must be a list of folders, got str",
        "Pass a list: `package_dirs=['/opt/share']`.",
        api(lambda: ms.load_robot("pendulum", package_dirs="/opt/share")),  # type: ignore[arg-type]
        ms.InvalidArgumentError,
    ),
    BadInput(
        "q0-wrong-shape",
        "Python API",
        "`simulate(pendulum, [0, 0], [0], ...)` (two numbers for a one-joint robot)",
        "q0 must have shape (1,), got (2,)",
        "Give nq numbers (`robot.nq`).",
        api(lambda: ms.simulate(pendulum(), [0.0, 0.0], [0.0], duration=1.0, dt=1e-3)),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "dt-zero",
        "Python API",
        "`simulate(..., dt=0)`",
        "dt must be a positive number of seconds, got 0",
        "Give a positive step.",
        api(lambda: ms.simulate(pendulum(), [0.0], [0.0], duration=1.0, dt=0)),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "option-not-for-this-integrator",
        "Python API",
        "`simulate(..., integrator='rk4', rtol=1e-6)`",
        "option 'rtol' does not apply to the fixed-step integrator 'rk4' (it applies to the adaptive "
        "integrators: {adaptive})",
        "Drop the option, or choose an adaptive integrator.",
        lambda tmp: Trigger(
            call=lambda: ms.simulate(pendulum(), [0.0], [0.0], duration=1.0, dt=1e-3, rtol=1e-6),
            fields={"adaptive": adaptive_names()},
        ),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "quaternion-not-unit",
        "Python API",
        "a floating base's quaternion that is not of unit norm",
        "q0 is not a valid configuration: its quaternion / (cos, sin) entries must have unit norm",
        "Normalize the quaternion (x y z w, scalar last).",
        api(lambda: ms.simulate(ms.load_robot("free_body"), [0, 0, 0, 0, 0, 0, 2.0], [0.0] * 6, duration=1.0, dt=1e-3)),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "torque-on-floating-base",
        "Python API",
        "a non-zero torque on a floating base's six unactuated coordinates",
        "tau[0:6] acts on the unactuated floating base and must be zero, got [1.0, 0.0, 0.0, 0.0, 0.0, 0.0]",
        "Forces on the base come from scene elements, not from tau.",
        api(
            lambda: ms.load_robot("free_body").forward_dynamics(
                [0, 0, 0, 0, 0, 0, 1.0], [0.0] * 6, [1.0, 0, 0, 0, 0, 0]
            )
        ),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "scene-unknown-key",
        "scene file",
        "a misspelt top-level key in a scene",
        "{scene}: unknown key 'gravty' (did you mean 'gravity'? valid: actuator, actuators, constraint, contact, "
        "controller, description, force, friction_velocity, gravity, ground, initial, joints, lock, object, payload, "
        "randomize, robot, sensor, simulation)",
        "Fix the key; every table lists its valid keys the same way.",
        scene_trigger('gravty = [0, 0, 0]\n[robot]\nsource = "ur5"\n'),
        ms.SceneError,
    ),
    BadInput(
        "scene-unknown-joint",
        "scene file",
        "joint settings for a joint the robot does not have",
        "{scene}: joints.elbow: unknown joint 'elbow' (valid: {joints})",
        "Use one of the listed names (`multibody-sim inspect ROBOT` shows them).",
        scene_trigger('[robot]\nsource = "ur5"\n[joints.elbow]\ndamping = 1.0\n'),
        ms.SceneError,
    ),
    BadInput(
        "scene-unknown-frame",
        "scene file",
        "a force on a frame the robot does not have (a misspelt one)",
        "{scene}: force[0].frame: unknown frame 'tool9' (did you mean 'tool0'?)",
        "Use the frame offered, or one `multibody-sim inspect` lists (only frames on moving bodies take forces and "
        "payloads; a name close to none gets the list of valid frames).",
        scene_trigger('[robot]\nsource = "ur5"\n[[force]]\nframe = "tool9"\nforce = [1.0, 0.0, 0.0]\n'),
        ms.SceneError,
    ),
    BadInput(
        "scene-lock-floating-base",
        "scene file",
        "locking a floating base",
        "{scene}: lock.root_joint: 'root_joint' is the floating base: it cannot be locked or given joint settings",
        'Give the robot a fixed base instead ([robot] base = "fixed", with position and rpy).',
        scene_trigger('[robot]\nsource = "solo12"\n[lock]\nroot_joint = 0.0\n'),
        ms.SceneError,
    ),
    BadInput(
        "scene-q-length-after-locking",
        "scene file",
        "an initial configuration sized for the full robot after locking joints",
        "{scene}: initial.q: has 9 entries, the scene's model needs 7 after locking 2 joint(s)",
        "Give the reduced model's q (locked joints left out), or a table {{joint = value}}.",
        scene_trigger(
            '[robot]\nsource = "panda"\n[lock]\npanda_finger_joint1 = 0.0\npanda_finger_joint2 = 0.0\n'
            "[initial]\nq = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]\n"
        ),
        ms.SceneError,
    ),
    BadInput(
        "scene-toml-syntax",
        "scene file",
        "a scene file that is not valid TOML",
        "{scene}: TOML syntax error at line 1, column 7: Expected ']' at the end of a table declaration",
        "Fix the TOML at the given line and column.",
        scene_trigger('[robot\nsource = "ur5"\n'),
        ms.SceneError,
    ),
    BadInput(
        "constrained-scene-implicit",
        "Python API",
        "an implicit integrator on a scene with constraints",
        "integrator 'implicit_euler' needs the dynamics' analytic derivatives, which scene 'four_bar' does not "
        "provide (it has constraints: loop); use one of: bs32, dop853, dp54, euler, midpoint, rk4, "
        "semi_implicit_euler, timestepping",
        "Use an explicit integrator: constraints are solved with Lagrange multipliers at each stage.",
        api(constrained_scene_on_implicit),
        ms.InvalidArgumentError,
    ),
]


# ---- trajectory headers, outputs, runs that end early, chunked parts (issue 17, the files part) --------------
def edited_trajectory(edit: Callable[[dict[str, Any]], str | None]) -> Callable[[Path], Trigger]:
    """A real pendulum trajectory whose JSON header `edit` changes in place (or replaces: it returns the text)."""

    def build(tmp: Path) -> Trigger:
        path = tmp / "run.npz"
        ms.simulate(pendulum(), [1.0], [0.0], duration=0.05, dt=0.01).save(path)
        with np.load(path, allow_pickle=False) as npz:
            contents = {name: npz[name] for name in npz.files}
        header = json.loads(str(contents["header"][()]))
        text = edit(header)
        contents["header"] = np.array(json.dumps(header) if text is None else text)
        with path.open("wb") as f:
            np.savez(f, **contents)
        return npz_trigger(path)

    return build


def nesting_bomb(header: dict[str, Any]) -> str:
    """The header with a list nested 100 000 deep in it (json.loads would recurse 100 000 times)."""
    return json.dumps(header)[:-1] + ', "deep": ' + "[" * 100_000 + "]" * 100_000 + "}"


def wrong_nq(header: dict[str, Any]) -> None:
    header["metadata"]["robot"]["nq"] = 3


def string_wall_time(header: dict[str, Any]) -> None:
    header["stats"]["wall_time"] = "slow"


def fifo(tmp: Path, name: str = "run.npz") -> Path:
    path = tmp / name
    os.mkfifo(path)
    return path


def unix_socket(tmp: Path, name: str) -> Path:
    """A socket file (it stays in the folder once the socket is closed)."""
    path = tmp / name
    with socket.socket(socket.AF_UNIX) as server:
        server.bind(str(path))
    return path


def saved_run(tmp: Path) -> Path:
    return ms.simulate(pendulum(), [1.0], [0.0], duration=0.05, dt=0.01).save(tmp / "saved.npz")


def output_api(make: Callable[[Path], Path], call: Callable[[Path], object]) -> Callable[[Path], Trigger]:
    """An API writer given the output `make` builds; fields: out (and target, for a link)."""

    def build(tmp: Path) -> Trigger:
        path = make(tmp)
        return Trigger(call=lambda: call(path), fields={"out": str(path), "target": os.path.realpath(path)})

    return build


def to_out(path: Path) -> object:
    return ms.simulate(pendulum(), [1.0], [0.0], duration=0.05, dt=0.01, out=path)


def save_to(path: Path) -> object:
    return ms.simulate(pendulum(), [1.0], [0.0], duration=0.05, dt=0.01).save(path)


def link_to_fifo(tmp: Path) -> Path:
    link = tmp / "run.npz"
    link.symlink_to(fifo(tmp, "pipe"))
    return link


def locked(tmp: Path) -> Trigger:
    """out.lock names a live process (this one): another run is writing out."""
    out = tmp / "run.npz"
    lock = tmp / "run.npz.lock"
    lock.write_text(f"{os.getpid()} {socket.gethostname()} 0123456789abcdef0123456789abcdef\n")
    fields = {"out": str(out), "lock": str(lock), "pid": str(os.getpid())}
    return Trigger(call=lambda: to_out(out), fields=fields)


def output_cli(option: str, make: Callable[[Path], Path], command: str = "run") -> Callable[[Path], Trigger]:
    def build(tmp: Path) -> Trigger:
        path = make(tmp)
        argv = ["run", "pendulum", "--duration", "0.05", option, str(path)]
        if command != "run":
            argv = [command, str(saved_run(tmp)), option, str(path)]
        return Trigger(argv=argv, fields={"out": str(path)})

    return build


def folder(tmp: Path) -> Path:
    path = tmp / "run.npz"
    path.mkdir()
    return path


def unmerged_parts(tmp: Path, name: str = "run.npz") -> Path:
    """A chunked run's parts (6 chunks of 20 samples) left unmerged: its merge found the disk full."""
    from unittest import mock

    def full(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    with mock.patch("multibody_sim.driver.merge_parts", full), contextlib.suppress(ms.SimulationError):
        ms.simulate(pendulum(), [1.0], [0.0], duration=1.0, dt=1e-3, output_dt=1e-2, out=tmp / name, chunk=20)
    return tmp / f"{name}.parts"


def parts_with_a_hole(tmp: Path) -> Trigger:
    parts = unmerged_parts(tmp)
    (parts / "chunk_000002.npz").unlink()
    return npz_trigger(parts, {"parts": str(parts)})


def run_id(chunk: Path) -> str:
    with np.load(chunk) as npz:
        return str(json.loads(str(npz["header"][()]))["metadata"]["chunk"]["run_id"])[:12]


def parts_with_a_stranger(tmp: Path) -> Trigger:
    parts = unmerged_parts(tmp)
    stranger = unmerged_parts(tmp, "other.npz") / "chunk_000003.npz"
    stranger.replace(parts / "chunk_000003.npz")
    fields = {
        "parts": str(parts),
        "other": run_id(parts / "chunk_000003.npz"),
        "mine": run_id(parts / "chunk_000000.npz"),
    }
    return npz_trigger(parts, fields)


CHUNKED_RUN = ["run", "pendulum", "--q0", "1", "--output-dt", "0.01", "--chunk", "20"]


@contextlib.contextmanager
def disk_full_from(call: int) -> Any:
    """Trajectory.save (every chunk and file) finds the disk full from its `call`-th call on."""
    from unittest import mock

    real = ms.Trajectory.save
    calls = []

    def save(self: ms.Trajectory, path: Any) -> Any:
        calls.append(path)
        if len(calls) >= call:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, path)

    with mock.patch.object(ms.Trajectory, "save", save):
        yield


@contextlib.contextmanager
def signal_inside(target: str, signum: int, call: int) -> Any:
    """A real signal sent to this process from inside `target` (module.function), at its `call`-th call."""
    from unittest import mock

    module, name = target.rsplit(".", 1)
    real = getattr(__import__(module, fromlist=[name]), name)
    calls = []

    def signalled(*args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        if len(calls) == call:
            os.kill(os.getpid(), signum)
        return real(*args, **kwargs)

    with mock.patch(target, signalled):
        yield


def runtime(argv: list[str], during: Callable[[], Any], *, chunked: bool = True) -> Callable[[Path], Trigger]:
    def build(tmp: Path) -> Trigger:
        out = tmp / "run.npz"
        fields = {"out": str(out), "parts": f"{out}.parts"}
        return Trigger(argv=[*argv, "--out", str(out)], fields=fields, during=during)

    return build


@contextlib.contextmanager
def file_size_limit(nbytes: int) -> Any:
    """RLIMIT_FSIZE (ulimit -f) lowered for the block (the hard limit unchanged, so it can be raised back)."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))


FILES = [
    BadInput(
        "npz-header-nesting-bomb",
        "trajectory file",
        "a trajectory whose JSON header nests a list 100 000 deep (json.loads would recurse 100 000 times)",
        "{npz}: refused: its header nests 100001 levels deep, more than the 64 a trajectory header may",
        "The file is forged: the headers we write nest 5 deep.",
        edited_trajectory(nesting_bomb),
        ms.TrajectoryFileError,
    ),
    BadInput(
        "npz-shape-vs-metadata",
        "trajectory file",
        "a trajectory whose q has 1 column while its metadata's robot has nq = 3",
        "{npz}: array 'q' has shape (6, 1), but the metadata's robot has nq = 3",
        "The file was edited or forged: regenerate it.",
        edited_trajectory(wrong_nq),
        ms.TrajectoryFileError,
    ),
    BadInput(
        "npz-header-field-type",
        "trajectory file",
        "a trajectory whose header gives its wall time as a string (summary() would fail on it)",
        "{npz}: malformed stats.wall_time in the header (expected a number)",
        "The file was edited or forged: regenerate it.",
        edited_trajectory(string_wall_time),
        ms.TrajectoryFileError,
    ),
    BadInput(
        "output-fifo",
        "output file",
        "a FIFO (named pipe) given as a run's out",
        "out {out}: is a FIFO (named pipe), only regular files are replaced; give a file name such as run.npz",
        "Give a file name: outputs are written to a temporary file and renamed over a regular file only.",
        output_api(fifo, to_out),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "output-link-to-fifo",
        "output file",
        "a symbolic link to a FIFO given to Trajectory.save (a link is written through: its target counts)",
        "out {out} (a symbolic link to {target}): is a FIFO (named pipe), only regular files are replaced; give a "
        "file name such as run.npz",
        "Point the link at a regular file (or none yet): the link stays, its target is replaced.",
        output_api(link_to_fifo, save_to),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "output-socket",
        "output file",
        "a socket file given to Trajectory.save",
        "out {out}: is a socket, only regular files are replaced; give a file name such as run.npz",
        "Give a file name.",
        output_api(lambda tmp: unix_socket(tmp, "run.npz"), save_to),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "output-directory",
        "output file",
        "a folder given as a run's out",
        "out {out}: is a directory, expected a file name such as run.npz",
        "Give a file name inside the folder.",
        output_api(folder, to_out),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "output-locked",
        "output file",
        "a second run given the out another live run is writing (its lock file names a live process)",
        "out {out}: another run is writing it (process {pid}, lock file {lock}); choose another file, or wait for "
        "that run to end",
        "Choose another file. A lock whose process has exited is stale and taken over by the next run.",
        locked,
        ms.InvalidArgumentError,
    ),
    BadInput(
        "cli-out-directory",
        "command line",
        "`run --out` naming a folder",
        "--out {out}: is a directory, expected a file name such as run.npz",
        "Give a file name inside the folder.",
        output_cli("--out", folder),
    ),
    BadInput(
        "cli-csv-socket",
        "command line",
        "`export --csv` naming a socket file",
        "--csv {out}: is a socket, only regular files are replaced; give a file name such as table.csv",
        "Give a file name.",
        output_cli("--csv", lambda tmp: unix_socket(tmp, "table.csv"), "export"),
    ),
    BadInput(
        "cli-html-fifo",
        "command line",
        "`play --html` naming a FIFO",
        "--html {out}: is a FIFO (named pipe), only regular files are replaced; give a file name such as view.html",
        "Give a file name.",
        output_cli("--html", lambda tmp: fifo(tmp, "view.html"), "play"),
    ),
    BadInput(
        "parts-missing-chunk",
        "trajectory file",
        "a chunked run's parts folder with a chunk missing",
        "{parts}: chunk_000002.npz is missing: the samples from t = 0.39 s to t = 0.6 s are lost; load the chunk "
        "files one by one (Trajectory.load(chunk))",
        "Find the missing chunk; the others load one by one. A trajectory with a hole is never stitched together.",
        parts_with_a_hole,
        ms.TrajectoryFileError,
    ),
    BadInput(
        "parts-foreign-chunk",
        "trajectory file",
        "a parts folder holding a chunk of another run (same times and shapes)",
        "{parts}: chunk_000003.npz belongs to another run (run {other}, not {mine} of chunk_000000.npz); move it "
        "out of the folder",
        "Move the stranger out; each chunk records the run it belongs to.",
        parts_with_a_stranger,
        ms.TrajectoryFileError,
    ),
    BadInput(
        "disk-full-mid-run",
        "run ending early",
        "the disk fills up while a chunked run writes its fourth chunk",
        "could not write {parts}/chunk_000003.npz (No space left on device) at t = 0.79 s: the run stopped; 60 "
        "samples stay in {parts} (Trajectory.load reads the folder), the last 20 only in memory; partial trajectory "
        "(80 samples, t = 0..0.79 s) kept in {parts} (`multibody-sim plot`, `export` and Trajectory.load read the "
        "folder)",
        "Free some space; the parts load as they are (status incomplete).",
        runtime([*CHUNKED_RUN, "--duration", "1"], lambda: disk_full_from(4)),
        ms.SimulationError,
        code=1,
    ),
    BadInput(
        "disk-full-at-the-end",
        "run ending early",
        "the disk is full when a completed in-memory run writes its file",
        "the run completed, but {out} could not be written (No space left on device); partial trajectory (101 "
        "samples, t = 0..1 s) not written to {out}: lost when this command exits",
        "Free some space, or stream long runs to disk as they go (--chunk N): chunks already written stay.",
        runtime(["run", "pendulum", "--q0", "1", "--output-dt", "0.01", "--duration", "1"], lambda: disk_full_from(1)),
        ms.SimulationError,
        code=1,
    ),
    BadInput(
        "sigint-during-merge",
        "run ending early",
        "Ctrl-C while a chunked run's chunks are merged into its file",
        "interrupted while writing the samples, after the run completed at t = 1 s; 101 samples kept; merging the "
        "chunks was interrupted: 101 samples stay in {parts} (Trajectory.load reads the folder); partial trajectory "
        "(101 samples, t = 0..1 s) kept in {parts} (`multibody-sim plot`, `export` and Trajectory.load read the "
        "folder)",
        "Nothing is lost: the parts load as they are; the half-written file was removed.",
        runtime(
            [*CHUNKED_RUN, "--duration", "1"],
            lambda: signal_inside("numpy.lib.format.write_array_header_2_0", signal.SIGINT, 3),
        ),
        ms.SimulationError,
        code=130,
    ),
    BadInput(
        "sigterm-during-chunk-write",
        "run ending early",
        "`kill` (SIGTERM) while a chunk file is being written",
        "interrupted at t = 0.59 s (step 590); 60 samples kept; partial trajectory (60 samples, t = 0..0.59 s) "
        "written to {out}",
        "Nothing is lost: the chunk is completed before the signal takes effect, then the chunks are merged.",
        runtime(
            [*CHUNKED_RUN, "--duration", "1"],
            lambda: signal_inside("multibody_sim.driver.write_chunk", signal.SIGTERM, 3),
        ),
        ms.SimulationError,
        code=143,
    ),
    BadInput(
        "file-size-limit",
        "run ending early",
        "a run whose file would outgrow this process's file-size limit (ulimit -f 1000, i.e. 1 MB)",
        "out {out} would take about 8 MB, more than this process's file-size limit (1 MB, ulimit -f): sample less "
        "often (output_dt) or raise the limit",
        "Refused before the run, not cut short at its end: sample less often, stream with --chunk, or raise the limit.",
        runtime(
            ["run", "pendulum", "--duration", "100", "--output-dt", "0.001"],
            lambda: file_size_limit(10**6),
        ),
        ms.InvalidArgumentError,
    ),
]
CATALOGUE += FILES


# ---- numbers, names, scene folders (issue 17: ranges in validation.py, safe_name, scene roots) ------------
SUBNORMAL = "9.99989e-321"  # how 1e-320 (a subnormal double) reads back
COUNT_LIMIT = "is more than 2**53, the most a run can count exactly"


def scene_outside(key: str) -> Callable[[Path], Trigger]:
    """A scene file in scenes/ whose robot file or package_dirs lie in a folder beside it (or in /etc)."""

    def build(tmp: Path) -> Trigger:
        folder, outside = tmp / "scenes", tmp / "elsewhere"
        folder.mkdir()
        outside.mkdir()
        (folder / "robot.urdf").write_text(urdf(ONE_JOINT))
        (outside / "robot.urdf").write_text(urdf(ONE_JOINT))
        if key == "source":
            text, value = f'[robot]\nsource = "{outside / "robot.urdf"}"\n', str(outside / "robot.urdf")
        else:
            text, value = '[robot]\nsource = "robot.urdf"\npackage_dirs = ["/etc"]\n', "/etc"
        path = folder / "scene.toml"
        path.write_text(text)
        roots = [os.path.realpath(folder), os.path.realpath(ms.catalog.shipped_models_dir())]
        roots.append(str(ms.catalog.example_robot_data_share()))
        fields = {"scene": str(path), "value": value, "roots": ", ".join(roots)}
        return Trigger(call=lambda: ms.load_scene(path), argv=["run", str(path)], fields=fields)

    return build


def forged_times(times: list[float]) -> Callable[[Path], Trigger]:
    """A saved run whose sample times were rewritten."""

    def build(tmp: Path) -> Trigger:
        run = ms.simulate(pendulum(), [0.1], [0.0], duration=0.003, dt=1e-3)
        run.t = np.array(times)
        path = run.save(tmp / "run.npz")
        return npz_trigger(path)

    return build


def hostile_frame_names(tmp: Path) -> Trigger:
    """A robot whose link names hold a right-to-left override and a CSI, asked for a frame it lacks."""
    path = tmp / "robot.urdf"
    path.write_text(urdf(BASE, link("arm&#x202e;&#x9b;2J"), joint("j1", "base", "arm&#x202e;&#x9b;2J")))
    robot = ms.load_robot(path)
    run = ms.simulate(robot, [0.0], [0.0], duration=0.002, dt=1e-3)
    return Trigger(call=lambda: ms.analysis.frame_placements(robot, run, "tool"))


def replayed(npz: Path, fields: dict[str, str]) -> Trigger:
    """Replaying a saved run: viz.robot_from_trajectory of it (the API) and `play npz --html` (the command line)."""

    def call() -> object:
        import multibody_sim.viz as viz

        return viz.robot_from_trajectory(ms.Trajectory.load(npz))

    return Trigger(call=call, argv=["play", str(npz), "--html", str(npz.with_name("view.html"))], fields=fields)


def forged_package_dirs(tmp: Path) -> Trigger:
    """A run whose metadata was edited to name /etc as its robot's package folder (its page would embed meshes
    found there)."""
    folder = tmp / "robot"
    folder.mkdir()
    path = folder / "robot.urdf"
    path.write_text(urdf(ONE_JOINT))
    run = ms.simulate(ms.load_robot(path), [0.1], [0.0], duration=0.002, dt=1e-3)
    run.metadata["robot"]["load_robot"]["package_dirs"] = ["/etc"]
    npz = run.save(tmp / "run.npz")
    roots = [os.path.realpath(ms.catalog.shipped_models_dir()), str(ms.catalog.example_robot_data_share())]
    roots.append(os.path.realpath(folder))

    return replayed(npz, {"npz": str(npz), "trusted": ", ".join(roots)})


RANGES_AND_NAMES = [
    BadInput(
        "port-above-65535",
        "command line",
        "`run pendulum --view --view-port 70000` (a port that would wrap to 4464)",
        "--view-port must be a whole number from 0 to 65535 (0: any free port), got 70000",
        "Give a port from 1024 to 65535, or 0 for any free one.",
        cli("run", "pendulum", "--view", "--view-port", "70000"),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "dt-subnormal",
        "command line",
        "`run pendulum --dt 1e-320` (a step that underflows below the smallest normal double)",
        f"duration / dt = 1 s / {SUBNORMAL} s = inf {COUNT_LIMIT}: choose a larger dt or a smaller duration",
        "Give a step the run can take: duration / dt must be at most 2**53.",
        cli("run", "pendulum", "--dt", "1e-320"),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "step-count-overflow",
        "command line",
        "`run pendulum --duration 1e300 --dt 1e-300` (the number of steps overflows)",
        f"duration / dt = 1e+300 s / 1e-300 s = inf {COUNT_LIMIT}: choose a larger dt or a smaller duration",
        "Times are t0 + k dt with k counted: a run has at most 2**53 steps.",
        cli("run", "pendulum", "--duration", "1e300", "--dt", "1e-300"),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "rtol-below-epsilon",
        "command line",
        "`run pendulum --integrator dp54 --rtol 1e-320`",
        f"rtol must be a number from {sys.float_info.epsilon:g} to 1 (1 excluded), got {SUBNORMAL}",
        "No step can meet a relative tolerance below machine epsilon; use 1e-14 or more.",
        cli("run", "pendulum", "--integrator", "dp54", "--rtol", "1e-320"),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "view-speed-nan",
        "command line",
        "`run pendulum --view --view-speed nan`",
        "--view-speed must be a number from 0.001 to 1000 (1 = real time), got nan",
        "Give a playback speed from 0.001 to 1000.",
        cli("run", "pendulum", "--view", "--view-speed", "nan"),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "play-fps-huge",
        "command line",
        "`play run.npz --fps 1e9`",
        "--fps must be a number from 1 to 1000 frames per second, got 1e+09",
        "Give a frame rate from 1 to 1000 (30 is plenty for a screen).",
        lambda tmp: Trigger(argv=["play", str(tmp / "run.npz"), "--fps", "1e9"]),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "chunk-beyond-2-53",
        "Python API",
        "`simulate(..., out='run.npz', chunk=2**60)`",
        f"chunk must be at most 2**53 = {2**53}, got {2**60}",
        "Give a chunk of a few thousand samples: it is held in memory.",
        lambda tmp: Trigger(
            call=lambda: ms.simulate(pendulum(), [0.0], [0.0], duration=1.0, dt=1e-3, out=tmp / "r.npz", chunk=2**60)
        ),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "stepper-advance-overflow",
        "Python API",
        "`Stepper(robot, dt=1e-10).advance_to(1e300)`",
        f"(t - current time) / control_dt = 1e+300 s / 1e-10 s = inf {COUNT_LIMIT}: choose a larger control_dt or "
        "a smaller (t - current time)",
        "Advance by spans the stepper can count in steps.",
        api(lambda: ms.Stepper(pendulum(), dt=1e-10).advance_to(1e300)),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "npz-times-go-back",
        "trajectory file",
        "a trajectory whose sample times go back",
        "{npz}: sample times: t must be strictly increasing, got 0.002 then 0.001 at indices 1 and 2",
        "The file was edited or forged: regenerate it.",
        forged_times([0.0, 0.002, 0.001, 0.003]),
        ms.TrajectoryFileError,
    ),
    BadInput(
        "npz-time-nan",
        "trajectory file",
        "a trajectory with a NaN sample time",
        "{npz}: sample times: t must hold finite times, got nan at index 2",
        "The file was edited or forged: regenerate it.",
        forged_times([0.0, 0.001, float("nan"), 0.003]),
        ms.TrajectoryFileError,
    ),
    BadInput(
        "scene-package-dirs-etc",
        "scene file",
        "a scene from elsewhere whose `package_dirs` point at /etc",
        "{scene}: robot.package_dirs[0]: '{value}' is outside the folders a scene may read from (its own folder "
        "and the catalog's: {roots}); to allow it, pass --allow-root DIR (allowed_roots=[DIR] in load_scene)",
        "A scene reads meshes from its own folder and the catalog only; allow another folder yourself if you trust it.",
        scene_outside("package_dirs"),
        ms.SceneError,
    ),
    BadInput(
        "scene-robot-outside",
        "scene file",
        "a scene whose robot file lies in a folder beside the scene's",
        "{scene}: robot.source: '{value}' is outside the folders a scene may read from (its own folder and the "
        "catalog's: {roots}); to allow it, pass --allow-root DIR (allowed_roots=[DIR] in load_scene)",
        "Put the URDF beside the scene, or allow its folder: `--allow-root DIR`.",
        scene_outside("source"),
        ms.SceneError,
    ),
    BadInput(
        "npz-metadata-widens-mesh-folders",
        "Python API",
        "`viz.robot_from_trajectory(run)` (and `play run.npz`) for a trajectory whose metadata names /etc as its "
        "robot's package folder (`play --html` would embed meshes from there)",
        "cannot load the trajectory's robot: its metadata names the folder '/etc' (package_dirs), outside the URDF's "
        "folder and the catalog's ({trusted}); to allow it, pass --allow-root /etc (allowed_roots=['/etc'])",
        "A trajectory from elsewhere reads meshes only beside its URDF and in the catalog; allow a folder yourself if "
        "you trust it (`play --allow-root DIR`).",
        forged_package_dirs,
        ms.ModelError,
    ),
    BadInput(
        "frame-names-bidi",
        "Python API",
        "asking a robot whose link names hold a right-to-left override and a CSI for a frame it lacks",
        "robot 'robot' has no frame 'tool' (its 4 frames: universe, base, j1, arm\\u202e\\x9b2J; "
        "multibody_sim.analysis.frame_names(robot) lists them)",
        "Names from files are escaped in every message and printout: they cannot reorder or recolour your terminal.",
        hostile_frame_names,
        ms.UnknownNameError,
    ),
]
TYPES = [
    BadInput(
        "trajectory-load-none",
        "Python API",
        "`Trajectory.load(None)`",
        "path must be a path to a trajectory file (.npz) or a parts folder, got NoneType",
        "Pass the file's path (a str or a pathlib.Path).",
        api(lambda: ms.Trajectory.load(None)),  # type: ignore[arg-type]
        ms.InvalidArgumentError,
    ),
    BadInput(
        "system-a-name",
        "Python API",
        "`simulate('pendulum', ...)` (a robot's name where the robot goes)",
        "system must be a Robot or a Scene, got str (load it first: load_robot('pendulum') or load_scene('pendulum'))",
        "Load the robot first; every function that takes a robot checks this.",
        api(lambda: ms.simulate("pendulum", [0.0], [0.0], duration=1.0, dt=1e-3)),  # type: ignore[arg-type]
        ms.InvalidArgumentError,
    ),
    BadInput(
        "q0-strings",
        "Python API",
        "`simulate(pendulum, ['a'], [0], ...)` (strings where numbers go)",
        "q0 must be an array of 1 real numbers, got list",
        "Give numbers; strings are not converted (they hide mistakes).",
        api(lambda: ms.simulate(pendulum(), ["a"], [0.0], duration=1.0, dt=1e-3)),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "count-a-float",
        "Python API",
        "`rollout(..., num_threads=2.5)` (a float where a whole number goes)",
        "num_threads must be a positive whole number, got 2.5",
        "Give a whole number; nothing is rounded for you.",
        api(lambda: ms.rollout(pendulum(), [[0.0]], [[0.0]], duration=1.0, dt=1e-3, num_threads=2.5)),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "flag-a-string",
        "Python API",
        "`Trajectory.load(path, mmap='no')` (a string where True or False goes: 'no' would be true)",
        "mmap must be True or False, got 'no'",
        "Pass True or False.",
        api(lambda: ms.Trajectory.load("run.npz", mmap="no")),  # type: ignore[arg-type]
        ms.InvalidArgumentError,
    ),
]


# ---- issue 26: the surfaces added since (gym environments, presentation, nested fields) -----------------------
def vector_env() -> Any:
    """ur5 in a two-row MultibodyVectorEnv, reset."""
    from multibody_sim.gym import MultibodyVectorEnv

    envs = MultibodyVectorEnv(ms.load_robot("ur5"), 2, reward=lambda q, v, tau: 0.0, control_dt=0.01)
    envs.reset(seed=0)
    return envs


DEEP = 100_000  # nesting levels: Python's parsers (json, tomllib) recurse once or more per level


def deep_scene_file(tmp: Path) -> Trigger:
    return scene_trigger('[robot]\nsource = "pendulum"\nx = ' + "[" * DEEP + "]" * DEEP + "\n")(tmp)


def deep_stored_scene(tmp: Path) -> Trigger:
    """A run of a scene file whose stored scene text (its metadata) was replaced by one nesting DEEP arrays."""
    path = tmp / "scene.toml"
    path.write_text('[robot]\nsource = "pendulum"\n')
    run = ms.load_scene(path).run(duration=0.002)
    run.metadata["robot"]["scene"]["toml"] = "x = " + "[" * DEEP + "]" * DEEP + "\n"
    npz = run.save(tmp / "run.npz")

    return replayed(npz, {"scene": str(path)})


def deep_table(tmp: Path) -> Trigger:
    path = tmp / "study.json"
    path.write_text("[" * DEEP + "]" * DEEP)
    return Trigger(call=lambda: ms.bench.WorkPrecision.from_json(path), fields={"table": str(path)})


def forged_run(tmp: Path, edit: Callable[[ms.Trajectory], None], robot: str = "pendulum") -> Path:
    """A short saved run of a catalog robot, edited before saving (numbers a real run cannot reach)."""
    system = ms.load_robot(robot)
    run = ms.simulate(system, system.default_pose(), np.zeros(system.nv), duration=0.05, dt=0.01)
    edit(run)
    return run.save(tmp / "run.npz")


def huge_energies(run: ms.Trajectory) -> None:
    for name in ("kinetic_energy", "total_energy"):
        values = getattr(run, name).copy()
        values[2:4] = [1e308, -1e308]
        setattr(run, name, values)


def far_base(run: ms.Trajectory) -> None:
    q = run.q.copy()
    q[3:, 0] = 1e300  # the base 1e300 m along x from t = 0.03 s
    run.q = q


def long_run(run: ms.Trajectory) -> None:
    run.t = np.concatenate((run.t[:-1], [1e300]))


def presentation(
    edit: Callable[[ms.Trajectory], None], call: str, robot: str = "pendulum"
) -> Callable[[Path], Trigger]:
    """A forged run shown by viz.plot_trajectory / export_html / export_video (and `play` with the same options)."""

    def build(tmp: Path) -> Trigger:
        npz = forged_run(tmp, edit, robot)

        def api_call() -> object:
            import multibody_sim.viz as viz

            run = ms.Trajectory.load(npz)
            if call == "plot":
                return viz.plot_trajectory(run)
            if call == "html":
                return viz.export_html(run, tmp / "view.html")
            return viz.export_video(run, tmp / "motion.mp4")

        option = {"plot": ["--html", str(tmp / "view.html"), "--plot"], "html": ["--html", str(tmp / "view.html")]}
        argv = ["play", str(npz), *option.get(call, ["--video", str(tmp / "motion.mp4")])]
        return Trigger(call=api_call, argv=argv)

    return build


def object_scene(*objects: str, robot: str | None = None) -> Callable[[Path], Trigger]:
    """A scene file of the given [[object]] bodies (TOML fragments), beside a robot when one is named."""
    head = f'[robot]\nsource = "{robot}"\n' if robot else ""
    return scene_trigger(head + "".join(f"[[object]]\n{body}" for body in objects))


def ball(i: int) -> str:
    return f'name = "ball{i}"\nshape = "sphere"\nradius = 0.05\nmass = 1.0\nposition = [1.0, 0.0, {i}]\n'


def namespaced_mjcf_mesh(tmp: Path) -> Trigger:
    """An MJCF robot whose <mesh> sits in a default XML namespace and names the secret file (Pinocchio's parser,
    which knows no namespaces, reads it as a mesh; lxml's lookups of <mesh> did not see it)."""
    secret = secret_file(tmp).resolve()
    text = (
        '<mujoco model="r"><asset><mesh xmlns="http://example.com/x" name="m" file="' + str(secret) + '"/></asset>'
        '<worldbody><body name="b"><joint name="j" type="hinge"/><geom type="sphere" size="0.1" mass="1"/></body>'
        "</worldbody></mujoco>"
    )
    trigger = urdf_trigger(tmp, text, name="robot.xml")
    return Trigger(trigger.call, trigger.argv, {**trigger.fields, "uri": str(secret)})


def scene_file_now_a_fifo(tmp: Path) -> Trigger:
    """A scene run whose scene file was replaced by a FIFO: replaying it opened the recorded scene file to compare
    it with the stored text, and open() waited for a writer forever."""
    folder = tmp / "scenes"
    folder.mkdir()
    (folder / "robot.urdf").write_text(urdf(ONE_JOINT))
    scene = folder / "scene.toml"
    scene.write_text('[robot]\nsource = "robot.urdf"\n')
    npz = ms.load_scene(scene).run(duration=0.002).save(tmp / "run.npz")
    scene.unlink()
    os.mkfifo(scene)
    roots = [os.path.realpath(ms.catalog.shipped_models_dir()), str(ms.catalog.example_robot_data_share())]
    fields = {"scene": str(scene), "value": str(folder / "robot.urdf"), "roots": ", ".join(roots)}

    return replayed(npz, fields)


# ---- a library's exception inside a step (issue 26 class 1) ----------------------------------------------------
SLIDING_BOX_TOML = """
[ground]
friction = 0.8

[[object]]
name = "box"
shape = "box"
size = [0.2, 0.2, 0.1]
mass = 1.0
position = [0.0, 0.0, 0.05]
velocity = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0]
"""


@contextlib.contextmanager
def cholesky_fails_past(x: float) -> Any:
    """On the Python kernel, Pinocchio's Cholesky raises what its ADMM raised on go2 ("L should be > m") once the
    first body is past `x` [m]: a library's exception inside a contact step, whatever the library."""
    from unittest import mock

    import pinocchio as pin

    decompose = pin.cholesky.decompose

    def failing(model: Any, data: Any) -> Any:
        if data.oMi[1].translation[0] > x:
            raise ValueError("L should be > m")
        return decompose(model, data)

    with mock.patch.dict(os.environ, {"MULTIBODY_SIM_NATIVE": "0"}), mock.patch.object(pin.cholesky, "decompose", failing):
        yield


def library_error_in_a_step(tmp: Path) -> Trigger:
    """`run` of a box sliding at 1 m/s (a scene file), timestepping for 0.3 s, while Cholesky fails past x = 0.05 m
    (the API's simulate() raises the same message without the file's part: tests/test_contact_failures.py)."""
    scene_file = tmp / "scene.toml"
    scene_file.write_text(SLIDING_BOX_TOML)
    out = tmp / "run.npz"
    argv = ["run", str(scene_file), "--integrator", "timestepping", "--dt", "0.001", "--duration", "0.3", "--out",
            str(out)]  # fmt: skip
    return Trigger(argv=argv, fields={"out": str(out)}, during=lambda: cholesky_fails_past(0.05))

ROUND_3 = [
    BadInput(
        "vector-env-complex-actions",
        "Python API",
        "`MultibodyVectorEnv.step(actions)` with complex actions (NumPy would drop the imaginary parts with a warning)",
        "actions must be an array of real numbers of shape (2, 6), got dtype complex128",
        "Give real torques; MultibodyEnv refuses the same actions (strings, objects, complex numbers) the same way.",
        api(lambda: vector_env().step(np.full((2, 6), 1 + 1j))),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "vector-env-reset-rows",
        "Python API",
        "`MultibodyVectorEnv.reset(options={'q': ...})` with one state for two rows (NumPy would raise IndexError)",
        "options['q'] must have shape (2, 6), one row per reset row, got (1, 6)",
        "Give one state per row reset (all rows, or the rows of options['reset_mask']).",
        api(lambda: vector_env().reset(options={"q": np.zeros((1, 6))})),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "deep-stored-scene",
        "Python API",
        "`viz.robot_from_trajectory(run)` (and `play run.npz`) of a trajectory whose metadata holds a scene text "
        "nesting arrays 100 000 deep (tomllib would recurse past Python's limit)",
        "{scene} (the trajectory's stored scene text): refused: it nests arrays and inline tables 100000 levels deep, "
        "more than the 64 a scene may (the shipped scenes nest 2 deep)",
        "The file was edited or forged: every nested field read from a file (TOML, JSON, XML) is bounded before it "
        "is parsed.",
        deep_stored_scene,
        ms.SceneError,
    ),
    BadInput(
        "deep-scene-file",
        "scene file",
        "a scene file nesting arrays 100 000 deep",
        "{scene}: refused: it nests arrays and inline tables 100000 levels deep, more than the 64 a scene may (the "
        "shipped scenes nest 2 deep)",
        "Check the file: scenes nest arrays two deep (waypoints).",
        deep_scene_file,
        ms.SceneError,
    ),
    BadInput(
        "deep-work-precision-table",
        "Python API",
        "`bench.WorkPrecision.from_json(path)` (and `bench`'s pilot cache) of a JSON file nesting 100 000 deep",
        "cannot read work-precision table {table}: it nests 100000 levels deep, more than the 64 a table may",
        "The file is damaged or forged: delete it (a pilot cache is rebuilt).",
        deep_table,
        ms.InvalidArgumentError,
    ),
    BadInput(
        "scene-object-size-1e308",
        "scene file",
        "a scene object 1e308 m wide (its inertia overflows: it ran, then 'diverged ... try a smaller dt')",
        "{scene}: object[0] ('crate'): a box of 1e+308 x 1 x 1 m and 1 kg has principal inertias 0.167, inf, inf "
        "kg·m²: they overflow (sizes in m, masses in kg)",
        "Give sizes in metres and masses in kilograms; a URDF body like it is refused the same way.",
        object_scene('name = "crate"\nshape = "box"\nsize = [1e308, 1.0, 1.0]\nmass = 1.0\nposition = [0, 0, 1]\n'),
        ms.SceneError,
    ),
    BadInput(
        "scene-object-size-1e-300",
        "scene file",
        "a scene object 1e-300 m wide (its inertia underflows to 0: it ran, then diverged)",
        "{scene}: object[0] ('dust'): a sphere of 1e-300 m and 1 kg has principal inertias 0, 0, 0 kg·m²: they "
        "underflow to 0 (sizes in m, masses in kg)",
        "Give sizes in metres and masses in kilograms.",
        object_scene('name = "dust"\nshape = "sphere"\nradius = 1e-300\nmass = 1.0\nposition = [0, 0, 1]\n'),
        ms.SceneError,
    ),
    BadInput(
        "scene-10000-objects",
        "scene file",
        "a scene of 10 000 objects (it ran for 23 s, then died of a MemoryError)",
        "{scene}: object: 10000 objects have 60000 degrees of freedom, more than the 128 this simulator accepts (21 "
        "objects at most, fewer beside a robot)",
        "Simulate fewer bodies: the dense dynamics and contact solve cost grows as the cube of the degrees of "
        "freedom, for objects as for robots.",
        object_scene(*(ball(i) for i in range(10_000))),
        ms.SceneError,
    ),
    BadInput(
        "scene-objects-beside-a-robot-past-128-dof",
        "scene file",
        "solo12 (18 degrees of freedom) with 19 free objects (114 more)",
        "{scene}: the scene has 132 degrees of freedom (18 of its robot, 6 for each of its 19 objects), more than "
        "the 128 this simulator accepts",
        "The 128-dof limit counts a scene's objects (6 each) with its robot's joints.",
        object_scene(*(ball(i) for i in range(19)), robot="solo12"),
        ms.SceneError,
    ),
    BadInput(
        "mjcf-namespaced-mesh",
        "URDF file",
        'an MJCF robot file (robot.xml) whose `<mesh>` sits in a default XML namespace (`xmlns="..."`) and names a '
        "file outside (the check did not see it; Pinocchio's parser, which knows no namespaces, did)",
        OUTSIDE,
        "Elements are judged by the name the loaders read: a namespace does not hide a `<mesh>`, `<texture>` or "
        "`<compiler>`.",
        namespaced_mjcf_mesh,
    ),
    BadInput(
        "npz-scene-file-a-fifo",
        "Python API",
        "`viz.robot_from_trajectory(run)` (and `play run.npz`) of a scene's run whose scene file was replaced by a "
        "FIFO (replaying opened it to compare it with the stored text, and waited for a writer forever)",
        "{scene}: robot.source: '{value}' is outside the folders a scene may read from (its own folder and the "
        "catalog's: {roots}); to allow it, pass --allow-root DIR (allowed_roots=[DIR] in load_scene)",
        "A path a file names is looked at before it is opened: only a regular file holding the recorded text vouches "
        "for its folder.",
        scene_file_now_a_fifo,
        ms.SceneError,
    ),
    BadInput(
        "camera-near-1e308",
        "command line",
        "`play run.npz --video v.mp4 --camera-position 1e308 0 0` (distances overflowed; the overflow warning, shown "
        "again while warnings were recorded, grew their list until memory ran out)",
        "--camera-position must lie within 1e+06 m of the world origin (positions reach the page as 32-bit floats), "
        "got 1e+308 0 0",
        "Place the camera within 1000 km (meshcat carries positions as 32-bit floats).",
        lambda tmp: Trigger(
            argv=["play", str(forged_run(tmp, lambda run: None)), "--video", str(tmp / "v.mp4"), "--camera-position"]
            + ["1e308", "0", "0"]
        ),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "plot-energies-1e308",
        "Python API",
        "`viz.plot_trajectory(run)` (and `play run.npz --html v.html --plot`) of a trajectory whose energies reach "
        "±1e308 J (matplotlib's axis span overflowed)",
        "cannot plot kinetic_energy: it reaches 1e+308 J at t = 0.02 s, beyond the ±1e+300 a plot's axes can span "
        "(the run diverged, or the file was edited); `multibody-sim export` writes its numbers as a table",
        "Read the numbers as a table; a run we compute stops long before its energies get there.",
        presentation(huge_energies, "plot"),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "view-body-1e300",
        "Python API",
        "`viz.export_html(run, path)` (and `play run.npz --html`) of a trajectory whose base is 1e300 m away (its "
        "32-bit positions overflowed)",
        "the body of joint 'root_joint' is 1e+300 m from the world origin at t = 0.0333333 s, beyond the 1e+06 m a "
        "view can show (positions reach the page as 32-bit floats): the motion left the scene (it diverged, or the "
        "file was edited)",
        "Show the part of the motion that stays within 1000 km of the origin.",
        presentation(far_base, "html", "solo12"),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "video-of-1e300-seconds",
        "Python API",
        "`viz.export_video(run, 'v.mp4')` (and `play --video`) of a trajectory lasting 1e300 s",
        "a video of 1e+300 s of motion at speed 1 and 30 frames per second would have 3e+301 frames, more than the "
        "108000 a video may (an hour at 30 fps): choose a higher speed, a lower fps, or film part of the trajectory",
        "Speed it up (--speed) or film a part of it.",
        presentation(long_run, "video"),
        ms.InvalidArgumentError,
    ),
    BadInput(
        "library-error-in-a-step",
        "run ending early",
        "a library (Pinocchio, coal, Boost, Eigen) raises inside a step: here Pinocchio's Cholesky, on one row's "
        "state, in a contact step (the native kernel turns a C++ exception into the same status and message)",
        "failed at t = 0.069 s (step 70): ValueError raised in the contact step: L should be > m; try a smaller dt "
        "(now 0.001 s); partial trajectory (70 samples, t = 0..0.069 s) written to {out}",
        "The run stops at the step that failed and keeps its samples; in a batch (rollout, BatchStepper, a vector "
        "env) only that row stops. Try a smaller dt; report the library's message if it persists.",
        library_error_in_a_step,
        ms.SimulationError,
        code=1,
    ),
]
CATALOGUE += RANGES_AND_NAMES + TYPES + ROUND_3


# ---- the installed package (issue 26 class 7): which kernel runs, and why, in a fresh process ------------------
def installed_copy(edit: Callable[[Path, Path], dict[str, str]], *, sources: bool = False) -> Callable[[Path], Trigger]:
    """A copy of the installed package in a fresh folder (its Python files, and the compiled extension with its
    build record), changed by edit(package folder, extension file) -> message fields; `multibody-sim --version` then
    runs on it in a fresh process. With sources, a copy of the C++ sources sits beside it, as in a checkout."""

    def build(tmp: Path) -> Trigger:
        spec = importlib.util.find_spec("multibody_sim._native")
        if (spec is None or spec.origin is None) and os.environ.get("CI") != "true":
            pytest.skip("no C++ extension is built here to damage")
        assert spec is not None and spec.origin is not None
        built = Path(spec.origin)
        package = tmp / "src" / "multibody_sim"
        shutil.copytree(Path(ms.__file__).parent, package, ignore=shutil.ignore_patterns("__pycache__"))
        for path in (built, built.with_name("_native_build.py")):
            shutil.copy2(path, package / path.name)
        if sources:
            shutil.copytree(ROOT / "src" / "native", tmp / "src" / "native")
        fields = edit(package, package / built.name)
        probe = (
            "import sys\n"
            # An editable install of the checkout hooks imports ahead of the path: drop its hook, so the copy loads.
            "sys.meta_path[:] = [f for f in sys.meta_path if type(f).__name__ != 'ScikitBuildRedirectingFinder']\n"
            "import multibody_sim\n"
            f"assert multibody_sim.__file__.startswith({str(package)!r}), multibody_sim.__file__\n"
            "from multibody_sim.cli import main\n"
            "sys.exit(main(['--version']))\n"
        )
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "MULTIBODY_SIM_NATIVE")}
        run = functools.partial(
            subprocess.run,
            [sys.executable, "-c", probe],
            capture_output=True,
            text=True,
            timeout=120,
            cwd=tmp,
            env={**env, "PYTHONPATH": str(tmp / "src")},
        )
        return Trigger(process=run, fields=fields)

    return build


def truncate(package: Path, extension: Path) -> dict[str, str]:
    built = extension.stat().st_size
    with open(extension, "r+b") as file:  # cut short, as an interrupted copy leaves it
        file.truncate(built // 2)
    return {"extension": str(extension), "size": str(built // 2), "built": str(built)}


def alter(package: Path, extension: Path) -> dict[str, str]:
    data = bytearray(extension.read_bytes())
    data[-1] ^= 0xFF  # one byte of its section headers, which the loader does not read: it would load
    extension.write_bytes(bytes(data))
    return {"extension": str(extension)}


def another_pinocchio(package: Path, extension: Path) -> dict[str, str]:
    record = package / "_native_build.py"
    record.write_text(record.read_text().replace(f'PINOCCHIO_VERSION = "{PINOCCHIO}"', 'PINOCCHIO_VERSION = "4.0.9"'))
    return {"pinocchio": PINOCCHIO}


def edit_a_source(package: Path, extension: Path) -> dict[str, str]:
    sources = package.parent / "native"
    source = sources / "module.cpp"
    source.write_bytes(source.read_bytes() + b"\n")
    return {"sources": str(sources)}


def not_built(package: Path, extension: Path) -> dict[str, str]:
    extension.unlink()
    (package / "_native_build.py").unlink()
    return {}


PINOCCHIO = importlib.metadata.version("pin")
REINSTALL = (
    "Reinstall (`pip install --force-reinstall .`; in a checkout `bash scripts/test.sh`). Until then runs take the "
    "Python kernel: the same results, slower."
)
INSTALLED = [
    BadInput(
        "truncated-extension",
        "installed package",
        "a compiled extension (`_native*.so`) cut short by an interrupted copy or install (the dynamic loader would "
        "die of SIGBUS)",
        "kernel: python (the C++ extension {extension} is damaged: {size} bytes where its build wrote {built} (an "
        "interrupted copy or install?): reinstall multibody-sim)",
        REINSTALL,
        installed_copy(truncate),
        code=0,
    ),
    BadInput(
        "altered-extension",
        "installed package",
        "a compiled extension of the right size whose bytes changed since its build",
        "kernel: python (the C++ extension {extension} is damaged: its SHA-256 is not the one its build recorded: "
        "reinstall multibody-sim)",
        REINSTALL,
        installed_copy(alter),
        code=0,
    ),
    BadInput(
        "extension-another-pinocchio",
        "installed package",
        "an extension built against another Pinocchio than the one installed (`pip install pin==…` after the build)",
        "kernel: python (the C++ extension was built against Pinocchio 4.0.9 but Pinocchio {pinocchio} is installed "
        "(no ABI promise across versions): reinstall multibody-sim)",
        "Reinstall multibody-sim against the Pinocchio you keep (its `pin` pin is exact).",
        installed_copy(another_pinocchio),
        code=0,
    ),
    BadInput(
        "extension-older-than-sources",
        "installed package",
        "a checkout whose C++ sources changed since its extension was built (edited or pulled)",
        "kernel: python (the C++ extension is older than its sources in {sources} (edited or pulled, not rebuilt): "
        "rebuild it (`bash scripts/test.sh --co -q` or `pip install -e .`))",
        "Rebuild: `bash scripts/test.sh` (it recompiles only what changed).",
        installed_copy(edit_a_source, sources=True),
        code=0,
    ),
    BadInput(
        "extension-not-built",
        "installed package",
        "an install without the extension (no C++ compiler at install time, or its build failed)",
        "kernel: python (the C++ extension is not built (no C++ compiler at install time, or its build failed: "
        "`pip install -v .` shows why))",
        "Install a C++17 compiler and reinstall; `pip install -v .` shows why the build failed.",
        installed_copy(not_built),
        code=0,
    ),
]
CATALOGUE += INSTALLED

BY_ID = {entry.id: entry for entry in CATALOGUE}
assert len(BY_ID) == len(CATALOGUE), "catalogue ids must be unique"


def display_fields(entry: BadInput) -> dict[str, Any]:
    """Placeholder values for the table: DISPLAY, plus the fixed counts some entries report."""
    fields: dict[str, Any] = dict(DISPLAY)
    fields["uri"] = {
        "mesh-package-dotdot": "package://x/../../secret/passwords.txt",
        "mesh-absolute-path": "/home/me/secret/passwords.txt",
        "mjcf-namespaced-mesh": "/home/me/secret/passwords.txt",
        "mesh-file-uri": "file:///home/me/secret/passwords.txt",
    }.get(entry.id, "")
    fields["count"] = {"too-many-elements": "100013", "nested-100k-deep": "100013"}.get(entry.id, "")
    fields["described"] = "24000000000128"
    if entry.id == "megabyte-name":
        fields["head"] = "/home/me/robot/robot.urdf: link 'AAAA…AAAA"
        fields["tail"] = "AAAA…AAAA' has mass nan; it must be finite and >= 0"
        fields["omitted"] = "998175"
    if entry.id == "not-xml":
        fields["libxml2"] = "Start tag expected, '<' not found, line 1, column 1"
    fields["value"] = {
        "scene-package-dirs-etc": "/etc",
        "scene-robot-outside": "/home/elsewhere/robot.urdf",
        "npz-scene-file-a-fifo": "/home/me/scenes/robot.urdf",
    }.get(entry.id, "")
    if entry.id == "npz-scene-file-a-fifo":
        fields["scene"] = "/home/me/scenes/scene.toml"
        fields["roots"] = "<site-packages>/multibody_sim/models, <site-packages>/cmeel.prefix/share"
    if entry.id == "mjcf-namespaced-mesh":
        fields["urdf"] = "/home/me/robot/robot.xml"
    return fields
