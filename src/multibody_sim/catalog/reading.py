"""Reading robot files as untrusted input: size and element limits, XML without DTDs or entities, URDF parsing,
and file paths that must stay inside the allowed folders."""

from __future__ import annotations

import contextlib
import os
import stat
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..exceptions import InvalidArgumentError, ModelError

MAX_URDF_BYTES = 32 * 1024 * 1024  # the largest catalog URDF is ~200 kB; anything this big is not a robot
# Refused before parsing: 28 MB of tiny elements cost libxml2 4-6 s and 600-900 MB, and yourdfpy more. The
# largest catalog URDF (talos) has ~2000 elements; 100k parse in ~0.1 s and ~37 MB.
MAX_XML_ELEMENTS = 100_000
# The largest catalog robot has 78 links (anymal_c). Pinocchio's URDF parser recurses along chains and
# overflows an 8 MiB stack near 4000 links (a crash, not an error), and a 8000-link star takes ~20 s to build.
MAX_LINKS = 1000
MAX_JOINTS = 1000
# Pinocchio's Data (created with every Robot) takes ~64 nv^3 bytes: 136 MB and 0.3 s at 128 dof, 1.7 GB at 300,
# out of memory near 1000. The largest example-robot-data model has 107 (tiago_dual on a free-flyer).
MAX_DOFS = 128


def folder_list(argument: str, folders: Any) -> list[Path]:
    """The resolved folders of a package_dirs / allowed_roots argument, or InvalidArgumentError."""
    if folders is None:
        return []
    # A single path would otherwise be iterated letter by letter.
    if isinstance(folders, (str, bytes, os.PathLike)) or not isinstance(folders, (list, tuple)):
        raise InvalidArgumentError(f"{argument} must be a list of folders, got {type(folders).__name__}")
    resolved = []
    for folder in folders:
        if not isinstance(folder, (str, os.PathLike)):
            raise InvalidArgumentError(f"{argument} entries must be folder paths, got {type(folder).__name__}")
        if not Path(folder).expanduser().is_dir():
            raise InvalidArgumentError(f"{argument}: '{os.fspath(folder)}' is not a folder")
        resolved.append(Path(folder).expanduser().resolve())
    return resolved


def read_urdf(path: Path) -> bytes:
    """The URDF's bytes, refusing what is not a regular file and files over MAX_URDF_BYTES.

    Never blocks on a FIFO or reads more than MAX_URDF_BYTES + 1 bytes, whatever the size the file claims.
    """
    return read_xml_file(path, "URDF")


def read_xml_file(path: Path, kind: str) -> bytes:
    """A robot description file's bytes (kind: "URDF", "SRDF", "SDF", "MJCF"), refusing what is not a regular file
    and files over MAX_URDF_BYTES; never blocks on a FIFO or reads more than MAX_URDF_BYTES + 1 bytes."""
    try:
        # Looked at before it is opened: opening a device can act (a tape rewinds, a watchdog arms) and a FIFO waits
        # for a writer. The path may come from a stranger's file (a trajectory's urdf_path).
        if not stat.S_ISREG(os.stat(path).st_mode):
            raise ModelError(f"{path}: not a regular file")
        # O_NONBLOCK: if it became a FIFO since, opening it for reading would otherwise wait for a writer forever.
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with os.fdopen(fd, "rb") as f:
            info = os.fstat(f.fileno())
            if not stat.S_ISREG(info.st_mode):
                raise ModelError(f"{path}: not a regular file")
            if info.st_size > MAX_URDF_BYTES:
                raise ModelError(
                    f"{path}: file is {info.st_size} bytes, larger than the {MAX_URDF_BYTES}-byte limit for a {kind}"
                )
            # Its stat size and one byte more (not the limit: a 32 MiB buffer per load); a file still growing (or
            # in /proc, whose size says 0) may exceed its stat size: then read on, up to the limit.
            xml = f.read(min(info.st_size, MAX_URDF_BYTES) + 1)
            if len(xml) > info.st_size:
                xml += f.read(MAX_URDF_BYTES + 1 - len(xml))
    except OSError as exc:
        raise ModelError(f"{path}: cannot read {kind} ({exc.strerror})") from None
    if len(xml) > MAX_URDF_BYTES:
        raise ModelError(f"{path}: file is larger than the {MAX_URDF_BYTES}-byte limit for a {kind}")
    return xml


