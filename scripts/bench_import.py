"""Start-up cost: `import multibody_sim` and `multibody-sim --help` against `import pinocchio`, as ratios.

Each command runs in a fresh Python process; its cost is the child's CPU time (user + system, from os.wait4), which
a shared machine's load disturbs less than wall time. The commands are interleaved round by round (each round
runs every command once, in a rotated order) and the figures are medians over the rounds. Python's own start
(`python -c pass`) is measured in the same rounds and subtracted. The children may write bytecode caches
(PYTHONDONTWRITEBYTECODE is removed from their environment; the warm-up round writes them), as an installed
package has them: without them every run would compile our sources, and only ours (pip compiles what it installs).


The package is lazy (PEP 562): `import multibody_sim` alone loads almost nothing, so what a user pays is the import
and the first use of its API, "import + use" below (`import multibody_sim as ms; ms.simulate; ms.load_robot`):

    import ratio = (import + use - start) / (import pinocchio - start)     target <= 1.5
    help ratio   = (multibody-sim --help - start) / (import + use - start)   target <= 1.0
    (and, for reference, the bare lazy import, and --help against import pinocchio)

Usage: python scripts/bench_import.py [--rounds 21] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

IMPORT_TARGET = 1.5  # (import + use - start) <= 1.5 x (import pinocchio - start)
HELP_TARGET = 1.0  # multibody-sim --help no slower than importing and using the package


def commands() -> dict[str, list[str]]:
    """The measured commands: Python's start, the imports (the package's bare and with its first use) and the
    console script's --help."""
    python = sys.executable
    script = Path(python).with_name("multibody-sim")
    cli = [str(script)] if script.exists() else [shutil.which("multibody-sim") or "multibody-sim"]
    return {
        "python start": [python, "-c", "pass"],
        "import pinocchio": [python, "-c", "import pinocchio"],
        "import multibody_sim": [python, "-c", "import multibody_sim"],
        "import + use": [python, "-c", "import multibody_sim as ms; ms.simulate; ms.load_robot"],
        "multibody-sim --help": [*cli, "--help"],
    }


def cpu_seconds(argv: list[str]) -> float:
    """The CPU time (user + system) [s] of one run of argv in a child process; raises if it fails."""
    env = {key: value for key, value in os.environ.items() if key != "PYTHONDONTWRITEBYTECODE"}
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    stderr = proc.stderr.read().decode() if proc.stderr else ""
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} exited with {proc.returncode}: {stderr.strip()}")
    return usage.ru_utime + usage.ru_stime


def measure(rounds: int) -> dict[str, list[float]]:
    """CPU seconds of each command over `rounds` interleaved rounds (after one warm-up round, not kept)."""
    cmds = commands()
    names = list(cmds)
    for name in names:  # warm-up: file caches, .pyc files
        cpu_seconds(cmds[name])
    times: dict[str, list[float]] = {name: [] for name in names}
    for r in range(rounds):
        order = names[r % len(names) :] + names[: r % len(names)]
        for name in order:
            times[name].append(cpu_seconds(cmds[name]))
    return times


def report(times: dict[str, list[float]]) -> dict[str, float]:
    """Medians [s] and the two ratios."""
    median = {name: statistics.median(values) for name, values in times.items()}
    start = median["python start"]
    out = {f"{name} [s]": value for name, value in median.items()}
    out["import ratio"] = (median["import + use"] - start) / (median["import pinocchio"] - start)
    out["help ratio"] = (median["multibody-sim --help"] - start) / (median["import + use"] - start)
    out["help / pinocchio"] = (median["multibody-sim --help"] - start) / (median["import pinocchio"] - start)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=21, help="interleaved rounds (default 21)")
    parser.add_argument("--json", action="store_true", help="print the figures as one JSON document")
    args = parser.parse_args(argv)
    if args.rounds < 1:
        parser.error("--rounds must be at least 1")
    times = measure(args.rounds)
    figures = report(times)
    if args.json:
        print(json.dumps({**figures, "rounds": args.rounds}, indent=2))
        return 0
    start = figures["python start [s]"]
    print(f"CPU time per command, median of {args.rounds} interleaved rounds (python start subtracted in brackets):")
    for name in times:
        value = figures[f"{name} [s]"]
        extra = "" if name == "python start" else f"  ({(value - start) * 1e3:7.1f} ms)"
        print(f"  {name:<22} {value * 1e3:7.1f} ms{extra}")
    print(
        f"import ratio (import + use / pinocchio, start subtracted): {figures['import ratio']:.2f}"
        f"  (target <= {IMPORT_TARGET})"
    )
    print(
        f"help ratio (--help / import + use, start subtracted): {figures['help ratio']:.2f}  (target <= {HELP_TARGET})"
    )
    print(f"help / import pinocchio, start subtracted: {figures['help / pinocchio']:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
