"""``train.teacher`` / ``imitation_steps`` / ``imitation_weight``: the classical team as a teacher (DAgger, then
TD3+BC), tested on the learner and on a short run."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from runtime.spec import Role, SpecError
from training.baselines import ClassicalPursuers, FleeingEvaders, TeamPolicy
from training.config import ExperimentConfig, TrainConfig
from training.env import PursuitEnv
from training.learned_eval import load_learned
from training.maddpg import MADDPG, ReplayBuffer
from training.train import CSV_COLUMNS, Trainer


def _cfg(**train) -> ExperimentConfig:
    return ExperimentConfig.from_dict({
        "name": "imitation_check",
        "spec": {"team": {"n_pursuers": 2, "n_scouts": 1, "n_evaders": 1}},
        "train": {"steps": 300, "n_envs": 8, "seed": 0, "batch_size": 128, "warmup_steps": 20, "threads": 1,
                  "log_every": 100, "checkpoint_every": 100000, "checkpoint_buffer": False, **train}})


@pytest.mark.parametrize("train, field", [
    ({"teacher": "expert"}, "train.teacher"),
    ({"imitation_steps": 100}, "train.teacher = 'classical'"),
    ({"imitation_weight": 1.0}, "train.teacher = 'classical'"),
    ({"teacher": "classical", "imitation_steps": 999}, "train.imitation_steps"),
    ({"teacher": "classical", "imitation_weight": -1.0}, "train.imitation_weight"),
    ({"teacher": "classical", "evaders": "static"}, "train.teacher"),
    ({"teacher": "classical", "teacher_separation_gain": -1.0}, "train.teacher_separation_gain"),
    ({"teacher": "classical", "teacher_separation_gain": float("nan")}, "train.teacher_separation_gain"),
    ({"teacher": "classical", "teacher_assignment": "nearest"}, "train.teacher_assignment"),
    ({"teacher": "classical", "teacher_obstacle_softness": -0.1}, "train.teacher_obstacle_softness"),
    ({"teacher": "classical", "teacher_lead_time": -0.1}, "train.teacher_lead_time"),
    ({"teacher": "classical", "teacher_lead_others": float("inf")}, "train.teacher_lead_others"),
    ({"teacher": "classical", "teacher_lead_others": 9.0}, "train.teacher_lead_others"),
    ({"teacher": "classical", "teacher_side_lead": -0.1}, "train.teacher_side_lead"),
    ({"teacher": "classical", "teacher_side_lead": float("nan")}, "train.teacher_side_lead"),
    ({"teacher": "classical", "teacher_side_angle": 0.0}, "train.teacher_side_angle"),
    ({"teacher": "classical", "teacher_side_angle": 270.0}, "train.teacher_side_angle"),
    ({"teacher": "classical", "teacher_side_wall": 0.5}, "train.teacher_side_wall"),
    ({"teacher": "classical", "teacher_side_lead": 0.4, "teacher_side_wall": -0.5}, "train.teacher_side_wall"),
    ({"teacher": "classical", "teacher_side_lead": 0.4, "teacher_side_wall": float("inf")}, "train.teacher_side_wall"),
    ({"teacher": "classical", "teacher_scout_sweep": -0.1}, "train.teacher_scout_sweep"),
    ({"teacher": "classical", "teacher_scout_sweep": float("nan")}, "train.teacher_scout_sweep"),
    ({"teacher": "classical", "teacher_scout_sweep": 3.0}, "train.teacher_scout_sweep"),
    ({"teacher": "classical", "teacher_scout_sweep_mode": "spiral"}, "train.teacher_scout_sweep_mode"),
    ({"teacher": "classical", "teacher_scout_sweep_clear": 1.0}, "train.teacher_scout_sweep_clear"),
    ({"teacher": "classical", "teacher_scout_sweep": 0.5, "teacher_scout_sweep_clear": -1.0},
     "train.teacher_scout_sweep_clear"),
])
def test_bad_teacher_settings_name_the_field(train, field):
    with pytest.raises(SpecError, match=field.replace("(", r"\(").replace(".", r"\.")):
        _cfg(**train)


def test_imitation_updates_regress_the_actors_onto_the_teacher_and_leave_the_paper_loss_alone():
    cfg = _cfg(teacher="classical", imitation_steps=100)
    spec, tc = cfg.spec, cfg.train
    g = torch.Generator().manual_seed(0)
    k, n, d = 256, spec.n_agents, spec.max_obs_dim
    obs = torch.rand(k, n, d, generator=g) * 2 - 1
    teach = torch.tanh(3 * obs[..., :2] - obs[..., 2:4])  # a smooth function of the observation
    batch = (obs, torch.zeros(k, n, 2), torch.zeros(k, n), obs, torch.zeros(k, n, 2), teach)
    agent = MADDPG(spec, tc)
    first = agent.update(batch, imitation=True)["imitation_mse"]
    for _ in range(300):
        last = agent.update(batch, imitation=True)["imitation_mse"]
    assert last < 0.2 * first, (first, last)
    # without a teacher weight the actor loss is the paper's: the teacher column changes nothing
    plain = dataclasses.replace(tc, teacher="none", imitation_steps=0)
    a, b = MADDPG(spec, plain), MADDPG(spec, plain)
    la = a.update(batch)
    lb = b.update(batch[:5])
    assert la == lb and "imitation_mse" not in la
    # TD3+BC after the imitation: the loss reports the distance to the teacher; rows without one are ignored
    bc = MADDPG(spec, dataclasses.replace(tc, imitation_weight=2.5))
    half = teach.clone()
    half[: k // 2] = float("nan")
    out = bc.update((*batch[:5], half))
    assert np.isfinite(out["imitation_mse"]) and np.isfinite(out["actor_loss"])
    with pytest.raises(ValueError, match="teacher"):
        MADDPG(spec, tc).update(batch[:5], imitation=True)


def test_a_short_dagger_run_brings_the_actors_close_to_the_classical_team(tmp_path):
    cfg = _cfg(teacher="classical", imitation_steps=300, noise_std=0.1, noise_std_final=0.05)
    spec = cfg.spec
    trainer = Trainer(cfg, tmp_path / "run")
    teacher = TeamPolicy(ClassicalPursuers(), FleeingEvaders())
    # states the run never saw: the untrained actors against the teacher
    env = PursuitEnv(spec, cfg.rewards, n_envs=16, seed=123)
    obs = env.reset()
    states = []
    for _ in range(40):
        states.append((obs.copy(), teacher.act(obs, env)))
        obs, *_ = env.step(teacher.act(obs, env))

    def mse(policy) -> float:
        errs = [np.mean(np.sum((np.clip(policy.act(o, None), -1, 1) - np.clip(t, -1, 1)) ** 2, -1))
                for o, t in states]
        return float(np.mean(errs))

    class _Agent:
        def act(self, o, env):
            return trainer.agent.act(o).numpy()

    before = mse(_Agent())
    result = trainer.run(progress=False)
    assert result.env_steps == 300
    _, learned, _ = load_learned(run=tmp_path / "run")
    after = mse(learned)
    assert after < 0.5 * before, (before, after)
    buf = trainer.buffer
    assert torch.isfinite(buf.teach[: len(buf)]).all()  # every transition carries the teacher's action
    rows = (tmp_path / "run" / "metrics.csv").read_text().splitlines()
    header = rows[0].split(",")
    assert tuple(header) == CSV_COLUMNS
    last = dict(zip(header, rows[-1].split(",")))
    assert float(last["imitation_mse"]) < 0.5 and 0.0 <= float(last["teacher_share"]) < 0.5


def test_the_teacher_separation_gain_reaches_the_teacher_and_only_it(tmp_path):
    """The teacher flies ``ClassicalPursuers`` with ``train.teacher_separation_gain``; its labels of two pursuers
    crowding one evader are those of a classical team with that push, and differ from the default's, which stays
    the classical team every evaluation compares with."""
    trainer = Trainer(_cfg(teacher="classical", imitation_steps=100, teacher_separation_gain=1.0), tmp_path / "run")
    assert trainer.teacher.pursuer_team.separation_gain == 1.0
    assert ClassicalPursuers().separation_gain == 3.0 and TrainConfig().teacher_separation_gain == 3.0
    env = trainer.env
    obs = env.reset()
    s = env.state
    s.pos[:, 0], s.pos[:, 1], s.pos[:, 3] = [0.0, 0.1], [0.0, -0.1], [0.4, 0.0]  # two pursuers 0.2 m apart
    s.obstacle_pos[:] = 2.5  # far away
    got = trainer.teacher.act(obs, env)
    gentle, default = ClassicalPursuers(), ClassicalPursuers()
    gentle.separation_gain = 1.0
    np.testing.assert_allclose(got, TeamPolicy(gentle, FleeingEvaders()).act(obs, env))
    assert np.abs(got[:, :2] - default.act(obs, env)[:, :2]).max() > 0.05


def test_the_teacher_assignment_reaches_the_teacher_and_only_it(tmp_path):
    """``train.teacher_assignment = "local"``: the teacher's pursuers choose their targets from what each observes
    (``local_assign_targets``); the classical team every evaluation compares with keeps the central assignment."""
    cfg = _cfg(teacher="classical", imitation_steps=100, teacher_assignment="local")
    cfg = ExperimentConfig.from_dict({**cfg.to_dict(), "spec": {"team": {"n_pursuers": 3, "n_scouts": 2,
                                                                         "n_evaders": 2}}})
    trainer = Trainer(cfg, tmp_path / "run")
    assert trainer.teacher.pursuer_team.assignment == "local"
    assert trainer.teacher.pursuer_team.obstacle_side_softness == 0.0 == ClassicalPursuers().obstacle_side_softness
    soft = Trainer(_cfg(teacher="classical", imitation_steps=100, teacher_obstacle_softness=0.3), tmp_path / "soft")
    assert soft.teacher.pursuer_team.obstacle_side_softness == 0.3
    assert ClassicalPursuers().assignment == "central" and TrainConfig().teacher_assignment == "central"
    env = trainer.env
    obs = env.reset()
    local = ClassicalPursuers()
    local.separation_gain, local.assignment = trainer.tc.teacher_separation_gain, "local"
    np.testing.assert_allclose(trainer.teacher.act(obs, env), TeamPolicy(local, FleeingEvaders()).act(obs, env))
    central = ClassicalPursuers()
    central.separation_gain = trainer.tc.teacher_separation_gain
    # all three pursuers by evader 0, the scouts halfway: centrally (2 slots each) pursuer 2 goes for evader 1;
    # locally its group is the whole team of 5 (3 slots each), the scouts take evader 1's, and it stays
    s = env.state
    s.pos[:, :5] = [[-2.1, 0.0], [-1.9, 0.0], [-1.5, 0.5], [0.0, 0.5], [0.0, -0.5]]
    s.pos[:, 5:] = [[-2.0, 0.0], [2.0, 0.0]]
    s.obstacle_pos[:] = 2.5
    p_local, p_central = trainer.teacher.act(obs, env)[:, :3], TeamPolicy(central, FleeingEvaders()).act(obs, env)[:, :3]
    assert np.abs(p_local - p_central).max() > 0.05


def test_the_teacher_lead_times_reach_the_teacher_and_only_it(tmp_path):
    """``train.teacher_lead_time`` / ``teacher_lead_others``: of two pursuers on one evader that flies across them,
    the nearer aims ``teacher_lead_time`` ahead of it and the farther ``teacher_lead_others`` (each capped by its
    distance over its top speed, as the classical team's lead); the defaults are the classical team's one lead."""
    assert ClassicalPursuers().lead_time_others is None and ClassicalPursuers().lead_time_max == 0.6
    assert TrainConfig().teacher_lead_time == TrainConfig().teacher_lead_others == 0.6
    plain = Trainer(_cfg(teacher="classical", imitation_steps=100), tmp_path / "plain")
    assert plain.teacher.pursuer_team.lead_time_others is None
    trainer = Trainer(_cfg(teacher="classical", imitation_steps=100, teacher_lead_time=0.3, teacher_lead_others=0.9),
                      tmp_path / "duo")
    team = trainer.teacher.pursuer_team
    assert (team.lead_time_max, team.lead_time_others) == (0.3, 0.9)
    env = trainer.env
    obs = env.reset()
    s = env.state
    s.pos[:, 0], s.pos[:, 1], s.pos[:, 2], s.pos[:, 3] = [-1.0, 0.0], [-2.0, 1.5], [2.0, -2.0], [0.0, 0.0]
    s.vel[:, 3] = [0.0, 1.0]  # the evader flies up at 1 m/s
    s.obstacle_pos[:] = 2.5  # far away
    got = trainer.teacher.act(obs, env)[:, :2]
    far = np.hypot(2.0, 1.5)
    for i, goal in ((0, [0.0, 0.3]), (1, [0.0, min(far / env.spec.pursuer.max_speed, 0.9)])):
        want = np.asarray(goal) - s.pos[:, i]
        np.testing.assert_allclose(got[:, i], want / np.linalg.norm(want, axis=-1, keepdims=True), atol=1e-9)
    one = ClassicalPursuers()
    one.separation_gain, one.lead_time_max = trainer.tc.teacher_separation_gain, 0.3
    assert np.abs(got - TeamPolicy(one, FleeingEvaders()).act(obs, env)[:, :2]).max() > 0.05


def test_the_teacher_side_lead_shortens_the_look_ahead_on_a_target_running_sideways(tmp_path):
    """``train.teacher_side_lead`` / ``teacher_side_angle``: a pursuer whose target flies along the bearing from it
    leads by ``teacher_lead_time``; one whose target flies across it (90 degrees, past the 60 of the angle) by
    ``teacher_side_lead``; halfway in the angle's cosine, halfway between. The default is the classical team's one
    lead."""
    assert ClassicalPursuers().lead_side_time is None
    assert TrainConfig().teacher_side_lead is None
    assert Trainer(_cfg(teacher="classical", imitation_steps=100), tmp_path / "plain").teacher.pursuer_team \
        .lead_side_time is None
    trainer = Trainer(_cfg(teacher="classical", imitation_steps=100, teacher_side_lead=0.2, teacher_side_angle=60.0),
                      tmp_path / "side")
    # a run's config.toml leaves the None out (TOML has no null) and loads back as it was
    for run, want in (("plain", None), ("side", 0.2)):
        assert ExperimentConfig.from_toml(tmp_path / run / "config.toml").train.teacher_side_lead == want
    team = trainer.teacher.pursuer_team
    assert (team.lead_side_time, team.lead_side_angle) == (0.2, 60.0)
    spec = trainer.env.spec
    pp = np.array([[[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]])  # three pursuers at the origin, each on its own target
    ep = np.array([[[2.0, 0.0], [0.0, 2.0], [-2.0, 0.0]]])
    half = np.degrees(np.arccos(1 - (1 - np.cos(np.radians(60.0))) / 2))  # halfway in cosine: lead 0.4 s
    h = np.radians(half)
    ev = np.array([[[1.0, 0.0], [1.0, 0.0], [-np.cos(h), np.sin(h)]]])  # along, across, and `half` degrees off
    got = team._pursue(spec, pp, ep, ev, target=np.array([[0, 1, 2]]))
    for i, lead in enumerate((0.6, 0.2, 0.4)):
        want = ep[0, i] + ev[0, i] * lead
        np.testing.assert_allclose(got[0, i], want / np.linalg.norm(want), atol=1e-9)
    plain = ClassicalPursuers()._pursue(spec, pp, ep, ev, target=np.array([[0, 1, 2]]))
    np.testing.assert_allclose(plain[0, 0], got[0, 0], atol=1e-12)  # along the bearing: the classical team's lead
    assert np.abs(plain[0, 1:] - got[0, 1:]).max() > 0.05


def test_the_teacher_side_wall_keeps_the_full_lead_on_a_target_near_a_wall(tmp_path):
    """``train.teacher_side_wall``: the side lead applies to a target at least ``teacher_side_wall`` + 0.3 m from
    every wall, not to one within ``teacher_side_wall`` of a wall, and halfway in between it is half applied; along
    the bearing nothing changes. Off by default (the side lead everywhere)."""
    assert ClassicalPursuers().lead_side_wall is None and TrainConfig().teacher_side_wall is None
    trainer = Trainer(_cfg(teacher="classical", imitation_steps=100, teacher_side_lead=0.2, teacher_side_angle=60.0,
                           teacher_side_wall=0.5), tmp_path / "wall")
    assert ExperimentConfig.from_toml(tmp_path / "wall" / "config.toml").train.teacher_side_wall == 0.5
    team = trainer.teacher.pursuer_team
    assert team.lead_side_wall == 0.5 and team.lead_side_fade == 0.3
    spec = trainer.env.spec
    hw = spec.arena.half_width
    # four targets running across the line of sight (full side lead without the wall rule): in the open, 0.4 m from
    # the right wall, 0.65 m from it (halfway through the fade), and one running along the bearing near the wall
    ep = np.array([[[0.0, 1.0], [hw - 0.4, 1.0], [hw - 0.65, -1.0], [hw - 0.2, -2.0]]])
    pp = ep - np.array([[[0.0, 1.0], [0.0, 1.0], [0.0, 1.0], [0.0, 1.0]]])
    ev = np.array([[[1.0, 0.0], [1.0, 0.0], [1.0, 0.0], [0.0, 1.0]]])
    target = np.array([[0, 1, 2, 3]])
    got = team._pursue(spec, pp, ep, ev, target=target)
    for i, lead in enumerate((0.2, 0.6, 0.4, 0.6)):
        want = np.clip(ep[0, i] + ev[0, i] * lead, -hw, hw) - pp[0, i]
        np.testing.assert_allclose(got[0, i], want / np.linalg.norm(want), atol=1e-9)
    team.lead_side_wall = None  # the side lead everywhere: the target near the wall is led 0.2 s too
    everywhere = team._pursue(spec, pp, ep, ev, target=target)
    np.testing.assert_allclose(everywhere[0, [0, 3]], got[0, [0, 3]], atol=1e-12)
    assert np.abs(everywhere[0, 1] - got[0, 1]).max() > 0.05


def test_the_teacher_scout_sweep_keeps_the_scouts_moving_and_leaves_the_pursuers_alone(tmp_path):
    """``train.teacher_scout_sweep``: the teacher's scouts add a wish of that size to Lloyd's step, along their own
    velocity ("heading", none at rest) or counter-clockwise about the arena's centre ("orbit"); the pursuers' actions
    do not change. Off by default (Lloyd's step alone, the classical team's)."""
    assert ClassicalPursuers().scout_sweep is None and TrainConfig().teacher_scout_sweep is None
    trainer = Trainer(_cfg(teacher="classical", imitation_steps=100, teacher_scout_sweep=0.5), tmp_path / "sweep")
    tc = ExperimentConfig.from_toml(tmp_path / "sweep" / "config.toml").train
    assert (tc.teacher_scout_sweep, tc.teacher_scout_sweep_mode) == (0.5, "heading")
    team = trainer.teacher.pursuer_team
    assert (team.scout_sweep, team.scout_sweep_mode) == (0.5, "heading")
    pos = np.array([[[1.0, 0.0], [0.0, -2.0], [0.1, 0.0]]])
    vel = np.array([[[0.0, 0.3], [0.0, 0.0], [-0.6, 0.8]]])
    np.testing.assert_allclose(team._sweep(pos, vel, 3.0), [[[0.0, 0.5], [0.0, 0.0], [-0.3, 0.4]]], atol=1e-12)
    team.scout_sweep_mode = "orbit"  # tangent, counter-clockwise, faded in over the 0.5 m around the centre
    np.testing.assert_allclose(team._sweep(pos, vel, 3.0), [[[0.0, 0.5], [0.5, 0.0], [0.0, 0.1]]], atol=1e-12)
    team.scout_sweep_mode = "heading"
    # kept off the walls: none within 0.5 m of one, half at 0.65 m, all from 0.8 m (fade 0.3 m)
    team.scout_sweep_wall = 0.5
    near = np.array([[[2.6, 0.0], [0.0, -2.35], [0.0, 0.0]]])
    heading = np.array([[[0.0, 1.0], [1.0, 0.0], [1.0, 0.0]]])
    np.testing.assert_allclose(team._sweep(near, heading, 3.0), [[[0.0, 0.0], [0.25, 0.0], [0.5, 0.0]]], atol=1e-12)
    team.scout_sweep_wall = None
    # kept off the evaders (train.teacher_scout_sweep_clear): none within 1 m of one, half at 1.15 m
    trainer_c = Trainer(_cfg(teacher="classical", imitation_steps=100, teacher_scout_sweep=0.5,
                             teacher_scout_sweep_clear=1.0), tmp_path / "clear")
    clear = trainer_c.teacher.pursuer_team
    assert clear.scout_sweep_clear == 1.0
    scouts = np.array([[[2.0, 0.0], [0.0, 0.0], [-2.0, -2.0]]])
    evaders = np.array([[[0.0, 1.15], [-2.5, -2.5]]])  # 2.3, 1.15 and 0.71 m from the scouts
    np.testing.assert_allclose(clear._sweep(scouts, heading, 3.0, evaders), [[[0.0, 0.5], [0.25, 0.0], [0.0, 0.0]]],
                               atol=1e-12)
    env = trainer.env
    obs = env.reset()
    for _ in range(5):  # under way, so that the scouts fly at a velocity
        obs, *_ = env.step(ClassicalPursuers().act(obs, env))
    swept = team.act(obs, env)
    team.scout_sweep = None
    lloyd = team.act(obs, env)
    p, sc = list(env.spec.team.indices(Role.PURSUER)), list(env.spec.team.indices(Role.SCOUT))
    np.testing.assert_array_equal(swept[:, p], lloyd[:, p])  # the pursuers: unchanged
    assert np.abs(swept[:, sc] - lloyd[:, sc]).max() > 0.05
    # moving with the sweep: the scouts' actions lean along their velocity more than Lloyd's step alone does
    v = env.state.vel[:, sc]
    moving = np.linalg.norm(v, axis=-1) > 0.1

    def along(a: np.ndarray) -> np.ndarray:
        return ((a[:, sc] * v).sum(-1) / np.maximum(np.linalg.norm(v, axis=-1), 1e-9))[moving]
    assert moving.any() and along(swept).mean() > along(lloyd).mean()


def test_the_paper_configs_have_no_teacher():
    from pathlib import Path
    root = Path(__file__).resolve().parents[1]
    for name in ("paper_role_based", "paper_multi_target", "paper_flight"):
        tc = ExperimentConfig.from_toml(root / "configs" / f"{name}.toml").train
        assert tc.teacher == "none" and tc.imitation_steps == 0 and tc.imitation_weight == 0.0, name
    assert TrainConfig().teacher == "none"


def test_imitation_near_weight_weighs_the_rows_next_to_a_known_target():
    cfg = _cfg(teacher="classical", imitation_steps=100, imitation_near_weight=4.0, imitation_near_radius=0.5)
    spec = dataclasses.replace(cfg.spec, team=dataclasses.replace(cfg.spec.team, n_evaders=2))
    tc = cfg.train
    agent = MADDPG(spec, tc)
    k, n, d = 6, spec.n_agents, spec.max_obs_dim
    layout = spec.layout(spec.roles[0])
    f = layout["targets"]
    assert f.rows == 2
    dx, dy, known = (f.start + f.columns.index(c) for c in ("dx", "dy", "known"))
    obs = torch.zeros(k, n, d)
    obs[:, :, dx] = torch.tensor([0.3, 0.3, 0.6, -0.2, 0.0, 3.0]).view(k, 1)
    obs[:, :, dy] = torch.tensor([0.0, 0.45, 0.0, 0.2, 0.0, 0.0]).view(k, 1)
    obs[:, :, known] = torch.tensor([1.0, 1.0, 1.0, 1.0, 0.0, 1.0]).view(k, 1)
    second = f.start + len(f.columns)  # the second target row: near in row 5 only
    obs[5, :, second + f.columns.index("dx")] = 0.1
    obs[5, :, second + f.columns.index("known")] = 1.0
    w = agent.near_weights(obs)
    team = torch.tensor([4.0, 1.0, 1.0, 4.0, 1.0, 4.0])  # 0.3; 0.54 out; 0.6 out; 0.28; unknown; the 2nd row
    for i, role in enumerate(spec.roles):
        want = team if "targets" in spec.layout(role).names() else torch.ones(k)
        assert torch.equal(w[i], want), (i, role, w[i])
    # the loss is the weighted mean over the rows that have a teacher action
    mu = torch.zeros(n, k, 2)
    teach = torch.rand(k, n, 2, generator=torch.Generator().manual_seed(1))
    teach[0, :] = float("nan")
    sq = teach.transpose(0, 1).pow(2).sum(-1)
    has = torch.isfinite(sq)
    ww = torch.where(has, w, 0.0)
    want = (torch.nan_to_num(sq) * ww).sum(1) / ww.sum(1)
    assert torch.allclose(agent._bc_loss(mu, teach, obs), want)
    plain = MADDPG(spec, dataclasses.replace(tc, imitation_near_weight=1.0))
    assert plain._near is None
    assert torch.allclose(plain._bc_loss(mu, teach, obs), torch.nan_to_num(sq).sum(1) / has.sum(1))


def test_imitation_obstacle_weight_weighs_the_rows_next_to_an_obstacle():
    """Rows whose agent is within ``imitation_obstacle_radius`` of an obstacle's surface (centre distance minus the
    obstacle's radius minus its own) weigh ``imitation_obstacle_weight``; with the near-target weight, the product."""
    cfg = _cfg(teacher="classical", imitation_steps=100, imitation_obstacle_weight=3.0, imitation_obstacle_radius=0.3)
    spec, tc = cfg.spec, cfg.train
    agent = MADDPG(spec, tc)
    k, n, d = 4, spec.n_agents, spec.max_obs_dim
    obs = torch.zeros(k, n, d)
    for i, role in enumerate(spec.roles):
        f = spec.layout(role)["obstacles"]
        assert f.rows >= 2
        col = {c: [f.start + row * len(f.columns) + f.columns.index(c) for row in range(f.rows)] for c in f.columns}
        for row in range(1, f.rows):  # every obstacle but the first far away
            obs[:, i, col["dx"][row]], obs[:, i, col["radius"][row]] = 5.0, 0.4
        r = spec.per_agent("radius")[i]
        # the first: surface gaps 0.1 and 0.29 (near), 0.31 (not), and a radius-0 row (no obstacle) 0.2 away
        obs[:, i, col["dx"][0]] = torch.tensor([0.5 + r, 0.69 + r, 0.71 + r, 0.2 + r])
        obs[:, i, col["radius"][0]] = torch.tensor([0.4, 0.4, 0.4, 0.0])
    w = agent.near_weights(obs)
    assert torch.equal(w, torch.tensor([3.0, 3.0, 1.0, 1.0]).expand(n, k)), w
    # with the near-target weight 2 as well: a known target 0.2 m away in rows 0 and 2, for the pursuer team
    both = MADDPG(spec, dataclasses.replace(tc, imitation_near_weight=2.0))
    for i, role in enumerate(spec.roles):
        if "targets" in spec.layout(role).names():
            f = spec.layout(role)["targets"]
            obs[[0, 2], i, f.start + f.columns.index("dx")] = 0.2
            obs[[0, 2], i, f.start + f.columns.index("known")] = 1.0
    wb = both.near_weights(obs)
    for i, role in enumerate(spec.roles):
        sees = "targets" in spec.layout(role).names()
        want = torch.tensor([6.0, 3.0, 2.0, 1.0]) if sees else torch.tensor([3.0, 3.0, 1.0, 1.0])
        assert torch.equal(wb[i], want), (i, role, wb[i])
    plain = MADDPG(spec, dataclasses.replace(tc, imitation_obstacle_weight=1.0))
    assert plain._obstacle is None and plain._near is None
    # the walls counted too: rows 2 and 3 (no obstacle near) with the body 0.1 m and 0.31 m from a wall
    walls = MADDPG(spec, dataclasses.replace(tc, imitation_obstacle_walls=True))
    hw = spec.arena.half_width
    for i, role in enumerate(spec.roles):
        f = spec.layout(role)["self_pos"]
        r = spec.per_agent("radius")[i]
        obs[:, i, f.start:f.start + 2] = 0.0
        obs[2, i, f.start] = -(hw - r - 0.1)  # x: 0.1 m from the left wall
        obs[3, i, f.start + 1] = hw - r - 0.31  # y: 0.31 m from the top wall
    ww = walls.near_weights(obs)
    for i, role in enumerate(spec.roles):
        assert torch.equal(ww[i], torch.tensor([3.0, 3.0, 3.0, 1.0])), (i, role, ww[i])
    assert torch.equal(agent.near_weights(obs), torch.tensor([3.0, 3.0, 1.0, 1.0]).expand(n, k))  # walls off


@pytest.mark.parametrize("train, field", [
    ({"imitation_obstacle_weight": 0.0}, "train.imitation_obstacle_weight"),
    ({"imitation_obstacle_radius": float("nan")}, "train.imitation_obstacle_radius"),
    ({"imitation_obstacle_walls": True}, "train.imitation_obstacle_walls"),
    ({"imitation_near_weight": 0.0}, "train.imitation_near_weight"),
    ({"imitation_near_weight": float("inf")}, "train.imitation_near_weight"),
    ({"imitation_near_radius": -0.5}, "train.imitation_near_radius"),
])
def test_bad_near_weights_name_the_field(train, field):
    with pytest.raises(SpecError, match=field.replace(".", r"\.")):
        _cfg(teacher="classical", **train)


@pytest.mark.parametrize("train, field", [
    ({"teacher": "classical", "imitation_steps": 100, "imitation_polish_steps": -1}, "train.imitation_polish_steps"),
    ({"teacher": "classical", "imitation_steps": 100, "imitation_polish_steps": True}, "train.imitation_polish_steps"),
    ({"teacher": "classical", "imitation_steps": 100, "imitation_polish_steps": 2.5}, "train.imitation_polish_steps"),
    ({"teacher": "classical", "imitation_polish_steps": 10}, "train.imitation_polish_steps"),
])
def test_bad_polish_settings_name_the_field(train, field):
    with pytest.raises(SpecError, match=field.replace(".", r"\.")):
        _cfg(**train)


def test_kept_rows_puts_the_other_roles_actors_and_moments_back():
    """Cloning the team only (``clone_step(..., only)``) inside ``kept_rows(evaders)``: the team's actors learn,
    the evaders' weights and Adam moments are those from before, bit for bit (Adam's momentum alone would move
    them), with and without one actor per role."""
    for share in (True, False):
        cfg = _cfg(teacher="classical", imitation_steps=100, share_params=share)
        spec = cfg.spec
        agent = MADDPG(spec, cfg.train)
        g = torch.Generator().manual_seed(1)
        k, n, d = 256, spec.n_agents, spec.max_obs_dim
        obs = torch.rand(k, n, d, generator=g) * 2 - 1
        teach = torch.tanh(3 * obs[..., :2] - obs[..., 2:4])
        for _ in range(3):  # Adam has moments for every model before the block
            agent.clone_step(obs, teach)
        nt = spec.team.n_team
        ev = [agent.model_of[i] for i in range(nt, n)]
        tm = [agent.model_of[i] for i in range(nt)]
        before = [w.detach().clone() for w in agent.actors.parameters()]
        team = torch.zeros(n)
        team[:nt] = 1.0
        first = agent.clone_step(obs, teach, team)  # outside the block: the evaders' rows drift on momentum
        drifted = [w.detach().clone() for w in agent.actors.parameters()]
        assert any(not torch.equal(a[ev], b[ev]) for a, b in zip(drifted, before))
        st = agent.actor_opt.opt.state[agent.actor_opt.param]
        moments = {key: st[key].clone() for key in ("exp_avg", "exp_avg_sq")}
        with agent.kept_rows(range(nt, n)):
            for _ in range(20):
                last = agent.clone_step(obs, teach, team)
        assert last < first
        for a, b in zip(agent.actors.parameters(), drifted):
            assert torch.equal(a.detach()[ev], b[ev])  # as they were when the block began
            assert not torch.equal(a.detach()[tm], b[tm])  # the team's actors learned
        off = 0
        for p in agent.actor_opt.flat.params:
            nel = p.numel()
            for key, was in moments.items():
                now = st[key][off:off + nel].view_as(p)
                assert torch.equal(now[ev], was[off:off + nel].view_as(p)[ev]), key
                assert not torch.equal(now[tm], was[off:off + nel].view_as(p)[tm]), key
            off += nel


def test_polish_clones_the_team_after_dagger_and_resumes_exactly(tmp_path, monkeypatch):
    """``train.imitation_polish_steps``: that many cloning steps after the DAgger phase (``summary.json`` counts
    them); the team's actors differ from a run without them, the evaders' are the same (the last env step's one
    update is made on the same sample either way: the polish draws after it); and a run interrupted in the middle of
    its polish and resumed ends with the same actors, bit for bit."""
    base = dict(teacher="classical", imitation_steps=40, steps=40, batch_size=64, imitation_batch=128)
    plain = Trainer(_cfg(**base), tmp_path / "plain")
    plain.run(progress=False)
    full = Trainer(_cfg(**base, imitation_polish_steps=30), tmp_path / "full")
    full.run(progress=False)
    assert json.loads((tmp_path / "full" / "summary.json").read_text())["polish_steps"] == 30
    assert json.loads((tmp_path / "plain" / "summary.json").read_text())["polish_steps"] == 0
    nt = full.spec.team.n_team
    a_full, a_plain = full.agent.to_actors(), plain.agent.to_actors()
    for i, (x, y) in enumerate(zip(a_full, a_plain)):
        same = all(torch.equal(p, q) for p, q in zip(x.state_dict().values(), y.state_dict().values()))
        assert same == (i >= nt), i
    # interrupted after 12 polish steps, then resumed
    cut = _cfg(**base, imitation_polish_steps=30, checkpoint_buffer=True)
    interrupt_polish_at(monkeypatch, 13)
    first = Trainer(cut, tmp_path / "cut")
    assert first.run(progress=False).interrupted
    assert first.polished == 12
    monkeypatch.undo()
    again = Trainer(cut, tmp_path / "cut", resume=True)
    assert again.polished == 12
    again.run(progress=False)
    assert again.polished == 30
    assert_same_actors(again.agent.to_actors(), a_full)


def interrupt_polish_at(monkeypatch, step: int) -> None:
    """Make the ``step``-th team-only cloning step (the polish's) raise KeyboardInterrupt, as Ctrl-C would; every
    other cloning step runs as it is. ``monkeypatch.undo()`` puts ``MADDPG.clone_step`` back."""
    calls = {"n": 0}
    real = MADDPG.clone_step

    def interrupted(self, obs, teach, only=None):
        if only is not None:
            calls["n"] += 1
            if calls["n"] == step:
                raise KeyboardInterrupt
        return real(self, obs, teach, only)

    monkeypatch.setattr(MADDPG, "clone_step", interrupted)


def assert_same_actors(a, b) -> None:
    """Two lists of actors hold the same weights, bit for bit."""
    assert len(a) == len(b)
    for x, y in zip(a, b):
        for p, q in zip(x.state_dict().values(), y.state_dict().values()):
            assert torch.equal(p, q)
