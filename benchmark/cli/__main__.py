"""``python -m benchmark.cli``: the same as ``stillbox-bench``."""

from . import main

if __name__ == "__main__":
    main()
