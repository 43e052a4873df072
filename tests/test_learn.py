"""Tests of dexdrake.learn (policy, BC, GAE, NPG, samplers, DAPG) and PolicySystem on a toy env."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dexdrake.errors import DexdrakeError
from dexdrake.learn.bc import BCConfig, load_demo_dataset, save_demo_dataset, split_train_val, train_bc
from dexdrake.learn.curves import read_csv
from dexdrake.learn.dapg import DAPGConfig, DAPGTrainer, demo_weight, rollout_seeds, train_dapg
from dexdrake.learn.demo_dataset import DemoDataset
from dexdrake.learn.gae import discounted_returns, gae_advantages
from dexdrake.learn.npg import conjugate_gradient, fisher_vector_product, flat_params
from dexdrake.learn.policy import UNRECORDED_SCENARIO, DexRepNetPolicy, PolicyConfig, load_policy, save_policy
from dexdrake.learn.samplers import ProcessSampler, SequentialSampler, make_sampler, rollout

TOY_BLOCKS = {"hand": 4, "occ_surf": 2, "local_geo": 3}


pytestmark = pytest.mark.usefixtures("one_torch_thread")


class PointMassReach:
    """2-D point mass steered toward a random target; same interface and block layout as the grasp env.

    Observation blocks: hand = [position, velocity command], occ_surf = target - position,
    local_geo = [distance, x-step, y-step to target direction]. Reward = -distance.
    """

    observation_blocks = dict(TOY_BLOCKS)
    action_dim = 2
    horizon = 20

    def __init__(self, step: float = 0.1):
        self._step = step
        self._pos = np.zeros(2)
        self._target = np.zeros(2)
        self._last = np.zeros(2)

    def _obs(self) -> np.ndarray:
        rel = self._target - self._pos
        dist = float(np.linalg.norm(rel))
        unit = rel / max(dist, 1e-9)
        return np.concatenate([self._pos, self._last, rel, [dist], unit]).astype(np.float32)

    def reset(self, seed: int) -> np.ndarray:
        rng = np.random.default_rng(seed)
        self._pos = rng.uniform(-1, 1, 2)
        self._target = rng.uniform(-1, 1, 2)
        self._last = np.zeros(2)
        return self._obs()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, dict]:
        self._last = np.clip(action, -1, 1)
        self._pos = self._pos + self._step * self._last
        dist = float(np.linalg.norm(self._target - self._pos))
        return self._obs(), -dist, False, {"success": dist < 0.1}


def make_toy_env() -> PointMassReach:
    return PointMassReach()


def toy_policy(seed: int = 0, **kwargs) -> DexRepNetPolicy:
    torch.manual_seed(seed)
    return DexRepNetPolicy(PolicyConfig.from_blocks(TOY_BLOCKS, 2, feature_set="toy", hand="toy", **kwargs))


def expert_dataset(n: int = 2000, seed: int = 0) -> DemoDataset:
    """Demos of the reaching expert a = clip(5 * (target - pos)) collected in the toy env."""
    env, obs, act, starts = PointMassReach(), [], [], []
    rng = np.random.default_rng(seed)
    while len(obs) < n:
        o = env.reset(int(rng.integers(1 << 30)))
        for t in range(env.horizon):
            a = np.clip(5.0 * o[4:6], -1, 1)
            obs.append(o)
            act.append(a)
            starts.append(t == 0)
            o, _, _, _ = env.step(a)
    return DemoDataset(np.array(obs[:n], np.float32), np.array(act[:n], np.float32), np.array(starts[:n]))


# ----------------------------------------------------------------------------- policy
@pytest.mark.parametrize(
    "blocks",
    [{"hand": 105, "occ_surf": 1088, "local_geo": 1408}, {"hand": 105, "hand2obj": 27}, {"only": 7}],
)
def test_policy_shapes_per_block_set(blocks):
    policy = DexRepNetPolicy(PolicyConfig.from_blocks(blocks, 30))
    assert list(policy.encoders) == list(blocks)
    for name, size in blocks.items():
        assert policy.encoders[name].in_features == size and policy.encoders[name].out_features == 128
    assert policy.mlp[0].in_features == 128 * len(blocks)
    assert [m.out_features for m in policy.mlp if isinstance(m, torch.nn.Linear)] == [512, 128, 30]
    obs = torch.randn(5, sum(blocks.values()))
    assert policy(obs).shape == (5, 30)
    assert policy.log_prob(obs, torch.zeros(5, 30)).shape == (5,)
    with pytest.raises(DexdrakeError, match="expects"):
        policy(torch.randn(5, sum(blocks.values()) + 1))


def test_encoder_sees_only_its_block():
    policy = toy_policy()
    obs = torch.randn(3, 9)
    feats_before = policy.encoders["hand"](obs[:, :4])
    obs2 = obs.clone()
    obs2[:, 4:] += 10.0  # change other blocks only
    assert torch.allclose(policy.encoders["hand"](obs2[:, :4]), feats_before)
    assert not torch.allclose(policy(obs2), policy(obs))


def test_bad_config_rejected():
    with pytest.raises(DexdrakeError, match="size"):
        DexRepNetPolicy(PolicyConfig.from_blocks({"hand": 0}, 2))
    with pytest.raises(DexdrakeError, match="encoder_activation"):
        DexRepNetPolicy(PolicyConfig.from_blocks({"hand": 3}, 2, encoder_activation="tanh"))


def test_act_logprob_matches_log_prob():
    policy = toy_policy()
    obs = np.random.default_rng(0).standard_normal(9).astype(np.float32)
    action, logp = policy.act(obs, np.random.default_rng(1))
    ref = policy.log_prob(torch.as_tensor(obs)[None], torch.as_tensor(action, dtype=torch.float32)[None])
    assert math.isclose(logp, float(ref.detach()), rel_tol=1e-4)
    mean, _ = policy.act(obs)
    assert np.allclose(mean, policy(torch.as_tensor(obs)[None])[0].detach().numpy(), atol=1e-6)


def test_checkpoint_round_trip_reproduces_outputs(tmp_path):
    policy = toy_policy(seed=3, encoder_activation="none")
    policy.set_obs_normalization(np.arange(9.0), np.full(9, 2.0))
    with torch.no_grad():
        policy.log_std.fill_(-0.7)
    policy.freeze_encoders()
    path = save_policy(tmp_path / "p.pt", policy, {"note": "hello", "epoch": 3})
    loaded, meta = load_policy(path)
    assert meta == {"note": "hello", "epoch": 3, "scenario": UNRECORDED_SCENARIO}  # none recorded
    assert loaded.config == policy.config and loaded.config.hand == "toy"
    obs = torch.randn(16, 9)
    assert torch.equal(loaded(obs), policy(obs))
    assert torch.equal(loaded.log_std, policy.log_std)
    assert all(not p.requires_grad for p in loaded.encoders.parameters())


def test_residual_arm_head_leads_the_current_arm_position(tmp_path):
    """With `residual_arm`, an MLP output of 0 holds the arm where it is (its normalised joint
    positions, read from the hand block) and leaves the fingers at 0; the limits travel in
    the checkpoint, and a policy whose first block is not the hand's is refused."""
    from dexdrake.hands.description import load_hand

    hand = load_hand("adroit")
    n, lo, hi = len(hand.arm_joints), *hand.joint_limits()
    config = PolicyConfig.from_blocks({"hand": 40, "occ": 7}, 30, hand="adroit", residual_arm=True)
    policy = DexRepNetPolicy(config)
    with torch.no_grad():
        policy.mlp[-1].weight.zero_()
        policy.mlp[-1].bias.zero_()
    obs = torch.randn(5, 47)
    obs[:, :30] = torch.as_tensor(lo + (hi - lo) * np.random.default_rng(0).random((5, 30)), dtype=torch.float32)
    out = policy(obs).detach().numpy()
    np.testing.assert_allclose(out[:, :n], (obs[:, :n].numpy() - (hi + lo)[:n] / 2) / ((hi - lo)[:n] / 2), atol=1e-5)
    np.testing.assert_array_equal(out[:, n:], 0.0)
    loaded, _ = load_policy(save_policy(tmp_path / "r.pt", policy))
    assert loaded.config.residual_arm and torch.equal(loaded(obs), policy(obs))
    with pytest.raises(DexdrakeError, match="hand block first"):
        DexRepNetPolicy(PolicyConfig.from_blocks({"occ": 7, "hand": 40}, 30, hand="adroit", residual_arm=True))
    with pytest.raises(DexdrakeError, match="joints"):
        DexRepNetPolicy(PolicyConfig.from_blocks({"hand": 40}, 22, hand="adroit", residual_arm=True))


