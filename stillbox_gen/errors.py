"""The two kinds of user error of StillBox-gen, apart from the modules that raise them so that a
reader of datasets (the benchmark) can catch them without importing the generator's config.

Both are ValueErrors whose message is one line naming what is wrong; the command lines print it
and exit with code 2.
"""


class ConfigError(ValueError):
    """A user mistake in a preset file or a command-line flag (message names it)."""


class DatasetError(ValueError):
    """A dataset, or one of its files, that cannot be read; the message names the file (or the
    record) and what is wrong with it. The command lines print it as a one-line user error."""


class WorkerDied(RuntimeError):
    """The live Blender worker (stillbox_gen.live) ended while the driver still needed it."""


class WorkerHung(WorkerDied):
    """The live Blender worker gave no answer in time; it was killed."""
