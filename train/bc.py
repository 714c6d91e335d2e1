"""Behaviour cloning from the expert: demonstrations and a warm start for PPO's actor.

PPO from scratch learns this task slowly (the expert's actions are small, ~0.05 of the action
range, and the tracking signal is weak against exploration noise). ``collect`` runs
`ExpertPolicy` on seeded random worlds and records every live agent's (observation, action);
``pretrain`` sets the VecNormalize observation statistics from the demonstrations and fits the SB3
policy's mean action to them (MSE per action dimension, scaled by its spread). PPO then fine-tunes
from there. Only the actor is fitted; ``train.ppo`` then trains the critic alone for
``--value-warmup`` steps (actor frozen), because PPO steps taken with an untrained critic's
advantages first undo much of what was cloned (measured: the mean episode return fell from 0.77 to
0.60 per step in the first 300k steps).
"""

from __future__ import annotations

import functools
import multiprocessing
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.running_mean_std import RunningMeanStd
from tqdm import tqdm

from uavtrack_env.expert import ExpertPolicy
from uavtrack_env.presets import ExpertConfig

from .frames import FrameHistory


@dataclass(frozen=True)
class Learner:
    """A saved SB3 policy that acts while the expert labels its states (DAgger, Ross et al.
    2011): ``model`` (.zip) and its VecNormalize statistics ``normalizer`` (.pkl; none if None
    or missing), over ``frames`` stacked observations; with ``shield`` (an `ExpertConfig`) its
    actions pass `CBFShield` as in shielded training."""

    model: Path
    normalizer: Path | None = None
    shield: ExpertConfig | None = None
    frames: int = 1

    def policy(self) -> Any:
        """The deterministic policy (``policy(obs, infos) -> {agent: action}``)."""
        from baselines.compare import load_policy

        return load_policy(self.model, self.normalizer, self.frames)


