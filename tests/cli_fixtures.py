"""Running ``swarm-train`` in the test's own interpreter (cheaper than a subprocess)."""
from __future__ import annotations


def in_process(capsys, *args: str) -> tuple[int, str, str]:
    """``swarm-train ARGS`` in this interpreter (cheaper than a subprocess): exit status, stdout, stderr."""
    from training.cli import main
    try:
        rc = main(list(args))
    except SystemExit as exc:  # argparse's own usage errors
        rc = exc.code
    out = capsys.readouterr()
    return rc, out.out, out.err
