"""TRPO fine-tuning (thesis Fig. 5.9): solver pieces, trust region, learning, the run's CSV."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf

from hmepol_cli.envs.base import Box, NavigationWorld
from hmepol_cli.errors import ConfigError
from hmepol_cli.finetune.runner import finetune, trpo_settings
from hmepol_cli.finetune.task import GoalTask, collect_episodes, draw_target, make_tasks
from hmepol_cli.finetune.trpo import (
    TRPO,
    TRPOSettings,
    conjugate_gradient,
    fisher_vector_product,
    gaussian_kl,
    get_flat,
    line_search,
    masked_mean,
)
from hmepol_cli.policies.markov import MarkovPolicy
from hmepol_cli.policies.recursive import RecursivePolicy
from hmepol_cli.run import (
    CHECKPOINT,
    CONFIG,
    FINETUNE_CSV,
    RUN_INFO,
    atomic_write_text,
    save_checkpoint,
    write_json,
)

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
REQUIRED_COLUMNS = [
    "epoch",
    "target",
    "config",
    "return",
    "success_rate",
    "kl",
    "init",
    "algo_init",
    "seed",
]


class OpenWorld(NavigationWorld):
    """One wall-less configuration; the agent starts on the left of [-1, 1]^2."""

    name = "open"
    arena = Box(-1.0, -1.0, 1.0, 1.0)
    start = Box(-0.9, -0.1, -0.7, 0.1)
    configuration_names = ("open",)
    configuration_probs = (1.0,)
    walls = ((),)


NEAR_TARGET = Box(
    0.1, -0.3, 0.5, 0.3
)  # ~1 unit right of the start: a random walk finds it sometimes


def tiny_markov(seed: int = 0, dtype: torch.dtype = torch.float32) -> MarkovPolicy:
    torch.manual_seed(seed)
    return MarkovPolicy(2, 2, hidden=[16, 16], init_log_std=-0.5).to(dtype=dtype)


def tiny_recursive(seed: int = 0, dtype: torch.dtype = torch.float32) -> RecursivePolicy:
    torch.manual_seed(seed)
    policy = RecursivePolicy(
        2, 2, hidden=[8], encoder_hidden=[8], history_size=4, init_log_std=-0.5
    )
    return policy.to(dtype=dtype)


def tiny_settings(**kw) -> TRPOSettings:
    base = dict(max_kl=0.02, value_hidden=(16, 16), value_epochs=5, value_batch=128)
    return TRPOSettings(**{**base, **kw})


# --------------------------------------------------------------------------- solver pieces
def test_conjugate_gradient_solves_a_known_spd_system():
    gen = torch.Generator().manual_seed(0)
    m = torch.randn(12, 12, generator=gen, dtype=torch.float64)
    a = m @ m.T + 0.5 * torch.eye(12, dtype=torch.float64)
    b = torch.randn(12, generator=gen, dtype=torch.float64)
    x = conjugate_gradient(lambda v: a @ v, b, iters=50, tol=1e-20)
    torch.testing.assert_close(x, torch.linalg.solve(a, b), rtol=1e-8, atol=1e-8)


class _KL(torch.nn.Module):
    """The mean KL as a module's forward, so torch.func can take its Hessian in the parameters."""

    def __init__(self, policy, rollout, bptt):
        super().__init__()
        self.policy, self.rollout, self.bptt = policy, rollout, bptt

    def forward(self):
        kl = gaussian_kl(self.policy, self.rollout, self.bptt)
        return masked_mean(kl, self.rollout.alive.to(kl.dtype))


