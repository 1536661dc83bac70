"""A scene file from elsewhere cannot widen where files are read from: its robot file and its package_dirs must lie
in its own folder or the catalog's, unless the user allows a folder (`--allow-root DIR`, `allowed_roots=[DIR]`).

Without that rule a scene from a stranger could name `package_dirs = ["/etc"]` (or a folder of someone else's)
and have its URDF's meshes read, and embedded in an exported page, from there.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest
from conftest import joint, link, urdf

import multibody_sim as ms
from multibody_sim.cli import main

PREFIX = "multibody-sim: error: "
STL = (
    "solid bob\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 0.1 0 0\nvertex 0 0.1 0\nendloop\nendfacet\n"
    "endsolid bob\n"
)


def pendulum_urdf(mesh_uri: str | None = None) -> str:
    bob = link("bob")
    if mesh_uri is not None:
        bob = bob.replace("</link>", f'<visual><geometry><mesh filename="{mesh_uri}"/></geometry></visual></link>')
    return urdf('<link name="base"/>', bob, joint("j1", "base", "bob"))


@pytest.fixture
def layout(tmp_path: Path) -> dict[str, Path]:
    """scene/ (the stranger's scene and its URDF, which names package://pkg/bob.stl) beside outside/pkg/bob.stl."""
    scene_dir, outside = tmp_path / "scene", tmp_path / "outside"
    (outside / "pkg").mkdir(parents=True)
    (outside / "pkg" / "bob.stl").write_text(STL)
    scene_dir.mkdir()
    (scene_dir / "robot.urdf").write_text(pendulum_urdf("package://pkg/bob.stl"))
    return {"scene": scene_dir, "outside": outside, "root": tmp_path}


def write_scene(folder: Path, source: str, package_dirs: list[str]) -> Path:
    dirs = ", ".join(f'"{d}"' for d in package_dirs)
    path = folder / "scene.toml"
    path.write_text(f'[robot]\nsource = "{source}"\npackage_dirs = [{dirs}]\n')
    return path


def outside_message(scene: Path, key: str, value: str) -> str:
    roots = [os.path.realpath(scene.parent), os.path.realpath(ms.catalog.shipped_models_dir())]
    roots.append(str(ms.catalog.example_robot_data_share()))
    return (
        f"{scene}: {key}: '{value}' is outside the folders a scene may read from (its own folder and the catalog's: "
        f"{', '.join(roots)}); to allow it, pass --allow-root DIR (allowed_roots=[DIR] in load_scene)"
    )


@pytest.mark.parametrize("target", ["/etc", "outside"])
def test_package_dirs_outside_the_scene_folder_are_refused(
    layout: dict[str, Path], target: str, capfd: pytest.CaptureFixture[str]
):
    value = "/etc" if target == "/etc" else str(layout["outside"])
    scene = write_scene(layout["scene"], "robot.urdf", [value])
    message = outside_message(scene, "robot.package_dirs[0]", value)
    with pytest.raises(ms.SceneError, match=f"^{re.escape(message)}$"):
        ms.load_scene(scene)
    capfd.readouterr()
    assert main(["run", str(scene), "--duration", "0.01"]) == 2
    out, err = capfd.readouterr()
    assert (out, err) == ("", f"{PREFIX}{message}\n")


def test_relative_escapes_and_symlinks_out_are_refused(layout: dict[str, Path]):
    scene = write_scene(layout["scene"], "robot.urdf", ["../outside"])
    with pytest.raises(ms.SceneError, match="robot.package_dirs\\[0\\]: '.*/outside' is outside the folders"):
        ms.load_scene(scene)
    (layout["scene"] / "link").symlink_to(layout["outside"])  # inside by its name, outside in fact
    scene = write_scene(layout["scene"], "robot.urdf", ["link"])
    with pytest.raises(ms.SceneError, match="robot.package_dirs\\[0\\]: '.*/link' is outside the folders"):
        ms.load_scene(scene)


def test_a_robot_file_outside_the_scene_folder_is_refused(layout: dict[str, Path]):
    other = layout["outside"] / "robot.urdf"
    other.write_text(pendulum_urdf())
    scene = write_scene(layout["scene"], str(other), [])
    with pytest.raises(ms.SceneError, match=f"robot.source: '{other}' is outside the folders"):
        ms.load_scene(scene)
    assert ms.load_scene(scene, allowed_roots=[layout["outside"]]).nv == 1


def test_allow_root_admits_a_folder_and_the_meshes_come_from_there(
    layout: dict[str, Path], capfd: pytest.CaptureFixture[str]
):
    """With the folder allowed (API and CLI) the scene loads and its visual mesh is the outside STL."""
    pytest.importorskip("trimesh")
    from multibody_sim.viz.scene import RobotScene, allowed_roots

    scene_path = write_scene(layout["scene"], "robot.urdf", [str(layout["outside"])])
    scene = ms.load_scene(scene_path, allowed_roots=[layout["outside"]])
    roots = allowed_roots(scene)
    assert Path(os.path.realpath(layout["outside"])) in roots
    parts = [part for visual in RobotScene(scene).visuals for part in visual.parts]
    assert len(parts) == 1 and parts[0].bounds()[1].max() == pytest.approx(0.1)  # the STL's triangle
    capfd.readouterr()
    code = main(["run", str(scene_path), "--duration", "0.01", "--allow-root", str(layout["outside"])])
    assert code == 0, capfd.readouterr().err


def test_package_dirs_inside_the_scene_folder_and_the_catalog_load(layout: dict[str, Path]):
    (layout["scene"] / "pkg").mkdir()
    (layout["scene"] / "pkg" / "bob.stl").write_text(STL)
    assert ms.load_scene(write_scene(layout["scene"], "robot.urdf", ["."])).nv == 1
    share = str(ms.catalog.example_robot_data_share())
    assert ms.load_scene(write_scene(layout["scene"], "ur5", [share])).nv == 6


def test_an_allowed_root_that_does_not_exist_is_bad_input(layout: dict[str, Path]):
    scene = write_scene(layout["scene"], "robot.urdf", [])
    with pytest.raises(ms.InvalidArgumentError, match="^allowed_roots: '/nonexistent/x' is not a folder$"):
        ms.load_scene(scene, allowed_roots=["/nonexistent/x"])


def test_a_replayed_scene_needs_the_folder_allowed_again(layout: dict[str, Path], capfd: pytest.CaptureFixture[str]):
    """The folders allowed at load time are recorded but not trusted from the file: `play` (and
    robot_from_trajectory) rebuild the scene only with the folder allowed again."""
    pytest.importorskip("meshcat")
    import multibody_sim.viz as viz

    scene_path = write_scene(layout["scene"], "robot.urdf", [str(layout["outside"])])
    scene = ms.load_scene(scene_path, allowed_roots=[layout["outside"]])
    out = ms.simulate(scene, scene.q0, scene.v0, duration=0.01, dt=1e-3).save(layout["root"] / "run.npz")
    run = ms.Trajectory.load(out)
    message = outside_message(scene_path, "robot.package_dirs[0]", str(layout["outside"]))
    with pytest.raises(ms.SceneError, match=f"^{re.escape(message)}$"):
        viz.robot_from_trajectory(run)
    assert viz.robot_from_trajectory(run, allowed_roots=[layout["outside"]]).nv == 1
    html = layout["root"] / "view.html"
    capfd.readouterr()
    assert main(["play", str(out), "--html", str(html)]) == 2
    assert capfd.readouterr().err == f"{PREFIX}{message}\n" and not html.exists()
    assert main(["play", str(out), "--html", str(html), "--allow-root", str(layout["outside"])]) == 0
    assert html.exists()


def forged_metadata_run(layout: dict[str, Path], folder: str) -> Path:
    """A run of the scene folder's own URDF whose metadata was edited to name `folder` as a package folder (the
    URDF names package://pkg/bob.stl: with /etc it would read /etc/pkg/bob.stl, with outside/ its STL)."""
    robot = ms.load_robot(layout["scene"] / "robot.urdf", package_dirs=[layout["outside"]])
    run = ms.simulate(robot, [0.1], [0.0], duration=0.01, dt=1e-3)
    run.metadata["robot"]["load_robot"]["package_dirs"] = [folder]
    return run.save(layout["root"] / "forged.npz")


@pytest.mark.parametrize("target", ["/etc", "outside"])
def test_a_trajectory_from_elsewhere_cannot_widen_the_mesh_folders(
    layout: dict[str, Path], target: str, capfd: pytest.CaptureFixture[str]
):
    """A trajectory's metadata names its package folders: outside the URDF's folder and the catalog's they are
    refused (its page would embed their files) unless the user allows them."""
    pytest.importorskip("meshcat")
    import multibody_sim.viz as viz

    folder = "/etc" if target == "/etc" else str(layout["outside"])
    out = forged_metadata_run(layout, folder)
    run = ms.Trajectory.load(out)
    with pytest.raises(ms.ModelError, match=f"its metadata names the folder '{re.escape(folder)}' \\(package_dirs\\)"):
        viz.robot_from_trajectory(run)
    html = layout["root"] / "view.html"
    with pytest.raises(ms.ModelError, match="outside the URDF's folder and the catalog's"):
        viz.export_html(run, html)
    capfd.readouterr()
    assert main(["play", str(out), "--html", str(html)]) == 2
    err = capfd.readouterr().err
    assert err.startswith(f"{PREFIX}cannot load the trajectory's robot: its metadata names the folder '{folder}'")
    assert err.count("\n") == 1 and not html.exists()
    if target == "outside":  # allowed by the user, the page is written with the STL in it
        assert main(["play", str(out), "--html", str(html), "--allow-root", folder]) == 0
        assert html.exists()


def test_a_trajectory_cannot_name_a_folder_of_its_own_as_the_scene_folder(layout: dict[str, Path]):
    """A scene run's metadata records the scene's folder; a stranger could point it at any folder holding a copy
    of the URDF and meshes of their choice. The folder is trusted only while it holds the recorded scene file."""
    pytest.importorskip("meshcat")
    import shutil

    import multibody_sim.viz as viz

    (layout["scene"] / "pkg").mkdir()
    (layout["scene"] / "pkg" / "bob.stl").write_text(STL)
    scene_path = write_scene(layout["scene"], "robot.urdf", ["."])
    scene = ms.load_scene(scene_path)
    run = ms.simulate(scene, scene.q0, scene.v0, duration=0.01, dt=1e-3)
    assert viz.robot_from_trajectory(run).nv == 1  # the user's own run: the scene file is there, unchanged
    elsewhere = layout["root"] / "elsewhere"
    shutil.copytree(layout["scene"], elsewhere, ignore=shutil.ignore_patterns("scene.toml"))
    run.metadata["robot"]["scene"]["base_dir"] = str(elsewhere)  # forged: the same URDF, meshes of their own
    with pytest.raises(ms.SceneError, match=f"robot.source: '{re.escape(str(elsewhere / 'robot.urdf'))}' is outside"):
        viz.robot_from_trajectory(run)
    assert viz.robot_from_trajectory(run, allowed_roots=[elsewhere]).nv == 1  # the user may allow it
    (layout["scene"] / "scene.toml").write_text("# edited since\n" + scene_path.read_text())
    run.metadata["robot"]["scene"]["base_dir"] = str(layout["scene"])
    with pytest.raises(ms.SceneError, match="robot.source: .* is outside"):  # no longer the recorded scene
        viz.robot_from_trajectory(run)
