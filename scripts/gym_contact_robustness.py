"""The go2_standing vector env under random actions (issue 24's learning load): no exception may escape step(), and
a row whose step fails carries infos["failure"] and infos["message"] and resets alone.

    python scripts/gym_contact_robustness.py [--seeds 20] [--steps 300] [--envs 16]

Prints, per action seed, the failed rows and their statuses, and the totals; exits 1 if any exception escaped.
"""

from __future__ import annotations

import argparse
import collections
import os
import sys
import time
import traceback

import numpy as np

import multibody_sim as ms
from multibody_sim import native
from multibody_sim.gym import MultibodyVectorEnv


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--envs", type=int, default=16)
    args = parser.parse_args()
    scene = ms.load_scene("go2_standing")
    env = MultibodyVectorEnv(scene, args.envs, reward=lambda q, v, tau: 0.0, method="timestepping")
    kernel = "native" if native.available and os.environ.get("MULTIBODY_SIM_NATIVE") != "0" else "python"
    escaped, failures, statuses = 0, 0, collections.Counter()
    start = time.process_time()
    for seed in range(args.seeds):
        env.reset(seed=seed)
        env.action_space.seed(seed)
        seen = 0
        try:
            for _ in range(args.steps):
                _, _, _, _, infos = env.step(env.action_space.sample())
                if "failure" in infos:
                    for i in np.flatnonzero(infos["_failure"]):
                        assert infos["message"][i], "a failed row without a message"
                        statuses[str(infos["failure"][i])] += 1
                        seen += 1
        except Exception:  # noqa: BLE001 - what this script counts
            escaped += 1
            print(f"seed {seed}: an exception escaped step():\n{traceback.format_exc()}", flush=True)
        failures += seen
        print(f"seed {seed}: {seen} failed rows", flush=True)
    cpu = time.process_time() - start
    print(
        f"go2_standing vector env, {args.envs} envs, {args.seeds} seeds x {args.steps} steps, random actions, "
        f"kernel {kernel}: exceptions escaped {escaped}; failed rows {failures} {dict(statuses)}; CPU {cpu:.1f} s"
    )
    return 1 if escaped else 0


if __name__ == "__main__":
    sys.exit(main())
