"""The PyTorch reference of `make bench`'s model-free rows: one SAC update of MEDAL's shapes, timed.

Not a project dependency: run it with a Python that has torch (a throwaway venv), and the bench reads the
JSON it prints (experiments/benchmarks/model_free.py, TORCH_PYTHON=/path/to/venv/bin/python):

    python3 -m venv /tmp/torchvenv && /tmp/torchvenv/bin/pip install torch
    /tmp/torchvenv/bin/python experiments/benchmarks/torch_sac_reference.py obs=12 action=2

The networks and the update are MEDAL's SACAgent (docs/baselines.md, "The SAC learner", as in
morefree_jax/baselines/sac/learner.py): actor trunk Linear-LayerNorm-tanh (50) then 2 x 256 ReLU, critic trunk
then twin 2 x 256 heads, batch 256; per update: critic, actor, temperature, Polyak target. The batch is
fixed (no replay sampling, no env step): this times the update alone, as the bench bar states.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import torch
from torch import nn


def trunk(inputs: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(inputs, 50), nn.LayerNorm(50), nn.Tanh())


def head(inputs: int, out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(inputs, 256), nn.ReLU(), nn.Linear(256, 256), nn.ReLU(),
                         nn.Linear(256, out))


class Critic(nn.Module):
    def __init__(self, obs: int, action: int):
        super().__init__()
        self.trunk, self.q1, self.q2 = trunk(obs), head(50 + action, 1), head(50 + action, 1)

    def forward(self, obs, action):
        features = torch.cat([self.trunk(obs), action], -1)
        return self.q1(features), self.q2(features)


class Actor(nn.Module):
    def __init__(self, obs: int, action: int):
        super().__init__()
        self.net = nn.Sequential(trunk(obs), head(50, 2 * action))

    def sample(self, obs):
        mean, log_std = self.net(obs).chunk(2, -1)
        log_std = log_std.clamp(-20, 2)
        normal = torch.distributions.Normal(mean, log_std.exp())
        u = normal.rsample()
        log_pi = normal.log_prob(u) - 2 * (torch.log(torch.tensor(2.0)) - u - nn.functional.softplus(-2 * u))
        return torch.tanh(u), log_pi.sum(-1, keepdim=True)


class SAC:
    def __init__(self, obs: int, action: int):
        self.actor, self.critic, self.target = Actor(obs, action), Critic(obs, action), Critic(obs, action)
        self.target.load_state_dict(self.critic.state_dict())
        self.log_alpha = torch.zeros(1, requires_grad=True)
        self.optimizers = [torch.optim.Adam(p, lr=3e-4) for p in
                           (self.actor.parameters(), self.critic.parameters(), [self.log_alpha])]
        self.target_entropy = -action / 2

    def update(self, obs, action, reward, next_obs, not_done):
        actor_opt, critic_opt, alpha_opt = self.optimizers
        with torch.no_grad():
            next_action, next_log_pi = self.actor.sample(next_obs)
            q1, q2 = self.target(next_obs, next_action)
            value = torch.min(q1, q2) - self.log_alpha.exp() * next_log_pi
            target = 10.0 * reward + 0.99 * not_done * value
        q1, q2 = self.critic(obs, action)
        critic_loss = 0.5 * (((q1 - target) ** 2).mean() + ((q2 - target) ** 2).mean())
        critic_opt.zero_grad()
        critic_loss.backward()
        critic_opt.step()
        sampled, log_pi = self.actor.sample(obs)
        q1, q2 = self.critic(obs, sampled)
        actor_loss = (self.log_alpha.exp().detach() * log_pi - torch.min(q1, q2)).mean()
        actor_opt.zero_grad()
        actor_loss.backward()
        actor_opt.step()
        _, fresh_log_pi = self.actor.sample(obs)
        alpha_loss = (self.log_alpha.exp() * (-fresh_log_pi - self.target_entropy).detach()).mean()
        alpha_opt.zero_grad()
        alpha_loss.backward()
        alpha_opt.step()
        with torch.no_grad():
            for t, p in zip(self.target.parameters(), self.critic.parameters(), strict=True):
                t.mul_(0.995).add_(0.005 * p)


def parse(argv: list[str]) -> argparse.Namespace:
    """obs=N action=N [updates=300], key=value as every entry point takes (no project import: this runs
    under a Python with torch, outside the project's environment). obs: the policy input size."""
    values = {"updates": 300}
    for argument in argv:
        key, sep, text = argument.partition("=")
        if not sep or key not in ("obs", "action", "updates") or not text.isdigit():
            sys.exit(f"bad argument {argument!r}; valid keys: obs, action, updates (key=<int>)")
        values[key] = int(text)
    if "obs" not in values or "action" not in values:
        sys.exit("obs=... and action=... are required")
    return argparse.Namespace(**values)


def main() -> None:
    args = parse(sys.argv[1:])
    torch.manual_seed(0)
    agent, batch = SAC(args.obs, args.action), 256
    data = (torch.randn(batch, args.obs), torch.rand(batch, args.action) * 2 - 1, torch.rand(batch, 1),
            torch.randn(batch, args.obs), torch.ones(batch, 1))
    for _ in range(30):  # warm-up
        agent.update(*data)
    start = time.perf_counter()
    for _ in range(args.updates):
        agent.update(*data)
    seconds = (time.perf_counter() - start) / args.updates
    print(json.dumps({"update_ms": 1e3 * seconds, "torch": torch.__version__,
                      "threads": torch.get_num_threads(), "obs": args.obs, "action": args.action,
                      "batch": batch}))


if __name__ == "__main__":
    main()
