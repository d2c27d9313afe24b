import sys

from planner_core.formats.cli import main

sys.exit(main())
