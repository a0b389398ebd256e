"""``swarm-train crossplay``: every source's pursuers against every source's evaders, the classical row."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from cli_fixtures import in_process
from training.learned_eval import evaluate_learned

ROOT = Path(__file__).resolve().parent.parent
A, B = "models/paper_role_based", "models/role_based_int8"  # one spec: the paper setting's team


def test_crossplay_matrix_diagonal_is_self_play_and_classical_row(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    js, md = tmp_path / "cp.json", tmp_path / "cp.md"
    rc, out, err = in_process(capsys, "crossplay", A, B, "--episodes", "2", "--n-envs", "2", "--seed", "7",
                              "--json", str(js), "--md", str(md), "--no-progress")
    assert rc == 0, err
    doc = json.loads(js.read_text())
    assert doc["names"] == ["paper_role_based", "role_based_int8"]
    m = doc["matrix"]["mean_min_dist"]
    assert len(m) == 2 and all(len(r) == 2 for r in m)
    # the diagonal is what `evaluate --evader learned` reports; the classical row meets the same evaders
    for i, src in enumerate((A, B)):
        ref = evaluate_learned(models=src, evader="learned", episodes=2, seed=7, n_envs=2, progress=False)
        assert m[i][i] == ref["mean_min_dist"]
        assert doc["matrix"]["tracking_rate"][i][i] == ref["tracking_rate"]
        assert doc["classical"]["mean_min_dist"][i] == ref["classical"]["mean_min_dist"]
    assert m[0][1] != m[0][0]  # off-diagonal cells are other pairings, not copies
    assert doc["pursuer_mean"]["mean_min_dist"][0] == pytest.approx((m[0][0] + m[0][1]) / 2)
    assert doc["evader_mean"]["mean_min_dist"][1] == pytest.approx((m[0][1] + m[1][1]) / 2)
    assert "pursuers \\ evaders" in out and "classical" in out and f"{m[0][1]:.3f}" in out
    text = md.read_text()
    assert "| pursuers \\ evaders | paper_role_based | role_based_int8 | row mean |" in text
    assert f"| classical | {doc['classical']['mean_min_dist'][0]:.3f} |" in text


@pytest.mark.parametrize("args, needle", [
    ([A, "models/multi_target"], "cross-play needs the same team"),
    ([A, "configs"], "neither a training run"),
    (["models/none_*"], "matches no folder"),
])
def test_crossplay_bad_sources_exit_2(capsys, monkeypatch, args, needle):
    monkeypatch.chdir(ROOT)
    rc, _, err = in_process(capsys, "crossplay", *args, "--episodes", "1", "--n-envs", "1", "--no-progress")
    assert rc == 2 and needle in err and "Traceback" not in err
