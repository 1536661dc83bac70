"""The catalog and load_robot(): every entry loads with its natural base; untrusted URDFs are checked first."""

from __future__ import annotations

import os
import re
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from conftest import joint, link, urdf
from lxml import etree

import multibody_sim as ms
from multibody_sim.catalog import catalog_urdf

BASE = '<link name="base"/>'
# Sizes (nq, nv) of each URDF joint type in Pinocchio: a continuous joint is stored as (cos, sin).
JOINT_SIZES = {
    "revolute": (1, 1),
    "prismatic": (1, 1),
    "continuous": (2, 1),
    "fixed": (0, 0),
    "planar": (4, 3),
    "floating": (7, 6),
}
FREE_FLYER = (7, 6)
# The base each robot has, as example-robot-data's own loaders gave it (free_flyer), written out here rather than
# read from the catalog: arms, hands, pendulums and the welded mobile manipulators (tiago) are bolted down;
# legged robots, humanoids, drones and the free box are not. One departure: the loaders put the SO-ARM desktop
# arms on a free-flyer, which left them falling; here they are fixed like every other arm.
NATURALLY_FIXED = {
    "pendulum",
    "stiff_arm",
    "point_robot",
    "spring_chain",
    "four_bar",
    "double_pendulum",
    "double_pendulum_continuous",
    "double_pendulum_simple",
    "asr_twodof",
    "ur3",
    "ur3_gripper",
    "ur3_limited",
    "ur5",
    "ur5_gripper",
    "ur5_limited",
    "ur10",
    "ur10_limited",
    "panda",
    "panda_collision",
    "z1",
    "kinova",
    "xarm7",
    "so_arm",
    "so100",
    "so101",
    "finger_edu",
    "allegro_right_hand",
    "allegro_left_hand",
    "baxter",
    "alex_nub_hands",
    "alex_psyonic_hands",
    "alex_sake_hands",
    "talos_arm",
    "tiago",
    "tiago_dual",
    "tiago_no_hand",
    "tiago_pro",
}
NATURALLY_FLOATING = {
    "free_body",
    "solo8",
    "solo12",
    "bolt",
    "a1",
    "go1",
    "go2",
    "b1",
    "b1_z1",
    "laikago",
    "anymal",
    "anymal_kinova",
    "anymal_c",
    "hyq",
    "quadruped",
    "centauro",
    "cassie",
    "talos",
    "talos_box",
    "talos_full",
    "talos_full_box",
    "talos_legs",
    "icub",
    "icub_reduced",
    "romeo",
    "simple_humanoid",
    "simple_humanoid_classical",
    "g1",
    "g1_with_hands",
    "alexander",
    "human",
    "pr2",
    "hector",
    "iris",
    "borinot",
    "hextilt",
}
# The names the issue lists (example-robot-data's loaders' names): every one must be in the catalog.
LOADER_NAMES = [
    "a1",
    "alex_nub_hands",
    "allegro_right_hand",
    "anymal",
    "anymal_kinova",
    "anymal_c",
    "asr_twodof",
    "b1",
    "b1_z1",
    "baxter",
    "bolt",
    "borinot",
    "cassie",
    "centauro",
    "double_pendulum",
    "finger_edu",
    "g1",
    "go1",
    "go2",
    "hector",
    "hextilt",
    "human",
    "hyq",
    "icub",
    "icub_reduced",
    "iris",
    "kinova",
    "laikago",
    "panda",
    "pr2",
    "quadruped",
    "romeo",
    "simple_humanoid",
    "so_arm",
    "solo8",
    "solo12",
    "talos",
    "talos_arm",
    "talos_full",
    "talos_legs",
    "tiago",
    "tiago_dual",
    "tiago_pro",
    "ur3",
    "ur5",
    "ur10",
    "xarm7",
    "z1",
]
CATALOG_NAMES = sorted(ms.CATALOG)


def exact(message: str) -> str:
    """A regex matching exactly `message` (pytest.raises searches, so anchor both ends)."""
    return f"^{re.escape(message)}$"


