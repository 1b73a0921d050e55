"""The ``hmepol`` command's entry point (and ``python -m hmepol_cli``).

It sets the process's OpenMP wait policy before torch is imported, since the OpenMP runtime
reads it once, when it loads: threads that spin while they wait slow torch down many-fold on a
shared or oversubscribed machine (a sweep, a laptop). A user who wants spinning sets the
variable themselves. Importing :mod:`hmepol_cli.cli` (tests, benchmarks, a notebook) changes no
environment variable.
"""

from __future__ import annotations

import os


def main() -> None:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from hmepol_cli.cli import main as command  # torch loads here, after the variable is set

    command()


if __name__ == "__main__":
    main()
