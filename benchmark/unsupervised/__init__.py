"""Thesis chapters 4-5: learning depth without ground truth; the reprojection losses
(reprojection) so far."""
