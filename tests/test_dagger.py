"""The expert (ReactiveGrasp) and DAgger on it (`dexdrake train dagger`)."""

from __future__ import annotations

import hashlib
from dataclasses import replace

import numpy as np
import pytest
import torch

from dexdrake.cli import main
from dexdrake.errors import DexdrakeError
from dexdrake.learn.curves import read_csv
from dexdrake.learn.dagger import (Aggregate, DaggerConfig, DaggerData, init_sha256, labelled_episode, prior_files,
                                   relabel_job, run_capacity, run_config, train_dagger)
from dexdrake.learn.policy import load_policy
from dexdrake.systems.env_factory import GraspEnvFactory
from dexdrake.systems.reactive_grasp import ReactiveGrasp, ReactiveRules
from dexdrake.systems.scene import ObjectPlacement

OBJECT = "sphere_small"


@pytest.fixture(scope="module")
def env():
    return GraspEnvFactory("adroit", None, (OBJECT, "can_soda"), horizon=100)()


def test_expert_grasps_and_lifts_within_the_evaluation_episode(env):
    env.reset(0, object_name=OBJECT)
    expert = ReactiveGrasp(env)
    phases, success, lifting = [], False, []
    for _ in range(env.horizon):
        q = expert(env)
        if not phases or phases[-1] != expert.phase:
            phases.append(expert.phase)
        if expert.phase == "lift":
            lifting.append(expert.ik.palm_pose(env.hand_state()[: expert.n_arm])[0])
        success = env.step_positions(q)[3]["success"] or success
    assert success
    # From the start pose: over the object, descend, close, lift, and never back to the descent
    # (the fingers' speed can still flip a lift that has not risen 1 cm back to closing for a step).
    assert phases[:4] == ["approach", "descend", "close", "lift"] and set(phases[4:]) <= {"close", "lift"}
    assert phases[-1] == "lift"
    lifting = np.array(lifting)  # up from where the grasp closed, ...
    assert lifting[-1, 2] - lifting[0, 2] > 0.1
    xy = env.object_position()[:2]  # ... the sphere, pushed out of the placement range by the closing
    assert np.linalg.norm(xy - ObjectPlacement.nearest_start(xy)) < 0.003  # fingers, carried back over it


def test_expert_label_depends_on_state_not_time_and_leads_the_arm(env):
    env.reset(3, object_name="can_soda")
    expert = ReactiveGrasp(env)
    first = expert(env)
    env.context.SetTime(1.7)  # a clock-driven script would be closing the fingers by now
    assert np.array_equal(expert(env), first)
    n_arm = expert.n_arm
    q_arm = env.hand_state()[:n_arm]
    lead = np.abs(env.normalise(first)[:n_arm] - env.normalise(np.r_[q_arm, first[n_arm:]])[:n_arm])
    assert lead.max() == pytest.approx(expert.rules.max_lead, rel=1e-6)  # moves at once, as fast as allowed
    assert expert.phase in ("approach", "descend")


def test_expert_opens_fingers_closed_away_from_the_object(env):
    env.reset(1, object_name=OBJECT)
    expert = ReactiveGrasp(env)
    plant = env.scene.plant
    q = plant.GetPositions(env.plant_context)
    fingers = env.scene.q_index[expert.n_arm:]
    q[fingers] = expert.q_closed[expert.n_arm:]  # fingers shut at the start pose, far above the object
    plant.SetPositions(env.plant_context, q)
    out = expert(env)
    assert expert.phase == "open"
    assert np.allclose(out[expert.n_arm:], expert.q_open[expert.n_arm:])


def test_reset_refuses_an_object_outside_the_env(env):
    with pytest.raises(DexdrakeError, match="not one of this env's objects"):
        env.reset(0, object_name="apple")


def test_labelled_episode_records_states_and_expert_labels(env):
    data = labelled_episode(env, OBJECT, 0, None, 0.0, ReactiveGrasp)
    assert data.objects == [OBJECT] and data.success.tolist() == [True]
    n = env.horizon
    assert data.labels.shape == (n, env.action_dim) and data.observations.shape == (n, 2 * env.action_dim)
    assert data.states.shape == (n, env.scene.plant.num_positions() + env.scene.plant.num_velocities())
    assert data.episode_starts.sum() == 1 and data.episode_starts[0]
    assert np.all(np.abs(data.labels) <= 1.0)


