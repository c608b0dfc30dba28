"""What every chapter uses: the pairs of a dataset (data), the thesis' metrics, the focus of
expansion (geometry), flow from depth and back (flow), the networks (models, posenet, dispnet),
the registered methods and their recipes (registry), a training run's configuration (config),
checkpoints read back (checkpoint), the run folder (runfolder), the torch device (device), a
user's footage in and depth files out (footage) and the multi-shift maths (multishift).

Imports one way: nothing here imports another benchmark package (engine, the chapters, cli)."""
