"""``python -m layoutkit``: the same command line as ``layoutkit`` (:mod:`layoutkit.cli`)."""
from layoutkit.cli import main

if __name__ == "__main__":
    main()
