"""Any Gymnasium environment as a world: stepping, episodes that end early, the
entropy on the chosen features, one configuration per mini-batch, seeds, workers, resume,
evaluation's projection and fine-tuning on the environment's own reward."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf
from scipy.special import digamma

from hmepol_cli.envs import ENVIRONMENTS, GymWorld, make_world
from hmepol_cli.errors import ConfigError
from hmepol_cli.evaluation import rollout_positions
from hmepol_cli.finetune.task import collect_episodes
from hmepol_cli.population import PolicyPopulation
from hmepol_cli.rollout import collect, collect_single, draw_configurations
from hmepol_cli.surrogate import _live
from hmepol_cli.trainer import Trainer
from tests.gym_toy import MAX_STEP, WALK_ID

SMALL = [
    "policy.hidden=[16]",
    "policy.encoder_hidden=[16]",
    "policy.history_size=4",
    "progress=false",
    "eval.trajectories=3",
    "eval.horizon=10",
]
WALK = ["env=gym", f"env.id={WALK_ID}", "algo.trajectories=6", "algo.horizon=12",
        "algo.batch_size=2", "estimator.k=3", "algo.max_off_iters=3"]  # fmt: skip


def compose_cfg(*overrides: str):
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="hmepol_cli.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=[*SMALL, *overrides])
    GlobalHydra.instance().clear()
    return cfg


def walk_world(**env) -> GymWorld:
    return make_world(OmegaConf.create({"name": "gym", "id": WALK_ID, **env}))


def policy_of(world: GymWorld, name: str = "markov", log_std: float = -0.5):
    from hmepol_cli.config import PolicyConfig
    from hmepol_cli.policies import make_policy

    torch.manual_seed(0)
    cfg = PolicyConfig(
        name=name, hidden=[8], encoder_hidden=[8], history_size=4, init_log_std=log_std
    )
    return make_policy(cfg, world.state_dim, world.action_dim)


def knn_entropy_by_hand(points: np.ndarray, k: int) -> float:
    """Eq. 2.6 by brute force, in float64: points (P, p)."""
    p, dim = points.shape
    distances = np.sqrt(((points[:, None, :] - points[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(distances, np.inf)
    radius = np.sort(distances, axis=1)[:, k - 1]  # the k-th nearest other particle
    log_volume = dim * np.log(radius) + dim / 2 * math.log(math.pi) - math.lgamma(dim / 2 + 1)
    return float(-(math.log(k / p) - log_volume).mean() + math.log(k) - digamma(k))


# ------------------------------------------------------------------ the world
def test_the_gym_world_reads_spaces_configurations_and_probabilities():
    world = walk_world(configs=[{"drift": 0.0}, {"drift": 0.1}], probs=[0.75, 0.25], features=[0])
    assert ENVIRONMENTS["gym"] is GymWorld
    assert (world.state_dim, world.action_dim) == (2, 1)
    assert world.configuration_names == ("drift=0.0", "drift=0.1")
    assert world.configuration_probs == (0.75, 0.25)
    with pytest.raises(ConfigError, match="sum to 4"):  # never renormalised behind one's back
        walk_world(configs=[{"drift": 0.0}, {"drift": 0.1}], probs=[3, 1])
    assert world.features == (0,) and world.projection == (0, 0)
    assert math.isnan(world.free_area(0))
    draws = world.sample_configurations(4000, torch.Generator().manual_seed(0))
    assert abs(float((draws == 0).double().mean()) - 0.75) < 5 * math.sqrt(0.75 * 0.25 / 4000)
    states = torch.arange(12.0).view(2, 3, 2)
    assert torch.equal(world.entropy_features(states), states[..., :1])
    assert torch.equal(walk_world().entropy_features(states), states)  # all: the same tensor


def test_actions_are_clipped_to_the_action_space_and_the_horizon_replaces_the_time_limit():
    """The walker refuses actions beyond +-0.5: a policy whose mean is far beyond them moves
    exactly 0.5 a step, for all T = 20 steps although the id registers a limit of 5."""
    world = walk_world()
    policy = policy_of(world)
    with torch.no_grad():
        for p in policy.parameters():
            p.zero_()
        policy.mean_net[-1].bias.fill_(3.0)  # mean action 3 >> 0.5
    rollout = collect_single(world, policy, torch.zeros(4, dtype=torch.long), 20,
                             torch.Generator().manual_seed(0), deterministic=True)  # fmt: skip
    moves = rollout.states[:, 1:, 0] - rollout.states[:, :-1, 0]
    torch.testing.assert_close(moves, torch.full_like(moves, MAX_STEP))
    assert torch.equal(rollout.actions, torch.full_like(rollout.actions, 3.0))  # stored unclipped
    assert rollout.alive.all() and not rollout.ended.any()
    torch.testing.assert_close(rollout.reward, rollout.states[:, 1:, 0])  # reward x after the move


def test_an_episode_that_ends_early_keeps_its_last_state_and_its_later_actions_count_nowhere():
    """Wall at |x| = 1, moves of 0.5: the episode ends on step 2 or 3 (x_0 in [-0.1, 0.1]); the
    trajectory keeps T + 1 states, the last one repeated, marked not alive after the end."""
    world = walk_world(configs=[{"wall": 1.0}])
    policy = policy_of(world)
    with torch.no_grad():
        for p in policy.parameters():
            p.zero_()
        policy.mean_net[-1].bias.fill_(1.0)
    rollout = collect_single(world, policy, torch.zeros(5, dtype=torch.long), 8,
                             torch.Generator().manual_seed(1), deterministic=True)  # fmt: skip
    x0 = rollout.states[:, 0, 0]
    end = torch.where(x0 + 2 * MAX_STEP >= 1.0, 2, 3)  # steps until |x| >= 1
    for i in range(5):
        e = int(end[i])
        assert rollout.alive[i, :e].all() and not rollout.alive[i, e:].any()
        assert rollout.ended[i].nonzero().flatten().tolist() == [e - 1]
        assert (rollout.states[i, e:] == rollout.states[i, e]).all()
        assert (rollout.reward[i, e:] == 0).all() and rollout.reward[i, e - 1] >= 1.0
    assert rollout.particles.shape == (5, 8, 2)
    # The importance weight of a particle after the end: only the actions before it count.
    log_ratios = torch.randn(5, 8, dtype=torch.float64)
    kept = _live(log_ratios, rollout.alive)
    assert torch.equal(kept[rollout.alive], log_ratios[rollout.alive])
    assert (kept[~rollout.alive] == 0).all()


def test_episodes_are_fixed_by_their_seeds_and_the_same_with_worker_processes():
    """Same generator: the same starts and trajectories; another seed: other starts. Two worker
    processes (each stepping half of the slots) give exactly what this process gives."""
    world = walk_world(configs=[{"drift": 0.0}, {"drift": 0.05}])
    policy = policy_of(world)
    configurations = torch.tensor([0, 0, 1, 1, 0])

    def states(w: GymWorld, seed: int) -> torch.Tensor:
        g = torch.Generator().manual_seed(seed)
        return collect_single(w, policy, configurations, 6, g).states

    a, b = states(world, 0), states(world, 0)
    assert torch.equal(a, b)
    assert len(set(a[:, 0, 0].tolist())) == 5  # every episode its own seed: its own start
    assert not torch.equal(a[:, 0], states(world, 1)[:, 0])
    pooled = walk_world(configs=[{"drift": 0.0}, {"drift": 0.05}], workers=2)
    try:
        assert torch.equal(states(pooled, 0), a)
    finally:
        pooled.close()


def test_each_member_of_a_population_steps_its_own_episodes():
    """Two members in one vector environment: member i's rollout equals a rollout of its own."""
    world = walk_world(configs=[{"drift": 0.0}, {"drift": 0.1}])
    policies = [policy_of(world), policy_of(world, log_std=-1.0)]
    population = PolicyPopulation(policies)
    configurations = torch.tensor([[0, 0, 1, 1], [1, 1, 0, 0]])
    together = collect(world, population, None, configurations, 5,
                       [torch.Generator().manual_seed(s) for s in (3, 4)])  # fmt: skip
    for i, seed in enumerate((3, 4)):
        alone = collect_single(world, policies[i], configurations[i], 5,
                               torch.Generator().manual_seed(seed))  # fmt: skip
        assert torch.equal(together.states[i], alone.states)


