"""``vector_env``: K worlds of n UAVs stepped as arrays, for RL that wants samples.

``env = uavtrack_v0.vector_env(num_envs=K, **config)``; every world has the same `EnvConfig`
(``**config``, as for ``parallel_env``) and its own seed:

* ``reset(seed=s) -> (obs, infos)``: world k is reset with seed s + k (None: fresh entropy).
* ``step(actions) -> (obs, rewards, terminations, truncations, infos)``: actions (K, n, 4) in
  [-1, 1] (finite values beyond are clipped, as in the ParallelEnv); obs (K, n, n_obs) float32,
  rewards (K, n) float32, terminations and truncations (K, n) bool.

Row (k, i) is agent ``possible_agents[i]`` of world k. A UAV that has left its episode while its
world goes on (``terminate_on_collision="agent"``) is *inactive*: its action is ignored (any
value, NaN included), its observation and reward are 0, ``infos["active"][k, i]`` is False.
Terminations and truncations are True on the step an agent's episode ends.

**Autoreset** (Gymnasium's ``AutoresetMode.SAME_STEP``): when the last agent of world k has
ended, world k resets within the same ``step`` (seeded from its own stream, so a seeded run is
reproducible) and ``obs[k]`` is its first observation; the last one is in
``infos["final_obs"][k]`` with ``infos["_final_obs"][k]`` True.

**Infos** are arrays (K, n) about this step's transition, like the rewards (for a world that
ended, its last step): ``cost`` (the sum of ``costs``), ``costs`` = {collision, disconnection,
occlusion} as 0/1 floats, ``reward_tracking``, ``reward_effort``, ``action_clipped`` and
``active`` (the row took part in the step). ``full_infos=True`` adds ``infos["agents"]``: each
world's ParallelEnv info dicts of the step, and for a world that reset, its reset infos in
``infos["reset_infos"][k]`` (slower: it builds every nested dict).

World k behaves exactly as ``parallel_env(**config)`` reset with seed s + k and given the same
actions: same observations, rewards, terminations and infos (tested).

**Speed**: a step is one batched step of all worlds (`uavtrack_env.core`, the arithmetic the
ParallelEnv runs with K = 1); each world keeps its own PyBullet client, car and random stream.
With ``full_infos=True`` the worlds step one by one through their ParallelEnvs instead (the same
arrays, bit for bit, tested), so that each can build its info dicts. SB3:
`uavtrack_env.wrappers.sb3.VectorSharedPolicyVecEnv`. The CBF shield:
`uavtrack_env.wrappers.VectorCBFShield`, which reads each world's measurements, own states and
messages through ``sensor_infos(k)``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium
import numpy as np
from gymnasium.vector import AutoresetMode

from . import core, core_kernels
from .core import Obstacles, Score
from .env import UAVTrackEnv
from .infos import sensor_infos

VIOLATIONS = ("collision", "disconnection", "occlusion")


class UAVTrackVectorEnv:
    """K `UAVTrackEnv` worlds stepped together as arrays (module docstring)."""

    metadata: ClassVar[dict[str, Any]] = {"autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, num_envs: int, full_infos: bool = False, **config: Any) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int | np.integer):
            raise TypeError(f"num_envs must be an int >= 1, got {num_envs!r}")
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if config.get("render_mode") is not None:
            raise ValueError("vector_env does not render; use parallel_env(render_mode=...)")
        self.num_envs = int(num_envs)
        self.full_infos = bool(full_infos)
        self.envs = [UAVTrackEnv(**config) for _ in range(self.num_envs)]
        first = self.envs[0]
        self.config = first.config
        self._constants = first._constants
        self.possible_agents = list(first.possible_agents)
        self.n_agents = len(self.possible_agents)
        self.single_observation_space = first.observation_space(self.possible_agents[0])
        self.single_action_space = first.action_space(self.possible_agents[0])
        shape = (self.num_envs, self.n_agents)
        self.observation_space = gymnasium.spaces.Box(
            np.broadcast_to(self.single_observation_space.low, (*shape, first.n_obs)),
            np.broadcast_to(self.single_observation_space.high, (*shape, first.n_obs)),
            dtype=np.float32,
        )
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (*shape, 4), np.float32)
        self._scale = first._scale
        self._active = np.zeros(shape, bool)
        self._started = False
        # The worlds' state as arrays (K, n, ...): the batched step reads and writes these; each
        # world's env keeps its PyBullet client, car, layout and random stream.
        K, n = shape
        self._state = (np.zeros((K, n, 3)), np.zeros(shape), np.zeros((K, n, 3)), np.zeros(shape))
        self._alive = np.zeros(shape, bool)
        self._references = np.zeros((K, n, 4))
        self._cycles = np.zeros(K, int)
        self._max_cycles = first.max_cycles
        self._detector = first.detector
        self._bounds = (first._obs_low, first._obs_high)
        self._obstacles: Obstacles | None = None
        # What `sensor_infos` reads: a world's info dicts where the step or a reset built them,
        # else the batch's measurements and the agents that took part in the step.
        self._world_infos: list[dict[str, dict] | None] = [None] * K
        self._sensed: core.Measurements | None = None
        self._stepped = np.zeros(shape, bool)

    # ------------------------------------------------------------------ reset
    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every world; world k with seed ``seed + k``."""
        self._check_open("reset")
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int | np.integer)):
            raise TypeError(f"seed must be an int or None, got {seed!r}")
        obs = np.zeros(self.observation_space.shape, np.float32)
        per_world = []
        for k in range(self.num_envs):
            obs[k], info = self._reset_world(k, None if seed is None else int(seed) + k, options)
            per_world.append(info)
        self._obstacles = Obstacles.stack([env.layout for env in self.envs])
        self._started = True
        return obs, self._concat(per_world)

    def _load(self, k: int) -> None:
        """Take world k's state from its env (after its reset, or a step of it)."""
        env = self.envs[k]
        for mine, theirs in zip(
            self._state, (env.position, env.yaw, env.velocity, env.yaw_rate), strict=True
        ):
            mine[k] = theirs
        self._alive[k] = env.alive
        self._references[k] = env.references
        self._cycles[k] = env.num_cycles

    def _reset_world(self, k: int, seed: int | None, options: dict | None):
        env = self.envs[k]
        obs, infos = env.reset(seed=seed, options=options)
        self._active[k] = True
        self._world_infos[k] = infos
        self._load(k)
        return np.stack([obs[a] for a in self.possible_agents]), self._reset_info(env, infos)

    def _reset_info(self, env: UAVTrackEnv, infos: dict) -> dict[str, Any]:
        """One world's reset infos as arrays (1, n) (and its info dicts with ``full_infos``)."""
        rows = [infos[a] for a in self.possible_agents]
        out = {
            "cost": np.array([[r["cost"] for r in rows]]),
            "costs": {v: np.array([[r["costs"][v] for r in rows]]) for v in VIOLATIONS},
            "reward_tracking": np.array([[r["reward_tracking"] for r in rows]]),
            "reward_effort": np.array([[r["reward_effort"] for r in rows]]),
            "action_clipped": np.zeros((1, self.n_agents), bool),
            "active": np.ones((1, self.n_agents), bool),
        }
        if self.full_infos:
            out["agents"] = [infos]
        return out

    # ------------------------------------------------------------------- step
    def step(self, actions: Any):
        """One step of every world (module docstring); bad input raises and changes nothing."""
        u, clipped = self._checked(actions)
        active = self._active.copy()
        u, clipped = u * active[..., None], clipped & active
        self._world_infos = [None] * self.num_envs
        self._stepped = active
        if self.full_infos:
            obs, rewards, terminated, truncate, infos = self._step_each(u, clipped, active)
        else:
            obs, rewards, terminated, truncate, infos = self._step_batch(u, clipped, active)
        terminations = terminated & active
        truncations = truncate[:, None] & active
        self._active = active & ~terminations & ~truncations
        ended = truncate | ~self._alive.any(axis=1)
        if ended.any():
            infos["final_obs"] = np.where(ended[:, None, None], obs, np.float32(0.0))
            infos["_final_obs"] = ended
            reset_infos: list[Any] = [None] * self.num_envs
            for k in np.flatnonzero(ended):
                obs[k], reset_info = self._reset_world(k, None, None)
                reset_infos[k] = reset_info.get("agents", [None])[0]
            self._obstacles = Obstacles.stack([env.layout for env in self.envs])
            if self.full_infos:
                infos["reset_infos"] = reset_infos
        return obs, rewards, terminations, truncations, infos

    def _step_batch(self, u: np.ndarray, clipped: np.ndarray, active: np.ndarray):
        """simulate -> sense -> score -> observe of all worlds as arrays (`uavtrack_env.core`);
        then which UAVs the step terminates (K, n) and which worlds it truncates (K,)."""
        cfg, envs = self.config, self.envs
        worlds, targets = [e.world for e in envs], [e.target for e in envs]
        self._state, _ = core.simulate(cfg, worlds, targets, self._state, self._alive, u)
        self._cycles += 1
        position, yaw = self._state[0], self._state[1]
        m = core.sense(
            cfg, self._detector, worlds, targets, [e.np_random for e in envs], self._obstacles,
            position, yaw, self._alive,
        )  # fmt: skip
        self._sensed = m
        score = core.score(self._constants, m, self._references, self._alive, u)
        obs = core.observation(
            cfg, self._constants, m, self._state, self._references, self._obstacles, self._bounds
        )
        obs *= active[..., None]
        infos = self._info_arrays(score, clipped, active)
        terminated, truncate = self._end(score.collided)
        return obs, (score.reward * active).astype(np.float32), terminated, truncate, infos

    def _end(self, collided: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`UAVTrackEnv._end_arrays` of every world: terminated (K, n), truncated (K,); parks
        the UAVs that left worlds that go on."""
        mode = self.config.terminate_on_collision
        if mode == "never":
            collided = np.zeros_like(collided)  # charged as cost only
        elif mode == "all":
            collided = np.where(collided.any(axis=1, keepdims=True), self._alive, collided)
        truncate = self._cycles >= self._max_cycles
        self._alive &= ~collided
        position, yaw = self._state[0], self._state[1]
        park = collided.any(axis=1) & self._alive.any(axis=1) & ~truncate
        for k in np.flatnonzero(park):
            target = self.envs[k].target
            self.envs[k].world.set_poses(
                position[k], yaw[k], self._alive[k], target.center(), target.heading
            )
        return collided, truncate

    def _step_each(self, u: np.ndarray, clipped: np.ndarray, active: np.ndarray):
        """The step world by world through each ParallelEnv (``full_infos``: its info dicts)."""
        obs = np.zeros(self.observation_space.shape, np.float32)
        rewards = np.zeros(self._active.shape, np.float32)
        terminated = np.zeros(self._active.shape, bool)
        truncate = np.zeros(self.num_envs, bool)
        per_world: list[dict[str, Any]] = []
        for k, env in enumerate(self.envs):
            batch, batch_score = env._advance(u[k], clipped[k])
            obs[k] = env._observation_array(batch) * active[k, :, None]
            m, score = env._view(batch, batch_score)
            rewards[k] = score.reward * active[k]
            info = self._info_arrays(batch_score, clipped[k][None], active[k][None])
            info["agents"] = [env._infos(m, score, u[k], clipped[k])]
            self._world_infos[k] = info["agents"][0]
            terminated[k], truncate[k] = env._end_arrays(score.collided)
            self._load(k)
            per_world.append(info)
        return obs, rewards, terminated, truncate, self._concat(per_world)

    @staticmethod
    def _info_arrays(score: Score, clipped: np.ndarray, active: np.ndarray) -> dict[str, Any]:
        """The array infos (K, n) of a step's batch score."""
        collided = score.collided.astype(float)
        disconnected = np.broadcast_to(score.disconnected[:, None], active.shape).astype(float)
        costs = {
            "collision": collided * active,
            "disconnection": disconnected * active,
            "occlusion": score.occluded.astype(float) * active,
        }
        return {
            "cost": costs["collision"] + costs["disconnection"] + costs["occlusion"],
            "costs": costs,
            "reward_tracking": -score.tracking * active,
            "reward_effort": -score.effort * active,
            "action_clipped": clipped & active,
            "active": active.copy(),
        }

    @staticmethod
    def _concat(per_world: list[dict[str, Any]]) -> dict[str, Any]:
        """Join the worlds' infos (1, n) along the world axis."""
        out: dict[str, Any] = {}
        for key, value in per_world[0].items():
            if key == "agents":
                out[key] = [a for w in per_world for a in w[key]]
            elif isinstance(value, dict):
                out[key] = {v: np.concatenate([w[key][v] for w in per_world]) for v in value}
            else:
                out[key] = np.concatenate([w[key] for w in per_world])
        return out

    def _checked(self, actions: Any) -> tuple[np.ndarray, np.ndarray]:
        """(u (K, n, 4) in SI units, clipped (K, n)) of valid actions; raises otherwise."""
        self._check_open("step")
        if not self._started:
            raise RuntimeError("step() called before reset(); call env.reset(seed=...) first")
        try:
            a = np.asarray(actions, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(
                f"actions must be a float array of shape {self.action_space.shape} "
                f"(worlds, agents, 4), got {type(actions).__name__}"
            ) from exc
        if a.shape != self.action_space.shape:
            raise ValueError(
                f"actions have shape {a.shape}; expected {self.action_space.shape} = (num_envs, "
                "n_uavs, 4) of [v_cx, v_cy, v_cz, omega_cy] normalised to [-1, 1]"
            )
        a = np.where(self._active[..., None], a, 0.0)  # inactive rows: ignored
        bad = ~np.isfinite(a).all(axis=-1)
        if bad.any():
            k, i = (int(x) for x in np.argwhere(bad)[0])
            raise ValueError(
                f"action of world {k}, agent {self.possible_agents[i]!r} is not finite: "
                f"{a[k, i].tolist()}"
            )
        u, clipped = core_kernels.scaled_actions(a.reshape(-1, 4), self._scale)
        return u.reshape(a.shape), clipped.reshape(a.shape[:-1])

    def sensor_infos(self, k: int) -> dict[str, dict]:
        """World k's `infos.sensor_infos` of every agent of its latest step (or of its reset, if it
        reset since), by agent: the measurement, own state and messages an onboard stack reads
        (`uavtrack_env.wrappers.VectorCBFShield`)."""
        infos = self._world_infos[k]
        if infos is not None:
            return infos
        m, names = self._sensed, self.possible_agents
        rows = np.flatnonzero(self._stepped[k]).tolist()
        state = tuple(a[k] for a in self._state)
        sensed = sensor_infos(rows, names, m.detections.world(k), m.received[k], state)
        return {names[i]: info for i, info in zip(rows, sensed, strict=True)}

    # ----------------------------------------------------------------- extras
    def close(self) -> None:
        """Release every world's PyBullet client (idempotent); no step or reset after it."""
        for env in self.envs:
            env.close()

    def _check_open(self, call: str) -> None:
        self.envs[0].world.require_open(call, "uavtrack_v0.vector_env(num_envs, **config)")

    def __enter__(self) -> UAVTrackVectorEnv:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __reduce_ex__(self, protocol):
        return self.envs[0].__reduce_ex__(protocol)  # refuses: the worlds own live clients
