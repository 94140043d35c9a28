"""``cosy-lite check-dataset``: validate a BOP dataset folder; exit code 1 if any error."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", type=Path, help="dataset folder (contains models/)")
    p.add_argument("--name", default=None, help="dataset name in the parameter table (default: folder name)")
    p.add_argument("--split", dest="splits", action="extend", nargs="+", default=None, metavar="S",
                   help="split folders to check (default: every folder except models*)")
    p.add_argument("--no-images", dest="check_images", action="store_false",
                   help="do not read image headers (sizes, principal point)")


def run(args: argparse.Namespace) -> int:
    from cosy_lite.bop.validate import check_dataset, report

    problems = check_dataset(args.path, args.name, args.splits, args.check_images)
    return report(problems, str(args.path))