def test_ant_xy_replays_in_a_plain_gymnasium_ant_from_its_seed():
    """env=ant_xy (MuJoCo): the reference's 29-number state (qpos, qvel; x, y first), entropy
    on x-y; a rollout's trajectory is what gymnasium.make('Ant-v5', ...) gives when reset with
    the episode's seed (the first draw of the generator) and stepped with the clipped actions."""
    pytest.importorskip("mujoco")
    import gymnasium

    from hmepol_cli.envs.gym_world import SEED_BOUND

    cfg = compose_cfg("env=ant_xy")
    world = make_world(cfg.env)
    assert (world.state_dim, world.action_dim, world.features) == (29, 8, (0, 1))
    policy = policy_of(world, log_std=0.5)  # actions often beyond the bound of 1: clipped
    rollout = collect_single(world, policy, torch.zeros(2, dtype=torch.long), 6,
                             torch.Generator().manual_seed(7))  # fmt: skip
    seed = int(torch.randint(0, SEED_BOUND, (2,), generator=torch.Generator().manual_seed(7))[1])
    env = gymnasium.make("Ant-v5", **OmegaConf.to_container(cfg.env.configs[0]))
    obs, _ = env.reset(seed=seed)
    replayed = [obs]
    for action in rollout.actions[1].double().clamp(-1.0, 1.0).numpy():
        replayed.append(env.step(action.astype(np.float32))[0])
    np.testing.assert_allclose(rollout.states[1].double().numpy(), np.stack(replayed), atol=1e-5)
    assert (rollout.actions.abs() > 1).any()
    world.close()


