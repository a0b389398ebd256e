"""``train.imitation_augment``: cloning rows at the DAgger phase's states with the evaders' velocities redrawn,
observed as the env would and labelled by the teacher (``Trainer._augment``, ``CloneBuffer``)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from runtime.spec import Role, SpecError
from training.config import ExperimentConfig
from training.maddpg import CloneBuffer
from training.train import Trainer, _EnvView, full_speed_labels

from test_imitation import assert_same_actors, interrupt_polish_at


def _cfg(**train) -> ExperimentConfig:
    return ExperimentConfig.from_dict({
        "name": "augment_check",
        "spec": {"team": {"n_pursuers": 2, "n_scouts": 1, "n_evaders": 2}},
        "train": {"steps": 40, "n_envs": 6, "seed": 0, "batch_size": 64, "warmup_steps": 10, "threads": 1,
                  "log_every": 100, "checkpoint_every": 100000, "checkpoint_buffer": False,
                  "teacher": "classical", "imitation_steps": 40, "imitation_batch": 128, "imitation_updates": 1,
                  **train}})


@pytest.mark.parametrize("train, field", [
    ({"imitation_augment": -0.1}, "train.imitation_augment"),
    ({"imitation_augment": 1.0}, "train.imitation_augment"),
    ({"imitation_augment": float("nan")}, "train.imitation_augment"),
    ({"imitation_augment": 0.5, "imitation_steps": 0}, "train.imitation_augment"),
])
def test_bad_augment_settings_name_the_field(train, field):
    with pytest.raises(SpecError, match=field.replace(".", r"\.")):
        _cfg(**train)


def test_augmented_rows_are_the_states_with_new_evader_velocities_and_the_teachers_labels(tmp_path):
    cfg = _cfg(imitation_augment=0.5)
    tr = Trainer(cfg, tmp_path / "run")
    spec, env = cfg.spec, tr.env
    obs = env.reset()
    tr._actions(obs)  # one DAgger step's actions: one augmented row per env
    assert len(tr.clone_buffer) == cfg.train.n_envs
    aug = tr.clone_buffer.obs[:len(tr.clone_buffer)].double().numpy()
    lab = tr.clone_buffer.teach[:len(tr.clone_buffer)].double().numpy()
    nt, ne = spec.team.n_team, spec.team.n_evaders
    lay = spec.layout(Role.PURSUER)
    tgt = lay["targets"]
    cols = np.arange(tgt.start, tgt.start + tgt.size).reshape(ne, len(tgt.columns))
    vcols = cols[:, 2:4]
    p = spec.team.indices(Role.PURSUER)[0]
    # the pursuers see the targets where they are, moving at the redrawn velocities, within the evaders' top speed
    new_v = aug[:, p, vcols]  # [B, E, 2]
    assert not np.allclose(new_v, obs[:, p, vcols])
    assert (np.linalg.norm(new_v, axis=-1) <= spec.evader.max_speed + 1e-6).all()
    np.testing.assert_allclose(aug[:, p, cols[:, :2]], obs[:, p, cols[:, :2]], atol=1e-5)
    keep = np.ones(lay.dim, dtype=bool)
    keep[vcols.ravel()] = False
    np.testing.assert_allclose(aug[:, :nt, :lay.dim][..., keep], obs[:, :nt, :lay.dim][..., keep], atol=1e-5)
    # the labels are the teacher's on the world with those velocities
    vel = env.state.vel.copy()
    vel[:, nt:] = new_v
    view = _EnvView(spec, dataclasses.replace(env.state, vel=vel))
    want = full_speed_labels(np.asarray(tr.teacher.act(aug, view), dtype=np.float64))
    np.testing.assert_allclose(lab, want, atol=1e-5)
    # and they are not the labels of the real velocities: the lead follows the target's velocity
    real = full_speed_labels(np.asarray(tr.teacher.act(obs, env), dtype=np.float64))
    assert not np.allclose(lab[:, p], real[:, p], atol=1e-3)


def test_cloning_batches_mix_in_the_share_and_a_run_without_it_is_unchanged(tmp_path):
    plain = Trainer(_cfg(), tmp_path / "plain")
    assert plain.clone_buffer is None
    plain.run(progress=False)
    again = Trainer(_cfg(imitation_augment=0.0), tmp_path / "again")
    again.run(progress=False)
    assert_same_actors(plain.agent.to_actors(), again.agent.to_actors())
    aug = Trainer(_cfg(imitation_augment=0.25), tmp_path / "aug")
    aug.run(progress=False)
    assert len(aug.clone_buffer) == 40 * 6
    o, t = aug._clone_sample(aug.sample_gen)
    assert o.shape[0] == t.shape[0] == 128
    changed = any(not torch.equal(p, q) for x, y in zip(plain.agent.to_actors(), aug.agent.to_actors())
                  for p, q in zip(x.state_dict().values(), y.state_dict().values()))
    assert changed


def test_clone_buffer_wraps_and_round_trips():
    buf = CloneBuffer(5, 2, 3)
    for k in range(3):
        buf.add(np.full((2, 2, 3), k), np.full((2, 2, 2), -k))
    assert len(buf) == 5
    sd = buf.state_dict()
    assert sd["obs"][:, 0, 0].tolist() == [0, 1, 1, 2, 2]  # the oldest first, the newest kept
    other = CloneBuffer(5, 2, 3)
    other.load_state_dict(sd)
    assert torch.equal(other.state_dict()["teach"], sd["teach"])
    with pytest.raises(ValueError, match="empty clone buffer"):
        CloneBuffer(4, 2, 3).sample_fields(2, torch.Generator(), ("obs", "teach"))


def test_a_run_with_augmented_rows_interrupted_in_its_polish_resumes_exactly(tmp_path, monkeypatch):
    base = dict(imitation_augment=0.5, imitation_polish_steps=20, checkpoint_buffer=True)
    full = Trainer(_cfg(**base), tmp_path / "full")
    full.run(progress=False)
    interrupt_polish_at(monkeypatch, 9)
    first = Trainer(_cfg(**base), tmp_path / "cut")
    assert first.run(progress=False).interrupted and first.polished == 8
    assert (tmp_path / "cut" / "checkpoints" / "clone_buffer.pt").is_file()
    monkeypatch.undo()
    again = Trainer(_cfg(**base), tmp_path / "cut", resume=True)
    assert len(again.clone_buffer) == len(full.clone_buffer)
    again.run(progress=False)
    assert_same_actors(again.agent.to_actors(), full.agent.to_actors())