def collect(
    make_env: Callable[[], Any],
    episodes: int,
    seed: int,
    progress: bool = True,
    config: ExpertConfig | str | None = None,
    workers: int = 1,
    learner: Learner | None = None,
    frames: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Rollouts of a full episode each on ``make_env()`` worlds seeded ``seed + e``, labelled
    by the expert (``config``: its `ExpertConfig` or preset name, default 'tuned'). The expert
    acts, or with a ``learner`` the learner acts and the expert labels the states it visits
    (one DAgger round). With ``workers`` > 1 the episodes run in that many processes
    (``make_env`` must then be picklable, e.g. a `functools.partial`); the arrays are the same
    as with one.

    Returns (observations (N, frames * n_obs): each the last ``frames`` observations as
    `train.frames.FrameHistory` stacks them; expert actions (N, 4)), float32, one row per live
    agent-step.
    """
    FrameHistory(frames)  # a bad count fails here
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    seeds = range(seed, seed + episodes)
    desc = "expert demos" if learner is None else "DAgger labels"
    bar = tqdm(total=episodes, desc=desc, unit="episode", disable=not progress)
    done: list[tuple[list, list]] = []
    if workers == 1:
        for s in seeds:
            done.append(_episode(make_env, config, s, None, learner, frames))
            bar.update()
    else:
        run = functools.partial(
            _episode, make_env, config, threads=1, learner=learner, frames=frames
        )
        with multiprocessing.get_context("spawn").Pool(min(workers, episodes)) as pool:
            for pairs in pool.imap(run, seeds):  # in seed order
                done.append(pairs)
                bar.update()
    bar.close()
    obs_rows = [o for rows, _ in done for o in rows]
    act_rows = [a for _, rows in done for a in rows]
    return np.asarray(obs_rows, np.float32), np.asarray(act_rows, np.float32)


def _episode(
    make_env: Callable[[], Any],
    config: ExpertConfig | str | None,
    seed: int,
    threads: int | None,
    learner: Learner | None = None,
    frames: int = 1,
) -> tuple[list, list]:
    """One episode's (stacked observations, expert actions) of every live agent-step; the
    expert acts, or the ``learner`` acts (shielded if it says so) and the expert is told what
    was applied."""
    env = make_env()
    acting = None
    if learner is not None:
        acting = learner.policy()
        if learner.shield is not None:
            from uavtrack_env.wrappers import CBFShield

            env = CBFShield(env, learner.shield)
    obs, infos = env.reset(seed=seed)
    expert = ExpertPolicy.from_env(env.unwrapped, config, threads)
    history = FrameHistory(frames)
    obs_rows, act_rows = [], []
    while env.agents:
        labels = expert(obs, infos)
        stacked = history(obs)
        for agent, a in labels.items():
            obs_rows.append(stacked[agent])
            act_rows.append(a)
        actions = labels if acting is None else acting(obs, infos)
        obs, _, _, _, infos = env.step(actions)
        if acting is not None:
            expert.applied(
                {a: i.get("shield", {}).get("action", actions[a]) for a, i in infos.items()}
            )
    expert.close()
    env.close()
    return obs_rows, act_rows


class FrozenMeanStd(RunningMeanStd):
    """A VecNormalize ``obs_rms`` that keeps its mean and variance: ``update`` does nothing."""

    def update(self, arr: np.ndarray) -> None:
        pass


def freeze_observation_statistics(normalizer: Any) -> None:
    """Fix ``normalizer``'s (SB3 VecNormalize) observation statistics at their current values,
    for this run and any resumed from its checkpoints (`train.ppo --freeze-obs-stats`).

    Running statistics follow the states PPO visits, so an actor fitted on the demonstrations'
    statistics sees its inputs shift with no update of its own."""
    rms = normalizer.obs_rms
    if isinstance(rms, FrozenMeanStd):
        return
    frozen = FrozenMeanStd(shape=rms.mean.shape)
    frozen.mean, frozen.var, frozen.count = rms.mean.copy(), rms.var.copy(), rms.count
    normalizer.obs_rms = frozen


SCHEDULES = ("constant", "cosine")
"""`pretrain`'s learning-rate schedules."""


def actor_parameters(policy: Any, with_log_std: bool = True) -> list:
    """The parameters that define an SB3 ActorCriticPolicy's action distribution."""
    params = [
        *policy.features_extractor.parameters(),
        *policy.mlp_extractor.policy_net.parameters(),
        *policy.action_net.parameters(),
    ]
    return params + [policy.log_std] if with_log_std else params


def cloning_loss(policy: Any, obs: Any, actions: Any, scale: Any) -> Any:
    """Mean over dimensions of ((policy mean - action) / scale)^2 (torch tensors)."""
    mean = policy.get_distribution(obs).distribution.mean
    return (((mean - actions) / scale) ** 2).mean()


def pretrain(
    model: Any,
    normalizer: Any | None,
    obs: np.ndarray,
    actions: np.ndarray,
    *,
    epochs: int = 30,
    batch_size: int = 256,
    learning_rate: float = 1e-3,
    schedule: str = "constant",
    seed: int = 0,
    progress: bool = True,
) -> dict[str, float]:
    """Fit ``model.policy``'s mean action to ``actions`` (in place); returns the fit's losses.

    With a ``normalizer`` (SB3 VecNormalize), its observation statistics are first set to the
    demonstrations' mean and variance, so that PPO starts from the inputs the actor was fitted on.
    Loss: mean over dimensions of ((mean - action) / std(action))^2, so that a loss of 1 means
    "no better than the average action". ``schedule``: "constant" keeps ``learning_rate``; "cosine"
    anneals it to 0 over the epochs, so the actor kept is a converged one rather than wherever the
    last constant-rate step left it.
    """
    import torch

    if epochs < 1:
        raise ValueError(f"epochs must be >= 1, got {epochs}")
    if schedule not in SCHEDULES:
        raise ValueError(f"schedule must be one of {SCHEDULES}, got {schedule!r}")
    if len(obs) != len(actions) or len(obs) < batch_size:
        raise ValueError(f"need >= {batch_size} (obs, action) pairs, got {len(obs)}")
    if normalizer is not None:
        normalizer.obs_rms.mean = obs.mean(axis=0).astype(np.float64)
        normalizer.obs_rms.var = obs.var(axis=0).astype(np.float64)
        normalizer.obs_rms.count = float(len(obs))
        obs = normalizer.normalize_obs(obs)
    policy = model.policy
    x = torch.as_tensor(obs, dtype=torch.float32)
    y = torch.as_tensor(actions, dtype=torch.float32)
    scale = y.std(dim=0).clamp_min(1e-3)
    opt = torch.optim.Adam(actor_parameters(policy, with_log_std=False), lr=learning_rate)
    gen = torch.Generator().manual_seed(seed)
    n_val = max(1, len(x) // 10)
    perm = torch.randperm(len(x), generator=gen)
    val, train = perm[:n_val], perm[n_val:]
    steps = epochs * -(-len(train) // batch_size)
    cosine = schedule == "cosine"
    anneal = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=steps) if cosine else None

    def loss_of(idx: torch.Tensor) -> torch.Tensor:
        return cloning_loss(policy, x[idx], y[idx], scale)

    policy.train()
    first = None
    for _ in tqdm(range(epochs), desc="behaviour cloning", unit="epoch", disable=not progress):
        order = train[torch.randperm(len(train), generator=gen)]
        for start in range(0, len(order), batch_size):
            loss = loss_of(order[start : start + batch_size])
            opt.zero_grad()
            loss.backward()
            opt.step()
            if anneal is not None:
                anneal.step()
        with torch.no_grad():
            v = float(loss_of(val))
        first = v if first is None else first
    policy.set_training_mode(False)
    return {"bc_samples": float(len(x)), "bc_val_loss_first_epoch": first, "bc_val_loss": v}


def anchor_callback(
    obs: np.ndarray,
    actions: np.ndarray,
    steps: int,
    batch_size: int = 256,
    learning_rate: float = 1e-4,
    seed: int = 0,
) -> Any:
    """SB3 callback: after every PPO update, ``steps`` minibatch steps of the cloning loss on the
    demonstrations (observations normalised with the current VecNormalize statistics).

    This keeps the actor near the expert while PPO fine-tunes it (the augmented loss of DAPG,
    Rajeswaran et al. 2018, applied as separate steps); TensorBoard logs ``train/bc_loss``.
    """
    import torch
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import VecNormalize

    y = torch.as_tensor(actions, dtype=torch.float32)
    scale = y.std(dim=0).clamp_min(1e-3)
    gen = torch.Generator().manual_seed(seed)

    class Anchor(BaseCallback):
        def _on_training_start(self) -> None:
            self.opt = torch.optim.Adam(
                actor_parameters(self.model.policy, with_log_std=False), lr=learning_rate
            )
            self.updates = self.model._n_updates

        def _on_rollout_start(self) -> None:
            self._anchor()

        def _on_training_end(self) -> None:
            self._anchor()

        def _anchor(self) -> None:
            if self.model._n_updates == self.updates:  # no PPO update since the last call
                return
            self.updates = self.model._n_updates
            if not self.model.policy.log_std.requires_grad:  # actor frozen (critic warm-up)
                return
            env = self.model.get_env()
            normalize = env.normalize_obs if isinstance(env, VecNormalize) else None
            policy = self.model.policy
            total = 0.0
            for _ in range(steps):
                idx = torch.randint(len(obs), (batch_size,), generator=gen)
                o = obs[idx.numpy()]  # normalised per row: only the minibatch's rows
                x = torch.as_tensor(normalize(o) if normalize else o, dtype=torch.float32)
                loss = cloning_loss(policy, x, y[idx], scale)
                self.opt.zero_grad()
                loss.backward()
                self.opt.step()
                total += float(loss.detach())
            self.logger.record("train/bc_loss", total / max(steps, 1))

        def _on_step(self) -> bool:
            return True

    return Anchor()