# ------------------------------------------------------------------ training
def test_one_configuration_per_mini_batch_and_each_runs_its_own_environment(tmp_path):
    """Three drifts, p_M = (0.5, 0.25, 0.25), B = 2: both trajectories of a mini-batch share a
    configuration, drawn per member from p_M, and they move by their configuration's drift."""
    trainer = Trainer(
        compose_cfg(*WALK, "algo.trajectories=40",
                    "env.configs=[{drift:0.0},{drift:0.2},{drift:-0.2}]",
                    "env.probs=[0.5,0.25,0.25]"),
        tmp_path / "run",
    )  # fmt: skip
    g = trainer.members[0].generator
    configurations = draw_configurations(trainer.world, 40, 2, g)
    assert (configurations[0::2] == configurations[1::2]).all()
    assert set(configurations.tolist()) == {0, 1, 2}
    policy_mean_zero = policy_of(trainer.world, log_std=-20.0)  # practically no noise
    with torch.no_grad():
        policy_mean_zero.mean_net[-1].weight.zero_()
    rollout = collect_single(trainer.world, policy_mean_zero, configurations, 4, g)
    drift = torch.tensor([0.0, 0.2, -0.2], dtype=rollout.states.dtype)[configurations]
    moves = rollout.states[:, 1:, 1]  # the observation's last move
    torch.testing.assert_close(moves, drift[:, None].expand_as(moves), atol=1e-6, rtol=0)
    # Over many epochs' draws the frequencies follow p_M.
    draws = torch.cat([draw_configurations(trainer.world, 40, 2, g)[::2] for _ in range(200)])
    assert abs(float((draws == 0).double().mean()) - 0.5) < 5 * math.sqrt(0.25 / 4000)
    trainer.close()


def test_the_epoch_entropy_is_that_of_the_chosen_features(tmp_path):
    """features=[1] (the walker's last move): an epoch's mini-batch entropies equal eq. 2.6
    computed by brute force on that column of the same rollout (a second trainer with the same
    seed replays the epoch's draws)."""
    overrides = (*WALK, "env.features=[1]", "estimator.k=4", "precision=float64")
    first = Trainer(compose_cfg(*overrides), tmp_path / "a")
    (stats,) = first.epoch()
    again = Trainer(compose_cfg(*overrides), tmp_path / "b")
    g = again.members[0].generator
    configurations = draw_configurations(again.world, 6, 2, g)[None]
    rollout = collect(again.world, again.population, None, configurations, 12, [g])
    column = rollout.particles[0, ..., 1].reshape(3, 2 * 12, 1).numpy()
    expected = [knn_entropy_by_hand(batch, 4) for batch in column]
    np.testing.assert_allclose(stats.entropies, expected, rtol=1e-9)
    everything = rollout.particles[0].reshape(3, 24, 2).numpy()
    assert not np.allclose(stats.entropies, [knn_entropy_by_hand(b, 4) for b in everything])