@pytest.mark.parametrize(
    "make, bptt", [(tiny_markov, 1), (tiny_recursive, 1), (tiny_recursive, None)]
)
def test_fisher_vector_product_is_the_kl_hessian(make, bptt):
    world = OpenWorld().to("cpu", torch.float64)
    policy = make(dtype=torch.float64)
    task = GoalTask(NEAR_TARGET, 0, horizon=6)
    rollout = collect_episodes(world, policy, task, 5, torch.Generator().manual_seed(1))
    names = [n for n, _ in policy.named_parameters()]
    params = [p for _, p in policy.named_parameters()]
    module = _KL(policy, rollout, bptt)

    kl = module()
    assert abs(kl.item()) < 1e-10  # KL of the sampling policy with itself

    def kl_of(flat):
        chunks, i = {}, 0
        for name, p in zip(names, params, strict=True):
            chunks[f"policy.{name}"] = flat[i : i + p.numel()].view_as(p)
            i += p.numel()
        return torch.func.functional_call(module, chunks, ())

    hessian = torch.autograd.functional.hessian(kl_of, get_flat(params))
    fvp = fisher_vector_product(kl, params, damping=0.0)
    gen = torch.Generator().manual_seed(2)
    for _ in range(3):
        v = torch.randn(hessian.shape[0], generator=gen, dtype=torch.float64)
        torch.testing.assert_close(fvp(v), hessian @ v, rtol=1e-7, atol=1e-9)
    # damping adds a multiple of v; the Fisher is positive semi-definite
    v = torch.randn(hessian.shape[0], generator=gen, dtype=torch.float64)
    damped = fisher_vector_product(module(), params, damping=0.1)
    torch.testing.assert_close(damped(v), hessian @ v + 0.1 * v, rtol=1e-7, atol=1e-9)
    assert torch.linalg.eigvalsh((hessian + hessian.T) / 2).min() > -1e-8


@settings(max_examples=60, deadline=None)
@given(
    dim=st.integers(1, 6),
    seed=st.integers(0, 10_000),
    scale=st.floats(0.05, 20.0),
    cubic=st.floats(0.0, 5.0),
    max_kl=st.floats(1e-3, 0.1),
    tries=st.integers(1, 12),
    shrink=st.floats(0.3, 0.95),
)
def test_line_search_never_accepts_a_step_beyond_the_kl_bound(
    dim, seed, scale, cubic, max_kl, tries, shrink
):
    gen = torch.Generator().manual_seed(seed)
    theta = torch.nn.Parameter(torch.randn(dim, generator=gen, dtype=torch.float64))
    start = theta.detach().clone()
    m = torch.randn(dim, dim, generator=gen, dtype=torch.float64)
    fisher = m @ m.T + 0.1 * torch.eye(dim, dtype=torch.float64)
    g = torch.randn(dim, generator=gen, dtype=torch.float64)
    wobble = torch.randn(dim, generator=gen, dtype=torch.float64)

    def evaluate():  # a KL with a cubic term, so the quadratic model can under-estimate it
        d = theta.detach() - start
        kl = 0.5 * d @ fisher @ d + cubic * d.norm() ** 3
        objective = g @ d - 0.3 * (wobble @ d) ** 2
        return float(objective), float(kl)

    step = scale * torch.linalg.solve(fisher, g) * torch.sqrt(torch.tensor(2 * max_kl))
    result = line_search([theta], step, evaluate, 0.0, max_kl, tries, shrink)
    objective, kl = evaluate()
    if result.accepted:
        assert kl <= max_kl and objective > 0.0
        assert kl == pytest.approx(result.kl) and result.tries <= tries
    else:
        assert torch.equal(theta.detach(), start)  # restored exactly
        assert result.kl == 0.0 and result.fraction == 0.0


@pytest.mark.parametrize(
    "make, fisher_fraction", [(tiny_markov, 1.0), (tiny_recursive, 1.0), (tiny_recursive, 0.5)]
)
def test_a_trpo_update_stays_in_the_trust_region_on_the_stored_trajectories(make, fisher_fraction):
    world = OpenWorld()
    task = GoalTask(NEAR_TARGET, 0, horizon=25)
    policy = make()
    gen = torch.Generator().manual_seed(0)
    settings = tiny_settings(max_kl=0.01, fisher_fraction=fisher_fraction)
    trpo = TRPO(policy, world, task.horizon, settings, gen)
    for _ in range(3):
        rollout = collect_episodes(world, policy, task, 16, gen)
        before = get_flat(list(policy.parameters()))
        stats = trpo.update(rollout)
        with torch.no_grad():
            kl = float(masked_mean(gaussian_kl(policy, rollout, 1), rollout.alive.float()))
        assert kl <= 0.01 + 1e-6
        assert kl == pytest.approx(stats.kl, abs=1e-6)
        moved = not torch.equal(before, get_flat(list(policy.parameters())))
        assert moved == stats.accepted