def sizes_from_urdf_text(path: Path, floating_base: bool, removed: frozenset[str] = frozenset()) -> tuple[int, int]:
    """(nq, nv) counted from the URDF's own <joint> elements (not <transmission>'s), except `removed`, plus a
    free-flyer root."""
    joints = [j for j in ET.parse(path).getroot().findall("joint") if j.get("name") not in removed]
    nq = sum(JOINT_SIZES[j.get("type")][0] for j in joints)
    nv = sum(JOINT_SIZES[j.get("type")][1] for j in joints)
    if floating_base:
        nq, nv = nq + FREE_FLYER[0], nv + FREE_FLYER[1]
    return nq, nv


def joints_below(path: Path, joint_name: str) -> frozenset[str]:
    """The joint and every joint under its child link, read from the URDF with the standard library."""
    joints = ET.parse(path).getroot().findall("joint")
    cut = next(j for j in joints if j.get("name") == joint_name)
    links, names = {cut.find("child").get("link")}, {joint_name}
    grew = True
    while grew:
        grew = False
        for j in joints:
            if j.find("parent").get("link") in links and j.get("name") not in names:
                names.add(j.get("name"))
                links.add(j.find("child").get("link"))
                grew = True
    return frozenset(names)


def expected_sizes(name: str, floating_base: bool) -> tuple[int, int]:
    """(nq, nv) of a catalog robot, from its files (and what the catalog says it removes)."""
    entry = ms.CATALOG[name]
    path = catalog_urdf(entry)[0]
    if path.suffix == ".sdf":  # Cassie: its 22 revolute joints; its 4 ball joints close the rods' loops
        joints = ET.parse(path).getroot().find("model").findall("joint")
        assert sorted({j.get("type") for j in joints}) == ["ball", "revolute"]
        n = sum(j.get("type") == "revolute" for j in joints)
        assert n == 22
        return (n + 7, n + 6) if floating_base else (n, n)
    removed = frozenset(entry.locked) | (joints_below(path, entry.prune) if entry.prune else frozenset())
    return sizes_from_urdf_text(path, floating_base, removed)


# ---- the catalog ---------------------------------------------------------------------------------------
def test_every_catalog_entry_is_classified_by_these_tests():
    assert set(ms.CATALOG) == NATURALLY_FIXED | NATURALLY_FLOATING, "classify new entries above"
    assert not NATURALLY_FIXED & NATURALLY_FLOATING


def test_every_name_of_example_robot_datas_loaders_is_in_the_catalog():
    assert len(LOADER_NAMES) == 48
    assert set(LOADER_NAMES) <= set(ms.CATALOG)


@pytest.mark.parametrize("name", CATALOG_NAMES)
def test_catalog_entry_loads_with_its_natural_base(robot, name):
    loaded = robot(name)
    natural = name in NATURALLY_FLOATING
    assert loaded.floating_base is natural
    assert ms.CATALOG[name].floating_base is natural
    path = Path(loaded.source["urdf_path"])
    assert path == catalog_urdf(ms.CATALOG[name])[0].resolve() and path.is_file()
    assert path.suffix == (".sdf" if name == "cassie" else ".urdf")
    assert (loaded.nq, loaded.nv) == expected_sizes(name, natural)
    assert len(loaded.dof_names) == loaded.nv
    if natural:
        assert loaded.joint_names[0] == "root_joint"
        assert loaded.dof_names[:6] == [f"root_joint.{c}" for c in ("vx", "vy", "vz", "wx", "wy", "wz")]


# Overrides that leave nothing to simulate: the free box and the two quadrotors (single bodies) welded to the
# world have no joint left, and the pendulum's massless root link, set free, turns about the hinge's own axis
# (checked below with Pinocchio).
IMPOSSIBLE_OVERRIDES = {"free_body", "hector", "iris", "pendulum"}
# Overriding the base is the same code for every entry: a few of each kind (plain, pruned, locked, converted,
# turned) keep the default suite fast.
OVERRIDDEN = ["ur5", "panda", "solo12", "talos_legs", "romeo", "cassie", "human", "tiago_pro", "finger_edu"]


@pytest.mark.parametrize("name", OVERRIDDEN)
def test_floating_base_argument_overrides_the_natural_base(robot, name):
    natural = name in NATURALLY_FLOATING
    for floating in (not natural, natural):
        loaded = robot(name, floating_base=floating)
        assert loaded.floating_base is floating
        assert (loaded.nq, loaded.nv) == expected_sizes(name, floating)


