"""The commands behind results/c_export_report.md's per-actor parity table and int8 flight row."""
from __future__ import annotations

import numpy as np

from firmware_export.c_report import parity_rows
from firmware_export.int8_team import Int8Team, compare
from firmware_export.quantize import int8_forward
from runtime.policy import read_manifest
from runtime_fixtures import exported


def test_parity_rows_cover_every_actor_with_consistent_figures():
    _, models, _ = exported()
    rows = parity_rows(models, quant="float", n_obs=300)
    assert [r.agent for r in rows] == [a.id for a in read_manifest(models).agents]
    for r in rows:
        assert r.max_abs_diff == max(r.random_max, r.recorded_max) <= 1e-5
        assert 0 <= r.p99 <= r.max_abs_diff


def test_the_int8_team_flies_the_c_arithmetic_and_is_evaluated_beside_float():
    _, models, _ = exported()
    team = Int8Team(models, calib_obs=400)
    spec = read_manifest(models).spec
    assert [i for i, _, _ in team.layers] == list(range(spec.team.n_team))
    obs = np.random.default_rng(0).uniform(-1, 1, (5, spec.n_agents, spec.max_obs_dim))
    act = team.act(obs)
    i, dim, ql = team.layers[3]
    np.testing.assert_array_equal(act[:, 3], int8_forward(ql, obs[:, 3, :dim]))
    assert not act[:, spec.team.n_team:].any()
    from training.config import ExperimentConfig
    res = compare(models, episodes=2, n_envs=2, calib_obs=400, cfg=ExperimentConfig(spec=spec))
    assert set(res) == {"float", "int8w"} and all(res[k]["episodes"] == 2 for k in res)