def test_dagger_data_round_trip_and_format_check(tmp_path, env):
    data = labelled_episode(env, OBJECT, 1, None, 0.0, ReactiveGrasp)
    data.save(tmp_path / "d.npz", {"iteration": 0})
    back = DaggerData.load(tmp_path / "d.npz")
    assert back.objects == data.objects and np.array_equal(back.labels, data.labels)
    np.savez(tmp_path / "bad.npz", metadata=np.array('{"format": "other"}'))
    with pytest.raises(DexdrakeError, match="not a dexdrake.dagger/2 file"):
        DaggerData.load(tmp_path / "bad.npz")


def test_aggregate_joins_iterations_without_copying_earlier_ones(tmp_path):
    def part(n: int, value: float) -> DaggerData:
        starts = np.zeros(n, bool)
        starts[0] = True
        return DaggerData(["x"], np.array([value]), np.array([True]), starts, np.zeros((n, 3)),
                          np.full((n, 4), value, np.float32), np.full((n, 2), -value, np.float32))
    parts = [part(3, 1.0), part(5, 2.0)]
    agg = Aggregate(10)
    for p in parts:
        agg.add(p)
    joined, expected = agg.dataset(), DaggerData.concat(parts)
    assert np.array_equal(joined.observations, expected.observations) and np.array_equal(joined.actions, expected.labels)
    assert np.array_equal(joined.episode_starts, expected.episode_starts) and len(joined) == 8
    assert np.shares_memory(joined.observations, agg.observations)  # a view, not a copy
    assert joined.observations.dtype == np.float16  # half the memory of float32
    with pytest.raises(DexdrakeError, match="exceeds the 10 allocated"):
        agg.add(part(3, 3.0))
    config = DaggerConfig(iterations=3, episodes_per_object=2, horizon=7)
    part(4, 1.0).save(tmp_path / "data_00.npz", {})
    assert run_capacity(tmp_path, config, 5) == 4 + 2 * (5 * 2 * 7)  # on disk, then full horizons


def test_dagger_trains_resumes_and_cli(tmp_path, capsys, one_torch_thread):
    config = DaggerConfig(feature_set="Hand2obj", iterations=2, episodes_per_object=1, epochs=1, workers=1)
    final = train_dagger([OBJECT], tmp_path / "d", GraspEnvFactory, ReactiveGrasp, config)
    rows = read_csv(tmp_path / "d" / "dagger_log.csv")
    assert [r["driver"] for r in rows] == ["expert", "policy"]
    assert [int(r["samples_total"]) for r in rows] == [100, 200]  # aggregated
    assert float(rows[0]["success_rate"]) == 1.0  # the expert grasps the small sphere
    assert all(float(r["hold_val_loss"]) > 0 and float(r["train_loss"]) > 0 for r in rows)
    policy, meta = load_policy(final)
    assert policy.config.feature_set == "Hand2obj" and meta["iteration"] == 0  # the only measured policy
    before = (tmp_path / "d" / "policy_01.pt").stat().st_mtime_ns
    train_dagger([OBJECT], tmp_path / "d", GraspEnvFactory, ReactiveGrasp, config)  # finished iterations are not redone
    assert (tmp_path / "d" / "policy_01.pt").stat().st_mtime_ns == before
    assert len(read_csv(tmp_path / "d" / "dagger_log.csv")) == 2
    assert main(["train", "dagger", "--out", str(tmp_path / "c"), "--objects", OBJECT, "--iterations", "1",
                 "--episodes-per-object", "1", "--epochs", "1", "--workers", "1", "--feature-set", "Hand2obj",
                 "--threads", "1", "--residual-arm", "--weight-decay", "0.01", "--obs-noise", "0.1"]) == 0
    assert load_policy(tmp_path / "c" / "dagger_policy.pt")[0].config.residual_arm
    made = run_config(tmp_path / "c")
    assert (made.weight_decay, made.obs_noise, made.residual_arm, made.feature_set) == (0.01, 0.1, True, "Hand2obj")
    with pytest.raises(DexdrakeError, match="holds no DAgger run"):
        run_config(tmp_path)
    assert main(["train", "dagger", "--out", str(tmp_path / "e"), "--objects", "unseen"]) == 2
    assert "evaluation splits" in capsys.readouterr().err