@pytest.mark.parametrize("name", sorted(IMPOSSIBLE_OVERRIDES - {"pendulum"}))
def test_welding_a_single_body_leaves_no_movable_joint(name):
    path = catalog_urdf(ms.CATALOG[name])[0].resolve()
    assert {j.get("type") for j in ET.parse(path).getroot().findall("joint")} <= {"fixed"}
    with pytest.raises(
        ms.ModelError, match=exact(f"{path}: the robot has no movable joint (a fixed base with only fixed joints)")
    ):
        ms.load_robot(name, floating_base=False)


def free_pendulum_mass_matrix(path: Path) -> tuple[np.ndarray, list[str]]:
    """M at the neutral configuration of the pendulum URDF on a free-flyer, straight from Pinocchio."""
    model = pin.buildModelFromUrdf(str(path), pin.JointModelFreeFlyer())
    M = pin.crba(model, model.createData(), pin.neutral(model))
    names = [f"root_joint.{c}" for c in ("vx", "vy", "vz", "wx", "wy", "wz")] + ["hinge"]
    return np.triu(M) + np.triu(M, 1).T, names


def test_freeing_the_pendulums_massless_root_is_refused(robot):
    path = Path(robot("pendulum").source["urdf_path"])
    M, _ = free_pendulum_mass_matrix(path)
    eigenvalues = np.linalg.eigvalsh(M)
    assert eigenvalues[0] < 1e-12 * eigenvalues[-1]  # truly singular, not a false alarm
    with pytest.raises(ms.ModelError) as info:
        ms.load_robot("pendulum", floating_base=True)
    assert str(info.value).startswith(f"{path}: the mass matrix is singular: the subtree moved by '")


def test_a_singular_mass_matrix_message_names_a_dof_of_the_null_direction(robot):
    path = Path(robot("pendulum").source["urdf_path"])
    M, names = free_pendulum_mass_matrix(path)
    null = np.linalg.eigh(M)[1][:, 0]
    involved = {names[i] for i in np.flatnonzero(np.abs(null) > 0.1)}
    assert involved == {"root_joint.wy", "hinge"}
    with pytest.raises(ms.ModelError) as info:
        ms.load_robot("pendulum", floating_base=True)
    named = re.search(r"moved by '([^']+)'", str(info.value))
    assert named and named.group(1) in involved


def test_a_urdf_path_loads_with_a_fixed_base_unless_asked(write_urdf):
    path = write_urdf(urdf(link("base", com="0 0 0"), link("bob"), joint("hinge", "base", "bob")))
    assert (ms.load_robot(path).nq, ms.load_robot(path).nv) == (1, 1)
    floating = ms.load_robot(str(path), floating_base=True)
    assert (floating.nq, floating.nv, floating.floating_base) == (8, 7, True)
    assert floating.name == "robot"  # the file's stem


def test_an_unknown_name_lists_close_matches_and_the_models_command():
    # difflib ratios against "ur55": ur5 6/7, ur3 4/7, ur10 4/8; every other name shares < half its letters.
    with pytest.raises(
        ms.RobotNotFoundError,
        match=exact(
            "unknown robot 'ur55': not a catalog name nor an existing URDF file (did you mean ur5, ur3, ur10? "
            "`multibody-sim models` lists the catalog)"
        ),
    ) as info:
        ms.load_robot("ur55")
    assert isinstance(info.value, LookupError) and isinstance(info.value, ms.UnknownNameError)
    assert isinstance(info.value, ms.MultibodySimError)
    assert not str(info.value).startswith('"')  # not quoted like a KeyError


def test_an_unknown_name_without_close_matches():
    with pytest.raises(
        ms.RobotNotFoundError,
        match=exact(
            "unknown robot 'xyzzy': not a catalog name nor an existing URDF file "
            "(`multibody-sim models` lists the catalog)"
        ),
    ):
        ms.load_robot("xyzzy")


@pytest.mark.parametrize("relative", ["missing.urdf", "sub/missing.urdf", "folder"])
def test_a_missing_urdf_path(tmp_path, relative):
    (tmp_path / "folder").mkdir()
    source = str(tmp_path / relative)
    with pytest.raises(ms.ModelError, match=exact(f"{source}: URDF file not found")) as info:
        ms.load_robot(source)
    assert isinstance(info.value, ValueError)


