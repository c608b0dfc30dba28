"""Thesis chapter 3: supervised training (train, train_speed), scoring (evaluate), one run per
method (runner), the comparison report and its figures (report, plots), and the size and speed
table (speed)."""