# --------------------------------------------------------------------------- the task and learning
def test_an_episode_ends_on_entering_the_target_with_reward_one():
    world = OpenWorld()
    task = GoalTask(NEAR_TARGET, 0, horizon=40)
    rollout = collect_episodes(world, tiny_markov(), task, 64, torch.Generator().manual_seed(0))
    assert set(rollout.returns.tolist()) <= {0.0, 1.0}
    assert torch.equal(rollout.returns.bool(), rollout.succeeded)
    assert 0 < rollout.succeeded.sum() < 64  # the tiny task is neither trivial nor hopeless
    for i in torch.nonzero(rollout.succeeded).flatten().tolist():
        t = int(torch.nonzero(rollout.success[i])[0])
        assert task.reached(rollout.states[i, t + 1 : t + 2]).item()
        assert not rollout.alive[i, t + 1 :].any() and rollout.lengths[i] == t + 1
    assert (rollout.lengths[~rollout.succeeded] == rollout.alive.shape[1]).all()


def test_random_targets_lie_in_free_space_away_from_the_start():
    from hmepol_cli.envs.slope import SlopeWorld

    world = SlopeWorld()
    boxes = [draw_target(world, 0, k, seed=3, side=0.2) for k in range(5)]
    assert boxes == [draw_target(world, 0, k, seed=3, side=0.2) for k in range(5)]  # from the seed
    assert len(set(boxes)) == 5
    for b in boxes:
        assert b.x1 - b.x0 == pytest.approx(0.2)
        corners = torch.tensor(
            [[x, y] for x in (b.x0, (b.x0 + b.x1) / 2, b.x1) for y in (b.y0, b.y1)]
        )
        assert not world.inside_wall(corners, torch.zeros(len(corners), dtype=torch.long)).any()
        s = world.start
        assert not (b.x0 < s.x1 and s.x0 < b.x1 and b.y0 < s.y1 and s.y0 < b.y1)
    same = make_tasks(
        world, 1, 50, "random", 5, 3, None
    )  # configurations sharing walls share targets
    assert [t.target for t in same] == boxes


def test_trpo_from_scratch_raises_the_return_on_a_tiny_goal_task():
    world = OpenWorld()
    task = GoalTask(NEAR_TARGET, 0, horizon=25)
    policy = tiny_markov(seed=0)
    gen = torch.Generator().manual_seed(0)
    trpo = TRPO(policy, world, task.horizon, tiny_settings(), gen)
    returns = []
    for _ in range(14):
        rollout = collect_episodes(world, policy, task, 32, gen)
        returns.append(float(rollout.returns.mean()))
        trpo.update(rollout)
    before, after = sum(returns[:2]) / 2, sum(returns[-2:]) / 2
    assert before < 0.35 and after > before + 0.4, returns


def test_a_recursive_policy_carries_its_history_through_the_episode_and_fine_tunes():
    world = OpenWorld()
    task = GoalTask(NEAR_TARGET, 0, horizon=25)
    policy = tiny_recursive()
    gen = torch.Generator().manual_seed(0)
    rollout = collect_episodes(world, policy, task, 8, gen)
    # h'_{-1} = 0 at the episode start only; afterwards each step reads the previous step's h'_t.
    assert torch.equal(rollout.histories[:, 0], torch.zeros(8, policy.history_size))
    with torch.no_grad():
        history = policy.initial_history(8)
        for t in range(rollout.histories.shape[1]):
            torch.testing.assert_close(rollout.histories[:, t], history)
            mean, history = policy.step(rollout.states[:, t], history)
            torch.testing.assert_close(rollout.means[:, t], mean)
    assert rollout.histories[:, 1:].abs().sum() > 0
    for bptt in (1, 3, None):
        policy = tiny_recursive()
        trpo = TRPO(
            policy, world, task.horizon, tiny_settings(bptt=bptt), torch.Generator().manual_seed(0)
        )
        for _ in range(2):
            stats = trpo.update(collect_episodes(world, policy, task, 8, gen))
            assert stats.kl <= 0.02 + 1e-6 and torch.isfinite(torch.tensor(stats.value_loss))
        assert all(torch.isfinite(p).all() for p in policy.parameters())


# --------------------------------------------------------------------------- the run
def _compose(*overrides: str):
    from hmepol_cli.cli import compose

    return compose("finetune", list(overrides))