class HalfLeadExpert(ReactiveGrasp):
    """Another expert (half the arm lead), to tell which expert labelled a state."""

    def __init__(self, env):
        super().__init__(env, rules=replace(ReactiveRules(), max_lead=0.15, lift_lead=0.15))


def test_relabel_replays_recorded_states_and_a_run_continues_from_an_earlier_one(tmp_path, env, capsys,
                                                                                 one_torch_thread):
    data = labelled_episode(env, "can_soda", 4, None, 0.0, ReactiveGrasp)
    again = relabel_job(ReactiveGrasp, env, None, ("can_soda", 4, data.states))
    np.testing.assert_array_equal(again, data.labels)  # the same expert in the same states: the same labels
    config = DaggerConfig(feature_set="Hand2obj", iterations=1, episodes_per_object=1, epochs=1, backend="sequential")
    train_dagger([OBJECT], tmp_path / "a", GraspEnvFactory, ReactiveGrasp, config)
    later = replace(config, init=str(tmp_path / "a" / "policy_00.pt"), prior=(str(tmp_path / "a"),), seed=1)
    train_dagger([OBJECT], tmp_path / "b", GraspEnvFactory, HalfLeadExpert, later)
    source, prior = DaggerData.load(tmp_path / "a" / "data_00.npz"), DaggerData.load(tmp_path / "b" / "prior_00.npz")
    assert np.array_equal(prior.observations, source.observations) and np.array_equal(prior.states, source.states)
    n_arm = len(env.scene.hand.arm_joints)
    q_arm = env.normalise(source.states[:, env.scene.q_index])[:, :n_arm]
    assert np.abs(source.labels[:, :n_arm] - q_arm).max() > 0.25  # the first expert led by up to 0.3 ...
    assert np.abs(prior.labels[:, :n_arm] - q_arm).max() < 0.15 + 1e-4  # ... the second, which relabelled, by 0.15
    assert [f.name for f in prior_files(replace(later, prior=(str(tmp_path / "b"),)))] == ["prior_00.npz",
                                                                                       "data_00.npz"]  # its whole history
    both = prior_files(replace(later, prior=(str(tmp_path / "a"), str(tmp_path / "b"))))  # several runs, in order
    assert [f"{f.parent.name}/{f.name}" for f in both] == ["a/data_00.npz", "b/prior_00.npz", "b/data_00.npz"]
    (row,) = read_csv(tmp_path / "b" / "dagger_log.csv")
    assert row["driver"] == "init" and int(row["samples_total"]) == 200  # the prior's states, then its own
    with pytest.raises(DexdrakeError, match="prior"):  # resumed with another prior: refused
        train_dagger([OBJECT], tmp_path / "b", GraspEnvFactory, HalfLeadExpert, replace(later, prior=(str(tmp_path / "b"),)))
    assert main(["train", "dagger", "--out", str(tmp_path / "c"), "--objects", OBJECT, "--prior", str(tmp_path / "none")]) == 2
    assert "holds no DAgger data" in capsys.readouterr().err
    with pytest.raises(DexdrakeError, match="holds adroit Hand2obj observations; this run is adroit DexRep"):
        train_dagger([OBJECT], tmp_path / "d", GraspEnvFactory, ReactiveGrasp, replace(later, feature_set="DexRep", init=""))
    with pytest.raises(DexdrakeError, match="trained for adroit with Hand2obj features"):
        train_dagger([OBJECT], tmp_path / "d", GraspEnvFactory, ReactiveGrasp, replace(later, feature_set="DexRep", prior=()))
    with pytest.raises(DexdrakeError, match="has an absolute arm head; add --residual-arm"):
        train_dagger([OBJECT], tmp_path / "d", GraspEnvFactory, ReactiveGrasp, replace(later, residual_arm=True, prior=()))
    started_from = hashlib.sha256((tmp_path / "a" / "policy_00.pt").read_bytes()).hexdigest()
    (tmp_path / "a" / "policy_00.pt").write_bytes(b"replaced after the run started")
    assert init_sha256(tmp_path / "b") == started_from and init_sha256(tmp_path / "a") is None  # an expert start: none


