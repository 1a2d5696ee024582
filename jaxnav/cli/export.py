"""`python -m jaxnav.export RUN --bundle DIR` (or `--format numpy|onnx --out FILE`): ship the actor.

The command line over `jaxnav.export` (which says what a bundle and each format hold): the outputs
are checked before the checkpoint is read, and the check of the written file is printed. Exit
status 0, 1 when the written file fails its check or cannot be written, 2 for user mistakes.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from jaxnav.bundle import smoother_note
from jaxnav.cli import Parser, UsageError, print_error
from jaxnav.export import (
    CHECK_OBS,
    FORMATS,
    TOLERANCE,
    CheckFailed,
    ExportError,
    bundle_saved,
    check_bundle,
    check_out,
    export_saved,
    read_saved,
)
from jaxnav.io.checkpoint import CheckpointError


def parse_args(argv=None) -> argparse.Namespace:
    parser = Parser(prog="python -m jaxnav.export", description=__doc__.splitlines()[0])
    parser.add_argument("dir", metavar="RUN", help="a training run folder or a checkpoint in it")
    parser.add_argument(
        "--bundle", type=Path, metavar="DIR", help="write the robot's folder (package, policy.npz)"
    )
    parser.add_argument("--format", help=f"one of {', '.join(FORMATS)} (default numpy)")
    parser.add_argument("--out", type=Path, help="output file (default: RUN's checkpoint/policy.*)")
    args = parser.parse_args(argv)
    if args.bundle is not None:
        for flag in ("format", "out"):
            if getattr(args, flag) is not None:
                raise ExportError(f"--{flag}: not with --bundle (it writes DIR/policy.npz)")
    return args


def main(argv=None) -> int:
    try:
        args = parse_args(argv)
        fmt = args.format or "numpy"
        if fmt not in FORMATS:  # before reading the checkpoint: the flag is the first mistake
            raise ExportError(f"--format: unknown format '{fmt}'; valid: {', '.join(FORMATS)}")
        if args.bundle is not None:  # the outputs first: reading and checking take a while
            check_bundle(args.bundle)
        elif args.out is not None:
            check_out(args.out)
        saved = read_saved(args.dir)
        if args.bundle is not None:
            out, result = bundle_saved(saved, args.bundle)
        else:
            out, result = export_saved(saved, fmt, args.out)
    except CheckFailed as err:
        print_error(err)
        return 1
    except (UsageError, ExportError, CheckpointError) as err:  # argparse's own, the flags'
        print_error(err)
        return 2
    except OSError as err:  # a write that failed after the checks (disk full)
        where = err.filename or args.bundle or args.out or "output"
        print_error(f"{where}: cannot write ({err.strerror or err})")
        return 1
    print(f"wrote {out} ({'bundle' if args.bundle else fmt}) from {saved.ckpt}")
    if result is None:
        print("warning: onnxruntime is not installed; the ONNX model was not run", file=sys.stderr)
        return 0
    print(
        f"check: max |logit - JAX logit| = {result[0]:.2e} on {CHECK_OBS} random observations "
        f"(ok, tolerance {TOLERANCE:.0e}); greedy actions agree on {result[1]}/{CHECK_OBS}"
    )
    if args.bundle is not None:
        print(f"on the robot: see {args.bundle / 'README.txt'}")
        note = smoother_note(saved.config.randomize.coupled_smoother)
        if note:
            print(f"note: {note}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
