"""Fuzz the loaders of untrusted files and report how many cases ran and what failed.

Two engines:
- hypothesis (tests/test_fuzz.py, its slow tier): structured mutations of valid URDFs, trajectory files and
  scene files, objects in contact among them (hostile numbers, names, paths and shapes in every key), random
  bytes, the gym environments' settings, actions, seeds and reset options, and the command line's numeric options
  given hostile numbers (NaN, infinities, subnormals, overflows, ports beyond 65535); CASES examples per fuzzer.
  The default test suite runs each fuzzer's first 25 cases as a smoke test.
- atheris (coverage-guided libFuzzer, when `pip install atheris` works): raw bytes into load_robot and
  Trajectory.load, seeded with catalog URDFs and a saved trajectory; RUNS executions per target, each under
  a 10 s timeout and a 2 GiB RSS limit (a slow or memory-hungry input is a failure too).

Only multibody_sim's own errors (MultibodySimError) may come out; anything else is reported with its input.

Usage:
    .venv/bin/python scripts/fuzz.py [--cases 10000] [--runs 10000] [--skip-hypothesis] [--skip-atheris]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
MAX_LEN = 256 * 1024  # the largest seed (ur5's URDF) is ~13 kB; libFuzzer's default of 4 kB would cut it
# libFuzzer splices these tokens into inputs: it reaches the checks behind the XML syntax far sooner.
URDF_TOKENS = [
    "<robot", "</robot>", "<link", "</link>", "<joint", "</joint>", 'name="', 'type="', "revolute", "continuous",
    "prismatic", "fixed", "floating", "planar", "<parent", "<child", 'link="', "<origin", 'xyz="', 'rpy="',
    "<axis", "<limit", 'lower="', 'upper="', 'effort="', 'velocity="', "<dynamics", 'damping="', 'friction="',
    "<inertial>", "<mass", 'value="', "<inertia", 'ixx="', 'ixy="', 'iyy="', 'izz="', "<visual>", "<collision>",
    "<geometry>", "<mesh", 'filename="', 'scale="', "<box", 'size="', "<material", "<texture", "package://",
    "file://", "../", "/etc/passwd", "nan", "inf", "-inf", "1e308", "1e309", "-1", "0", "<!DOCTYPE", "<!ENTITY",
    "&", "<![CDATA[", "<!--", "-->",
]  # fmt: skip
NPZ_TOKENS = ["PK\x03\x04", "PK\x01\x02", "PK\x05\x06", "\x93NUMPY", "'descr'", "'shape'", "<f8", "|O", "<U"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=10_000, help="hypothesis examples per fuzzer")
    parser.add_argument("--runs", type=int, default=10_000, help="atheris executions per target")
    parser.add_argument("--skip-hypothesis", action="store_true")
    parser.add_argument("--skip-atheris", action="store_true")
    parser.add_argument("--atheris-worker", choices=["urdf", "npz"], help=argparse.SUPPRESS)
    parser.add_argument("--work", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.atheris_worker:
        return atheris_worker(args.atheris_worker, args.runs, args.work)

    rows: list[dict[str, Any]] = []
    failed = False
    with tempfile.TemporaryDirectory(prefix="mbs-fuzz-") as work:
        if not args.skip_hypothesis:
            failed |= run_hypothesis(args.cases, Path(work), rows)
        if not args.skip_atheris:
            failed |= run_atheris(args.runs, Path(work), rows)
    print()
    print(f"{'fuzzer':24s} {'engine':10s} {'cases':>8s} {'failures':>8s} {'time':>8s}  outcomes (exception: count)")
    for row in rows:
        outcomes = ", ".join(f"{k} {v}" for k, v in sorted(row.get("outcomes", {}).items(), key=lambda kv: -kv[1]))
        print(
            f"{row['fuzzer']:24s} {row['engine']:10s} {row['cases']:>8d} {len(row['failures']):>8d} "
            f"{row['seconds']:>7.0f}s  {outcomes}"
        )
    known = sum(len(r["failures"]) for r in rows if r.get("known"))
    for row in rows:
        if row.get("known"):
            kinds = sorted({failure.splitlines()[0] for failure in row["failures"]})
            print(f"\n--- {row['fuzzer']}: {len(row['failures'])} kinds of failure, all of a known, reported bug ---")
            print("\n".join(f"  {kind}" for kind in kinds))
            continue
        for failure in row["failures"]:
            print(f"\n--- {row['fuzzer']} failure ---\n{failure}")
    new = any(row["failures"] and not row.get("known") for row in rows)
    # A known bug makes its fuzzer xfail (exit 0): any failing exit is something new (or a crash).
    bad = new or failed
    verdict = "NEW FAILURES FOUND" if bad else "no new failures"
    if known:
        verdict += f" ({known} kinds of failure of known, reported bugs)"
    print(f"\ntotal cases: {sum(r['cases'] for r in rows)}; {verdict}")
    return 1 if bad else 0


def run_hypothesis(cases: int, work: Path, rows: list[dict[str, Any]]) -> bool:
    report = work / "hypothesis.jsonl"
    env = {**os.environ, "MBS_FUZZ_CASES": str(cases), "MBS_FUZZ_REPORT": str(report)}
    command = [sys.executable, "-m", "pytest", "tests/test_fuzz.py", "-m", "slow", "-k", "not atheris", "-q"]
    command += ["-p", "no:cacheprovider"]
    print("$", " ".join(command), f"(MBS_FUZZ_CASES={cases})", flush=True)
    start = time.perf_counter()
    result = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    print(result.stdout[-2000:], result.stderr[-2000:], sep="")
    records = [json.loads(line) for line in report.read_text().splitlines()] if report.exists() else []
    for record in records:
        rows.append({**record, "engine": "hypothesis", "seconds": seconds / max(len(records), 1)})
    if not records:
        rows.append({"fuzzer": "hypothesis", "engine": "hypothesis", "cases": 0, "seconds": seconds, "failures": []})
    return result.returncode != 0


def run_atheris(runs: int, work: Path, rows: list[dict[str, Any]]) -> bool:
    try:
        import atheris  # noqa: F401
    except ImportError:
        print("atheris is not installed (pip install atheris): coverage-guided fuzzing skipped")
        return False
    failed = False
    for target in ("urdf", "npz"):
        folder = work / f"atheris-{target}"
        folder.mkdir()
        command = [sys.executable, __file__, "--atheris-worker", target, "--runs", str(runs), "--work", str(folder)]
        print("$", " ".join(command), flush=True)
        start = time.perf_counter()
        result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
        seconds = time.perf_counter() - start
        done = re.search(r"Done (\d+) runs", result.stderr)
        failures = [] if result.returncode == 0 else [result.stderr[-4000:]]
        failed |= bool(failures)
        cases = int(done.group(1)) if done else _executed(result.stderr)
        rows.append(
            {"fuzzer": f"{target}-bytes", "engine": "atheris", "cases": cases, "seconds": seconds, "failures": failures}
        )
    return failed


def _executed(log: str) -> int:
    """Executions reached before a crash: libFuzzer's last '#N' status line."""
    counts = re.findall(r"^#(\d+)", log, flags=re.MULTILINE)
    return int(counts[-1]) if counts else 0


