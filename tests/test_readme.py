"""The README's Python examples run as written (a README that lies is worse than none)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)


def test_readme_has_python_examples() -> None:
    assert len(BLOCKS) >= 2


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_python_example_runs(index: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)  # examples write files into the working directory
    exec(compile(BLOCKS[index], f"README.md python block {index}", "exec"), {"__name__": "__readme__"})


TOML_BLOCKS = re.findall(r"```toml\n(.*?)```", README.read_text(), re.S)


@pytest.mark.parametrize("index", range(len(TOML_BLOCKS)))
def test_readme_scene_example_runs(index: int, tmp_path: Path) -> None:
    """The README's scene file loads and runs as its [simulation] table says."""
    import multibody_sim as ms

    path = tmp_path / "scene.toml"
    path.write_text(TOML_BLOCKS[index])
    scene = ms.load_scene(path)
    traj = scene.run(duration=0.05)
    assert traj.status == "completed" and traj.t[-1] == pytest.approx(0.05)
    assert scene.nv == 7 and "force:push" in traj.ledger  # the locks and the force it declares are in force
