"""``swarm-export``: export trained actors for deployment.

Each subcommand is one ``add_<name>(subparsers)`` function that registers its parser and sets ``func``;
``main`` runs it, prints ``CExportError``/``SpecError`` messages (which say how to fix the input) to stderr and
exits 2 without a traceback.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from firmware_export.cgen import DEFAULT_WEIGHTS_IN, QUANTS, TANHS, WEIGHTS_IN
from firmware_export.mlp_graph import CExportError
from runtime.cliutil import ArgumentParser, EXIT_USAGE, in_file, int_in, out_dir, seed
from runtime.spec import SpecError

MAX_OBS = 1_000_000
"""Observations a parity check or a calibration takes at most: they are drawn at once (45 float64 each, about
360 MB at the bound); more is a typo."""
observations = int_in(1, MAX_OBS, "observations")


def _check_overrides(args: argparse.Namespace) -> None:
    """``--spec-toml`` and ``--role`` are for models without that metadata: on an exported actor that has it, a
    different one would generate C for another spec or role than the weights were trained on, silently."""
    import json

    from firmware_export.mlp_graph import load_onnx
    from runtime.spec import Role, SwarmSpec
    if args.spec_toml is None and args.role is None:
        return
    props = {p.key: p.value for p in load_onnx(args.model).metadata_props}
    if args.spec_toml is not None and "spec_json" in props:
        given = SwarmSpec.from_toml(args.spec_toml).hash
        stored = SwarmSpec.from_dict(json.loads(props["spec_json"])).hash
        if given != stored:
            raise CExportError(f"--spec-toml {args.spec_toml}: spec {given}, but {args.model} was exported for "
                               f"spec {stored} (its metadata): leave --spec-toml out, it is for models without "
                               f"spec metadata")
    if args.role is not None and "role" in props:
        if Role.parse(args.role) != Role.parse(props["role"]):
            raise CExportError(f"--role {args.role}: {args.model} is a {props['role']} actor (its metadata): leave "
                               f"--role out, it is for models without role metadata")


def _cmd_c(args: argparse.Namespace) -> int:
    from firmware_export.c_export import export_c

    _check_overrides(args)

    ex = export_c(args.model, args.out, quant=args.quant, tanh=args.tanh, spec_toml=args.spec_toml, role=args.role,
                  weights_in=args.weights_in, int8_rounding=args.int8_rounding, calib_obs=args.calib_obs,
                  check_budget=not args.ignore_budget)
    m = ex.model
    print(f"wrote {ex.header} and {ex.source}: agent {m.agent_id} ({m.role.label}), spec {m.spec.hash}, "
          f"obs {m.obs_dim} -> act {m.act_dim}, weights {ex.quant} ({ex.sources.weight_bytes} B of tables, "
          f"read from {ex.weights_in})")
    if args.app is not None:
        from firmware_export.c_export import install_app

        print(f"wrote the Crazyflie app to {install_app(ex, args.app)}: build it with "
              f"`make -C {args.app} CRAZYFLIE_BASE=/path/to/crazyflie-firmware`")
    if args.report:
        from firmware_export.c_report import cost_report, format_report

        print(format_report(ex, cost_report(ex, args.model, n_obs=args.report_obs)))
    return 0


def add_c(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("c", help="write self-contained C99 (policy.h, policy.c) for one ONNX actor",
                       description="Generate C99 for the drone's microcontroller from an actor exported by "
                                   "`swarm-export onnx`: policy.h (API, dimensions, spec hash, role, observation "
                                   "offsets) and policy.c (static const weights, no heap, no stdio).")
    p.add_argument("--model", required=True, type=Path, help="actor ONNX file, e.g. models/role_based/pursuer_0.onnx")
    p.add_argument("--out", required=True, type=out_dir, help="output directory, e.g. build/c/")
    p.add_argument("--quant", choices=QUANTS, default="float",
                   help="float: float32 weights; int8w: hidden layers int8 with one float scale per neuron times "
                        "q15 inputs (SMLAD on the Cortex-M4), the output layer float")
    p.add_argument("--weights-in", choices=WEIGHTS_IN, default=DEFAULT_WEIGHTS_IN,
                   help="ram (default): swarm_policy_init copies the tables to main SRAM (zero wait states; fits "
                        "the stock Crazyflie firmware); ccm: to the STM32F405's CCM RAM (zero wait states; the stock "
                        "firmware leaves about 0.6 KB of it); flash: read them in place (5 wait states per ART miss)")
    p.add_argument("--ignore-budget", action="store_true",
                   help="write the sources even when the tables do not fit the memory the stock Crazyflie firmware "
                        "leaves free (for a firmware built with less of its own state)")
    p.add_argument("--int8-rounding", choices=("gptq", "nearest"), default="gptq",
                   help="int8w only: gptq (error compensation on calibration observations) or nearest")
    p.add_argument("--calib-obs", type=observations, default=20_000,
                   help="int8w with gptq: calibration observations (half random in the spec's ranges, half "
                        "recorded from the simulator; other seeds than the --report parity check)")
    p.add_argument("--tanh", choices=TANHS, default="fast",
                   help="fast: rational approximation (error <= 5e-7, no libm); libm: tanhf (link -lm)")
    p.add_argument("--spec-toml", type=_spec_toml, default=None,
                   help="spec TOML ([spec] table) for models without spec metadata")
    p.add_argument("--role", default=None, help="pursuer|scout|evader, for models without role metadata")
    p.add_argument("--app", type=out_dir, default=None,
                   help="also write the Crazyflie app-layer app (template + this policy) to this directory")
    p.add_argument("--report", action="store_true",
                   help="also check parity against onnxruntime and report Cortex-M4 size and cycles "
                        "(needs a host C compiler, arm-none-eabi-gcc and unicorn)")
    p.add_argument("--report-obs", type=observations, default=10_000, help="observations for the --report parity check")
    p.set_defaults(func=_cmd_c)


def _run_folder(text: str) -> Path:
    """An argparse type for ``--run``: a training run folder, or its ``actors.pt`` itself (a folder that does not
    exist is left to the exporter, whose message says how to train one)."""
    p = Path(text)
    if p.exists() and not p.is_dir() and p.suffix != ".pt":
        raise argparse.ArgumentTypeError(f"{text!r} is a file, not a training run folder; give the folder that "
                                         f"`swarm-train train --out RUN` wrote (holding actors.pt)")
    return p


def _spec_toml(text: str) -> Path:
    """An argparse type for ``--spec-toml``: a readable TOML file with a ``[spec]`` table (without one the spec's
    defaults would be taken, and a wrong file would pass silently)."""
    from runtime.spec import load_toml
    p = in_file(text)
    try:
        doc = load_toml(p)
    except SpecError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    if "spec" not in doc:
        raise argparse.ArgumentTypeError(f"{text!r} has no [spec] table: give the experiment TOML the model was "
                                         f"trained on, e.g. configs/role_based.toml")
    return p


def _cmd_onnx(args: argparse.Namespace) -> int:
    try:
        from firmware_export.onnx_export import run_onnx_command
    except ImportError as exc:
        raise CExportError(f"swarm-export onnx needs torch ({exc}); install it with "
                           "`pip install -c constraints.txt '.[train]'`") from None
    return run_onnx_command(args)


def add_onnx(sub: argparse._SubParsersAction) -> None:
    """``swarm-export onnx`` (firmware_export.onnx_export, imported only when it runs: it needs torch, which
    ``swarm-export c`` does not)."""
    p = sub.add_parser("onnx", help="write one ONNX actor per agent and a manifest.json (parity-checked)",
                       description="Export every actor of a training run (runs/NAME/actors.pt) to ONNX with the "
                                   "spec in its metadata, checked against torch on random and recorded "
                                   "observations.")
    p.add_argument("--run", required=True, type=_run_folder,
                   help="training run folder holding actors.pt (runs/NAME)")
    p.add_argument("--out", required=True, type=out_dir, help="models folder to write (models/NAME/)")
    p.add_argument("--random", type=observations, default=10_000, help="random observations for the parity check")
    p.add_argument("--recorded", type=observations, default=10_000, help="recorded observations for the parity check")
    p.add_argument("--seed", type=seed, default=0, help="seed of the parity check's observations")
    p.set_defaults(func=_cmd_onnx)


SUBCOMMANDS = [add_onnx, add_c]
"""One registration function per subcommand."""


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="swarm-export", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in SUBCOMMANDS:
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(message)s")
    try:
        return args.func(args)
    except (CExportError, SpecError) as exc:
        print(f"swarm-export {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as exc:  # a disk or permission failure after the checks: still one line, no traceback
        print(f"swarm-export {args.command}: failed: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