def atheris_worker(target: str, runs: int, work: Path) -> int:
    """Run libFuzzer on one loader (this process exits when the runs are done or on the first failure)."""
    import atheris

    with atheris.instrument_imports(include=["multibody_sim", "yourdfpy"]):
        import yourdfpy  # noqa: F401  (instrumented now: load_robot imports it lazily)

        import multibody_sim as ms

    corpus = work / "corpus"
    corpus.mkdir(parents=True, exist_ok=True)
    case = work / ("case.urdf" if target == "urdf" else "case.npz")
    if target == "urdf":
        for name in ("pendulum", "double_pendulum", "ur5", "free_body"):
            source = Path(ms.load_robot(name).source["urdf_path"])
            (corpus / f"{name}.urdf").write_bytes(source.read_bytes())
        package_dirs = [str(Path(ms.load_robot("ur5").source["urdf_path"]).parents[4])]

        def load() -> None:
            ms.load_robot(case, package_dirs=package_dirs)

    else:
        robot = ms.load_robot("double_pendulum")
        run = ms.simulate(robot, [3.0, 0.1], [0.0, 0.0], duration=0.05, dt=0.01)
        run.save(corpus / "seed.npz")

        def load() -> None:
            ms.Trajectory.load(case)

    devnull = os.open(os.devnull, os.O_WRONLY)

    def test_one_input(data: bytes) -> None:
        case.write_bytes(data)
        # urdfdom logs to stderr, which is libFuzzer's channel: keep it quiet during the call.
        saved = os.dup(2)
        os.dup2(devnull, 2)
        try:
            load()
        except ms.MultibodySimError:
            pass
        finally:
            os.dup2(saved, 2)
            os.close(saved)

    tokens = work / "tokens.dict"
    tokens.write_text("".join(f'"{_escaped(t)}"\n' for t in (URDF_TOKENS if target == "urdf" else NPZ_TOKENS)))
    options = [f"-runs={runs}", f"-max_len={MAX_LEN}", "-timeout=10", "-rss_limit_mb=2048", "-seed=1"]
    options += [f"-dict={tokens}", f"-artifact_prefix={work}/"]
    atheris.Setup([sys.argv[0], *options, str(corpus)], test_one_input)
    atheris.Fuzz()
    return 0


def _escaped(token: str) -> str:
    """A token in libFuzzer's dictionary syntax: quotes and backslashes escaped, bytes as \\xNN."""
    out = []
    for byte in token.encode("latin-1"):
        char = chr(byte)
        out.append(f"\\x{byte:02x}" if byte < 32 or byte > 126 or char in '"\\' else char)
    return "".join(out)


if __name__ == "__main__":
    sys.exit(main())
