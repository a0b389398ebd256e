import json

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from firmware_export import onnx_export
from firmware_export.observations import random_observations
from firmware_export.onnx_export import ExportError, export_run, flown_observations, sha256_file
from runtime.spec import Role, SwarmSpec
from runtime_fixtures import exported, make_run
from training.checkpoint import load_actors


def test_export_writes_checked_models_and_manifest():
    run, models, manifest = exported()
    spec = SwarmSpec()
    on_disk = json.loads((models / "manifest.json").read_text())
    assert on_disk == json.loads(json.dumps(manifest))
    assert on_disk["format"] == 1 and on_disk["spec_hash"] == spec.hash
    assert SwarmSpec.from_dict(on_disk["spec"]).hash == spec.hash
    assert on_disk["config"] == {"note": "random-initialised test actors"}
    assert on_disk["evaluation"] == {"tracking_rate": 0.5}
    assert [a["id"] for a in on_disk["agents"]] == list(spec.team.agent_ids())
    for entry, role in zip(on_disk["agents"], spec.roles):
        assert set(entry) == {"id", "role", "file", "sha256", "obs_dim"}
        path = models / entry["file"]
        assert entry["sha256"] == sha256_file(path) and entry["role"] == role.label
        assert entry["obs_dim"] == spec.obs_dim(role)
        model = onnx.load(str(path))
        onnx.checker.check_model(model, full_check=True)
        assert not any(init.data_location == onnx.TensorProto.EXTERNAL for init in model.graph.initializer)
        meta = {p.key: p.value for p in model.metadata_props}
        assert meta == {"spec_hash": spec.hash, "role": role.label, "agent_id": entry["id"],
                        "spec_json": json.dumps(spec.to_dict(), sort_keys=True),
                        "obs_dim": str(spec.obs_dim(role)), "act_dim": "2"}
        assert min(o.version for o in model.opset_import if o.domain in ("", "ai.onnx")) >= 17
        (inp,), (out,) = model.graph.input, model.graph.output
        assert inp.name == "obs" and out.name == "action"
        dims = [d.dim_param or d.dim_value for d in inp.type.tensor_type.shape.dim]
        assert isinstance(dims[0], str) and dims[1] == spec.obs_dim(role)
        assert [d.dim_value for d in out.type.tensor_type.shape.dim][1] == 2
    figures = on_disk["parity"]["agents"]
    assert on_disk["parity"]["n_random"] == 10_000 and on_disk["parity"]["n_recorded"] == 10_000
    assert all(v <= 1e-5 for f in figures.values() for v in f.values())


def test_parity_against_torch_on_random_and_recorded_observations():
    run, models, _ = exported()
    spec, agents, _ = load_actors(run)
    actors = [a for _, _, a in agents]
    recorded = flown_observations(spec, actors, 10_000, seed=7)
    rng = np.random.default_rng(3)
    for (aid, role, actor), rec in zip(agents, recorded):
        sess = ort.InferenceSession(str(models / f"{aid}.onnx"), providers=["CPUExecutionProvider"])
        rand = random_observations(spec, role, 10_000, rng)
        assert rec.shape == (10_000, spec.obs_dim(role)) and np.isfinite(rec).all()
        for obs in (rand, rec):
            got = sess.run(["action"], {"obs": obs})[0]
            with torch.no_grad():
                want = actor(torch.from_numpy(obs)).numpy()
            assert np.max(np.abs(got - want)) <= 1e-5
    # recorded observations are real flight states: the pursuers know the targets (full observability)
    t = spec.layout(Role.PURSUER)["targets"]
    assert np.all(recorded[0][:, t.slice].reshape(-1, spec.team.n_evaders, 6)[..., 5] == 1.0)


def test_parity_failure_is_an_error_and_writes_nothing(tmp_path, monkeypatch):
    spec = SwarmSpec.from_dict({"team": {"n_pursuers": 1, "n_scouts": 0, "n_evaders": 1}})
    run = make_run(tmp_path / "run", spec)
    real = onnx_export._with_weights

    def broken(template, actor):
        model = real(template, actor)
        b = model.graph.initializer[-1]
        arr = onnx.numpy_helper.to_array(b).copy()
        arr += 1e-3
        b.CopyFrom(onnx.numpy_helper.from_array(arr, b.name))
        return model

    monkeypatch.setattr(onnx_export, "_with_weights", broken)
    with pytest.raises(ExportError, match="differ"):
        export_run(run, tmp_path / "models", n_random=1000, n_recorded=1000)
    assert not (tmp_path / "models").exists()


def test_missing_run_is_a_named_error_and_cli_exits_nonzero(tmp_path, capsys):
    with pytest.raises(ExportError, match="no actor checkpoint"):
        export_run(tmp_path / "nope", tmp_path / "out")
    import argparse
    args = argparse.Namespace(run=str(tmp_path / "nope"), out=str(tmp_path / "out"), random=10, recorded=10, seed=0)
    assert onnx_export.run_onnx_command(args) == 2
    assert "no actor checkpoint" in capsys.readouterr().err