def test_a_bare_file_name_that_does_not_exist_is_a_missing_path(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ms.ModelError, match=exact("robot.urdf: URDF file not found")):
        ms.load_robot("robot.urdf")


# ---- malformed and hostile XML -------------------------------------------------------------------------
def load_error(path: Path) -> str:
    """The ModelError message load_robot gives for `path` (also a ValueError)."""
    with pytest.raises(ms.ModelError) as info:
        ms.load_robot(path)
    assert isinstance(info.value, ValueError)
    return str(info.value)


def test_malformed_xml(write_urdf):
    text = '<robot name="x"><link name="a"></robot>'
    path = write_urdf(text)
    with pytest.raises(etree.XMLSyntaxError) as parsed:  # libxml2's own account of the fault
        etree.fromstring(text.encode())
    assert load_error(path) == f"{path.resolve()}: malformed XML ({parsed.value.msg})"


def test_a_root_element_that_is_not_robot(write_urdf):
    path = write_urdf('<sdf version="1.6"><model name="m"/></sdf>')
    assert load_error(path) == f"{path.resolve()}: not a URDF: the root element is <sdf>, expected <robot>"


def passwd_lines() -> list[str]:
    """Non-trivial lines of /etc/passwd, which must never leak into a message."""
    try:
        return [line for line in Path("/etc/passwd").read_text().splitlines() if len(line) > 8]
    except OSError:
        return []


def lol_entities(levels: int) -> str:
    """The classic billion-laughs DTD: each entity is ten of the previous one (10**levels 'lol's at the top)."""
    entities = ['<!ENTITY lol0 "lol">']
    entities += [f'<!ENTITY lol{i} "{f"&lol{i - 1};" * 10}">' for i in range(1, levels + 1)]
    return f'<?xml version="1.0"?><!DOCTYPE robot [{"".join(entities)}]>'


ONE_JOINT = BASE + link("bob") + joint("j1", "base", "bob")


@pytest.mark.parametrize(
    "text",
    [
        lol_entities(2) + f'<robot name="r">{ONE_JOINT}<material>&lol2;</material></robot>',
        '<?xml version="1.0"?><!DOCTYPE robot [<!ENTITY xxe SYSTEM "file:///etc/passwd">]>'
        f'<robot name="r">{ONE_JOINT}<material>&xxe;</material></robot>',
        f'<?xml version="1.0"?><!DOCTYPE robot SYSTEM "file:///etc/passwd"><robot name="r">{ONE_JOINT}</robot>',
        lol_entities(2) + f'<robot name="&lol2;">{ONE_JOINT}</robot>',
    ],
    ids=["entity-in-content", "external-entity", "external-dtd", "entity-in-attribute"],
)
def test_doctype_declarations_are_refused(write_urdf, text):
    path = write_urdf(text)
    message = load_error(path)
    assert message == f"{path.resolve()}: DOCTYPE declarations are not allowed in a URDF (entities could expand)"
    assert not any(line in message for line in passwd_lines())


@pytest.mark.parametrize("where", ["content", "attribute"])
def test_billion_laughs_is_refused(write_urdf, where):
    # 10**9 'lol's (~3 GB) if expanded. libxml2's amplification guard may refuse the DTD itself (as malformed)
    # before our DOCTYPE check sees it: either way the file is refused at once.
    body = "<material>&lol9;</material>" if where == "content" else ""
    name = "&lol9;" if where == "attribute" else "r"
    path = write_urdf(lol_entities(9) + f'<robot name="{name}">{ONE_JOINT}{body}</robot>')
    message = load_error(path)
    assert message.startswith(f"{path.resolve()}: ")
    assert "lollol" not in message


def test_an_external_entity_in_an_attribute_is_refused_without_reading_it(write_urdf):
    path = write_urdf(
        '<?xml version="1.0"?><!DOCTYPE robot [<!ENTITY xxe SYSTEM "file:///etc/passwd">]>'
        f'<robot name="r">{BASE}<link name="&xxe;"/></robot>'
    )
    message = load_error(path)
    assert message.startswith(f"{path.resolve()}: ")
    assert not any(line in message for line in passwd_lines())