def test_the_entropy_of_mountaincar_position_and_velocity_rises_over_a_few_epochs(tmp_path):
    """env=mountaincar, entropy on (position, velocity), the reference's initial std (log-std
    -0.5): ten epochs take the policy from jiggling in the valley to swinging (+1.6 nats with
    seed 0; seeds 0-3 gained 1.2-2.2 nats when this test was written)."""
    cfg = compose_cfg(
        "env=mountaincar", "algo.trajectories=20", "algo.batch_size=10", "algo.horizon=200",
        "algo.lr=3e-2", "algo.kl_threshold=10", "algo.max_off_iters=30", "estimator.k=4",
        "policy.init_log_std=-0.5",
    )  # fmt: skip
    trainer = Trainer(cfg, tmp_path / "run")
    curve = [float(trainer.epoch()[0].entropies.mean()) for _ in range(10)]
    assert np.mean(curve[-3:]) > np.mean(curve[:2]) + 1.0, curve
    assert trainer.world.features == (0, 1)


@pytest.mark.slow  # heavy: make test runs it, make test-fast does not
def test_hmepol_in_a_gym_world_resumes_exactly(tmp_path):
    """HMepol (recursive policy, bptt = 2) on the walker with two drifts: 3 epochs straight equal
    2 epochs, then a resume for the third (the episode seeds come from the checkpointed
    generator); the evaluation holds each configuration's projection (n, T + 1, 2)."""
    overrides = (*WALK, "algo=hmepol", "policy.bptt=2", "env.configs=[{drift:0.0},{drift:0.1}]")
    straight = Trainer(compose_cfg(*overrides, "epochs=3"), tmp_path / "straight")
    straight.train()
    Trainer(compose_cfg(*overrides, "epochs=2"), tmp_path / "cut").train()
    Trainer(compose_cfg(*overrides, "epochs=3"), tmp_path / "cut").train(resume=True)
    timing = ["seconds", "collect_seconds", "neighbours_seconds", "update_seconds", "wall_time"]
    a, b = (
        pd.read_csv(tmp_path / d / "epochs.csv").drop(columns=timing) for d in ("straight", "cut")
    )
    pd.testing.assert_frame_equal(a, b)
    final = np.load(tmp_path / "straight" / "eval" / "final.npz")
    assert sorted(final.files) == ["positions_c0", "positions_c1"]
    assert final["positions_c0"].shape == (3, 11, 2)
    assert (tmp_path / "straight" / "eval" / "final" / "heatmap.png").is_file()


@pytest.mark.slow  # heavy: make test runs it, make test-fast does not
def test_the_report_names_a_gym_run_by_its_id_and_groups_its_configurations(tmp_path):
    """Two seeds on the walker with two drifts: one group, figures named after the id (made
    safe for file names), configurations named by what differs between them."""
    from hmepol_cli.report import run_report

    for seed in (0, 1):
        cfg = compose_cfg(*WALK, f"seed={seed}", "epochs=2",
                          "env.configs=[{drift:0.0,wall:9.0},{drift:0.1,wall:9.0}]")  # fmt: skip
        Trainer(cfg, tmp_path / "runs" / f"seed{seed}").train()
    run_report(tmp_path / "runs", tmp_path / "report")
    figures = {p.name for p in (tmp_path / "report" / "figures").glob("*.png")}
    assert "hmepol-test-Walk-v0_heatmaps.png" in figures, figures
    assert "hmepol-test-Walk-v0_entropy_epochs.png" in figures, figures
    summary = pd.read_csv(tmp_path / "report" / "summary.csv")
    assert set(summary.config) == {"average", "0: drift=0.0", "1: drift=0.1"}
    assert set(summary.n_seeds) == {2}


def test_evaluation_draws_the_projection_of_the_observation():
    world = walk_world(projection=[1, 0])
    population = PolicyPopulation([policy_of(world)])
    (positions,) = rollout_positions(world, population, 3, 4, [torch.Generator().manual_seed(0)])
    rollout = collect_single(world, policy_of(world), torch.zeros(3, dtype=torch.long), 4,
                             torch.Generator().manual_seed(0))  # fmt: skip
    np.testing.assert_array_equal(positions[0], rollout.states[..., [1, 0]].numpy())


