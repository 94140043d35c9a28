"""The ``cosy-lite`` command: one sub-command per task, looked up in a table.

Each entry names the module that implements it; that module exposes ``add_arguments(parser)``
and ``run(args) -> int`` for the command. Expected errors (bad files, configs, checkpoints) end
as one message naming the file and the field, exit status 2 (:func:`cosy_lite.errors.run_reporting_errors`).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

# name -> (module, help)
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("cosy_lite.demo", "The whole job end to end on the default data: generate, train, infer, evaluate"),
    "generate": ("cosy_lite.synth.command", "Generate the embedded synthetic BOP dataset"),
    "train": ("cosy_lite.train.command", "Train the detector, coarse or refiner network (one process, or torchrun DDP)"),
    "infer": ("cosy_lite.inference.command_infer", "Estimate 6D poses on a BOP test split: the BOP19 results CSV"),
    "show": ("cosy_lite.vis.command_show", "Overlay GT poses on a dataset image (PNG)"),
    "contact-sheet": ("cosy_lite.vis.command_contact_sheet", "Grid of random training images with GT contours (PNG)"),
    "check-dataset": ("cosy_lite.bop.command_check_dataset", "Validate a BOP dataset folder"),
    "check-results": ("cosy_lite.bop.command_check_results", "Validate a BOP19 results CSV"),
    "eval": ("cosy_lite.eval.command", "Score a BOP19 results CSV (VSD, MSSD, MSPD, AR)"),
    "predict": ("cosy_lite.inference.command_predict", "One image in: detections + 6D poses out (JSON, BOP19 CSV rows, overlay)"),
    "templates": (
        "cosy_lite.inference.command_templates",
        "Render the silhouette templates of objects into a cache folder (infer --templates-cache)",
    ),
    "score-refiner": ("cosy_lite.reference.score_refiner", "A refiner's median pose errors on held-out instances, per iteration"),
    "score-start": (
        "cosy_lite.reference.score_start",
        "How often the start stage is within 30 deg of GT (GT masks, held-out instances)",
    ),
    "export": ("cosy_lite.export.command", "Export detector / coarse / refiner checkpoints to ONNX (+ manifest.json)"),
}


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of ``cosy-lite``; with ``only``, the arguments of that command alone are loaded (the
    others are listed, not imported: a command starts ~0.8 s sooner)."""
    parser = argparse.ArgumentParser(prog="cosy-lite", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        p.set_defaults(_module=module)
        if only is None or name == only:
            importlib.import_module(module).add_arguments(p)
    return parser


def command_parser(command: str, prog: str) -> argparse.ArgumentParser:
    """The parser of one sub-command as a program of its own, ``prog`` (``train.py``, ``infer.py``)."""
    module, help_ = COMMANDS[command]
    parser = argparse.ArgumentParser(prog=prog, description=help_)
    parser.set_defaults(_module=module, command=command)
    importlib.import_module(module).add_arguments(parser)
    return parser


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """Run ``cosy-lite COMMAND ...`` (``argv`` default: ``sys.argv[1:]``); returns the exit status.

    prog: the program name of usage messages and expected errors (default ``cosy-lite COMMAND``); the
    ``train.py`` / ``infer.py`` wrappers give theirs (``main(["train", *argv], prog="train.py")``).
    """
    from cosy_lite.errors import run_reporting_errors

    argv = sys.argv[1:] if argv is None else list(argv)
    if prog is not None and argv and argv[0] in COMMANDS:
        args = command_parser(argv[0], prog).parse_args(argv[1:])
    else:
        args = build_parser(argv[0] if argv and argv[0] in COMMANDS else None).parse_args(argv)
    # Waiting OpenMP threads sleep instead of spinning (read when torch loads, so before any command
    # imports it: parsing does not): on CPUs shared with other jobs spinning threads made the
    # networks 3-8x slower (measured for infer).
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    return run_reporting_errors(lambda: importlib.import_module(args._module).run(args),
                                prog or f"cosy-lite {args.command}")


# Commands whose process ends without the interpreter's teardown once they have returned: they
# leave no file open, no thread or child process running, nothing buffered but stdout and stderr.
# Freeing numba's and matplotlib's objects at exit took 0.19 s after a 2.2 s evaluation (measured).
FAST_EXIT = frozenset({"eval"})


def console_main() -> None:
    """The ``cosy-lite`` program: :func:`main` on ``sys.argv``, then exit (at once for :data:`FAST_EXIT`)."""
    code = main()
    if len(sys.argv) > 1 and sys.argv[1] in FAST_EXIT:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    console_main()