# ---- structure -----------------------------------------------------------------------------------------
def test_unsupported_joint_type(write_urdf):
    path = write_urdf(urdf(BASE, link("bob"), joint("j1", "base", "bob", kind="ball")))
    assert load_error(path) == (
        f"{path.resolve()}: joint 'j1' has unsupported type 'ball' "
        "(supported: continuous, fixed, floating, planar, prismatic, revolute)"
    )


@pytest.mark.parametrize(
    ("parent", "child", "role", "ghost"), [("base", "ghost", "child", "ghost"), ("ghost", "bob", "parent", "ghost")]
)
def test_a_joint_naming_a_missing_link(write_urdf, parent, child, role, ghost):
    path = write_urdf(urdf(BASE, link("bob"), joint("j1", parent, child)))
    assert load_error(path) == f"{path.resolve()}: joint 'j1' names {role} link '{ghost}', which does not exist"


def test_two_roots(write_urdf):
    path = write_urdf(urdf(BASE, link("bob"), link("stray"), joint("j1", "base", "bob")))
    assert load_error(path) == f"{path.resolve()}: the links must form one tree, found 2 roots (base, stray)"


def test_a_link_with_two_parents(write_urdf):
    path = write_urdf(
        urdf(
            BASE,
            link("mid"),
            link("bob"),
            joint("j1", "base", "mid"),
            joint("j2", "mid", "bob"),
            joint("j3", "base", "bob"),
        )
    )
    assert load_error(path) == f"{path.resolve()}: link 'bob' is the child of two joints ('j2' and 'j3')"


def test_only_fixed_joints_on_a_fixed_base(write_urdf):
    path = write_urdf(urdf(BASE, link("bob"), joint("j1", "base", "bob", kind="fixed")))
    assert load_error(path) == (
        f"{path.resolve()}: the robot has no movable joint (a fixed base with only fixed joints)"
    )


# ---- masses and inertias -------------------------------------------------------------------------------
@pytest.mark.parametrize(("mass", "shown"), [("-1.0", "-1.0"), ("nan", "nan"), ("inf", "inf")])
def test_a_bad_mass(write_urdf, mass, shown):
    path = write_urdf(urdf(BASE, link("bob", mass=mass), joint("j1", "base", "bob")))
    assert load_error(path) == f"{path.resolve()}: link 'bob' has mass {shown}; it must be finite and >= 0"


def test_an_inertia_with_a_negative_eigenvalue(write_urdf):
    path = write_urdf(urdf(BASE, link("bob", inertia="-0.01 0.01 0.01"), joint("j1", "base", "bob")))
    assert load_error(path) == (f"{path.resolve()}: link 'bob' has an inertia with a negative eigenvalue (-0.01)")


def test_an_indefinite_inertia_with_a_positive_diagonal(write_urdf):
    # Diagonal 0.01 but ixy = 0.02: eigenvalues 0.01 ± 0.02 in the xy block, so -0.01 is one of them.
    text = urdf(BASE, link("bob"), joint("j1", "base", "bob")).replace('ixy="0"', 'ixy="0.02"')
    path = write_urdf(text)
    assert load_error(path) == (f"{path.resolve()}: link 'bob' has an inertia with a negative eigenvalue (-0.01)")


def test_principal_inertias_violating_the_triangle_inequality(write_urdf):
    # 0.01 + 0.01 < 0.05: no distribution of mass has these principal moments.
    path = write_urdf(urdf(BASE, link("bob", inertia="0.01 0.01 0.05"), joint("j1", "base", "bob")))
    assert load_error(path) == (
        f"{path.resolve()}: the body moved by joint 'j1' has principal inertias 0.01, 0.01, 0.05 that violate "
        "the triangle inequality"
    )


def test_a_thin_rod_meets_the_triangle_inequality_with_equality(write_urdf):
    path = write_urdf(urdf(BASE, link("rod", inertia="0.01 0.01 0"), joint("j1", "base", "rod")))
    assert ms.load_robot(path).nv == 1


@pytest.mark.parametrize(
    "tip", [link("tip", mass=0.0, inertia="0 0 0"), '<link name="tip"/>'], ids=["zero-mass", "no-inertial"]
)
def test_a_massless_moving_subtree_makes_a_singular_mass_matrix(write_urdf, tip):
    path = write_urdf(urdf(BASE, link("arm"), joint("j1", "base", "arm"), tip, joint("j2", "arm", "tip", xyz="0 0 -1")))
    assert load_error(path) == (
        f"{path.resolve()}: the mass matrix is singular: the subtree moved by 'j2' has no mass or inertia"
    )


