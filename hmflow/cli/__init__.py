"""The ``hmflow`` command line: a thin shell over hmcore and the Prefect flows. Each command
parses its options, checks them (exit 2 with every problem), calls one function and prints
what it returns; one module per command group:

* :mod:`~hmflow.cli.case`: ``init``, ``check``, ``evaluate`` (hmcore alone)
* :mod:`~hmflow.cli.campaign`: ``run``, ``report``, ``tables``
* :mod:`~hmflow.cli.ensemble`: ``ensemble`` (ES-MDA on field parameters)
* :mod:`~hmflow.cli.bench`: ``bench``; :mod:`~hmflow.cli.deploy`: ``deploy``
* :mod:`~hmflow.cli.diagnose`: ``diagnose``
* :mod:`~hmflow.cli.scenarios`: ``hide``, ``reveal``
* :mod:`~hmflow.cli.screen`: ``screen`` (sensitivity screening)

:mod:`~hmflow.cli.common` holds the Typer app and what the commands share,
:mod:`~hmflow.cli.flowrun` what starting a flow from the terminal takes. Importing the package
changes nothing in the process (Prefect's environment is set when a command runs).
"""

from hmflow.cli.common import app, main

# isort: off
# each module registers its commands when imported: in this order, the order `hmflow --help`
# lists them
from hmflow.cli import case, campaign, ensemble, bench, deploy, diagnose, scenarios  # noqa: F401
from hmflow.cli import screen  # noqa: F401
# isort: on

__all__ = ["app", "main"]
