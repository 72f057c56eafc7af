"""The IK expert baseline of dbdjax/IKChainReach-v0: the DBD inverse-kinematics solution (and,
for comparison, the pseudo-inverse one) sent as the drive targets at every step. Prints and writes
benchmarks/results/ik_chain_expert.json: success rate (tip within 1 cm at the end of the
100-step episode), time to the first success, final distances, return, and wall-clock timings.

    python benchmarks/ik_chain_expert.py [--episodes 256] [--seed 0] [--iterations 32]
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

import jax

from dbdjax.envs.ik_chain import IKChainReach, evaluate_expert


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--iterations", type=int, default=32, help="IK updates per step")
    parser.add_argument("--methods", nargs="+", default=["dbd", "pinv"])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "ik_chain_expert.json")
    args = parser.parse_args()

    env = IKChainReach(max_episode_steps=IKChainReach.default_max_episode_steps)
    results = {
        "env": "dbdjax/IKChainReach-v0 (defaults)",
        "device": str(jax.devices()[0]),
        "machine": platform.processor() or platform.machine(),
        "runs": [],
    }
    for method in args.methods:
        result = evaluate_expert(env, episodes=args.episodes, seed=args.seed, iterations=args.iterations, method=method)
        print(json.dumps(result, indent=1), flush=True)
        results["runs"].append(result)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
