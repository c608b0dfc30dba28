"""What every chapter uses: the pairs of a dataset (data), the thesis' metrics, the focus of
expansion (geometry), flow from depth and back (flow), the networks (models), the registered
methods and their recipes (registry), a training run's configuration (config), checkpoints read
back (checkpoint), the run folder (runfolder) and the torch device (device).

Imports one way: nothing here imports benchmark.supervised, .video, .unsupervised or .cli."""
