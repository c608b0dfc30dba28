"""Thesis chapter 3: the size and speed table (speed), samples/s of training steps (train_speed),
the author's DepthNet code run beside ours (reference, reference_launcher) and the test MAE
against training samples (scaling). Supervised training, scoring and runs are benchmark.engine's."""
