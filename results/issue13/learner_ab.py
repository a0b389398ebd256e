"""Short trainings of the same configs by two trees of this repository, compared bit for bit, and their times.

    .venv/bin/python results/issue13/learner_ab.py REV [--repeats 2] [--out runs/learner_ab]

REV (a commit) is checked out into a git worktree under OUT; the working tree is the other side. Each side trains
two short configs derived here from the shipped ones (role_based: 400 env steps of which 250 DAgger, no ES;
paper_role_based: 300 env steps of MADDPG), seed 0, one after the other (never both at once), once untimed (numba
compiles its kernels into each tree's cache) and then ``repeats`` times alternately; then every ``.pt`` file of the first repeat is compared tensor by tensor (NaN equal to NaN) and the
``train_time_s`` of each run printed. A learner change that claims to compute the same updates must print
"identical" for every file.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
SHORT = {"role_based": {"steps": 400, "imitation_steps": 250, "es_iterations": 0, "warmup_steps": 50,
                        "checkpoint_every": 200},
         "paper_role_based": {"steps": 300}}


def _toml(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return repr(value)


def short_config(name: str, out: Path) -> Path:
    """configs/NAME.toml with ``SHORT[name]`` in its [train] table, written to OUT/NAME_short.toml."""
    cfg = tomllib.loads((ROOT / "configs" / f"{name}.toml").read_text())
    cfg.setdefault("train", {}).update(SHORT[name])
    lines = []

    def emit(table: dict, prefix: str) -> None:
        scalars = {k: v for k, v in table.items() if not isinstance(v, dict)}
        if prefix and scalars:
            lines.append(f"[{prefix}]")
        lines.extend(f"{k} = {_toml(v)}" for k, v in scalars.items())
        for k, v in table.items():
            if isinstance(v, dict):
                emit(v, f"{prefix}.{k}" if prefix else k)

    emit(cfg, "")
    path = out / f"{name}_short.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def train(tree: Path, config: Path, run: Path) -> float:
    """One training by the code of ``tree`` (its packages first on the path), with this interpreter."""
    if run.exists():
        subprocess.run(["rm", "-rf", str(run)], check=True)
    code = ("import sys; sys.path.insert(0, sys.argv[1]); import training.cli as c; "
            "sys.argv = ['swarm-train', 'train', '--config', sys.argv[2], '--out', sys.argv[3], '--seed', '0']; "
            "c.main()")
    subprocess.run([sys.executable, "-c", code, str(tree), str(config), str(run)], check=True, cwd=tree,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return float(json.loads((run / "summary.json").read_text())["train_time_s"])


def differences(a, b, path: str = "") -> list[str]:
    """Paths where two loaded files differ: tensors and arrays bit for bit (NaN equal to NaN), other leaves by
    ``==``; a file's ``meta`` (the tree's git revision, the run's folder) and a checkpoint's ``elapsed`` (wall time)
    are not compared."""
    if path in ("/meta", "/elapsed"):
        return []
    if isinstance(a, np.ndarray):
        return [] if a.shape == b.shape and np.array_equal(a, b, equal_nan=a.dtype.kind == "f") else [path]
    if isinstance(a, dict):
        return [d for k in a for d in (differences(a[k], b[k], f"{path}/{k}") if k in b else [f"{path}/{k} missing"])]
    if isinstance(a, (list, tuple)):
        return [d for i, (u, v) in enumerate(zip(a, b)) for d in differences(u, v, f"{path}[{i}]")]
    if torch.is_tensor(a):
        same = a.shape == b.shape and torch.equal(torch.nan_to_num(a, nan=7.5), torch.nan_to_num(b, nan=7.5))
        return [] if same else [path]
    return [] if a == b or (a != a and b != b) else [path]  # (a float NaN is not equal to itself)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("rev", help="the commit to compare the working tree with")
    ap.add_argument("--repeats", type=int, default=2, help="trainings per side and config, alternately")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "learner_ab")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    other = args.out / "tree"
    if other.exists():
        subprocess.run(["git", "worktree", "remove", "--force", str(other)], cwd=ROOT, check=False)
    subprocess.run(["git", "worktree", "add", "--detach", "--force", str(other), args.rev], cwd=ROOT, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    sides = {"rev": other, "working": ROOT}
    try:
        for name in SHORT:
            config = short_config(name, args.out)
            times: dict[str, list[float]] = {side: [] for side in sides}
            for r in range(-1, args.repeats):  # run -1 untimed: numba fills each tree's kernel cache
                for side, tree in sides.items():
                    t = train(tree, config, args.out / f"{name}_{side}_{max(r, 0)}")
                    if r >= 0:
                        times[side].append(t)
            print(f"{name}: train_time_s {args.rev} {times['rev']}, working tree {times['working']}")
            for f in sorted((args.out / f"{name}_rev_0").rglob("*.pt")):
                g = args.out / f"{name}_working_0" / f.relative_to(args.out / f"{name}_rev_0")
                bad = differences(torch.load(f, weights_only=False), torch.load(g, weights_only=False))
                print(f"  {f.relative_to(args.out / f'{name}_rev_0')}: {'identical' if not bad else bad[:5]}")
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(other)], cwd=ROOT, check=False)


if __name__ == "__main__":
    main()
