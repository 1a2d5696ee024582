"""`python -m jaxnav.train`: runs the command line `jaxnav.cli.train`.

`jaxnav.train` is the function `jaxnav.training.train`; this module is only run, never imported
(importing it would rebind `jaxnav.train` to a module).
"""

import sys

if __name__ == "jaxnav.train":
    raise ImportError(
        "jaxnav.train is the function jaxnav.training.train (from jaxnav import train); "
        "the command line is jaxnav.cli.train"
    )

from jaxnav.cli.train import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
