"""Replay retargeted human grasps in Drake and record (observation, action) pairs for BC.

One episode per demo (episode seed s):
1. placement: the object placement of episode s (`ObjectPlacement.from_seed`, the one
   `GraspScene.reset` applies) is computed first,
   and the canonical demo (object at (0, 0, rest height), no rotation) is moved rigidly with
   it, so the retargeted arm trajectory fits the placed object;
2. replay: the retargeted joint trajectory is resampled at the control period (linear
   interpolation), the hand starts at its first pose and the set-points are executed with
   `GraspEnv.step_positions`; after the demo's last frame (object lifted ~4 cm) the fingers
   keep their last set-points while the arm raises the palm grasp centre so that the object
   reaches the task target (0.15 m above its start), then everything holds until the horizon;
   every attempt adds a closure squeeze (`config.squeeze`) once the demo's fingers have
   closed, so the position servos grip instead of resting on the surface;
3. correlated sampling (the paper's drop recovery): if the raw replay fails, up to K more
   attempts add a temporally correlated (Ornstein-Uhlenbeck) perturbation to all commands and
   an extra finger-closure ramp in each joint's `hand.closing` direction from the grasp phase
   on. Only successful episodes are kept (success = `dexdrake.task.SuccessTracker`).
Actions are recorded normalised like `GraspEnv.step`: (q_set - mid) / half_range.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pydrake.math import RollPitchYaw

from dexdrake.demos.format import HumanDemo
from dexdrake.demos.trim import matrix_to_quat_wxyz, quat_wxyz_to_matrix
from dexdrake.episode import run_episode
from dexdrake.errors import DexdrakeError
from dexdrake.hands.description import HandDescription, load_hand
from dexdrake.objects.library import ObjectInfo, get_object
from dexdrake.hands.arm_ik import ArmIK
from dexdrake.systems.grasp_env import GraspEnv
from dexdrake.systems.scenario import Scenario
from dexdrake.systems.scene import ObjectPlacement
from dexdrake.task import TaskSpec, target_position


@dataclass(frozen=True)
class ReplayConfig:
    """Episode length, lift motion and the correlated-sampling distribution."""

    horizon: int = 200  # control steps per episode (training episodes: 200)
    raise_time: float = 0.6  # s: arm blend from the demo's last set-points to the lift pose
    attempts: int = 8  # K: sampled attempts after a failed raw replay
    noise_scale: float = 0.04  # OU perturbation std, fraction of each joint's half range
    noise_time: float = 0.3  # s: OU correlation time
    closure: tuple[float, float] = (0.05, 0.30)  # extra closure, fraction of half range (uniform)
    closure_ramp_time: float = 0.2  # s: the closure ramp's rise time
    grasp_onset: float = 0.2  # grasp phase starts at this fraction of the demo's finger closure
    squeeze: float = 0.3  # extra closure (fraction of half range) of every replay, raw included,
    squeeze_onset: float = 0.9  # ... ramped in from this fraction of the demo's finger closure
    task: TaskSpec = TaskSpec()  # success criterion and lift target

    def __post_init__(self):
        if self.horizon < 2:
            raise DexdrakeError(f"ReplayConfig.horizon must be at least 2, got {self.horizon}")
        if self.attempts < 0:
            raise DexdrakeError(f"ReplayConfig.attempts must be >= 0, got {self.attempts}")
        if self.noise_scale < 0 or self.noise_time <= 0 or self.raise_time <= 0:
            raise DexdrakeError("ReplayConfig: noise_scale >= 0, noise_time > 0, raise_time > 0 required")
        lo, hi = self.closure
        if not 0 <= lo <= hi:
            raise DexdrakeError(f"ReplayConfig.closure must be 0 <= low <= high, got {self.closure}")
        if self.squeeze < 0 or not 0 < self.squeeze_onset <= 1:
            raise DexdrakeError("ReplayConfig: squeeze >= 0 and 0 < squeeze_onset <= 1 required")


# -- pure helpers ------------------------------------------------------------------------
def place_demo(demo: HumanDemo, placement: ObjectPlacement, rest_height: float) -> HumanDemo:
    """The demo moved rigidly so its first object pose becomes the placed pose
    (x, y, rest_height, yaw): keypoints keep their pose relative to the object."""
    R0 = quat_wxyz_to_matrix(demo.object_quat[0])
    p0 = demo.object_pos[0]
    Rp = RollPitchYaw(0.0, 0.0, placement.yaw).ToRotationMatrix().matrix()
    pp = np.array([placement.x, placement.y, rest_height])
    R = Rp @ R0.T  # x_new = R (x - p0) + pp
    kp = (demo.keypoints - p0) @ R.T + pp
    pos = (demo.object_pos - p0) @ R.T + pp
    quat = matrix_to_quat_wxyz(np.einsum("ij,tjk->tik", R, quat_wxyz_to_matrix(demo.object_quat)))
    return HumanDemo(kp, demo.time.copy(), demo.object_name, pos, quat, demo.meta)


def resample_trajectory(q: np.ndarray, time: np.ndarray, period: float) -> np.ndarray:
    """Joint trajectory (T x n at `time`) linearly interpolated at t0, t0 + period, ... up to
    the last frame (which is always included as the final row)."""
    q, time = np.asarray(q, float), np.asarray(time, float)
    if q.ndim != 2 or q.shape[0] != time.shape[0] or q.shape[0] < 1:
        raise DexdrakeError(f"resample_trajectory: q {q.shape} and time {time.shape} do not match")
    if period <= 0:
        raise DexdrakeError(f"resample_trajectory: period must be positive, got {period}")
    if q.shape[0] > 1 and not np.all(np.diff(time) > 0):
        raise DexdrakeError("resample_trajectory: time must be strictly increasing")
    duration = time[-1] - time[0]
    n = int(np.floor(duration / period + 1e-9))
    t = time[0] + period * np.arange(n + 1)
    if duration - period * n > 1e-9:
        t = np.append(t, time[-1])
    return np.stack([np.interp(t, time, q[:, j]) for j in range(q.shape[1])], axis=1)


def correlated_noise(rng: np.random.Generator, steps: int, dim: int, corr_steps: float) -> np.ndarray:
    """(steps, dim) Ornstein-Uhlenbeck sequence with unit stationary std and lag-1
    correlation exp(-1 / corr_steps), started at 0 so the first command is unperturbed."""
    if steps < 1 or dim < 1 or corr_steps <= 0:
        raise DexdrakeError(f"correlated_noise: need steps, dim >= 1 and corr_steps > 0 (got {steps}, {dim}, {corr_steps})")
    a = np.exp(-1.0 / corr_steps)
    w = rng.standard_normal((steps, dim)) * np.sqrt(1.0 - a * a)
    x = np.zeros((steps, dim))
    for k in range(1, steps):
        x[k] = a * x[k - 1] + w[k]
    return x


def closure_ramp(hand: HandDescription, steps: int, start: int, ramp_steps: int, amount: float) -> np.ndarray:
    """(steps, n) extra set-point offsets: 0 before `start`, rising linearly over `ramp_steps`
    to `amount` x half range in each joint's closing direction, then held."""
    lo, hi = hand.joint_limits()
    direction = np.array([hand.closing.get(j, 0.0) for j in hand.policy_joints])
    s = np.clip((np.arange(steps) - start + 1) / max(ramp_steps, 1), 0.0, 1.0)
    return s[:, None] * (amount * direction * (hi - lo) / 2)[None, :]


