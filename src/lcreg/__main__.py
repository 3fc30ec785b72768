"""The ``lcreg`` console script (and ``python -m lcreg``): the library's CLI and the experiments' command.

``lcreg reproduce ...`` runs :func:`lcreg.experiments.reproduce.command.main` (the paper's tables, beside the
library); every other command, ``fit|validate|test|predict|register``, is :func:`lcreg.cli.main`. This module is the
only one that imports both, so the library never imports the experiments.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence


def main(args: Sequence[str] | None = None) -> None:
    """Run ``lcreg`` with ``args`` (``None``: ``sys.argv[1:]``, and user errors end with one line, not a traceback).

    Args:
        args: Command-line arguments after ``lcreg``; given (tests, scripts), errors are raised typed to the caller.
    """
    argv = [str(a) for a in (sys.argv[1:] if args is None else args)]
    if argv[:1] == ["reproduce"]:
        from lcreg.experiments.reproduce.command import main as reproduce_main

        reproduce_main(argv[1:])
        return
    from lcreg.cli import main as cli_main

    cli_main(None if args is None else argv)


if __name__ == "__main__":  # pragma: no cover
    sys.argv[0] = "lcreg"  # `python -m lcreg` shows the usage of the `lcreg` command
    main()
