"""`python -m jaxnav.evaluate`: runs the command line `jaxnav.cli.evaluate`.

`jaxnav.evaluate` is the function `jaxnav.evaluation.evaluate`; this module is only run, never
imported (importing it would rebind `jaxnav.evaluate` to a module).
"""

import sys

if __name__ == "jaxnav.evaluate":
    raise ImportError(
        "jaxnav.evaluate is the function jaxnav.evaluation.evaluate (from jaxnav import evaluate); "
        "the command line is jaxnav.cli.evaluate"
    )

from jaxnav.cli.evaluate import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
