"""``python -m thermogrammetry``: the command line.

The guard matters: a worker process started with the ``spawn`` or ``forkserver`` method imports the parent's main
module again (as ``__mp_main__``); without it every worker would run the command itself, and start workers of its own.
"""

import sys

from .cli.main import main

if __name__ == "__main__":
    sys.exit(main())
