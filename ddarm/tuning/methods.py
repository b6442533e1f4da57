"""The gain searches by name, apart from their code, so that the command line can list them without loading it."""

METHODS = ('global', 'nelder-mead', 'cma')
# The default of `ddarm tune` and `ddarm pareto`'s single-index searches: it finds the better basins.
DEFAULT_METHOD = 'global'
