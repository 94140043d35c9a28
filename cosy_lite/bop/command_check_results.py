"""``cosy-lite check-results``: validate a BOP19 results CSV; exit code 1 if any error."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", type=Path, help="results file METHOD_DATASET-SPLIT.csv")
    p.add_argument("--dataset", default=None, metavar="PATH_OR_NAME",
                   help="dataset folder to check ids against, or a name under $COSY_LITE_DATA (default ./data); "
                        "without it only the file itself is checked")
    p.add_argument("--name", default=None, help="dataset name (default: from the file name)")
    p.add_argument("--split", default=None, help="split the file must be for (default: from the file name)")


def run(args: argparse.Namespace) -> int:
    from cosy_lite.bop.folders import dataset_folder
    from cosy_lite.bop.validate import check_results, report

    root = dataset_folder(args.dataset) if args.dataset else None
    problems = check_results(args.file, root, args.name, args.split)
    return report(problems, str(args.file))
