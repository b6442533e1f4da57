"""What bench/vector_padding.py and bench/thread_share.py share: their options and the compiled batch runner of the
paper's arm (or the Panda), computed torque at the ω = 15 rule gains."""

from __future__ import annotations

import argparse

from ddarm.episodes.bench import MANY_JOINT_ARM, perturbed_gains, reference_case
from ddarm.episodes.engine import BatchRunner
from ddarm.physics.arm import config_file


def options(description: str, sizes: list[int], rounds: int) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument('--sizes', type=int, nargs='+', default=sizes)
    parser.add_argument('--rounds', type=int, default=rounds)
    parser.add_argument('--panda', action='store_true', help='the Panda (7 joints) instead of the paper\'s arm')
    return parser.parse_args()


def compiled_runner(panda: bool):
    """The case's template and its BatchRunner, its dynamics compiled (or loaded) by a first call."""
    template = reference_case(*(str(config_file(*parts)) for parts in MANY_JOINT_ARM)) if panda else reference_case()
    runner = BatchRunner(template)
    runner(*perturbed_gains(template, 1, seed=1), threads=1)
    return template, runner
