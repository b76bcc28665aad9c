"""What a point is worth: the verdict, Gauss–Newton intervals with their round-off, sampling and
grid terms, profile likelihoods and posteriors."""
