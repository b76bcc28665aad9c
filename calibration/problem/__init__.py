"""What a fit solves: the scene, what it observes, the fitted keys and their bounds, the measured data
and the residuals between them."""