def parse_xml(xml: bytes, path: Path, kind: str, largest: str) -> Any:
    """Parse untrusted XML bytes into an lxml element: no DTD, no entities, no network, at most MAX_XML_ELEMENTS
    elements (counted before parsing), comments and processing instructions dropped.

    Args:
        kind: what the file is ("URDF", "SRDF", ...), for messages.
        largest: what the element limit is compared with, for its message ("(the largest catalog robot has ...)").
    """
    # Before any parsing, anywhere in the file: entities never get a chance to expand (a DOCTYPE may follow a
    # long comment, so the whole file is searched; the prefix also catches lower-case spellings).
    if b"<!DOCTYPE" in xml or b"<!DOCTYPE" in xml[:65536].upper():
        raise ModelError(f"{path}: DOCTYPE declarations are not allowed in a {kind} (entities could expand)")
    tags = count_start_tags(xml)
    if tags > MAX_XML_ELEMENTS:
        raise ModelError(
            f"{path}: the file has {tags} XML elements, more than the {MAX_XML_ELEMENTS} a {kind} may have {largest}"
        )
    from lxml import etree

    parser = etree.XMLParser(
        resolve_entities=False, no_network=True, load_dtd=False, huge_tree=False, remove_comments=True, remove_pis=True
    )
    try:
        root = etree.fromstring(xml, parser=parser)
    except etree.XMLSyntaxError as exc:
        reason = str(exc.msg).replace("\n", "")  # libxml2 ends some messages with a newline: keep one line
        raise ModelError(f"{path}: malformed XML ({reason})") from None
    if root.getroottree().docinfo.doctype:
        raise ModelError(f"{path}: DOCTYPE declarations are not allowed in a {kind} (entities could expand)")
    # The loaders that read the file after these checks (urdfdom's tinyxml2, Pinocchio's MJCF parser) know no
    # namespaces: they read an element by the name it is written with. An unprefixed element in a default namespace
    # (<mesh xmlns="..." file="..."/>) is a <mesh> to them, so it is one to the checks too; a prefixed one
    # (<x:mesh>) is a different element to them, as to lxml.
    for element in root.iter():
        if isinstance(element.tag, str) and element.tag.startswith("{") and element.prefix is None:
            element.tag = etree.QName(element).localname
    return root


def count_start_tags(xml: bytes) -> int:
    """Number of element start tags in XML bytes (an upper bound: tags inside comments and CDATA count too).

    Counted without parsing, so that a file of millions of tiny elements is refused before libxml2 builds them.
    """
    opening = xml.count(b"<")
    if opening <= MAX_XML_ELEMENTS:  # the common case: one pass is enough to know it is small
        return opening
    return opening - xml.count(b"</") - xml.count(b"<!") - xml.count(b"<?")


def parse_urdf(xml: bytes, path: Path) -> Any:
    """Parse URDF bytes safely (no DTD, no entities, no network, bounded size) into yourdfpy's description."""
    root = parse_xml(xml, path, "URDF", "(the largest catalog robot has about 2000)")
    if root.tag != "robot":
        raise ModelError(f"{path}: not a URDF: the root element is <{root.tag}>, expected <robot>")
    if "name" not in root.attrib:
        raise ModelError(f"{path}: the <robot> element has no 'name' attribute")
    for kind, limit in (("link", MAX_LINKS), ("joint", MAX_JOINTS)):
        count = int(root.xpath(f"count({kind})"))  # counted in libxml2: no Python object per element
        if count > limit:
            raise ModelError(
                f"{path}: the robot has {count} {kind}s, more than the {limit} this simulator accepts "
                "(the largest catalog robot has 78)"
            )
    import yourdfpy  # lazily: it imports trimesh, a second of start-up that `--help` should not pay

    try:
        # NaN or infinite origins make trimesh warn while composing matrices; check_urdf reports them.
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            return yourdfpy.URDF(
                robot=yourdfpy.URDF._parse_robot(xml_element=root),
                build_scene_graph=False,
                load_meshes=False,
                load_collision_meshes=False,
            )
    except (ValueError, TypeError, KeyError, AttributeError, IndexError) as exc:
        raise ModelError(f"{path}: invalid URDF ({exc})") from None