# ------------------------------------------------------------------ fine-tuning
def test_finetuning_uses_the_environments_reward_and_termination(tmp_path):
    """A Gymnasium world fine-tunes on its own task: the returns in finetune.csv are the sums of
    the walker's rewards (x after each move) until it terminates at the wall."""
    from hmepol_cli.finetune import check_finetune, finetune
    from hmepol_cli.finetune.task import RewardTask

    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="hmepol_cli.conf", version_base="1.3"):
        cfg = compose(
            config_name="finetune",
            overrides=["env=gym", f"env.id={WALK_ID}", "env.configs=[{wall:1.0}]", "epochs=2",
                       "episodes=4", "horizon=10", "progress=false", f"output_dir={tmp_path}/ft",
                       "policy.hidden=[8]"],
        )  # fmt: skip
    GlobalHydra.instance().clear()
    plan = check_finetune(cfg)
    assert plan.tasks == {0: [RewardTask(0, 10)]}
    finetune(cfg)
    rows = pd.read_csv(tmp_path / "ft" / "finetune.csv")
    assert len(rows) == 2 and rows.success_rate.isna().all()
    recorded = json.loads((tmp_path / "ft" / "run.json").read_text())
    assert recorded["return_bounds"] == [None, None] and recorded["world_map"] is None  # no map
    assert (rows.episode_length <= 10).all()
    # The returns of a rollout by hand: rewards of the live steps only.
    world = plan.world
    policy = policy_of(world, log_std=0.0)
    rollout = collect_episodes(
        world, policy, RewardTask(0, 10), 6, torch.Generator().manual_seed(0)
    )
    x = rollout.states[:, 1:, 0]
    by_hand = (x * rollout.alive).sum(-1)
    torch.testing.assert_close(rollout.returns, by_hand)
    ended = rollout.ends.any(-1)
    assert ((x.abs() >= 1.0).any(-1) == ended).all()
    if rollout.alive.shape[1] < 10:  # every episode hit the wall: the rollout stopped there
        assert ended.all()


def test_configurations_whose_spaces_differ_are_refused():
    with pytest.raises(ConfigError, match=r"env.configs\[1\].*share the observation"):
        walk_world(configs=[{}, {"dim": 3}])


