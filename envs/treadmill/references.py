"""The reference policies every treadmill learner is judged against, by name.

* ``random`` — uniform actions;
* ``constant-K`` — action K (0…8) at every step: an open-loop policy that ignores everything;
* ``scripted`` — the hand-written driver on private observations (``envs.treadmill.scripted``);
* ``team-information`` — the same driver told where every adversary is that some agent observes (in its
  ``observe_k`` slots), and that it is one: what perfectly decoded messages between agents could carry;
* ``full-information`` — the same driver told every car's position and which cars are adversaries;
* ``private-planner``, ``team-planner``, ``team16-planner``, ``full-planner`` — the model-predictive driver of
  ``envs.treadmill.planner`` told its own sensor, its teammates' observations, one 16-bit word per teammate, or every
  car, each level's parameters tuned on the rules it plays where a search ran on them (the charger rules), else on the
  default rules (``planner.tuned_for``): the strongest policy Convoy has for each information level, and the references
  every learner is judged against;
* ``private-driver``, ``team-driver``, ``team16-driver`` — the reactive family of ``envs.treadmill.drivers`` with the
  parameters tuned the same way (``drivers_for``): on its own sensor, told every teammate's observation, told a
  16-bit code per teammate. ``benchmarks/treadmill_search.py`` tunes them afresh on any rules and searches the
  open-loop policies (constants, cycles up to period 32, cross-entropy over whole sequences) beside them.

``full-information ÷ scripted`` is the value of information; ``team-information ÷ scripted`` the part of it
that communication can reach.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from convoy.envs.rollout import RolloutResult, random_policy, rollout
from convoy.envs.treadmill.config import CHARGER_RULES, N_ACTIONS, TreadmillConfig
from convoy.envs.treadmill.engine import TreadmillEngine
from convoy.envs.treadmill.scripted import DANGER, full_information_actions, scripted_actions

Policy = Callable[[np.ndarray], np.ndarray]
CONSTANTS: tuple[str, ...] = tuple(f"constant-{a}" for a in range(N_ACTIONS))
DRIVERS: tuple[str, ...] = ("private-driver", "team-driver", "team16-driver")
PLANNERS: tuple[str, ...] = ("private-planner", "team16-planner", "team-planner", "full-planner")
REFERENCES: tuple[str, ...] = (
    "random",
    *CONSTANTS,
    "scripted",
    "team-information",
    "full-information",
    *DRIVERS,
    *PLANNERS,
)


def reference_policy(name: str, engine: TreadmillEngine, seed: int | None = None) -> Policy:
    """The policy ``name`` driving ``engine``'s agents (the full-information one reads the engine's state)."""
    if name == "random":
        return random_policy(engine.spec, seed)
    if name == "scripted":
        return lambda obs: scripted_actions(obs, engine.cfg)
    if name == "full-information":
        return lambda obs: full_information_actions(engine)
    if name == "team-information":
        return lambda obs: full_information_actions(engine, team_only=True)
    if name in DRIVERS:
        kind = name.split("-")[0]
        return _driver_policy(kind, engine, drivers_for(engine.cfg)[kind])
    if name in PLANNERS:
        from convoy.envs.treadmill import planner

        level = name.split("-")[0]
        params = planner.tuned_for(engine.cfg)[level]
        return lambda obs: planner.level_actions(level, engine, obs, params)
    if name in CONSTANTS:
        action = int(name.rsplit("-", 1)[1])
        return lambda obs: np.full(obs.shape[:2], action, np.int64)
    raise ValueError(f"unknown reference policy {name!r}; choose one of: {', '.join(REFERENCES)}")


def _driver_policy(kind: str, engine: TreadmillEngine, params) -> Policy:
    """The family driver ``kind`` (private | team | team16) with ``params``, counting its own steps (for weaving)."""
    from convoy.envs.treadmill import drivers

    cfg, t = engine.cfg, [0]

    def policy(obs: np.ndarray) -> np.ndarray:
        if kind == "private":
            a = drivers.private_actions(obs, cfg, params, t[0])
        elif kind == "team":
            a = drivers.team_actions(engine, obs, params, t[0])
        elif kind == "team16":
            a = drivers.team16_actions(obs, cfg, params, t[0])
        else:
            raise ValueError(f"unknown driver kind {kind!r}: private | team | team16")
        t[0] += 1
        return a

    return policy


# (rules, episodes, seed, round size, policy) → its rollout: a reference and its episodes are deterministic, so a
# process plays each once (the planners take seconds per 100 episodes; every run of the same rules and seed shows them)
_PLAYED: dict[tuple[str, int, int, int, str], RolloutResult] = {}


def evaluate_references(
    cfg: TreadmillConfig,
    episodes: int = 500,
    seed: int = 0,
    names: tuple[str, ...] = REFERENCES,
    round_envs: int | None = None,
) -> dict[str, RolloutResult]:
    """One ``episodes``-episode rollout per reference policy, every policy on the same env seeds: one round of
    ``episodes`` envs, or rounds of ``round_envs`` envs seeded ``seed``, ``seed + 1``, … — the very episodes a
    learner's evaluation on ``round_envs`` envs plays (``analysis.evaluation.first_episodes``)."""
    out: dict[str, RolloutResult] = {}
    rules = cfg.model_dump_json()
    size = episodes if round_envs is None else min(round_envs, episodes)
    for name in names:
        key = (rules, episodes, seed, size, name)
        if key not in _PLAYED:
            if len(_PLAYED) >= 1024:  # a long-lived process over many rule sets: bounded
                _PLAYED.clear()
            engine = TreadmillEngine(cfg, size, autoreset=False)  # reseeded each round, as a learner's evaluation
            rounds = [rollout(engine, reference_policy(name, engine, seed + rnd), seed=seed + rnd)
                      for rnd in range(-(-episodes // size))]  # fmt: skip
            _PLAYED[key] = rounds[0] if len(rounds) == 1 else RolloutResult.joined(rounds, episodes)
        out[name] = _PLAYED[key]
    return out


def best_constant(results: dict[str, RolloutResult]) -> str:
    """The name of the constant action with the highest mean return."""
    return max((n for n in results if n in CONSTANTS), key=lambda n: results[n].ci95()[0])


def summary_references(
    cfg: TreadmillConfig, episodes: int, seed: int, round_envs: int | None = None
) -> dict[str, tuple[float, float]]:
    """What a trained policy's summary shows beside it, each as (mean, 95 % CI half-width) over ``episodes``
    episodes: random; the best constant action (named; on the default rules also the best open-loop policy the
    search of ``benchmarks/treadmill_search.py`` finds); the tuned reactive driver on its own sensor (the reference
    of earlier results); and the planners told their own sensor, a 16-bit word per teammate, their teammates'
    observations and every car (tuned on these rules or the defaults, ``planner.tuned_for``): the strongest policy
    known at each information level. ``round_envs``: played in rounds (``evaluate_references``)."""
    names = ("random", *CONSTANTS, "private-driver", *PLANNERS)
    results = evaluate_references(cfg, episodes, seed, names=names, round_envs=round_envs)
    best = best_constant(results)
    return {name: results[name].ci95() for name in ("random", best, "private-driver", *PLANNERS)}


def who_sees_the_threat(cfg: TreadmillConfig, steps: int = 400, envs: int = 256, seed: int = 0) -> dict[str, float]:
    """Where the information messages would need sits: over the agent-steps of the scripted driver on which an
    adversary is within the scripted driver's danger distance of an agent, the fraction on which the agent observes
    some adversary itself, only a teammate does, or nobody does. Messages can help only with "only a teammate"."""
    engine = TreadmillEngine(cfg, envs)
    obs = engine.reset(seed)
    n = cfg.n_agents
    own = team = nobody = 0
    for _ in range(steps):
        rel_x, rel_y = engine.offsets()
        danger = np.hypot(rel_x[:, :, n:], rel_y[:, :, n:]).min(axis=2) < DANGER  # [E, N]
        near, near_dist, _ = engine.nearest()
        sees = ((near >= n) & np.isfinite(near_dist)).any(axis=2)  # [E, N]: the agent observes an adversary
        anyone = sees.sum(axis=1, keepdims=True)
        own += int((danger & sees).sum())
        team += int((danger & ~sees & (anyone > 0)).sum())
        nobody += int((danger & (anyone == 0)).sum())
        obs = engine.step(scripted_actions(obs, cfg)).obs
    total = max(own + team + nobody, 1)
    return {"own": own / total, "only_teammate": team / total, "nobody": nobody / total}


# --------------------------------------------------------------------------------------------------------------------
# Searched and tuned references (issue 31): the strongest open-loop policy a search finds, and a family of reactive
# drivers tuned on one set of episode seeds and scored on another, told their own sensor, their teammates' sensors, or
# a 16-bit code per teammate. Every function below plays whole episodes, vectorised over envs.


# The family's parameters chosen by ``benchmarks/treadmill_search.py`` on 300 tuning episodes per grid point
# (seed TUNING_SEED; 144 private and 288 team grid points): see docs/treadmill.md for the scores.
def _tuned() -> dict:
    from convoy.envs.treadmill.drivers import DriverParams

    return {
        "private": DriverParams(danger=24.0, danger_adversary=24.0, hold="circle", flee_pace=3, brake=False, home=0.3),
        "team": DriverParams(danger=24.0, danger_adversary=24.0, hold="straight", flee_pace=3, brake=True, home=0.5),
        "team16": DriverParams(danger=16.0, danger_adversary=20.0, hold="weave", flee_pace=3, brake=False, home=0.3),
    }


# The same family tuned on the charger rules (docs/figures/treadmill_charger.json's "params").
def _tuned_charger() -> dict:
    from convoy.envs.treadmill.drivers import DriverParams

    return {
        "private": DriverParams(danger=24.0, danger_adversary=24.0, hold="circle", flee_pace=3, brake=False, home=0.3),
        "team": DriverParams(danger=16.0, danger_adversary=20.0, hold="straight", flee_pace=3, brake=False, home=0.5),
        "team16": DriverParams(danger=32.0, danger_adversary=32.0, hold="straight", flee_pace=3, brake=False, home=0.3),
    }


def drivers_for(cfg: TreadmillConfig) -> dict:
    """The family's parameters for ``cfg``: tuned on its rules where a search ran on them, else on the defaults."""
    return TUNED_CHARGER if cfg.moves_as(CHARGER_RULES) else TUNED


TUNING_SEED = 1  # episode seeds the searches and grids choose on (env_seeds(1, ·) shares no env with seed 0)
SCORING_SEED = 0  # episode seeds every reported figure is measured on


def sequence_returns(
    cfg: TreadmillConfig, seqs: np.ndarray, episodes: int, seed: int, chunk: int = 16384
) -> np.ndarray:
    """Per-episode return (mean over agents) ``[S, episodes]`` of open-loop action sequences ``seqs``: ``[S, T]``
    (every agent plays the same sequence) or ``[S, N, T]`` (one per agent); step t plays column t mod T. Every
    sequence is played on the same ``episodes`` env seeds (``env_seeds(seed, episodes)``)."""
    from convoy.envs.batched import env_seeds

    seqs = np.asarray(seqs, np.int64)
    if seqs.ndim == 2:
        seqs = np.repeat(seqs[:, None, :], cfg.n_agents, axis=1)
    s_count, _, period = seqs.shape
    seeds = env_seeds(seed, episodes)
    out = np.zeros(s_count * episodes)
    per = max(1, chunk // episodes)
    for lo in range(0, s_count, per):
        rows = np.repeat(np.arange(lo, min(lo + per, s_count)), episodes)
        engine = TreadmillEngine(cfg, len(rows), autoreset=False)
        engine.reset(np.tile(seeds, len(rows) // episodes))
        ret = np.zeros(len(rows))
        alive = np.ones(len(rows), bool)
        for t in range(cfg.max_steps):
            r = engine.step(seqs[rows, :, t % period])
            ret[alive] += r.reward[alive].mean(axis=1)
            alive &= ~r.done
            if not alive.any():
                break
        out[lo * episodes : lo * episodes + len(rows)] = ret
    return out.reshape(s_count, episodes)


def cycle_family(max_period: int = 32) -> list[list[int]]:
    """Every periodic open-loop cycle of the searched families, period ≤ ``max_period``: each constant action; every
    block cycle "a × k then b × m" (a ≠ b, k + m ≤ max_period); every weave "s × k, l × m, s × k, r × m" (s a straight,
    l a left and r a right action of one acceleration, 2k + 2m ≤ max_period) and the ones without the straight part."""
    out = [[a] for a in range(N_ACTIONS)]
    for a in range(N_ACTIONS):
        for b in range(N_ACTIONS):
            if a != b:
                out += [[a] * k + [b] * m for k in range(1, max_period) for m in range(1, max_period - k + 1)]
    for accel in range(3):
        for straight_accel in range(3):
            s, left, right = 3 + straight_accel, 6 + accel, accel
            for k in range(0, max_period // 2):
                for m in range(1, max_period // 2 - k + 1):
                    out.append([s] * k + [left] * m + [s] * k + [right] * m)
    return out


def unroll(cycle: list[int], steps: int) -> np.ndarray:
    return np.resize(np.asarray(cycle, np.int64), steps)


def search_cycles(
    cfg: TreadmillConfig,
    max_period: int = 32,
    screen: int = 4,
    keep: int = 64,
    episodes: int = 64,
    seed: int = TUNING_SEED,
) -> list[tuple[list[int], float]]:
    """Every cycle of ``cycle_family`` on ``screen`` tuning episodes, the best ``keep`` again on ``episodes``:
    ``(cycle, mean return)`` best first."""
    fam = cycle_family(max_period)
    width = max(len(c) for c in fam)
    table = np.array([unroll(c, width) for c in fam])  # periods divide nothing in general: pad by repetition
    periods = np.array([len(c) for c in fam])
    first = np.zeros(len(fam))
    for p in np.unique(periods):  # one batch per period, so t mod period is exact
        idx = np.flatnonzero(periods == p)
        first[idx] = sequence_returns(cfg, table[idx, :p], screen, seed + 7919).mean(axis=1)
    top = np.argsort(-first, kind="stable")[:keep]
    second = np.array([sequence_returns(cfg, np.asarray([fam[i]]), episodes, seed).mean() for i in top])
    order = np.argsort(-second, kind="stable")
    return [(fam[top[i]], float(second[i])) for i in order]


def cem_sequences(
    cfg: TreadmillConfig,
    seeds: list[list[int]],
    per_agent: bool,
    iterations: int = 20,
    population: int = 128,
    elite: int = 16,
    episodes: int = 16,
    seed: int = TUNING_SEED,
    rng_seed: int = 0,
) -> tuple[np.ndarray, float]:
    """Cross-entropy search over ``max_steps``-long action sequences (shared by the agents, or one per agent with
    ``per_agent``), its categorical distribution started from the seed cycles ``seeds`` (unrolled, mixed with
    uniform), which also join the first population. Returns (best sequence ``[N or 1, T]``, its tuning mean)."""
    rng = np.random.default_rng(rng_seed)
    t_len = cfg.max_steps
    rows = cfg.n_agents if per_agent else 1
    start = np.stack([unroll(c, t_len) for c in seeds])  # [K, T]
    probs = np.full((rows, t_len, N_ACTIONS), 0.3 / N_ACTIONS)
    probs += 0.7 * np.eye(N_ACTIONS)[start[0]][None]
    best_seq, best_val = np.repeat(start[:1], rows, axis=0), -np.inf
    for it in range(iterations):
        u = rng.random((population, rows, t_len, 1))
        pop = (u > np.cumsum(probs, axis=-1)[None]).sum(axis=-1).clip(0, N_ACTIONS - 1)
        if it == 0:
            k = min(len(start), population)
            pop[:k] = start[:k, None, :]
        pop[-1] = best_seq
        full = pop if per_agent else pop[:, 0]
        val = sequence_returns(cfg, full, episodes, seed).mean(axis=1)
        order = np.argsort(-val, kind="stable")
        if val[order[0]] > best_val:
            best_val, best_seq = float(val[order[0]]), pop[order[0]].copy()
        top = pop[order[:elite]]  # [E, rows, T]
        freq = np.eye(N_ACTIONS)[top].mean(axis=0)
        probs = 0.7 * freq + 0.3 * probs
    return best_seq, best_val


def open_loop_search(
    cfg: TreadmillConfig, max_period: int = 32, cem_iterations: int = 20, quick: bool = False
) -> dict[str, tuple[np.ndarray, float]]:
    """The open-loop references, each chosen on tuning episodes: best constant, best cycle, best CEM sequence shared
    by every agent and one per agent (``{name: (sequence [N, T] or [T], tuning mean)}``)."""
    steps = cfg.max_steps
    const = sequence_returns(cfg, np.arange(N_ACTIONS)[:, None], 8 if quick else 128, TUNING_SEED).mean(axis=1)
    if quick:  # a smoke test: the ~1,100 cycles up to period 6, not the ~37,000 up to 32
        max_period = min(max_period, 6)
    cycles = search_cycles(cfg, max_period, keep=8 if quick else 64, episodes=4 if quick else 64)
    seeds = [c for c, _ in cycles[:8]]
    kw = dict(iterations=2 if quick else cem_iterations, population=16 if quick else 128, episodes=4 if quick else 16)
    shared, shared_val = cem_sequences(cfg, seeds, per_agent=False, **kw)
    per_agent, per_val = cem_sequences(cfg, seeds, per_agent=True, **kw)
    best_c = int(np.argmax(const))
    return {
        f"open-loop: constant-{best_c}": (np.full(steps, best_c), float(const[best_c])),
        "open-loop: best cycle " + _cycle_name(cycles[0][0]): (unroll(cycles[0][0], steps), cycles[0][1]),
        "open-loop: CEM shared": (shared[0], shared_val),
        "open-loop: CEM per agent": (per_agent, per_val),
    }


def _cycle_name(cycle: list[int]) -> str:
    blocks: list[str] = []
    prev: int | None = cycle[0]
    count = 0
    for a in [*cycle, None]:
        if a == prev:
            count += 1
        else:
            blocks.append(f"{prev}×{count}")
            prev, count = a, 1
    return "(" + " ".join(blocks) + ")"


# ---------------------------------------------------------------------------------------------------- tuned drivers
def driver_grid(quick: bool = False) -> list:
    """The family's parameter grid (``drivers.DriverParams``): flee distance, how and where to hold a place, flee
    pace, braking for a car ahead (and, for team drivers, the flee distance of a known adversary)."""
    from convoy.envs.treadmill.scripted import HOLDS, DriverParams

    dangers = (8.0, 16.0, 32.0) if quick else (8.0, 12.0, 16.0, 24.0, 32.0, 48.0)
    holds = ("straight", "circle") if quick else HOLDS
    return [
        DriverParams(danger=d, danger_adversary=max(d, da), hold=h, flee_pace=fp, brake=b, home=home)
        for d in dangers
        for h in holds
        for home in ((0.5,) if quick else (0.3, 0.5))
        for fp in ((3,) if quick else (2, 3))
        for b in ((False,) if quick else (False, True))
        for da in ((30.0,) if quick else (20.0, 40.0))
    ]


def driver_returns(cfg: TreadmillConfig, kind: str, params, episodes: int, seed: int) -> np.ndarray:
    """Per-episode return (mean over agents) of the family driver ``kind`` (private | team | team16) with
    ``params`` on ``episodes`` episodes seeded ``seed``."""
    engine = TreadmillEngine(cfg, episodes, autoreset=False)
    return rollout(engine, _driver_policy(kind, engine, params), seed=seed).mean_return


def tune_driver(
    cfg: TreadmillConfig, kind: str, grid: list | None = None, episodes: int = 300, seed: int = TUNING_SEED
) -> tuple[object, float]:
    """The grid point with the highest mean return on the tuning episodes: (params, tuning mean). A private
    driver ignores ``danger_adversary``, so only one value of it is tried there."""
    grid = grid if grid is not None else driver_grid()
    if kind == "private":
        seen, unique = set(), []
        for p in grid:
            key = (p.danger, p.hold, p.flee_pace, p.brake, p.band, p.home)
            if key not in seen:
                seen.add(key)
                unique.append(p)
        grid = unique
    scores = [float(driver_returns(cfg, kind, p, episodes, seed).mean()) for p in grid]
    i = int(np.argmax(scores))
    return grid[i], scores[i]


def paired_ratio(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """mean(a) ÷ mean(b) and mean(a − b) over the same episodes, each with its 95 % CI (delta method for the ratio,
    Student's t for the difference)."""
    from convoy.stats import ci95_half

    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    ratio = a.mean() / b.mean()
    ratio_half = ci95_half((a - ratio * b) / b.mean())
    diff = a - b
    return {"ratio": float(ratio), "ratio_ci95": ratio_half, "diff": float(diff.mean()), "diff_ci95": ci95_half(diff)}


def full_information_returns(cfg: TreadmillConfig, episodes: int, seed: int) -> np.ndarray:
    engine = TreadmillEngine(cfg, episodes, autoreset=False)
    return rollout(engine, reference_policy("full-information", engine), seed=seed).mean_return


def random_returns(cfg: TreadmillConfig, episodes: int, seed: int) -> np.ndarray:
    engine = TreadmillEngine(cfg, episodes, autoreset=False)
    return rollout(engine, reference_policy("random", engine, seed), seed=seed).mean_return


TUNED = _tuned()
TUNED_CHARGER = _tuned_charger()
