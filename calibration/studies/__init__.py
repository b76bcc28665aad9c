"""The studies built on a fit: twins, coverage, the runout law, the flow rule, the cost of an evaluation."""
