"""MA-MeSN (the paper's Algorithm 1) in one file, CleanRL style: arguments, networks, then the training loop.

The reference a reader starts from: plain PyTorch, nothing from Convoy but the environment (the referential game of
``convoy.envs.particle``: the speaker sees one of K targets, the listener must name it without seeing it, so
chance is 1/K and only a message can do better). ``algos/ma_mesn.py`` is the product's implementation; this file
computes the same update — ``tests/test_single_file_reference.py`` gives both the same weights, batches and Gumbel
noise and checks that the losses, the gradients and the weights after Adam steps agree to 1e-5.

    python examples/ma_mesn_single.py --steps 25000

What the update is (comments cite the lines of Algorithm 1 as "l. 13", counting from its first ``for``):

* every agent j turns its *current* observation into a message ``m_j = f′_j(o_j)``: ``bits`` Gumbel-softmax bits,
  straight-through in training (a hard 0/1 forward, the soft gradient backward), the argmax at execution;
* agent i's policy network reads its own observation and the others' messages: ``Q_i = f″_i(o_i, m_−i)``;
* the loss is the sum of every agent's TD loss, so back-propagation gives each f″_i its own agent's gradient
  (l. 15–17) and each f′_j the summed gradients of every agent that heard it (l. 18–19: "collect gradients from all
  policy networks"), in one Adam step for all networks;
* targets use the target copies of f′ *and* f″ at o′, with double Q-learning (the action picked by the online
  pair, valued by the target pair: appendix A.3 says every method uses it), synced every C updates (l. 21–22).

Where the product has options this file leaves out, it runs them at the referential game's defaults: no parameter
sharing (section B.2: "MA-MeSN [doesn't] use parameter sharing"), no bound on message logits, no positive-
signalling term, the channel open, one-step returns, no advantage learning, no policy averaging, a target copied
every C updates. Hierarchical DQN (appendix A.2) wraps any algorithm on the treadmill only and is not here.

Where the product, and so this file, reads Algorithm 1 other than as printed:

* l. 9 picks the greedy action with the *target* network f″_θ′; here, as in DQN, the online networks act.
* l. 7–19 sample and update agent by agent; here one batch of joint transitions serves every agent (l. 13 needs
  the others' observations o_−i, which l. 11's per-agent transition does not hold) and one step applies the summed
  gradients, so every f′_j gets all its listeners' gradients at once, as l. 18 says.
* l. 14 bootstraps with ``max_a′`` of the target; here the double-Q target (appendix A.3; ``--no-double-q`` gives
  l. 14). Which network makes the next messages m′_−i the paper does not say: here the target f′, argmax bits.
* l. 22 reads "θ_{i,f′} ← θ_{i,f′}", a no-op as printed; here the target message networks are synced (θ′ ← θ).
* Appendix A.1's loss is the squared TD error; the product's default is Huber (``--no-huber`` gives A.1's, halved).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from convoy.envs.particle.referential import make_referential_batch


def arg(default: Any, help: str) -> Any:
    """A dataclass field that also carries its ``--help`` text."""
    return field(default=default, metadata={"help": help})


@dataclass
class Args:
    """Every hyper-parameter; the defaults are the product's `convoy train --algo ma-mesn $REF` (docs/algorithms.md)."""

    seed: int = arg(0, "seed of the env, exploration, replay draws, message noise and network init")
    steps: int = arg(25_000, "total env steps, summed over the parallel envs")
    num_envs: int = arg(64, "referential games stepped together")
    n_targets: int = arg(4, "candidate targets K (chance 1/K)")
    rounds: int = arg(1, "steps per game with one target; only the last guess is scored")
    hidden: tuple[int, ...] = arg((64,), "hidden widths of every f′ and f″")
    message_bits: int = arg(16, "bits per message (the paper's 2 bytes)")
    gumbel_tau: float = arg(1.0, "Gumbel-softmax temperature")
    gumbel_noise: float = arg(1.0, "scale of the Gumbel noise in training; 0 = deterministic straight-through")
    lr: float = arg(5e-4, "Adam learning rate")
    gamma: float = arg(0.99, "discount γ")
    batch_size: int = arg(64, "joint transitions per update")
    replay_capacity: int = arg(100_000, "replay memory M (joint transitions)")
    learning_starts: int = arg(256, "transitions stored before the first update")
    replay_ratio: float = arg(2.0, "sampled transitions per stored transition")
    target_update: int = arg(50, "updates between target syncs C")
    grad_clip: float = arg(10.0, "global gradient-norm clip")
    huber: bool = arg(True, "Huber TD loss; --no-huber = the paper's squared error")
    double_q: bool = arg(True, "double Q-learning target; --no-double-q = Algorithm 1's max over the target")
    eps_start: float = arg(1.0, "exploration ε at step 0")
    eps_end: float = arg(0.05, "ε after the decay")
    eps_decay_fraction: float = arg(0.2, "ε decays linearly over this fraction of the run ...")
    eps_decay_max_steps: int = arg(100_000, "... or over this many env steps, if fewer")
    eval_episodes: int = arg(500, "greedy (and random) evaluation episodes at the end")
    log_every: int = arg(2_000, "env steps between progress lines")
    device: str = arg("auto", "auto = cuda when present, else cpu")
    torch_threads: int = arg(1, "torch intra-op threads (tiny matmuls: one thread is fastest)")


