"""Episodes, performance indices, gain searches and the ddarm command."""
