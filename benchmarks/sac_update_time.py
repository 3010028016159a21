"""Milliseconds per SAC update of the intention policy, on one thread, with Adam as the agent makes it and
with torch's fused and for-each Adam (recorded in ``benchmarks/rat_profile.md``).

    python benchmarks/sac_update_time.py [--obs-dim 39] [--act-dim 4] [--batch 256]
"""

from __future__ import annotations

import argparse
import time

import torch

from rat.agents.sac import SAC, SACConfig


def time_updates(obs_dim: int, act_dim: int, batch_size: int, adam: dict, repeats: int = 5, updates: int = 100) -> list[float]:
    torch.manual_seed(0)
    agent = SAC(obs_dim, act_dim, SACConfig(batch_size=batch_size))
    if adam:
        agent.actor_opt = torch.optim.Adam(agent.actor.parameters(), lr=agent.config.lr, **adam)
        agent.critic_opt = torch.optim.Adam(agent.critic.parameters(), lr=agent.config.lr, **adam)
    batch = {"obs": torch.randn(batch_size, obs_dim), "action": torch.rand(batch_size, act_dim) * 2 - 1,
             "reward": torch.randn(batch_size), "next_obs": torch.randn(batch_size, obs_dim),
             "terminated": torch.zeros(batch_size)}
    for _ in range(50):  # warm-up
        agent.update(batch)
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        for _ in range(updates):
            agent.update(batch)
        times.append(1000 * (time.perf_counter() - started) / updates)
    return sorted(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--obs-dim", type=int, default=39)
    parser.add_argument("--act-dim", type=int, default=4)
    parser.add_argument("--batch", type=int, default=256)
    args = parser.parse_args()
    torch.set_num_threads(1)
    for name, adam in (("Adam (as the agent makes it)", {}), ("fused Adam", {"fused": True}),
                       ("for-each Adam", {"foreach": True})):
        times = time_updates(args.obs_dim, args.act_dim, args.batch, adam)
        print(f"{name}: {times[0]:.2f} ms an update at best, {times[len(times) // 2]:.2f} median")


if __name__ == "__main__":
    main()
