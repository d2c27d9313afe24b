import sys
import time

started = time.perf_counter()  # before any of the planner is imported: the CLI reports start-up apart

from planner_core.formats.cli import main  # noqa: E402

sys.exit(main(started=started))