def test_a_massless_link_fixed_to_its_parent_is_accepted(write_urdf):
    # Tool frames and sensor mounts in real URDFs (ur5, panda, talos) are exactly this.
    path = write_urdf(
        urdf(
            BASE,
            link("arm"),
            joint("j1", "base", "arm"),
            link("tool", mass=0.0, inertia="0 0 0"),
            joint("mount", "arm", "tool", kind="fixed", xyz="0 0 -1"),
        )
    )
    loaded = ms.load_robot(path)
    assert (loaded.nq, loaded.nv, loaded.joint_names) == (1, 1, ["j1"])


# ---- mesh paths ----------------------------------------------------------------------------------------
def mesh_robot(uri: str) -> str:
    """A one-joint URDF whose moving link shows the mesh at `uri`."""
    bob = link("bob").replace("</link>", f'<visual><geometry><mesh filename="{uri}"/></geometry></visual></link>')
    return urdf(BASE, bob, joint("j1", "base", "bob"))


@pytest.mark.parametrize(
    "uri",
    ["package://x/" + "../" * 30 + "etc/passwd", "/etc/passwd", "file:///etc/passwd", "../" * 30 + "etc/passwd"],
    ids=["package-dotdot", "absolute", "file-uri", "relative-dotdot"],
)
def test_mesh_paths_escaping_the_allowed_folders_are_refused(write_urdf, uri):
    path = write_urdf(mesh_robot(uri))
    assert load_error(path) == (
        f"{path.resolve()}: mesh '{uri}' resolves outside the allowed folders ({path.parent.resolve()}); "
        "add its folder to package_dirs"
    )


def test_a_symlink_out_of_the_urdf_folder_is_refused(write_urdf):
    path = write_urdf(mesh_robot("meshes/bob.stl"))
    (path.parent / "meshes").mkdir()
    os.symlink("/etc/passwd", path.parent / "meshes" / "bob.stl")
    assert load_error(path) == (
        f"{path.resolve()}: mesh 'meshes/bob.stl' resolves outside the allowed folders ({path.parent.resolve()}); "
        "add its folder to package_dirs"
    )


def test_a_mesh_uri_with_another_scheme_is_refused(write_urdf):
    path = write_urdf(mesh_robot("http://example.com/bob.stl"))
    assert load_error(path) == (
        f"{path.resolve()}: mesh URI 'http://example.com/bob.stl' has an unsupported scheme "
        "(use package:// or a file path)"
    )


@pytest.mark.parametrize("uri", ["meshes/bob.stl", "./meshes/../meshes/bob.stl", "meshes/absent.stl"])
def test_a_mesh_inside_the_urdf_folder_is_accepted(write_urdf, uri):
    path = write_urdf(mesh_robot(uri))
    (path.parent / "meshes").mkdir()
    (path.parent / "meshes" / "bob.stl").write_text("solid bob\nendsolid bob\n")
    assert ms.load_robot(path).nv == 1


def test_package_uris_resolve_in_package_dirs_and_may_not_leave_them(tmp_path: Path, write_urdf: Callable[..., Path]):
    share = tmp_path / "share"
    (share / "bobpkg" / "meshes").mkdir(parents=True)
    (share / "bobpkg" / "meshes" / "bob.stl").write_text("solid bob\nendsolid bob\n")
    (tmp_path / "secret.stl").write_text("not yours")
    inside = write_urdf(mesh_robot("package://bobpkg/meshes/bob.stl"), name="inside.urdf")
    assert ms.load_robot(inside, package_dirs=[share]).nv == 1
    uri = "package://bobpkg/../../secret.stl"
    outside = write_urdf(mesh_robot(uri), name="outside.urdf")
    with pytest.raises(
        ms.ModelError,
        match=exact(
            f"{outside.resolve()}: mesh '{uri}' resolves outside the allowed folders "
            f"({outside.parent.resolve()}, {share.resolve()}); add its folder to package_dirs"
        ),
    ):
        ms.load_robot(outside, package_dirs=[share])
