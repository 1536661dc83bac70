"""Names from untrusted files cannot drive the terminal: every command that prints link, joint, frame or file
names escapes control characters (C0, C1), line breaks and bidirectional overrides visibly, on stdout and stderr.

The robot here is a stranger's URDF whose file, link and joint names hold a line break followed by text that
would pose as a line of our output, a CSI (U+009B, which starts a terminal escape on its own), a right-to-left
override and isolates, and left-to-right marks. Each command's whole output is checked character by character.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from conftest import link, urdf

from multibody_sim.cli import main

# The characters a name must never carry to a terminal: C0 controls other than the line breaks and tabs our own
# output uses, DEL and C1 controls, and the bidirectional and zero-width format characters.
RAW = re.compile(r"[\x00-\x08\x0b-\x1f\x7f-\x9f\u061c\u200b-\u200f\u2028-\u202e\u2060-\u2069\ufeff]")
FAKE_LINE = "status: completed (forged)"
# As XML character references: a URDF may hold these in names (C0 controls other than tab/LF/CR it may not).
JOINT = "elbow&#10;" + FAKE_LINE + "&#x9b;2J&#x202e;&#x2066;&#x200e;"
LINK = "arm&#x202d;&#x85;&#x2069;&#x200f;"
JOINT_SHOWN = "elbow\\x0a" + FAKE_LINE + "\\x9b2J\\u202e\\u2066\\u200e"
LINK_SHOWN = "arm\\u202d\\x85\\u2069\\u200f"
FILE_NAME = "evil\u202e\u2066robot\x1b[2J.urdf"  # a file name is untrusted too: it becomes the robot's name
FILE_SHOWN = "evil\\u202e\\u2066robot\\x1b[2J"


@pytest.fixture
def hostile_urdf(tmp_path: Path) -> Path:
    """A one-joint pendulum with hostile names whose joint starts outside its limits (a limit report names it)."""
    path = tmp_path / FILE_NAME
    joint = (
        f'<joint name="{JOINT}" type="revolute"><parent link="base"/><child link="{LINK}"/>'
        '<origin xyz="0 0 0"/><axis xyz="0 1 0"/><limit lower="-0.5" upper="0.5" effort="10" velocity="10"/>'
        "</joint>"
    )
    path.write_text(urdf('<link name="base"/>', link(LINK), joint), encoding="utf-8")
    return path


def run_cli(capfd: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    capfd.readouterr()
    code = main(list(argv))
    out, err = capfd.readouterr()
    return code, out, err


def assert_escaped(*texts: str) -> None:
    """No raw control or bidi character, and no line forged by a name's line break."""
    for text in texts:
        raw = RAW.findall(text)
        assert not raw, f"raw characters {raw!r} reach the terminal in:\n{text}"
        assert not any(line.startswith(FAKE_LINE) for line in text.splitlines()), text


def test_safe_name_escapes_every_class_visibly():
    from multibody_sim.text import safe_name, terminal_text

    for char, shown in [
        ("\n", "\\x0a"),
        ("\r", "\\x0d"),
        ("\x1b", "\\x1b"),
        ("\x7f", "\\x7f"),
        ("\x85", "\\x85"),
        ("\x9b", "\\x9b"),
        ("\u2028", "\\u2028"),
        *[(chr(c), f"\\u{c:04x}") for c in range(0x202A, 0x202F)],
        *[(chr(c), f"\\u{c:04x}") for c in range(0x2066, 0x206A)],
        ("\u200e", "\\u200e"),
        ("\u200f", "\\u200f"),
        ("\u061c", "\\u061c"),
    ]:
        assert safe_name(f"a{char}b") == f"a{shown}b"
    assert safe_name("shoulder_pan_joint") == "shoulder_pan_joint"  # ordinary names are unchanged
    assert safe_name("épaule ∠ 关节") == "épaule ∠ 关节"  # printable non-ASCII stays
    long = safe_name("x" * 10_000)
    assert len(long) < 250 and long.startswith("x" * 150) and long.endswith("x" * 40) and "9810 characters" in long
    assert terminal_text("line one\nline\x1b[31m two\u202e") == "line one\nline\\x1b[31m two\\u202e"


def test_inspect_escapes_names(hostile_urdf: Path, capfd: pytest.CaptureFixture[str]):
    code, out, err = run_cli(capfd, "inspect", str(hostile_urdf))
    assert code == 0, err
    assert_escaped(out, err)
    assert JOINT_SHOWN in out and LINK_SHOWN in out and FILE_SHOWN in out


