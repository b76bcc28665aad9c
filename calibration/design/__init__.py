"""What to measure before measuring: expected intervals of candidate experiments."""