def test_an_init_policy_is_widened_to_a_feature_set_that_extends_its_own(tmp_path, capsys, one_torch_thread):
    """A DexRep policy starts a DexRep+Vel run: widened, it drives iteration 0 exactly as it
    would have (the same visited states), and the run's policies are DexRep+Vel."""
    from dexdrake.dexrep.feature_sets import observation_blocks
    from dexdrake.hands.description import load_hand
    from dexdrake.learn.policy import DexRepNetPolicy, PolicyConfig, save_policy

    blocks = observation_blocks(load_hand("adroit"), "DexRep")
    torch.manual_seed(3)
    old = DexRepNetPolicy(PolicyConfig.from_blocks(blocks, 30, feature_set="DexRep", hand="adroit"))
    init = save_policy(tmp_path / "init.pt", old)
    config = DaggerConfig(feature_set="DexRep+Vel", iterations=1, episodes_per_object=1, epochs=1,
                          backend="sequential", init=str(init))
    final = train_dagger([OBJECT], tmp_path / "d", GraspEnvFactory, ReactiveGrasp, config)
    assert "widened to DexRep+Vel" in capsys.readouterr().out
    assert load_policy(final)[0].config.feature_set == "DexRep+Vel"
    data = DaggerData.load(tmp_path / "d" / "data_00.npz")
    assert data.observations.shape[1] == sum(blocks.values()) + 30
    before = labelled_episode(GraspEnvFactory("adroit", "DexRep", (OBJECT,), horizon=100)(), OBJECT, 0, old, 0.0,
                              ReactiveGrasp)
    np.testing.assert_allclose(data.states, before.states, atol=1e-5)  # float32 sums in another order


def test_dagger_probe_runs_unseen_objects_without_training_on_them(tmp_path, one_torch_thread):
    config = DaggerConfig(feature_set="Hand2obj", iterations=1, episodes_per_object=1, epochs=1, workers=1,
                          probe_per_object=1)
    with pytest.raises(DexdrakeError, match="also training objects"):
        train_dagger([OBJECT], tmp_path / "x", GraspEnvFactory, ReactiveGrasp, config, probe_objects=[OBJECT])
    with pytest.raises(DexdrakeError, match="needs probe objects"):
        train_dagger([OBJECT], tmp_path / "x", GraspEnvFactory, ReactiveGrasp, config)
    final = train_dagger([OBJECT], tmp_path / "d", GraspEnvFactory, ReactiveGrasp, config, probe_objects=["apple"])
    (row,) = read_csv(tmp_path / "d" / "dagger_log.csv")
    assert int(row["samples_total"]) == 100  # the probe episode is not trained on
    probe = DaggerData.load(tmp_path / "d" / "probe_00.npz")
    assert probe.objects == ["apple"] and len(probe.labels) == 100
    assert float(row["unseen_success"]) == float(probe.success[0])  # the expert drove iteration 0
    policy = load_policy(final)[0]
    with torch.no_grad():
        err = (policy(torch.as_tensor(probe.observations)) - torch.as_tensor(probe.labels)) ** 2
    assert float(row["unseen_loss"]) == pytest.approx(float(err.sum(1).mean()), rel=1e-5)