def test_run_header_summary_and_limit_report_escape_names(hostile_urdf: Path, capfd: pytest.CaptureFixture[str]):
    code, out, err = run_cli(capfd, "run", str(hostile_urdf), "--q0", "1.0", "--duration", "0.01")
    assert code == 0, err
    assert_escaped(out, err)
    assert f"run: {FILE_SHOWN} (fixed base" in out  # the header
    assert f"worst: '{JOINT_SHOWN}'" in out  # the limit report of the summary


def test_run_json_keeps_names_exact_and_escaped(hostile_urdf: Path, capfd: pytest.CaptureFixture[str]):
    code, out, err = run_cli(capfd, "run", str(hostile_urdf), "--q0", "1.0", "--duration", "0.01", "--json")
    assert code == 0, err
    assert_escaped(out, err)
    document = json.loads(out)  # JSON escapes every non-ASCII and control character: a program gets the name
    assert document["summary"]["limit_violations"]["worst_joint"] == JOINT.replace("&#10;", "\n").replace(
        "&#x9b;", "\x9b"
    ).replace("&#x202e;", "\u202e").replace("&#x2066;", "\u2066").replace("&#x200e;", "\u200e")


@pytest.mark.filterwarnings("error:Glyph")
def test_plot_figure_escapes_names(hostile_urdf: Path, capfd: pytest.CaptureFixture[str], tmp_path: Path):
    out_file = tmp_path / "run.npz"
    assert run_cli(capfd, "run", str(hostile_urdf), "--duration", "0.01", "--out", str(out_file))[0] == 0
    code, out, err = run_cli(capfd, "plot", str(out_file), "--out", str(tmp_path / "p.png"))
    assert code == 0, err
    assert_escaped(out, err)


def test_failed_run_and_errors_escape_names(hostile_urdf: Path, capfd: pytest.CaptureFixture[str], tmp_path: Path):
    code, out, err = run_cli(capfd, "run", str(hostile_urdf), "--q0", "nan")
    assert code == 2 and out == ""
    assert_escaped(out, err)
    out_file = tmp_path / "run.npz"
    code, out, err = run_cli(capfd, "run", str(hostile_urdf), "--duration", "0.01", "--out", str(out_file))
    assert code == 0, err
    code, out, err = run_cli(capfd, "plot", str(out_file), "--joints", "nope", "--out", str(tmp_path / "p.png"))
    assert code == 2
    assert_escaped(out, err)
    assert JOINT_SHOWN in err  # the valid names are listed, escaped


@pytest.mark.filterwarnings("error:Glyph")  # matplotlib warns (quoting the raw character) of glyphs a title lacks
def test_bench_table_and_figure_escape_names(hostile_urdf: Path, capfd: pytest.CaptureFixture[str], tmp_path: Path):
    argv = ["bench", str(hostile_urdf), "--integrators", "euler,rk4", "--duration", "0.02", "--out", str(tmp_path)]
    code, out, err = run_cli(capfd, *argv)
    assert code == 0, err
    assert_escaped(out, err)
    assert f"bench: {FILE_SHOWN} (fixed base" in out and f"work-precision study of {FILE_SHOWN}:" in out


def test_play_escapes_names(hostile_urdf: Path, capfd: pytest.CaptureFixture[str], tmp_path: Path):
    pytest.importorskip("meshcat")
    out_file = tmp_path / "run.npz"
    assert run_cli(capfd, "run", str(hostile_urdf), "--duration", "0.05", "--out", str(out_file))[0] == 0
    code, out, err = run_cli(capfd, "play", str(out_file), "--html", str(tmp_path / "view.html"))
    assert code == 0, err
    assert_escaped(out, err)


def test_models_listing_is_escaped(capfd: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch):
    """The catalog and the shipped scenes are ours, but the listing goes through the same escaping."""
    import multibody_sim as ms

    rows = ms.catalog_table()
    hostile = dict(rows[0], name="x\u202ey\nINJECTED", description="d\x9b2J")
    monkeypatch.setattr(ms, "catalog_table", lambda: [hostile, *rows[1:]])
    code, out, err = run_cli(capfd, "models")
    assert code == 0
    assert_escaped(out, err)
    assert not any(line.startswith("INJECTED") for line in out.splitlines())
    assert "x\\u202ey\\x0aINJECTED" in out and "d\\x9b2J" in out