def resolve_mesh_uri(
    uri: str,
    urdf_path: Path,
    package_dirs: list[Path],
    *,
    allowed_roots: list[Path] | None = None,
    kind: str = "mesh",
) -> Path | None:
    """The file a mesh URI names, which must lie inside the URDF's folder, a package directory or an allowed root.

    The check is lexical first (a `..` escape is refused without touching the file system), then on the real
    path (a symlink leading out is refused); no file is opened.

    Args:
        uri: the mesh filename as the URDF writes it: `package://NAME/...`, `file://...` or a path (relative
            to the URDF's folder).
        urdf_path: the URDF file.
        package_dirs: the URDF's folder and the folders package:// URIs resolve against.
        allowed_roots: further folders the mesh may resolve into.
        kind: what the URI names, for messages ("mesh" or "texture").

    Returns:
        The mesh file, or None when no candidate file exists (meshes only matter for viewing).

    Raises:
        ModelError: the URI resolves outside every allowed folder, or has a scheme other than package://.
    """
    package_roots = [Path(os.path.realpath(p)) for p in package_dirs]
    roots = package_roots + [Path(os.path.realpath(p)) for p in allowed_roots or []]
    return resolve_in_roots(uri, urdf_path, package_roots, roots, kind)


def resolve_in_roots(uri: str, urdf_path: Path, package_roots: list[Path], roots: list[Path], kind: str) -> Path | None:
    """resolve_mesh_uri with the roots already resolved (check_urdf resolves them once for all its meshes)."""
    if uri.startswith("package://"):
        package, _, rest = uri[len("package://") :].partition("/")
        candidates = [root / package / rest for root in package_roots]
        candidates += [root / rest for root in package_roots if root.name == package]
    elif uri.startswith("file://"):
        candidates = [Path(uri[len("file://") :])]
    elif "://" in uri:
        raise ModelError(f"{urdf_path}: {kind} URI '{uri}' has an unsupported scheme (use package:// or a file path)")
    else:
        candidates = [urdf_path.parent / uri]
    found = None
    for candidate in candidates:
        lexical = Path(os.path.normpath(candidate))
        resolved = lexical if not inside_roots(lexical, roots) else Path(os.path.realpath(lexical))
        if not inside_roots(resolved, roots):
            raise ModelError(
                f"{urdf_path}: {kind} '{uri}' resolves outside the allowed folders "
                f"({', '.join(str(r) for r in roots)}); add its folder to package_dirs"
            )
        if found is None and os.path.isfile(resolved):
            found = resolved
    return found


def inside_roots(path: Path, roots: list[Path]) -> bool:
    """Whether a normalized absolute path lies in (or is) one of the roots (compared as strings: 10x faster than
    Path.is_relative_to, which the catalog's 2000-odd meshes felt)."""
    text = str(path)
    return any(text == str(root) or text.startswith(str(root).rstrip(os.sep) + os.sep) for root in roots)


@contextlib.contextmanager
def captured_stderr() -> Iterator[list[str]]:
    """Capture what C++ code writes to file descriptor 2 (urdfdom logs its parse errors there).

    Yields a list that holds the captured text once the block ends. The CLI promises one line on stderr for
    bad input; urdfdom's several lines would break that, and its first error is the useful part of the message.
    """
    captured: list[str] = []
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no usable fd 2 (embedded interpreters): do not capture
        yield captured
        return
    import tempfile

    try:
        with tempfile.TemporaryFile() as sink:
            os.dup2(sink.fileno(), 2)
            try:
                yield captured
            finally:
                os.dup2(saved, 2)
                sink.seek(0)
                captured.append(sink.read(1 << 20).decode("utf-8", "replace"))
    finally:
        os.close(saved)
