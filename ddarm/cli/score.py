"""`ddarm score`: recorded episodes scored from their bags alone."""

from __future__ import annotations

import argparse
import json
import sys

from ddarm.cli.output import print_summary


def command_score(args: argparse.Namespace) -> int:
    from ddarm.recording.bags import BagError, score_bag

    failures = 0
    for bag in args.bags:
        try:
            summary = score_bag(bag)
        except BagError as error:
            failures += 1
            print(f'ddarm score: {error}', file=sys.stderr)
            continue
        if args.json:
            print(json.dumps(summary))
        else:
            print(bag)
            print_summary(summary)
    return 2 if failures else 0
