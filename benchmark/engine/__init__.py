"""The engine every chapter trains, scores and runs its networks with, between benchmark.core and
the chapters: the one training loop (loop: steps, logs, saves, stops; train: its configuration
for a registered method, with optimiser, milestones, validation, exact resume and DDP; the
chapters' own configurations, e.g. finetune, run the same loop) with the
training step of each kind of method from a table (steps; pair_step: depth and flow from pairs
with ground truth; resume: what a resumed run keeps), scoring (evaluate, scaling: the "P" and "GT"
scales of a depth known up to a factor; predictions: another method's depth files), one run per
method (runner, the `run` and `eval` commands) with its report and figures (report, plots), and a
trained depth network on footage (network, export, footage_job, frame_depth).

Imports one way: only benchmark.core (and stillbox_gen's contract); the chapters import it."""
