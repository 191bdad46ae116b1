"""`minority oracle ...`: argument parsing of the GNS surrogate's subcommands."""

from __future__ import annotations

import argparse
import sys


def _not_built(name: str):
    def run(args: argparse.Namespace) -> int:
        print(f"minority oracle {name}: not built yet", file=sys.stderr)
        return 2
    return run


def add_oracle_parser(sub) -> None:
    p = sub.add_parser("oracle", help="GNS surrogate: dataset, train, rollout, spec",
                       description="Build the GNS training set from MPM runs, train the "
                                   "surrogate, roll it out on a scene, derive oracle specs.")
    osub = p.add_subparsers(dest="oracle_command", required=True, metavar="STEP")
    q = osub.add_parser("dataset", help="run the MPM sweep of a config and build the dataset")
    q.set_defaults(func=_not_built("dataset"))