def test_your_own_environment_by_module_and_id(tmp_path, monkeypatch):
    """env.id=<module>:<id>: the module that registers the id is imported first (Gymnasium's
    own convention, which gymnasium.make follows too); a module that is not there is refused."""
    (tmp_path / "my_walks.py").write_text(
        "import gymnasium\n"
        "gymnasium.register(id='MyWalk-v0', entry_point='tests.gym_toy:Walk',\n"
        "                   kwargs={'drift': 0.25})\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    world = make_world(OmegaConf.create({"name": "gym", "id": "my_walks:MyWalk-v0"}))
    policy, configurations = policy_of(world, log_std=-20.0), torch.zeros(2, dtype=torch.long)
    rollout = collect_single(world, policy, configurations, 3, torch.Generator().manual_seed(0))
    assert (rollout.states[:, 1:, 1] - 0.25).abs().max() < 0.01  # its drift: this environment
    with pytest.raises(ConfigError, match="'no_such_module' .* cannot be imported"):
        make_world(OmegaConf.create({"name": "gym", "id": "no_such_module:MyWalk-v0"}))


@pytest.mark.slow
def test_the_command_trains_and_finetunes_in_a_gymnasium_world(tmp_path):
    """The real command end to end: train HMepol on MountainCar, then fine-tune on its reward."""
    from tests.test_cli import hmepol

    run = tmp_path / "run"
    hmepol("train", "env=mountaincar", "algo=hmepol", "epochs=2", "algo.trajectories=4",
           "algo.horizon=30", "algo.batch_size=2", "estimator.k=3", *SMALL,
           f"hydra.run.dir={run}", cwd=tmp_path)  # fmt: skip
    rows = pd.read_csv(run / "epochs.csv")
    assert list(rows.epoch) == [0, 1] and np.isfinite(rows.entropy).all()
    info = pd.read_json(run / "run.json", typ="series")
    assert info["env_id"] == "MountainCarContinuous-v0" and info["status"] == "finished"
    hmepol("finetune", f"init={run}", "epochs=2", "episodes=3", "horizon=20", "progress=false",
           f"output_dir={tmp_path / 'ft'}", cwd=tmp_path)  # fmt: skip
    returns = pd.read_csv(tmp_path / "ft" / "finetune.csv")["return"]
    assert len(returns) == 2 and (returns <= 0).all()  # MountainCar charges for every push


def test_both_kinds_of_world_implement_the_world_protocol():
    from hmepol_cli.envs import World
    from hmepol_cli.envs.slope import SlopeWorld

    for world in (SlopeWorld(), walk_world()):
        assert isinstance(world, World)
        assert world.maps == isinstance(world, SlopeWorld)


def test_particles_after_an_episode_ended_take_no_part_in_the_entropy(tmp_path):
    """Half the mini-batches run in a configuration whose wall ends every episode after a few
    steps (a policy of mean +0.5), half in one without a wall. Each mini-batch's entropy is
    eq. 2.6 over its live particles alone (by brute force); before, the last state's copies
    counted too, each at a zero radius, ~18 nats too low apiece with k = 4."""
    from hmepol_cli import mepol

    cfg = compose_cfg(*WALK, "env.configs=[{wall:1.0},{wall:1000.0}]", "env.features=[0]",
                      "algo.batch_size=3", "estimator.k=3", "algo.max_off_iters=1")  # fmt: skip
    trainer = Trainer(cfg, tmp_path / "run")
    with torch.no_grad():
        trainer.population.params["mean_net.2.bias"].fill_(1.0)  # clipped to the bound, 0.5
    configurations = torch.tensor([[0, 0, 0, 1, 1, 1]])
    rollout = collect(trainer.world, trainer.population, None, configurations, 12,
                      [torch.Generator().manual_seed(0)])  # fmt: skip
    assert not rollout.alive[0, :3].all() and rollout.alive[0, 3:].all()
    (stats,) = mepol._update(trainer.world, trainer.population, trainer.optimizer,
                             trainer.settings, rollout, torch.tensor([0]), 0.0, 0.0)  # fmt: skip
    x = rollout.particles[0, ..., :1].double()  # the entropy's feature: the position
    for batch in range(2):
        rows = slice(3 * batch, 3 * batch + 3)
        live = x[rows][rollout.alive[0, rows]].numpy()
        assert stats.entropies[batch] == pytest.approx(knn_entropy_by_hand(live, 3), rel=1e-5)
    assert stats.floor_share == 0.0


# ------------------------------------------------------------------ hmepol show
def test_random_visits_follow_each_configuration_within_the_action_bounds():
    """Uniform actions in [-0.5, 0.5] (the walker refuses any other): the mean end of 200
    steps is 200 x drift, about 0 and 20 here (one episode's end has std ~4)."""
    from hmepol_cli.envs.render import random_visits

    world = walk_world(configs=[{"drift": 0.0}, {"drift": 0.1}])
    visits = random_visits(world, 32, 200)
    assert set(visits) == {0, 1} and visits[0].shape == (32, 201, 2)
    assert np.abs(visits[0][:, 0, 0]).max() <= 0.1  # the starts: x_0 in [-0.1, 0.1]
    assert abs(visits[0][:, -1, 0].mean()) < 3 and abs(visits[1][:, -1, 0].mean() - 20) < 3
    moves = visits[1][:, 1:, 1] - 0.1  # the projection's second index: the last move
    assert moves.min() >= -MAX_STEP - 1e-6 and moves.max() <= MAX_STEP + 1e-6
    assert moves.std() > 0.25  # uniform in [-0.5, 0.5]: std 0.29
    again = random_visits(world, 32, 200)
    assert all(np.array_equal(visits[c], again[c]) for c in visits)  # one seed, one picture


@pytest.mark.parametrize(
    "overrides",
    [
        [f"env.id={WALK_ID}", "env.configs=[{drift:0.0},{drift:0.1}]"],
        ["env.id=Pendulum-v1", "env.configs=[{g:5.0},{g:15.0}]", "env.projection=[0,2]"],
    ],
    ids=["walk", "pendulum"],
)
def test_show_draws_a_gymnasium_world_a_panel_per_configuration(tmp_path, capsys, overrides):
    import matplotlib.image as mpimg

    from hmepol_cli.cli import main

    main(["show", "env=gym", *overrides, "--out", str(tmp_path / "world.png")])
    assert "drawn to" in capsys.readouterr().out
    image = mpimg.imread(tmp_path / "world.png")
    assert image.shape[1] > 1.4 * image.shape[0]  # two panels side by side