TINY = [
    "epochs=2",
    "episodes=3",
    "horizon=15",
    "targets=2",
    "progress=false",
    "value_epochs=1",
    "policy.hidden=[8]",
]


def _fake_run(tmp_path: Path) -> Path:
    """A pre-training run directory as `hmepol train` leaves it (config, run info, checkpoint)."""
    run_dir = tmp_path / "pretrained"
    cfg = OmegaConf.create(
        {
            "env": {"name": "slope", "wind": 0.4},
            "algo": {"name": "hmepol"},
            "policy": {"name": "recursive", "hidden": [8], "encoder_hidden": [8], "history_size": 4,
                       "bptt": "1", "init_log_std": -0.5},
        }
    )  # fmt: skip
    atomic_write_text(run_dir / CONFIG, OmegaConf.to_yaml(cfg))
    write_json(run_dir / RUN_INFO, {"status": "finished", "epochs_done": 1})
    torch.manual_seed(5)
    policy = RecursivePolicy(
        2, 2, hidden=[8], encoder_hidden=[8], history_size=4, init_log_std=-0.5
    )
    state = {"policy": policy.state_dict(), "epoch": 1, "state_dim": 2, "action_dim": 2}
    save_checkpoint(run_dir / CHECKPOINT, state)
    return run_dir


def test_finetune_writes_one_row_per_epoch_target_and_configuration(tmp_path):
    cfg = _compose(*TINY, f"output_dir={tmp_path / 'a'}")
    out = finetune(cfg)
    df = pd.read_csv(out / FINETUNE_CSV)
    assert list(df.columns[: len(REQUIRED_COLUMNS)]) == REQUIRED_COLUMNS
    assert len(df) == 2 * 2 * 2  # slope's two configurations x two targets x two epochs
    assert sorted(df.groupby(["config", "target"]).epoch.apply(list).tolist()) == [[0, 1]] * 4
    assert (df.init == "none").all() and (df.algo_init == "scratch").all() and (df.seed == 0).all()
    assert df["return"].between(0, 1).all() and (df.kl <= 0.01 + 1e-6).all()
    again = pd.read_csv(finetune(_compose(*TINY, f"output_dir={tmp_path / 'b'}")) / FINETUNE_CSV)
    pd.testing.assert_frame_equal(df.drop(columns="seconds"), again.drop(columns="seconds"))


def test_finetune_from_a_pretrained_recursive_run(tmp_path):
    run_dir = _fake_run(tmp_path)
    cfg = _compose(
        *TINY, f"init={run_dir}", "config=1", "policy.bptt=full", f"output_dir={tmp_path / 'out'}"
    )
    df = pd.read_csv(finetune(cfg) / FINETUNE_CSV)
    assert len(df) == 2 * 2 and (df.config == 1).all() and (df.config_name == "north slope").all()
    assert (df.algo_init == "hmepol").all() and (df.init == str(run_dir.resolve())).all()


@pytest.mark.parametrize(
    "override, message",
    [
        ("max_kl=-1", "max_kl=-1"),
        ("gamma=1.5", "gamma=1.5"),
        ("policy.bptt=zero", "policy.bptt='zero'"),
        ("goal=somewhere", "goal='somewhere'"),
        ("epochs=0", "epochs=0"),
        ("config=7", "config=7"),
        ("env=moon", "moon"),
        ("env.name=corridor", "env=corridor"),
        ("init=/no/such/run", "/no/such/run"),
        ("goal_size=5", "goal_size=5"),
    ],
)
def test_bad_settings_are_refused_in_one_line(tmp_path, override, message):
    with pytest.raises(ConfigError) as error:
        finetune(_compose(*TINY, override, f"output_dir={tmp_path}"))
    assert message in str(error.value) and "\n" not in str(error.value)


def test_the_config_file_holds_the_thesis_like_defaults():
    cfg = _compose()
    s = trpo_settings(cfg, bptt=1)
    assert (cfg.init, cfg.goal, cfg.targets, cfg.horizon, cfg.epochs) == (
        "none",
        "random",
        5,
        400,
        50,
    )
    assert (s.max_kl, s.cg_iters, s.bptt, cfg.policy.name) == (0.01, 10, 1, "markov")
    assert cfg.env is None and cfg.config is None and cfg.policy.bptt is None
