import sys

from planner_core.cli import main

sys.exit(main())
