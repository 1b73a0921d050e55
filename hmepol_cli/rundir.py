"""The run directory's old module name, kept only for the report.

The code moved to :mod:`hmepol_cli.run`, one module a job. ``hmepol_cli/report/`` and
``tests/test_report.py`` still import from here (their owners switch them to
``hmepol_cli.run``); delete this file then. New code imports from :mod:`hmepol_cli.run`.
"""

from hmepol_cli.run import *  # noqa: F403
from hmepol_cli.run import __all__  # noqa: F401
