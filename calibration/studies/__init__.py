"""The studies built on a fit: twins, coverage, the runout law, the cost of an evaluation."""
