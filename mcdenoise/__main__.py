"""``python -m mcdenoise <stage> …`` and the installed ``mcdenoise`` command: the pipeline's command line
(``python -m pipeline`` in a source checkout), usable from any directory."""
from __future__ import annotations

import sys

from mcdenoise.pipeline.cli import main


def run(prog: str = "mcdenoise") -> int:
    """The command line under its installed name (the console script's entry point)."""
    return main(prog=prog)


if __name__ == "__main__":
    sys.exit(run("python -m mcdenoise"))