def test_widened_policy_acts_as_before_and_learns_from_its_new_inputs():
    """A policy widened by an appended group acts exactly as before whatever the new inputs
    hold; a gradient step on them reaches the new path; blocks that do not extend the old
    ones, or another architecture, are refused."""
    from dataclasses import replace

    from dexdrake.learn.policy import widened

    old = DexRepNetPolicy(PolicyConfig.from_blocks({"hand": 40, "occ": 7}, 30, hand="adroit", residual_arm=True))
    old.set_obs_normalization(np.full(47, 0.5), np.full(47, 2.0))
    new = widened(old, replace(old.config, blocks=old.config.blocks + (("vel", 5),), feature_set="vel"))
    obs = torch.randn(6, 47)
    wide = torch.cat([obs, 10 * torch.randn(6, 5)], dim=1)
    torch.testing.assert_close(new(wide), old(obs), rtol=0, atol=1e-6)
    loss = new(wide).square().sum()
    loss.backward()
    assert new.mlp[0].weight.grad[:, -new.config.encoder_dim:].abs().sum() > 0  # the new inputs get a gradient
    with pytest.raises(DexdrakeError, match="cannot widen"):
        widened(old, replace(old.config, blocks=(("hand", 40), ("vel", 5), ("occ", 7))))
    with pytest.raises(DexdrakeError, match="cannot widen"):
        widened(old, replace(old.config, blocks=old.config.blocks + (("vel", 5),), hidden_sizes=(64,)))