def test_hold_still_loss_scores_the_action_that_keeps_the_measured_joints():
    from dexdrake.hands.action_map import ActionMap
    from dexdrake.hands.description import load_hand
    from dexdrake.learn.dagger import hold_still_loss
    from dexdrake.learn.demo_dataset import DemoDataset

    hand = load_hand("adroit")
    lo, hi = hand.joint_limits()
    q = np.random.default_rng(0).uniform(lo, hi, (4, len(lo)))
    obs = np.hstack([q, np.ones((4, 5))]).astype(np.float32)  # joint positions lead the observation
    held = (q - (hi + lo) / 2) / ((hi - lo) / 2)
    actions = held.copy()
    actions[1, 0] += 0.5  # one sample's first set-point off by 0.5 (normalised)
    data = DemoDataset(obs, actions.astype(np.float32))
    assert hold_still_loss(data, np.array([0, 2, 3]), ActionMap(hand)) == pytest.approx(0.0, abs=1e-9)
    assert hold_still_loss(data, np.array([0, 1]), ActionMap(hand)) == pytest.approx(0.25 / 2, rel=1e-4)


def test_best_measured_iteration(tmp_path):
    from dexdrake.learn.dagger import best_measured_iteration

    log = tmp_path / "log.csv"
    log.write_text("iteration,driver,success_rate\n0,expert,0.5\n1,policy,0.1\n2,policy,0.3\n3,policy,0.3\n")
    assert best_measured_iteration(log, 4) == 2  # policy_02 drove iteration 3 (ties: the later)
    log.write_text("iteration,driver,success_rate\n0,expert,0.5\n")
    assert best_measured_iteration(log, 1) == 0


def test_hand_descriptions_override_the_grasp_geometry_and_expert_rules():
    from dataclasses import replace

    from dexdrake.hands.description import load_hand
    from dexdrake.systems.reactive_grasp import ReactiveRules
    from dexdrake.systems.scripted_grasp import GraspScript, script_for, with_overrides

    allegro, adroit = load_hand("allegro_z1"), load_hand("adroit")
    assert script_for(adroit) == GraspScript() and script_for(allegro) == GraspScript(palm_depth=0.02, max_yaw=1.15)
    assert with_overrides(ReactiveRules, allegro.grasp_expert, allegro, "grasp_expert") == ReactiveRules(
        descend_cone=0.5, at_grasp=0.025, max_lead=0.15, lift_lead=0.05, stopped_speed=0.05, touch=0.02,
        in_hand=0.03, follow_closing=False, preclose=0.85, preclose_height=0.07, lift_touching=True,
        settled_speed=2.5, approach_step=0.05)  # the Z1 mount's over the hand's
    with pytest.raises(DexdrakeError, match=r"grasp_script has unknown fields \['palm_dept'\]"):
        script_for(replace(allegro, grasp_script={"palm_dept": 0.02}))


def test_ablation_goes_on_with_the_sets_a_run_of_its_settings_left_and_refuses_other_settings(tmp_path):
    import json
    from dataclasses import asdict

    from dexdrake.eval.ablations import AblationSettings, AblationSettingsError, finished_rows

    settings = AblationSettings(str(tmp_path / "run"), stride=10, epochs=20, episodes=2, eval_seed=7)
    out = tmp_path / "abl"
    assert finished_rows(out, settings) == {}  # nothing run yet
    out.mkdir()
    row = {"feature_set": "DexRep", "ours_all_pct": "12.0"}
    (out / "ablations.json").write_text(json.dumps({"settings": asdict(settings), "rows": {"DexRep": row}}))
    assert finished_rows(out, settings) == {"DexRep": row}  # workers and the sets asked for are not settings
    with pytest.raises(AblationSettingsError, match=r"other settings: epochs 20 \(now 40\); use another --out"):
        finished_rows(out, replace(settings, epochs=40))


def test_every_nth_step_keeps_each_episodes_start_and_every_nth_step_after_it():
    from dexdrake.eval.ablations import every_nth_step

    starts = np.array([1, 0, 0, 0, 0, 1, 0, 0], bool)  # episodes of 5 and 3 steps
    n = len(starts)
    data = DaggerData(["a", "b"], np.array([0, 1]), np.array([True, False]), starts, np.arange(n)[:, None] * 1.0,
                      np.zeros((n, 2), np.float32), np.arange(n, dtype=np.float32)[:, None])
    kept = every_nth_step(data, 2)
    assert kept.labels[:, 0].tolist() == [0, 2, 4, 5, 7]
    assert kept.episode_starts.tolist() == [True, False, False, True, False]


