"""The gain searches by name and the tuning commands' defaults, apart from their code, so that the command line
can list them (and refuse their arguments) without loading the optimisers."""

from ddarm.errors import DdarmError

METHODS = ('global', 'nelder-mead', 'cma')
# The default of `ddarm tune` and `ddarm pareto`'s single-index searches: it finds the better basins.
DEFAULT_METHOD = 'global'
# `ddarm tune`'s budget, and that of `ddarm pareto`'s single-index searches: enough for differential evolution's
# generations and the local runs on a 6-joint arm.
DEFAULT_TUNE_BUDGET = 100_000
# `ddarm pareto`'s defaults (ddarm.tuning.pareto.pareto_front): its budget, NSGA-II's population, the refining
# searches and the points reported. On the paper's arm (computed torque, trajectory 1) the budget is about 20 s of
# episodes in batches of a few hundred; its front then lies within about 0.5 % (mean, in I1 or I2) of the best
# front known from several times the budget.
DEFAULT_BUDGET = 20_000
DEFAULT_POPULATION = 100
DEFAULT_SEARCHES = 32
DEFAULT_POINTS = 40


class ParetoError(DdarmError, ValueError):
    """A Pareto-front specification that cannot be run, or a run that found no bounded episode."""