def test_load_policy_rejects_garbage(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(DexdrakeError, match="cannot read"):
        load_policy(bad)
    with pytest.raises(DexdrakeError, match="does not exist"):
        load_policy(tmp_path / "missing.pt")


# ----------------------------------------------------------------------------- datasets and BC
def test_corrupt_dataset_refused(tmp_path):
    good = expert_dataset(50)
    obs = good.observations.copy()
    obs[7, 2] = np.nan
    np.savez(tmp_path / "nan.npz", observations=obs, actions=good.actions)
    with pytest.raises(DexdrakeError, match=r"non-finite values in 1 rows \(first rows: \[7\]\)"):
        load_demo_dataset(tmp_path / "nan.npz")
    np.savez(tmp_path / "rows.npz", observations=good.observations, actions=good.actions[:-1])
    with pytest.raises(DexdrakeError, match="50 observations but 49 actions"):
        load_demo_dataset(tmp_path / "rows.npz")
    np.savez(tmp_path / "keys.npz", obs=good.observations)
    with pytest.raises(DexdrakeError, match=r"lacks \['observations', 'actions'\]"):
        load_demo_dataset(tmp_path / "keys.npz")
    (tmp_path / "trunc.npz").write_bytes((tmp_path / "rows.npz").read_bytes()[:100])
    with pytest.raises(DexdrakeError, match="not a readable .npz"):
        load_demo_dataset(tmp_path / "trunc.npz")
    save_demo_dataset(tmp_path / "ok.npz", good.observations, good.actions, good.episode_starts, {"hand": "toy"})
    with pytest.raises(DexdrakeError, match="expected 10"):
        load_demo_dataset(tmp_path / "ok.npz", obs_dim=10)
    loaded = load_demo_dataset(tmp_path / "ok.npz", obs_dim=9, action_dim=2)
    assert loaded.metadata == {"hand": "toy"} and len(loaded) == 50
    assert np.array_equal(loaded.episode_starts, good.episode_starts)


def test_bc_drives_mse_down(tmp_path):
    data = expert_dataset(1000)
    policy = toy_policy()
    with torch.no_grad():
        initial = float(((policy(torch.as_tensor(data.observations)) - torch.as_tensor(data.actions)) ** 2).sum(-1).mean())
    cfg = BCConfig(epochs=6, lr=2e-3, checkpoint_every=3, progress=False)  # lr raised: few epochs
    result = train_bc(policy, data, tmp_path, cfg)
    assert result.val_loss[-1] < 0.05 * initial
    assert result.val_loss[-1] < result.val_loss[0]
    assert result.train_loss[-1] < result.train_loss[0]
    rows = read_csv(tmp_path / "bc_log.csv")
    assert [int(r["epoch"]) for r in rows] == list(range(1, 7))
    for name in ("bc_best.pt", "bc_last.pt", "bc_epoch_0003.pt", "bc_epoch_0006.pt", "bc_log.png"):
        assert (tmp_path / name).is_file(), name
    best, meta = load_policy(tmp_path / "bc_best.pt")
    assert meta["epoch"] == result.best_epoch and meta["bc_config"]["lr"] == 2e-3
    assert np.allclose(best.obs_mean.numpy(), policy.obs_mean.numpy())


def test_bc_on_float16_observations_fits_exactly_as_on_their_float32_values(tmp_path):
    data = expert_dataset(400)
    half = DemoDataset(data.observations.astype(np.float16), data.actions, data.episode_starts)
    exact = DemoDataset(half.observations.astype(np.float32), data.actions, data.episode_starts)
    fits = []
    for name, dataset in (("half", half), ("exact", exact)):
        policy = toy_policy()
        result = train_bc(policy, dataset, tmp_path / name, BCConfig(epochs=2, lr=2e-3, checkpoint_every=0, progress=False))
        fits.append((result.train_loss + result.val_loss, policy.state_dict()))
    assert fits[0][0] == pytest.approx(fits[1][0], rel=1e-6)
    assert all(torch.allclose(fits[0][1][k], fits[1][1][k], atol=1e-6) for k in fits[0][1])


def test_bc_normalises_by_the_training_split_and_never_trains_on_held_out_rows(tmp_path):
    data = expert_dataset(1000)
    data.observations[:, 2] += 1000.0  # a large offset: the chunked two-pass variance must stay exact
    train_idx, val_idx = split_train_val(data, 0.1, 0)
    policy = toy_policy()
    train_bc(policy, data, tmp_path / "a", BCConfig(epochs=1, checkpoint_every=0, progress=False))
    tr = data.observations[train_idx].astype(np.float64)
    assert np.allclose(policy.obs_mean.numpy(), tr.mean(0), rtol=0, atol=1e-4)
    assert np.allclose(policy.obs_std.numpy(), tr.std(0), rtol=1e-5, atol=1e-6)
    poisoned = DemoDataset(data.observations, data.actions.copy(), data.episode_starts)
    poisoned.actions[val_idx] = 1e6  # a held-out label seen by a training batch would blow up the loss
    result = train_bc(toy_policy(), poisoned, tmp_path / "b", BCConfig(epochs=2, checkpoint_every=0, progress=False))
    assert max(result.train_loss) < 10.0 and min(result.val_loss) > 1e11


def test_bc_action_weights_trade_error_between_dimensions_and_are_validated(tmp_path):
    data = expert_dataset(1000)
    errors = {}
    for weights in ((100.0, 0.01), (0.01, 100.0)):
        policy = toy_policy()
        train_bc(policy, data, tmp_path / str(weights[0]), BCConfig(epochs=2, lr=2e-3, checkpoint_every=0,
                                                                    progress=False, action_weights=weights))
        with torch.no_grad():
            err = ((policy(torch.as_tensor(data.observations)) - torch.as_tensor(data.actions)) ** 2).mean(0)
        errors[weights[0]] = err.numpy()
    assert errors[100.0][0] < errors[0.01][0] and errors[100.0][1] > errors[0.01][1]
    for bad in ((1.0,), (1.0, 0.0), (1.0, float("nan"))):
        with pytest.raises(DexdrakeError, match="action_weights must be 2 positive numbers"):
            train_bc(toy_policy(), data, tmp_path / "bad", BCConfig(epochs=1, progress=False, action_weights=bad))


def test_bc_weight_decay_shrinks_the_weights_and_input_noise_changes_the_fit_and_both_are_validated(tmp_path):
    data = expert_dataset(1000)
    norms, losses = {}, {}
    for name, extra in (("plain", {}), ("decay", {"weight_decay": 50.0}), ("noise", {"obs_noise": 0.5})):
        policy = toy_policy()
        result = train_bc(policy, data, tmp_path / name, BCConfig(epochs=2, lr=2e-3, checkpoint_every=0, progress=False,
                                                                   **extra))
        norms[name] = float(sum(p.detach().norm() ** 2 for n, p in policy.named_parameters() if "weight" in n))
        losses[name] = result.train_loss[-1]
    assert norms["decay"] < 0.5 * norms["plain"]
    assert losses["noise"] != losses["plain"] and losses["noise"] < 10 * losses["plain"] + 1.0
    for bad in ({"weight_decay": -1.0}, {"obs_noise": -0.1}):
        with pytest.raises(DexdrakeError, match="weight_decay and obs_noise must be >= 0"):
            train_bc(toy_policy(), data, tmp_path / "bad", BCConfig(epochs=1, progress=False, **bad))


def test_refitted_statistics_keep_a_trained_policys_actions_when_asked(tmp_path):
    data = expert_dataset(1000)
    policy = toy_policy()
    train_bc(policy, data, tmp_path, BCConfig(epochs=1, lr=2e-3, checkpoint_every=0, progress=False))
    obs = torch.as_tensor(data.observations[:200])
    rng = np.random.default_rng(0)
    d = policy.config.obs_dim
    with torch.no_grad():
        before = policy(obs).numpy()
        policy.set_obs_normalization(rng.normal(size=d), rng.uniform(0.02, 50.0, size=d), keep_function=True)
        np.testing.assert_allclose(policy(obs).numpy(), before, rtol=1e-4, atol=1e-4)
        policy.set_obs_normalization(rng.normal(size=d), rng.uniform(0.02, 50.0, size=d))
        assert np.abs(policy(obs).numpy() - before).max() > 0.1  # a plain refit moves the actions


def test_bc_defaults_are_the_papers():
    cfg = BCConfig()
    assert (cfg.epochs, cfg.batch_size, cfg.lr) == (150, 64, 1e-5)


def test_bc_split_keeps_episodes_whole():
    from dexdrake.learn.bc import split_train_val

    data = expert_dataset(400)
    tr, va = split_train_val(data, 0.25, seed=1)
    ep = data.episode_ids()
    assert set(ep[tr]).isdisjoint(set(ep[va])) and len(tr) + len(va) == 400
    assert 0 < len(va) < 400


def test_bc_split_of_a_growing_dataset_keeps_earlier_episodes_on_their_side():
    """DAgger appends episodes and refits: a held-out episode must never become training data."""
    from dexdrake.learn.bc import split_train_val

    small = expert_dataset(2000)
    more = DemoDataset(*(np.concatenate([getattr(small, k), getattr(expert_dataset(2000, seed=1), k)])
                         for k in ("observations", "actions", "episode_starts")))
    ep_small, ep_more = small.episode_ids(), more.episode_ids()
    val_small = set(ep_small[split_train_val(small, 0.2, seed=3)[1]])
    val_more = set(ep_more[split_train_val(more, 0.2, seed=3)[1]])
    assert val_small and val_small == {e for e in val_more if e <= ep_small.max()}
    assert val_more - val_small  # the appended episodes are split too
    assert 0.05 < len(val_more) / (ep_more.max() + 1) < 0.4


# ----------------------------------------------------------------------------- GAE, CG, Fisher
def test_gae_hand_computed():
    r, v = np.array([1.0, 0.0, 2.0]), np.array([0.5, 1.0, 1.5])
    gamma, lam = 0.9, 0.8
    # deltas: d0 = 1 + .9*1 - .5 = 1.4 ; d1 = 0 + .9*1.5 - 1 = 0.35 ; d2 = 2 + .9*0 - 1.5 = 0.5
    # A2 = 0.5 ; A1 = 0.35 + .72*0.5 = 0.71 ; A0 = 1.4 + .72*0.71 = 1.9112
    assert np.allclose(gae_advantages(r, v, gamma, lam), [1.9112, 0.71, 0.5])
    assert np.allclose(discounted_returns(r, 0.9), [1 + 0.81 * 2, 0.9 * 2, 2])
    # lambda = 1 with a zero baseline gives discounted returns
    assert np.allclose(gae_advantages(r, np.zeros(3), 0.9, 1.0), discounted_returns(r, 0.9))
    assert np.allclose(gae_advantages(r, v, gamma, lam, last_value=10.0)[-1], 2 + 9 - 1.5)
    with pytest.raises(DexdrakeError):
        gae_advantages(r, v[:2], gamma, lam)


def test_cg_solves_spd_system():
    rng = np.random.default_rng(0)
    m = rng.standard_normal((6, 6))
    a = torch.as_tensor(m @ m.T + 6 * np.eye(6))
    b = torch.as_tensor(rng.standard_normal(6))
    x = conjugate_gradient(lambda v: a @ v, b, iters=10)
    assert torch.allclose(x, torch.linalg.solve(a, b), atol=1e-8)


def test_fisher_vector_product_matches_analytic():
    # With the log-std held fixed at 0 the Fisher of the mean parameters is mean_i J_i^T J_i
    policy = toy_policy(seed=1, hidden_sizes=(8,), encoder_dim=4)
    policy.log_std.requires_grad_(False)
    obs = torch.randn(5, 9)
    names = [n for n, p in policy.named_parameters() if p.requires_grad]
    params = tuple(policy.trainable_parameters())

    def mean_fn(*values):
        return torch.func.functional_call(policy, dict(zip(names, values)), (obs,))

    jac = torch.cat([j.reshape(5 * 2, -1) for j in torch.autograd.functional.jacobian(mean_fn, params)], dim=1)
    fisher = jac.T @ jac / 5
    v = torch.randn(fisher.shape[0])
    fv = fisher_vector_product(policy, obs, damping=1e-4)(v)
    assert torch.allclose(fv, fisher @ v + 1e-4 * v, atol=1e-5)


# ----------------------------------------------------------------------------- samplers
def _same(a, b) -> bool:
    return all(
        x.seed == y.seed and x.success == y.success and np.array_equal(x.actions, y.actions)
        and np.array_equal(x.rewards, y.rewards) and np.allclose(x.log_probs, y.log_probs)
        for x, y in zip(a, b, strict=True)
    )


def test_rollout_is_seeded():
    policy, env = toy_policy(), PointMassReach()
    a, b, c = rollout(env, policy, 5), rollout(env, policy, 5), rollout(env, policy, 6)
    assert _same([a], [b]) and not np.array_equal(a.actions, c.actions)
    assert a.observations.shape == (20, 9) and a.actions.shape == (20, 2) and a.log_probs.shape == (20,)
    mean_run = rollout(env, policy, 5, deterministic=True)
    assert np.allclose(mean_run.actions[0], policy.act(env.reset(5))[0], atol=1e-6)


def test_process_sampler_matches_sequential():
    policy, seeds = toy_policy(), [11, 12, 13]
    with ProcessSampler(make_toy_env, num_workers=2) as proc, SequentialSampler(make_toy_env) as seq:
        got = proc.sample(policy, seeds)
        assert [t.seed for t in got] == seeds
        assert _same(got, seq.sample(policy, seeds))
        with torch.no_grad():
            policy.mlp[-1].bias.add_(0.5)  # workers must pick up new weights
        assert _same(proc.sample(policy, seeds[:1]), seq.sample(policy, seeds[:1]))


def test_sampler_rejects_mismatched_policy():
    other = DexRepNetPolicy(PolicyConfig.from_blocks({"hand": 9}, 2))
    with pytest.raises(DexdrakeError, match="does not match"):
        SequentialSampler(make_toy_env).sample(other, [0])
    with pytest.raises(DexdrakeError, match="unknown sampler backend"):
        make_sampler(make_toy_env, backend="mpi")


# ----------------------------------------------------------------------------- DAPG
FAST = dict(rollouts_per_iteration=4, time_scale=20, progress=False, checkpoint_every=0)


def test_demo_weight_and_seeds():
    cfg = DAPGConfig()
    assert (cfg.lam0, cfg.lam1, cfg.max_adv, cfg.step_size, cfg.gamma, cfg.gae_lambda) == (0.1, 0.95, 1.0, 0.05, 0.995, 0.97)
    assert demo_weight(cfg, 0) == pytest.approx(0.1) and demo_weight(cfg, 10) == pytest.approx(0.1 * 0.95**10)
    assert rollout_seeds(0, 3, 4) == rollout_seeds(0, 3, 4) != rollout_seeds(0, 4, 4)


def test_dapg_iteration_with_two_workers(tmp_path):
    policy = toy_policy()
    encoders_before = [p.detach().clone() for p in policy.encoders.parameters()]
    head_before = flat_params([p for n, p in policy.named_parameters() if not n.startswith("encoders")])
    demos = expert_dataset(200)
    with ProcessSampler(make_toy_env, num_workers=2) as sampler:
        result = train_dapg(policy, sampler, tmp_path, DAPGConfig(iterations=1, **{**FAST, "checkpoint_every": 1, "rerun": True}), demos=demos)
    head_after = flat_params([p for n, p in policy.named_parameters() if not n.startswith("encoders")])
    assert not torch.allclose(head_before, head_after)
    assert all(torch.equal(a, b) for a, b in zip(encoders_before, policy.encoders.parameters()))
    assert all(p.grad is None and not p.requires_grad for p in policy.encoders.parameters())
    (row,) = result.rows
    assert row["num_samples"] == 4 * 20 and 0 < row["kl"] < 0.2 and row["demo_weight"] == pytest.approx(0.1)
    assert [int(r["iteration"]) for r in read_csv(tmp_path / "dapg_log.csv")] == [0]
    for name in ("dapg_log.png", "dapg_state.pt", "dapg_iter_0001.pt", "dapg_policy_last.pt", "dapg_policy_best.pt", "dapg.rrd"):
        assert (tmp_path / name).is_file(), name
    reloaded, meta = load_policy(tmp_path / "dapg_policy_last.pt")
    assert meta["updates"] == 1 and torch.equal(flat_params(list(reloaded.parameters())), flat_params(list(policy.parameters())))
    best, meta = load_policy(tmp_path / "dapg_policy_best.pt")  # the sampled (pre-update) weights
    assert meta["updates"] == 0 and meta["mean_return"] == pytest.approx(row["mean_return"])
    head = [p for n, p in best.named_parameters() if not n.startswith("encoders") and n != "log_std"]
    assert torch.equal(flat_params(head), head_before[2:])  # head_before starts with the 2 log-std entries
    assert torch.allclose(best.log_std, torch.log(0.5 * torch.as_tensor(demos.actions).std(0, correction=0)))


def test_dapg_resume_continues_and_matches_uninterrupted_run(tmp_path):
    demos = expert_dataset(100)
    cfg1, cfg2 = DAPGConfig(iterations=1, **FAST), DAPGConfig(iterations=2, **FAST)
    sampler = SequentialSampler(make_toy_env)
    straight = toy_policy(seed=4)
    train_dapg(straight, sampler, tmp_path / "straight", cfg2, demos=demos)

    train_dapg(toy_policy(seed=4), sampler, tmp_path / "split", cfg1, demos=demos)
    resumed_policy = toy_policy(seed=99)  # weights come from the checkpoint
    result = train_dapg(resumed_policy, sampler, tmp_path / "split", cfg2, demos=demos, resume=True)
    assert [r["iteration"] for r in result.rows] == [1] and result.iterations_done == 2
    assert [int(r["iteration"]) for r in read_csv(tmp_path / "split" / "dapg_log.csv")] == [0, 1]
    assert torch.allclose(flat_params(list(resumed_policy.parameters())), flat_params(list(straight.parameters())), atol=1e-6)

    wrong = DexRepNetPolicy(PolicyConfig.from_blocks(TOY_BLOCKS, 2, hidden_sizes=(16,)))
    with pytest.raises(DexdrakeError, match="holds a policy with config"):
        DAPGTrainer(wrong, sampler, tmp_path / "split", cfg2).load_state()


def test_dapg_improves_toy_return(tmp_path):
    policy = toy_policy()
    cfg = DAPGConfig(iterations=15, rollouts_per_iteration=16, time_scale=20, progress=False, checkpoint_every=0)
    result = train_dapg(policy, SequentialSampler(make_toy_env), tmp_path, cfg)
    first = np.mean([r["mean_return"] for r in result.rows[:3]])
    last = np.mean([r["mean_return"] for r in result.rows[-3:]])
    assert last > first + 1.0


# ----------------------------------------------------------------------------- PolicySystem
def test_policy_system_in_diagram(tmp_path):
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.primitives import ConstantVectorSource

    from dexdrake.systems.policy_system import PolicySystem

    policy = toy_policy(seed=2)
    with torch.no_grad():
        policy.mlp[-1].bias.copy_(torch.tensor([3.0, -0.01]))  # one action saturates
    path = save_policy(tmp_path / "p.pt", policy, {"hand": "toy"})
    obs = np.linspace(-1, 1, 9)
    builder = DiagramBuilder()
    src = builder.AddSystem(ConstantVectorSource(obs))
    ctrl = builder.AddSystem(PolicySystem(path, control_period=0.01))
    builder.Connect(src.get_output_port(), ctrl.GetInputPort("observation"))
    builder.ExportOutput(ctrl.GetOutputPort("action"), "action")
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = simulator.get_context()
    assert np.array_equal(diagram.GetOutputPort("action").Eval(context), [0.0, 0.0])
    simulator.AdvanceTo(0.05)
    expected = np.clip(policy.act(obs)[0], -1, 1)
    got = diagram.GetOutputPort("action").Eval(context)
    assert got[0] == 1.0 and np.allclose(got, expected, atol=1e-6)
    assert ctrl.guard.counts == {"non_finite": 0, "clipped": 5}  # updates at 0, 0.01, ..., 0.04
    assert ctrl.metadata == {"hand": "toy", "scenario": UNRECORDED_SCENARIO}
    src.get_mutable_source_value(src.GetMyMutableContextFromRoot(simulator.get_mutable_context())).set_value(
        np.full(9, np.nan))  # a NaN observation gives a NaN action: the last action is held
    simulator.AdvanceTo(0.1)
    assert np.array_equal(diagram.GetOutputPort("action").Eval(context), got)
    assert ctrl.guard.counts == {"non_finite": 5, "clipped": 5}  # ... and at 0.05, ..., 0.09
