"""StillBox benchmark: train and score depth-from-motion models on stillbox-gen datasets."""
