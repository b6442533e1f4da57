"""`ddarm score`: recorded episodes scored from their bags alone."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ddarm.cli.output import print_json, print_summary


def command_score(args: argparse.Namespace) -> int:
    """Score each bag; a bag that cannot be scored is named on stderr and the others still scored (exit 2)."""
    from ddarm.errors import DdarmError
    from ddarm.recording.bags import BagError, score_bag

    failures = 0
    for bag in args.bags:
        try:
            summary = score_bag(bag)
        except DdarmError as error:
            failures += 1
            # score_bag's BagErrors name the bag already; any other refusal is named here.
            named = isinstance(error, BagError) and str(error).startswith(f'{Path(bag)}: ')
            print(f'ddarm score: {error if named else f"{bag}: {error}"}', file=sys.stderr)
            continue
        if args.json:
            print_json(summary)
        else:
            print(bag)
            print_summary(summary)
    return 2 if failures else 0