def grasp_onset_step(hand: HandDescription, q: np.ndarray, fraction: float) -> int:
    """First row of `q` where the fingers have closed `fraction` of their largest closure
    (sum over closing joints of the signed travel from row 0); the middle row if they never close."""
    direction = np.array([hand.closing.get(j, 0.0) for j in hand.policy_joints])
    closure = (q - q[0]) @ direction
    peak = closure.max()
    if peak <= 1e-6:
        return len(q) // 2
    return int(np.argmax(closure >= fraction * peak))


def _smooth(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10 - 15 * s + 6 * s * s)  # minimum-jerk profile


# -- records -----------------------------------------------------------------------------
@dataclass
class Episode:
    """One executed attempt: observation before each step and the normalised action applied."""

    observations: np.ndarray  # float32 (T, D)
    actions: np.ndarray  # float32 (T, A)
    success: bool
    max_lift: float
    attempt: int  # 0 = raw replay, k >= 1 = k-th correlated-sampling attempt
    demo_steps: int  # steps taken from the demo before the lift phase

    @property
    def sampled(self) -> bool:
        return self.attempt > 0


@dataclass
class ReplayPlan:
    """A demo placed and retargeted for one episode seed."""

    seed: int
    placement: ObjectPlacement
    q_demo: np.ndarray  # (S + 1, n) resampled set-points; row 0 is the initial hand pose
    grasp_step: int  # control step where the grasp phase (finger closing) starts
    squeeze: np.ndarray | None = None  # (horizon, n) closure offsets added to every attempt