def parse_args(argv: list[str] | None = None) -> Args:
    """``Args`` from the command line: one flag per field (``--no-huber`` for booleans, ``--hidden 64 64``)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    for f in dataclasses.fields(Args):
        flag, default, kw = "--" + f.name.replace("_", "-"), f.default, {"help": f.metadata["help"]}
        if isinstance(default, bool):
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=default, **kw)
        elif isinstance(default, tuple):
            parser.add_argument(flag, type=int, nargs="+", default=default, **kw)
        else:
            parser.add_argument(flag, type=type(default), default=default, **kw)
    ns = parser.parse_args(argv)
    return Args(**{**vars(ns), "hidden": tuple(ns.hidden)})


# --- networks: f′ (message) and f″ (policy) of every agent, each its own weights --------------------------------------
def mlp(n_in: int, hidden: tuple[int, ...], n_out: int) -> nn.Sequential:
    """ReLU MLP with a linear last layer (message logits or Q-values)."""
    sizes = [n_in, *hidden, n_out]
    layers: list[nn.Module] = []
    for a, b in itertools.pairwise(sizes):
        layers += [nn.Linear(a, b), nn.ReLU()]
    return nn.Sequential(*layers[:-1])


class MeSN(nn.Module):
    """The message networks f′_j and policy networks f″_i of all N agents (one copy: online or target, l. 3).

    Every f″ has ``max(n_actions)`` outputs; an agent's actions beyond its own count are masked (the speaker of the
    referential game has one no-op action, the listener K)."""

    action_mask: Tensor  # [N, A]: True where agent i has action a

    def __init__(self, obs_dim: int, n_actions: tuple[int, ...], bits: int, hidden: tuple[int, ...]) -> None:
        super().__init__()
        n, a = len(n_actions), max(n_actions)
        self.n_agents, self.bits = n, bits
        self.message = nn.ModuleList(mlp(obs_dim, hidden, 2 * bits) for _ in range(n))  # f′_j: 2 logits per bit
        self.policy = nn.ModuleList(mlp(obs_dim + (n - 1) * bits, hidden, a) for _ in range(n))  # f″_i(o_i, m_−i)
        mask = torch.arange(a)[None, :] < torch.tensor(n_actions)[:, None]
        self.register_buffer("action_mask", mask, persistent=False)

    def message_logits(self, obs: Tensor) -> Tensor:
        """f′_j(o_j) for every agent: ``[M, N, D]`` → ``[M, N, 2·bits]``."""
        return torch.stack([f(obs[:, j]) for j, f in enumerate(self.message)], dim=1)

    def q_values(self, obs: Tensor, sent: Tensor) -> Tensor:
        """f″_i(o_i, m_−i) for every agent (agent i hears the others' messages in agent order) → ``[M, N, A]``."""
        n = self.n_agents
        heard = [torch.cat([sent[:, j] for j in range(n) if j != i], dim=-1) for i in range(n)]
        return torch.stack([f(torch.cat([obs[:, i], heard[i]], dim=-1)) for i, f in enumerate(self.policy)], dim=1)


def gumbel_bits(logits: Tensor, args: Args, train: bool, generator: torch.Generator | None) -> Tensor:
    """Discrete messages ``[M, N, bits]`` in {0, 1} from the logit pairs ``[M, N, 2·bits]`` (section 4.1).

    Each bit is a two-way Gumbel-softmax over its pair of logits. The difference of two Gumbel draws is logistic, so
    one uniform u per bit gives ``d + log u − log(1 − u)``, and softmax over the pair is ``sigmoid(d / τ)``. Forward:
    the hard argmax (exactly 0/1, what a channel carries); backward: the soft sample's gradient (straight-through).
    Execution sends the argmax without noise."""
    pairs = logits.reshape(*logits.shape[:-1], args.message_bits, 2)
    diff = pairs[..., 1] - pairs[..., 0]
    if not train:
        return (diff > 0).to(logits.dtype)
    if args.gumbel_noise > 0:
        u = torch.rand(diff.shape, generator=generator, device=diff.device, dtype=diff.dtype).clamp_(1e-7, 1 - 1e-7)
        diff = diff + args.gumbel_noise * (torch.log(u) - torch.log1p(-u))
    soft = torch.sigmoid(diff / args.gumbel_tau)
    hard = (diff > 0).to(logits.dtype)
    return hard + (soft - soft.detach())


def act_q(net: MeSN, obs: Tensor, args: Args) -> Tensor:
    """Execution-mode Q-values ``[M, N, A]``: argmax messages, unavailable actions at −1e9 (acting and targets)."""
    q = net.q_values(obs, gumbel_bits(net.message_logits(obs), args, train=False, generator=None))
    return q.masked_fill(~net.action_mask, -1e9)


# --- the update: Algorithm 1, lines 12–19, for all agents at once -----------------------------------------------------
def td_losses(
    online: MeSN, target: MeSN, batch: dict[str, Tensor], args: Args, generator: torch.Generator | None
) -> Tensor:
    """Each agent's TD loss ``[N]`` on one joint batch (their sum is what one step minimises).

    ``batch``: obs, next_obs ``[M, N, D]``; action ``[M, N]``; reward ``[M, N]``; terminated ``[M]``. ``generator``
    draws the Gumbel noise (the product uses its own per-seed generator; a test passes the same state to both)."""
    obs, action = batch["obs"], batch["action"]
    # l. 13: every agent's message m_j = f′_j(o_j) from its *current* observation (Gumbel bits, straight-through)
    sent = gumbel_bits(online.message_logits(obs), args, train=True, generator=generator)
    # l. 16: Q_i(o_i, m_−i, a_i; f″_i,θ) of the actions taken
    q = online.q_values(obs, sent).gather(-1, action.unsqueeze(-1)).squeeze(-1)
    with torch.no_grad():  # l. 14: y = r, or r + γ Q′(o′, m′_−i, a*) with the target f′ and f″ (argmax messages)
        q_next = act_q(target, batch["next_obs"], args)
        if args.double_q:  # a* from the online pair, its value from the target pair (appendix A.3)
            a_star = act_q(online, batch["next_obs"], args).argmax(dim=-1, keepdim=True)
            best = q_next.gather(-1, a_star).squeeze(-1)
        else:  # Algorithm 1 as printed: max over the target network
            best = q_next.max(dim=-1).values
        y = batch["reward"] + args.gamma * (1.0 - batch["terminated"].float()).unsqueeze(-1) * best
    # l. 15–16: the TD error per agent, averaged over the batch
    td = F.smooth_l1_loss(q, y, reduction="none") if args.huber else 0.5 * (q - y) ** 2
    return td.mean(dim=0)


def train_step(
    online: MeSN,
    target: MeSN,
    optimizer: torch.optim.Optimizer,
    batch: dict[str, Tensor],
    args: Args,
    generator: torch.Generator | None,
    updates: int,
) -> tuple[float, int]:
    """One gradient step on ``batch`` and the target sync; (the summed loss, updates done so far).

    Summing the agents' losses is what routes the gradients: f″_i is reached by agent i's loss only (l. 17), each
    f′_j by every loss whose agent heard m_j (l. 18–19)."""
    loss = td_losses(online, target, batch, args, generator).sum()
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    nn.utils.clip_grad_norm_(online.parameters(), args.grad_clip)
    optimizer.step()
    updates += 1
    if updates % args.target_update == 0:  # l. 21–22: θ′ ← θ for f″ and f′ alike
        target.load_state_dict(online.state_dict())
    return float(loss.detach()), updates


# --- replay memory D (l. 2, l. 11–12): joint transitions, every agent's view of the same step -------------------------
class Replay:
    """A numpy ring of joint transitions; ``sample`` draws uniformly with replacement."""

    def __init__(self, capacity: int, n_agents: int, obs_dim: int) -> None:
        self.capacity, self.size, self.next = capacity, 0, 0
        self.data: dict[str, np.ndarray] = {
            "obs": np.zeros((capacity, n_agents, obs_dim), np.float32),
            "action": np.zeros((capacity, n_agents), np.int64),
            "reward": np.zeros((capacity, n_agents), np.float32),
            "next_obs": np.zeros((capacity, n_agents, obs_dim), np.float32),
            "terminated": np.zeros(capacity, bool),
        }

    def add(self, rows: dict[str, np.ndarray]) -> None:
        m = len(rows["obs"])
        idx = (self.next + np.arange(m)) % self.capacity
        for k, v in rows.items():
            self.data[k][idx] = v
        self.next, self.size = (self.next + m) % self.capacity, min(self.size + m, self.capacity)

    def sample(self, n: int, rng: np.random.Generator, device: torch.device) -> dict[str, Tensor]:
        idx = rng.integers(0, self.size, size=n)
        return {k: torch.as_tensor(v[idx], device=device) for k, v in self.data.items()}


def epsilon_at(args: Args, env_steps: int) -> float:
    """Linear decay from ``eps_start`` to ``eps_end`` over min(fraction × run, max steps), then constant."""
    horizon = max(1, min(int(args.eps_decay_fraction * args.steps), args.eps_decay_max_steps))
    return args.eps_start + min(1.0, env_steps / horizon) * (args.eps_end - args.eps_start)


@torch.no_grad()
def evaluate(net: MeSN | None, args: Args, device: torch.device) -> tuple[float, float]:
    """Mean episode return and its 95 % CI over ``eval_episodes`` fixed-seed games: greedy with true messages, or
    uniformly random actions (``net`` None) on the same games."""
    env = make_referential_batch(args.eval_episodes, n_targets=args.n_targets, rounds=args.rounds)
    obs, ret = env.reset(seed=args.seed + 1_000_003), np.zeros(args.eval_episodes)
    rng = np.random.default_rng(args.seed)
    for _ in range(args.rounds):  # every game lasts exactly `rounds` steps
        if net is None:
            actions = (rng.random((args.eval_episodes, len(env.spec.n_actions))) * env.spec.n_actions).astype(np.int64)
        else:
            actions = act_q(net, torch.as_tensor(obs, device=device), args).argmax(-1).cpu().numpy()
        res = env.step(actions)
        ret += res.reward.mean(axis=1)
        obs = res.obs
    return float(ret.mean()), float(1.96 * ret.std(ddof=1) / math.sqrt(len(ret)))


def main(args: Args) -> dict[str, float]:
    """Train MA-MeSN on the referential game for ``args.steps`` env steps; print progress and the final greedy
    evaluation beside random play. Returns the figures printed last."""
    device = torch.device(("cuda" if torch.cuda.is_available() else "cpu") if args.device == "auto" else args.device)
    torch.set_num_threads(args.torch_threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)  # exploration and replay draws
    generator = torch.Generator(device=device).manual_seed(args.seed)  # Gumbel noise

    env = make_referential_batch(args.num_envs, n_targets=args.n_targets, rounds=args.rounds)
    spec = env.spec
    n_actions = np.asarray(spec.n_actions)
    # l. 1–4: replay memory, online and target networks (the target starts as a copy)
    online = MeSN(spec.obs_dim, spec.n_actions, args.message_bits, args.hidden).to(device)
    target = MeSN(spec.obs_dim, spec.n_actions, args.message_bits, args.hidden).to(device)
    target.load_state_dict(online.state_dict())
    target.requires_grad_(False)
    optimizer = torch.optim.Adam(online.parameters(), lr=args.lr)
    replay = Replay(args.replay_capacity, spec.n_agents, spec.obs_dim)
    print(f"MA-MeSN on the referential game (K = {args.n_targets}, chance {1 / args.n_targets:.3f}): "
          f"{args.steps:,} env steps, {args.num_envs} envs, hidden {args.hidden}, {device}")  # fmt: skip

    obs = env.reset(seed=args.seed)
    env_steps, updates, owed, next_log, t0 = 0, 0, 0.0, args.log_every, time.perf_counter()
    ep_ret, returns, losses = np.zeros(args.num_envs), [], []  # returns and losses since the last progress line
    while env_steps < args.steps:
        # l. 8–9: ε-greedy on Q_i(o_i, m_−i) (online networks, argmax messages)
        eps = epsilon_at(args, env_steps)
        with torch.no_grad():
            greedy = act_q(online, torch.as_tensor(obs, device=device), args).argmax(-1).cpu().numpy()
        explore = rng.random(greedy.shape) < eps
        actions = np.where(explore, (rng.random(greedy.shape) * n_actions).astype(np.int64), greedy)
        # l. 10–11: step every env, store the joint transitions (next_obs: the observation the step ended on)
        res = env.step(actions)
        replay.add({"obs": obs, "action": actions, "reward": res.reward, "next_obs": res.final_obs,
                    "terminated": res.terminated})  # fmt: skip
        ep_ret += res.reward.mean(axis=1)
        returns += ep_ret[res.done].tolist()
        ep_ret[res.done] = 0.0
        obs, env_steps = res.obs, env_steps + args.num_envs
        # l. 12–22: `replay_ratio` sampled transitions per stored one, in batches
        if replay.size >= max(args.learning_starts, args.batch_size):
            owed += args.num_envs * args.replay_ratio / args.batch_size
            while owed >= 1.0:
                loss, updates = train_step(online, target, optimizer, replay.sample(args.batch_size, rng, device),
                                           args, generator, updates)  # fmt: skip
                losses.append(loss)
                owed -= 1.0
        if env_steps >= next_log or env_steps >= args.steps:
            recent = np.mean(returns) if returns else float("nan")
            loss_now = np.mean(losses) if losses else float("nan")
            returns, losses = [], []
            sps = env_steps / (time.perf_counter() - t0)
            print(f"{env_steps:>9,} steps · ε {eps:.2f} · training return {recent:.3f} · loss {loss_now:.4f} · "
                  f"{updates:,} updates · {sps:,.0f} steps/s")  # fmt: skip
            next_log += args.log_every

    greedy_ret, greedy_ci = evaluate(online, args, device)
    random_ret, random_ci = evaluate(None, args, device)
    wall = time.perf_counter() - t0
    print(f"greedy return {greedy_ret:.3f} ± {greedy_ci:.3f} vs random {random_ret:.3f} ± {random_ci:.3f} "
          f"({args.eval_episodes} episodes, 95 % CI; {updates:,} updates, {wall:.1f} s)")  # fmt: skip
    return {"greedy": greedy_ret, "greedy_ci": greedy_ci, "random": random_ret, "random_ci": random_ci,
            "updates": float(updates), "wall_s": wall}  # fmt: skip


if __name__ == "__main__":
    main(parse_args())