def test_the_ablation_command_tables_each_feature_set_on_a_dagger_runs_states(tmp_path, one_torch_thread, capsys):
    config = DaggerConfig(feature_set="Hand2obj", iterations=1, episodes_per_object=1, epochs=1, workers=1)
    train_dagger([OBJECT], tmp_path / "d", GraspEnvFactory, ReactiveGrasp, config)
    out = tmp_path / "abl"
    assert main(["ablations", "--dagger", str(tmp_path / "d"), "--out", str(out), "--feature-sets", "Hand2obj",
                 "--stride", "5", "--epochs", "1", "--episodes-per-object", "1", "--objects", "apple", "--workers", "1"]) == 0
    rows = read_csv(out / "ablations.csv")
    assert [r["feature_set"] for r in rows] == ["Hand2obj"]
    assert float(rows[0]["unseen_open_loop_mse"]) > 0 and 0 <= float(rows[0]["ours_all_pct"]) <= 100
    table = (out / "ablations.md").read_text()
    assert "- command: `dexdrake ablations --dagger" in table and "| Hand2obj |" in table
    assert table in capsys.readouterr().out


def test_rollout_benchmark_runs_the_shipped_policy_in_an_env_of_its_features(load_script, one_torch_thread):
    """The throughput benchmark's policy-driven collection (it once built DexRep envs for a DexRep+Vel policy)."""
    bench = load_script("bench_rollout")
    policy, factory = bench.shipped_policy_env(["sphere_small"], 3)
    parts, steps, cpu, _ = bench.breakdown([("sphere_small", 1000), ("sphere_small", 1001)], 2, policy, factory)
    assert steps == 6 and cpu > 0 and parts["policy inference"] > 0 and parts["expert label"] > 0
def test_every_dagger_episode_of_an_iteration_has_its_own_seed():
    """A seed fixes the placement: no two episodes of an iteration (objects, probes) share one, and
    an iteration too large for its seed block is refused."""
    from dexdrake.learn.dagger import PROBE_SEEDS, episode_jobs

    config = DaggerConfig(seed=3, episodes_per_object=2, probe_per_object=1)
    train, probe = episode_jobs(config, 1, ["a", "b", "c"]), episode_jobs(config, 1, ["p", "q"], probe=True)
    assert train == [("a", 3010000), ("b", 3010002), ("c", 3010004), ("a", 3010001), ("b", 3010003), ("c", 3010005)]
    assert probe == [("p", 3010000 + PROBE_SEEDS), ("q", 3010001 + PROBE_SEEDS)]
    assert not {s for _, s in train} & {s for _, s in episode_jobs(config, 2, ["a", "b", "c"])}
    with pytest.raises(DexdrakeError, match="exceed the 5000 seeds"):
        episode_jobs(config, 0, [f"o{i}" for i in range(2501)])


def test_dagger_and_demo_seeds_that_would_reach_the_evaluation_seeds_are_refused_in_one_line(tmp_path, capsys):
    from dexdrake.eval.seeds import TRAINING_SEEDS
    from dexdrake.learn.dagger import episode_jobs

    config = DaggerConfig(seed=999, iterations=99, episodes_per_object=2, probe_per_object=3)
    probes = episode_jobs(config, 98, ["a", "b"], probe=True)
    assert probes[-1] == ("b", 999 * 10**6 + 98 * 10**4 + 5000 + 5) and probes[-1][1] < TRAINING_SEEDS.stop
    assert main(["train", "dagger", "--out", str(tmp_path / "d"), "--objects", OBJECT, "--seed", "1000"]) == 2
    err = capsys.readouterr().err
    assert "DAgger's episode seeds" in err and "below the validation" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "d").exists()
    assert main(["demos", "synth", "--objects", OBJECT, "--out", str(tmp_path / "s"), "--seed", "10"]) == 2
    assert "demo episode seeds" in capsys.readouterr().err and not (tmp_path / "s").exists()