@dataclass
class DemoReplayResult:
    """What happened to one demo: the kept episode (if any) and every attempt's outcome."""

    object: str
    category: str
    seed: int
    placement: ObjectPlacement
    episode: Episode | None
    outcomes: list[tuple[int, bool, float]] = field(default_factory=list)  # (attempt, success, max lift)

    @property
    def raw_success(self) -> bool:
        return bool(self.outcomes and self.outcomes[0][1])

    @property
    def success(self) -> bool:
        return self.episode is not None


# -- the replayer ------------------------------------------------------------------------
class _SetPoints:
    """A GraspEnv as the episode loop's env for a replay: actions are joint set-points
    (`step_positions`), and every episode starts with the hand at `q_hand`."""

    def __init__(self, env: GraspEnv, q_hand: np.ndarray):
        self.env, self.q_hand = env, q_hand
        self.horizon, self.object_name = env.horizon, env.object_name

    def reset(self, seed: int) -> np.ndarray:
        return self.env.reset(seed, q_hand=self.q_hand)

    def step(self, q_command: np.ndarray) -> tuple[np.ndarray, float, bool, dict]:
        return self.env.step_positions(q_command)


class DemoReplayer:
    """Retargets, replays and perturbs demos of one hand; one GraspEnv per object, built lazily."""

    def __init__(self, hand: str = "adroit", feature_set: str | None = None, config: ReplayConfig = ReplayConfig()):
        from dexdrake.retarget.retargeter import Retargeter

        self.hand = load_hand(hand)
        self.feature_set, self.config = feature_set, config
        self.retargeter = Retargeter(self.hand)
        self.n_arm = len(self.hand.arm_joints)
        self._envs: dict[str, GraspEnv] = {}
        self._meshes: dict[str, object] = {}

    def env(self, object_name: str) -> GraspEnv:
        if object_name not in self._envs:
            scenario = Scenario(name="replay", hand=self.hand.name, object=object_name)
            self._envs[object_name] = GraspEnv(scenario, self.feature_set, self.config.horizon, self.config.task)
        return self._envs[object_name]

    def _mesh(self, info: ObjectInfo):
        if info.name not in self._meshes:
            import trimesh

            self._meshes[info.name] = trimesh.load(info.mesh_path, force="mesh")
        return self._meshes[info.name]

    # planning ------------------------------------------------------------------------
    def plan(self, demo: HumanDemo, seed: int) -> ReplayPlan:
        """Place the demo for episode `seed`, retarget it and resample at the control period."""
        if not demo.object_name:
            raise DexdrakeError("demo has no object_name; replay needs a library object")
        info = get_object(demo.object_name)
        env = self.env(info.name)
        placement = ObjectPlacement.from_seed(seed)
        placed = place_demo(demo, placement, info.rest_height)
        q = self.retargeter.retarget_sequence(placed, self._mesh(info), progress=False)
        q_demo = resample_trajectory(q, placed.time, env.scenario.control_period)
        c = self.config
        squeeze = closure_ramp(self.hand, c.horizon, grasp_onset_step(self.hand, q_demo, c.squeeze_onset),
                               int(round(c.closure_ramp_time / env.scenario.control_period)), c.squeeze)
        return ReplayPlan(seed, placement, q_demo, grasp_onset_step(self.hand, q_demo, c.grasp_onset), squeeze)

    # execution -----------------------------------------------------------------------
    def run(self, env: GraspEnv, plan: ReplayPlan, offsets: np.ndarray | None = None, attempt: int = 0) -> Episode:
        """Execute one attempt for `config.horizon` steps (the one episode loop,
        dexdrake/episode.py, over `GraspEnv.step_positions`); `offsets` (horizon, n) are added
        to every set-point (None: the raw replay)."""
        H = self.config.horizon
        if offsets is not None and offsets.shape != (H, self.hand.num_actuators):
            raise DexdrakeError(f"offsets must have shape {(H, self.hand.num_actuators)}, got {offsets.shape}")
        demo_steps = min(len(plan.q_demo) - 1, H)
        raise_steps = max(1, int(round(self.config.raise_time / env.scenario.control_period)))
        q_end = plan.q_demo[demo_steps]
        q_lift: np.ndarray | None = None  # arm set-points of the lift, solved when the demo ends
        obs, act = [], []

        def command(observation: np.ndarray) -> np.ndarray:
            nonlocal q_lift
            k = len(obs)
            if k < demo_steps:
                q = plan.q_demo[k + 1].copy()
            else:
                q_lift = self._lift_pose(env, q_end) if q_lift is None else q_lift
                s = _smooth(np.array((k - demo_steps + 1) / raise_steps))
                q = q_end.copy()
                q[: self.n_arm] = q_end[: self.n_arm] + s * (q_lift - q_end[: self.n_arm])
            if plan.squeeze is not None:
                q = q + plan.squeeze[k]
            if offsets is not None:
                q = q + offsets[k]
            obs.append(observation)
            return q

        result = run_episode(_SetPoints(env, plan.q_demo[0]), command, plan.seed, H,
                             on_step=lambda reward, info: act.append(env.normalise(env.q_command)))
        return Episode(np.asarray(obs, np.float32), np.asarray(act, np.float32), result.success, result.max_lift,
                       attempt, demo_steps)

    def _lift_pose(self, env: GraspEnv, q_end: np.ndarray) -> np.ndarray:
        """Arm set-points moving the commanded palm grasp centre by (target - object now),
        solved from the current arm set-points with rotations held near them."""
        ik = ArmIK(env.scene)
        centre = ik.palm_pose(q_end[: self.n_arm])[0]
        goal = centre + target_position(env.p_start, env.task) - env.object_position()
        return ik.solve(goal, q_end[: self.n_arm], stay=0.05)

    def perturbation(self, env: GraspEnv, plan: ReplayPlan, rng: np.random.Generator) -> np.ndarray:
        """(horizon, n) correlated offsets: OU noise on all joints plus a closure ramp from
        the grasp phase on, both scaled by each joint's half range."""
        c, H = self.config, self.config.horizon
        dt = env.scenario.control_period
        noise = correlated_noise(rng, H, self.hand.num_actuators, c.noise_time / dt)
        amount = rng.uniform(*c.closure)
        ramp = closure_ramp(self.hand, H, plan.grasp_step, int(round(c.closure_ramp_time / dt)), amount)
        return c.noise_scale * noise * env.actions.half[None, :] + ramp

    def replay(self, demo: HumanDemo, seed: int, attempts: int | None = None) -> DemoReplayResult:
        """Raw replay, then up to `attempts` (default config.attempts) correlated-sampling
        attempts until one succeeds; attempt k draws from default_rng([seed, k])."""
        K = self.config.attempts if attempts is None else attempts
        plan = self.plan(demo, seed)
        env = self.env(demo.object_name)
        info = env.scene.object_info
        result = DemoReplayResult(info.name, info.category, seed, plan.placement, None)
        for k in range(K + 1):
            offsets = None if k == 0 else self.perturbation(env, plan, np.random.default_rng([seed, k]))
            ep = self.run(env, plan, offsets, attempt=k)
            result.outcomes.append((k, ep.success, ep.max_lift))
            if ep.success:
                result.episode = ep
                break
        return result



def observation_blocks_for(hand: str, feature_set: str | None) -> dict[str, int]:
    """The observation layout GraspEnv produces for `hand` and `feature_set` (None: [q; v])."""
    desc = load_hand(hand)
    if feature_set is None:
        return {"hand": 2 * desc.num_actuators}
    from dexdrake.dexrep.feature_sets import observation_blocks

    return observation_blocks(desc, feature_set)
